"""The robust matching rule: NCC of radial profiles (section 5.2, robust).

See :mod:`omniflow.matching.radial` for the rule; :func:`match_robust` runs
it on the polar tables of both units, all radial lines at once.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from omniflow.matching.tables import TableGeometry, local_maxima, parabola_offset, sharp_peak

__all__ = ["Descriptors", "match_robust"]


class Descriptors:
    """Zero-mean, unit-norm polar patches of one table.

    A patch at (line k, column j) holds the radial profile at columns
    j - w stride .. j + w stride, every ``stride``-th, on lines
    k - lines .. k + lines (wrapping around theta); L = (2 lines + 1)(2 w + 1)
    values. The table is split by column parity into ``stride`` decimated
    copies so each profile is a contiguous run, and each window's mean and
    norm come from cumulative sums.
    """

    def __init__(self, table: NDArray, w: int, stride: int, lines: int):
        self.w, self.stride, self.lines = w, stride, lines
        self.n_lines, n_cols = table.shape
        m = 2 * w + 1
        width = -(-n_cols // stride)
        dec = np.zeros((stride, self.n_lines, width), dtype=np.float32)
        for par in range(stride):
            part = table[:, par::stride]
            dec[par, :, : part.shape[1]] = part
        self.view = sliding_window_view(dec, m, axis=2)  # (stride, lines, width - m + 1, m)
        # the same windows by the flat index of their first sample (one
        # index array gathers faster than three; windows never cross a row)
        self.width = width
        self.flat = sliding_window_view(dec.reshape(-1), m)

        # per window: sum and sum of squares over the (2 lines + 1) x m patch
        # (box filters anchored at the window's first sample)
        def window_sum(a):
            out = []
            for par in range(stride):
                x = a[par]
                if lines:  # wrap around theta
                    x = np.concatenate([x[-lines:], x, x[:lines]], axis=0)
                y = cv2.boxFilter(x, -1, (m, 2 * lines + 1), anchor=(0, 0), normalize=False,
                                  borderType=cv2.BORDER_CONSTANT)  # fmt: skip
                out.append(y[: self.n_lines])
            return np.stack(out)

        s1 = window_sum(dec)
        s2 = window_sum(dec * dec)
        length = (2 * lines + 1) * m
        self.length = length
        self.mean = s1 / np.float32(length)
        var = np.maximum(s2 - s1 * self.mean, np.float32(0.0))
        self.inv_norm = np.float32(1.0) / np.maximum(np.sqrt(var), np.float32(1e-12))

    def __call__(self, k: NDArray, j: NDArray) -> NDArray:
        """Patches at (k, j) of any equal shapes S; returns S + (L,), float32."""
        start = j - self.w * self.stride
        par, col = start % self.stride, start // self.stride
        n = self.n_lines
        # flat index of (par, k, col) in the (stride, lines, width) arrays
        fi = (par * n + k) * self.width + col
        if self.lines == 0:
            p = self.flat[fi]  # a copy: fancy indexing
        else:
            m = 2 * self.w + 1
            p = np.empty((*np.shape(k), self.length), dtype=np.float32)
            for i, dk in enumerate(range(-self.lines, self.lines + 1)):
                p[..., i * m : (i + 1) * m] = self.flat[(par * n + (k + dk) % n) * self.width + col]
        p -= self.mean.reshape(-1)[fi][..., None]
        p *= self.inv_norm.reshape(-1)[fi][..., None]
        return p


def _window_slots(
    cols: NDArray, exists: NDArray, line: NDArray, lo: NDArray, hi: NDArray
) -> tuple[NDArray, NDArray]:
    """Slots [first, stop) of the edges of ``line`` whose column lies in [lo, hi].

    ``cols``/``exists`` are a left-aligned layout from :func:`_per_line` (each
    row's edges ascending), so the slots in range are contiguous. ``line``,
    ``lo`` and ``hi`` have any one shape; so do the results.
    """
    n_lines, c = cols.shape
    big = np.int64(1) << 40
    key = np.where(exists, cols, big - 1).astype(np.int64)
    key += np.arange(n_lines, dtype=np.int64)[:, None] * big
    key = key.ravel()
    base = np.asarray(line, dtype=np.int64) * big
    first = np.searchsorted(key, (base + lo).ravel(), side="left").reshape(base.shape)
    stop = np.searchsorted(key, (base + hi).ravel(), side="right").reshape(base.shape)
    offset = np.asarray(line, dtype=np.int64) * c
    return first - offset, stop - offset


def _per_line(mask: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """The True columns of each row of ``mask``, left-aligned and padded.

    Returns (cols (n, c), exists (n, c), rank) where c is the largest count
    in a row, padded entries hold column 0, and rank is each True entry's
    position in its row (row-major order, as np.nonzero).
    """
    k, j = np.nonzero(mask)
    counts = np.bincount(k, minlength=mask.shape[0])
    c = max(int(counts.max()) if counts.size else 0, 1)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.arange(k.size) - starts[k]
    cols = np.zeros((mask.shape[0], c), dtype=np.intp)
    exists = np.zeros((mask.shape[0], c), dtype=bool)
    cols[k, rank] = j
    exists[k, rank] = True
    return cols, exists, rank


def match_robust(
    tab: TableGeometry,
    fh1,
    fh2,
    t1,
    t2,
    thr,
    *,
    w,
    stride,
    patch_lines,
    min_score,
    uniqueness,
    left_right,
    candidate_fraction,
    self_similarity=1.0,
    flatness=0.0,
    alias_score=1.0,
):
    """NCC of radial profiles between the edges of both images, line by line.

    The edges (local maxima of |f_h| along a line above candidate_fraction *
    thr) of each line are laid out left-aligned in (n_theta, c) arrays, so
    the NCC of every pair of edges on every line is one batched matrix
    product: first the significant edges of image 1 against all edges of
    image 2, then, for the left-right check, the chosen edges of image 2
    against all edges of image 1. Last, h_2 is refined to sub-pixel and the
    match kept when the refined NCC is at least min_score and its peak sharp
    enough for that (:func:`~omniflow.matching.tables.sharp_peak`, ``flatness``).
    """
    n_theta, pad, n_h = tab.n_theta, tab.pad, tab.n_h
    lo, hi = tab.win
    low = candidate_fraction * thr
    layout = []
    for fh in (fh1, fh2):
        a = np.abs(fh)
        m = local_maxima(a)
        m &= a > low
        m[:, :pad] = False
        m[:, pad + n_h :] = False
        cols, exists, _ = _per_line(m)
        rows = np.broadcast_to(np.arange(n_theta)[:, None], cols.shape)
        layout.append((cols, exists, rows, fh[rows, cols]))
    (c1, e1, rows1, g1), (c2, e2, rows2, g2) = layout
    # the significant edges of image 1, as slots of its edge layout
    sslot, es, _ = _per_line(e1 & (np.abs(g1) > thr))
    n_sig = int(np.count_nonzero(es))
    if n_sig == 0 or not e2.any():
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0), np.zeros(0), n_sig
    rows_s = np.broadcast_to(np.arange(n_theta)[:, None], sslot.shape)
    desc2 = Descriptors(t2, w, stride, patch_lines)
    D1 = Descriptors(t1, w, stride, patch_lines)(rows1, c1)  # (n_theta, c1, L)
    D2 = desc2(rows2, c2)  # (n_theta, c2, L)
    # padding slots get zero descriptors, hence NCC 0 with everything: never a
    # match (min_score > 0), never a left-right winner over a real edge
    D1[~e1] = 0.0
    D2[~e2] = 0.0
    D1s = _rows_take(D1, rows_s, sslot)  # D1[rows_s, sslot]
    D1s[~es] = 0.0

    # forward: each significant edge of image 1 takes its best edge of image 2
    # inside the disparity window
    j1 = c1[rows_s, sslot]
    S = np.matmul(D1s, D2.transpose(0, 2, 1))  # (n_theta, cs, c2) NCC
    _mask_outside(S, *_window_slots(c2, e2, rows_s, j1 + lo, j1 + hi))
    best_c = np.argmax(S, axis=2)
    best = np.take_along_axis(S, best_c[..., None], axis=2)[..., 0]
    # the NCC at whole columns can sit below its peak between them by up to
    # ~(1 - peak) (h_step / correlation length)^2; take a looser floor here
    # and apply min_score to the interpolated peak below
    floor = min_score - 0.5 * (1.0 - min_score)
    ok = es & np.isfinite(best) & (best >= floor)
    # the same edge polarity (an edge of the other polarity falls where this
    # one rises: NCC near -1, so it seldom wins anyway)
    ok &= (g1[rows_s, sslot] > 0) == (g2[rows_s, best_c] > 0)
    if uniqueness < 1.0 and S.shape[2] > 1:
        np.put_along_axis(S, best_c[..., None], -np.inf, axis=2)
        second = np.maximum(S.max(axis=2), -1.0)
        ok &= (1.0 - best) <= uniqueness * (1.0 - second)
    if self_similarity < 1.0 and ok.any():
        # periodic aliases: image 1's own profile recurs on its line within a
        # window's width (at a lag of at least half the profile), so an
        # equally good match sits a period away in image 2 whatever it scores
        A = np.matmul(D1s, D1.transpose(0, 2, 1))  # (n_theta, cs, c1)
        lag = np.abs(c1[:, None, :] - j1[:, :, None])
        far = (lag < (w * stride) // 2) | (lag > hi - lo) | ~e1[:, None, :]
        A[far] = -np.inf
        self_best = np.maximum(A.max(axis=2), -1.0)
        ok &= (1.0 - best) <= self_similarity * (1.0 - self_best)
    if alias_score < 1.0 and ok.any():
        lags = ((w * stride) // 2, hi - lo)
        line = ok.nonzero()[0]
        d1 = D1s[ok]
        ok[ok] = _not_periodic(D1, c1, e1, line, j1[ok], d1, lags=lags, alias_score=alias_score)
    if left_right and ok.any():
        # the best image-1 edge of each chosen image-2 edge, in its window
        oslot, eo, _ = _per_line(ok)
        rows_o = np.broadcast_to(np.arange(n_theta)[:, None], oslot.shape)
        b2 = best_c[rows_o, oslot]
        D2o = _rows_take(D2, rows_o, b2)  # D2[rows_o, b2]
        D2o[~eo] = 0.0
        Sb = np.matmul(D2o, D1.transpose(0, 2, 1))  # (n_theta, co, c1)
        j2 = c2[rows_o, b2]
        _mask_outside(Sb, *_window_slots(c1, e1, rows_o, j2 - hi, j2 - lo))
        back = np.argmax(Sb, axis=2)
        agree = eo & (back == sslot[rows_o, oslot])
        ok = np.zeros_like(ok)
        ok[rows_o[agree], oslot[agree]] = True
    ks, si = np.nonzero(ok)
    rs = sslot[ks, si]
    best = best[ks, si]
    jj1 = c1[ks, rs]
    jj2 = c2[ks, best_c[ks, si]]
    dd1 = _rows_take(D1, ks, rs)  # D1[ks, rs]

    # sub-sample h_2: parabola through the NCC at the neighbouring columns,
    # after moving one column if a neighbour scores higher
    lo_col, hi_col = w * stride, t2.shape[1] - 1 - w * stride

    def ncc(jj):
        return np.einsum("nl,nl->n", dd1, desc2(ks, np.clip(jj, lo_col, hi_col)))

    s0, sm, sp = best, ncc(jj2 - 1), ncc(jj2 + 1)
    step = np.where((sp > s0) & (sp >= sm), 1, np.where(sm > s0, -1, 0))
    moved = step != 0
    if np.any(moved):
        far = ncc(jj2 + 2 * step)
        sm, s0, sp = (
            np.where(step > 0, s0, np.where(moved, far, sm)),
            np.where(moved, np.maximum(sp, sm), s0),
            np.where(step > 0, far, np.where(moved, s0, sp)),
        )
        jj2 = jj2 + step
    off = parabola_offset(sm, s0, sp)
    peak = s0 + 0.25 * (sp - sm) * off  # the parabola's vertex value
    keep = (peak >= min_score) & sharp_peak(peak, sm, s0, sp, flatness)
    return (ks[keep], (jj1 - pad)[keep], (jj2 + off - pad)[keep],
            np.clip(peak[keep], 0.0, 1.0), n_sig)  # fmt: skip


def _not_periodic(
    D1: NDArray, c1: NDArray, e1: NDArray, line: NDArray, j1: NDArray, d1: NDArray,
    *, lags: tuple[int, int], alias_score: float,
) -> NDArray:  # fmt: skip
    """The periodic-alias test of :func:`match_robust`, for M chosen matches.

    Each match's image-1 profile ``d1`` (M, L), at column ``j1`` of line
    ``line``, is compared with the other edges of its own line (``D1``, ``c1``,
    ``e1``: the edge layout, columns ascending). It recurs when, at a lag
    ``lags[0] <= |lag| <= lags[1]``, the NCC is above ``alias_score`` after
    falling below 0 at a smaller lag on the same side (a period; a smooth
    ramp correlates with itself at every lag without falling, and is left to
    the other tests). Then an alias a period away in image 2 matches as well
    as the truth, or better, and the match is dropped however well it scores.
    Bool (M,), True = keep. Only the matches that passed the other tests are
    compared: M x (edges per line) profile products.
    """
    A = np.einsum("ml,mcl->mc", d1, _rows_take(D1, line[:, None], np.arange(D1.shape[1])[None, :]))
    lag = c1[line] - j1[:, None]
    A[~e1[line] | (np.abs(lag) > lags[1])] = np.nan
    recurs = np.zeros(A.shape[0], dtype=bool)
    for a, dist in (
        (np.where(lag > 0, A, np.nan), lag),
        (np.where(lag < 0, A, np.nan)[:, ::-1], -lag[:, ::-1]),
    ):
        # a: NCC by edge, walking outward from j1; fallen: it was below 0 at a smaller lag
        low = np.fmin.accumulate(np.where(np.isnan(a), np.inf, a), axis=1)
        fallen = np.zeros_like(a, dtype=bool)
        fallen[:, 1:] = low[:, :-1] < 0.0
        with np.errstate(invalid="ignore"):
            recurs |= np.any(fallen & (dist >= lags[0]) & (a > alias_score), axis=1)
    return ~recurs


def _rows_take(a: NDArray, k: NDArray, j: NDArray) -> NDArray:
    """a[k, j] for a C-contiguous (n, c, L) array: np.take of flat rows (the
    same values, gathered several times faster than by two index arrays)."""
    n, c, length = a.shape
    return np.take(a.reshape(n * c, length), np.asarray(k) * c + j, axis=0)


def _mask_outside(S: NDArray, first: NDArray, stop: NDArray) -> None:
    """Set S[..., m] = -inf outside first <= m < stop (in place)."""
    # int16 slots where they fit and an in-place or: less memory traffic on
    # the (lines, c, c) masks
    it = np.int16 if S.shape[-1] < np.iinfo(np.int16).max else np.int32
    slot = np.arange(S.shape[-1], dtype=it)
    out = np.less(slot, first[..., None].astype(it))
    out |= slot >= stop[..., None].astype(it)
    S[out] = -np.inf
