"""More matches per radial line: grow the robust matcher's matches to their neighbours.

The robust rule matches only edges (local maxima of |df/dh_i|), about one
sample in twenty. A surface's disparity varies slowly along a radial line, so
every other textured sample near a matched edge can be matched by a short
search around that edge's disparity: :func:`densify` tries each sample of
image 1 whose |df1/dh_1| passes a (lower) threshold and that lies within
``reach`` columns of a match on its line, with the NCC of its own radial
profile (the same profiles as the robust rule's descriptors) at the seed's disparity
+- ``search`` columns. Between two seeds the guess is interpolated, and a
sample between two seeds that disagree by more than one column (a depth edge
between them) is not tried. A sample is kept where its NCC peaks inside the
searched range, scores at least ``min_score``, is sharp enough
(:func:`~omniflow.matching.tables.sharp_peak`) and, with ``smooth`` < 1, its
image-1 profile is not smooth over its own length (:func:`smooth_profiles`).
"""

from __future__ import annotations

import math

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

from omniflow.matching.dense_kernels import profile_stats
from omniflow.matching.tables import sharp_peak
from omniflow.paper.matching import TableGeometry, parabola_offset
from omniflow.parallel import map_tasks

__all__ = [
    "candidates",
    "candidates_numpy",
    "densify",
    "grown_from",
    "ncc_offsets",
    "smooth_profiles",
]


@numba.njit(cache=True, nogil=True)
def _ncc(dot, b1, b2, inv1, length):  # pragma: no cover - compiled
    """The NCC from sum (v1 - mean1) v2, sum v2 and sum v2^2 (the first is zero-mean,
    so sum (v1 - mean1)(v2 - mean2) = sum (v1 - mean1) v2)."""
    return dot * inv1 * (1.0 / max(math.sqrt(max(b2 - b1 * (b1 / length), 0.0)), 1e-12))


@numba.njit(cache=True, nogil=True)
def ncc_offsets(t1, t2, k, j, cols, w, stride, out):  # pragma: no cover - compiled
    """NCC of the profile of ``t1`` at (k[i], j[i]) with those of ``t2`` at (k[i], cols[i, s]).

    A profile: the 2 w + 1 samples every ``stride`` columns centred on the column, on
    line k; zero-mean, unit-norm (a
    flat profile has norm 1e-12). Columns must keep the profile inside the table.
    Writes out[i, s]. :func:`omniflow.matching.dense_kernels.ncc_offsets`, value for value: each
    sum is taken in the same order, but four columns' sums at once (independent
    chains of additions the processor overlaps).
    """
    n_lines = t1.shape[0]
    length = 2 * w + 1
    n_s = cols.shape[1]
    for i in range(k.size):
        mean1, inv1 = profile_stats(t1, k[i], j[i], w, stride)
        for g in range(0, n_s, 4):
            # columns g .. g + 3 (the last repeated past the end, not written)
            c0 = cols[i, g]
            c1 = cols[i, min(g + 1, n_s - 1)]
            c2 = cols[i, min(g + 2, n_s - 1)]
            c3 = cols[i, min(g + 3, n_s - 1)]
            d0 = d1 = d2 = d3 = 0.0
            a0 = a1 = a2 = a3 = 0.0
            e0 = e1 = e2 = e3 = 0.0
            row = k[i] % n_lines
            for q in range(-w, w + 1):
                off = q * stride
                u = np.float64(t1[row, j[i] + off]) - mean1
                v0 = np.float64(t2[row, c0 + off])
                v1 = np.float64(t2[row, c1 + off])
                v2 = np.float64(t2[row, c2 + off])
                v3 = np.float64(t2[row, c3 + off])
                d0 += u * v0
                d1 += u * v1
                d2 += u * v2
                d3 += u * v3
                a0 += v0
                a1 += v1
                a2 += v2
                a3 += v3
                e0 += v0 * v0
                e1 += v1 * v1
                e2 += v2 * v2
                e3 += v3 * v3
            out[i, g] = _ncc(d0, a0, e0, inv1, length)
            if g + 1 < n_s:
                out[i, g + 1] = _ncc(d1, a1, e1, inv1, length)
            if g + 2 < n_s:
                out[i, g + 2] = _ncc(d2, a2, e2, inv1, length)
            if g + 3 < n_s:
                out[i, g + 3] = _ncc(d3, a3, e3, inv1, length)


def _seed_guess(
    k: NDArray, j: NDArray, disp: NDArray, ck: NDArray, cj: NDArray, n_cols: int, reach: int
) -> tuple[NDArray, NDArray]:
    """Each candidate's disparity guess from the nearest seeds on its line.

    Returns (usable, guess): a candidate is usable when a seed lies within
    ``reach`` columns on either side and, with one on each side, the two
    agree within one column (the guess is then interpolated between them).
    """
    order = np.lexsort((j, k))
    ks, js, ds = k[order], j[order], disp[order]
    key = ks.astype(np.int64) * n_cols + js
    right = np.searchsorted(key, ck.astype(np.int64) * n_cols + cj)  # first seed to the right
    left = right - 1
    li, ri = np.clip(left, 0, key.size - 1), np.clip(right, 0, key.size - 1)
    has_l = (left >= 0) & (ks[li] == ck) & (cj - js[li] <= reach)
    has_r = (right < key.size) & (ks[ri] == ck) & (js[ri] - cj <= reach)
    both = has_l & has_r
    usable = (has_l | has_r) & ~(both & (np.abs(ds[li] - ds[ri]) > 1.0))
    a = (cj - js[li]) / np.maximum(js[ri] - js[li], 1)
    guess = np.where(both, ds[li] + a * (ds[ri] - ds[li]), np.where(has_l, ds[li], ds[ri]))
    return usable, guess


def candidates(
    fh1: NDArray,
    thr: float,
    pad: int,
    n_h: int,
    k: NDArray,
    jj: NDArray,
    disp: NDArray,
    reach: int,
) -> tuple[NDArray, NDArray, NDArray]:
    """The samples :func:`densify` tries and each one's disparity guess.

    A candidate is a core sample (columns pad .. pad + n_h - 1) of line k with
    |fh1| >= thr (compared in float32, as numpy compares a float32 table with a
    Python float), not a seed, with a seed of its line within ``reach`` columns;
    the guess is that of :func:`_seed_guess` (kept where usable). Seeds: line
    ``k``, table column ``jj``, disparity ``disp`` (columns). Returns (ck, cj,
    guess) by line, then column. Compiled (:func:`_line_candidates`);
    :func:`candidates_numpy` is the same with a dilation and searchsorted.
    """
    order = np.lexsort((jj, k))
    ks = np.ascontiguousarray(np.asarray(k, dtype=np.int64)[order])
    js = np.ascontiguousarray(np.asarray(jj, dtype=np.int64)[order])
    ds = np.ascontiguousarray(np.asarray(disp, dtype=np.float64)[order])
    fh = np.ascontiguousarray(fh1)
    first = np.searchsorted(ks, np.arange(fh.shape[0] + 1))  # each line's seeds
    # at most 2 reach candidates per seed, n_h per line
    most = int(np.minimum(np.diff(first) * (2 * reach), n_h).sum())
    out_k = np.empty(most, dtype=np.intp)
    out_j = np.empty(most, dtype=np.intp)
    out_g = np.empty(most, dtype=np.float64)
    n = _line_candidates(fh, thr, int(pad), int(n_h), first, js, ds, int(reach), out_k, out_j,
                         out_g)  # fmt: skip
    return out_k[:n], out_j[:n], out_g[:n]


@numba.njit(cache=True, nogil=True)
def _line_candidates(fh, thr, pad, n_h, first, js, ds, reach, out_k, out_j,
                     out_g):  # pragma: no cover - compiled  # fmt: skip
    """:func:`candidates` line by line into out_*; returns how many."""
    thr32 = np.float32(thr)
    c = 0
    for k in range(fh.shape[0]):
        s0, s1 = first[k], first[k + 1]
        if s0 == s1:
            continue
        r = s0  # the first seed at or right of the column
        for j in range(pad, pad + n_h):
            while r < s1 and js[r] < j:
                r += 1
            if r < s1 and js[r] == j:
                continue  # a seed itself
            if not abs(fh[k, j]) >= thr32:
                continue
            has_l = r > s0 and j - js[r - 1] <= reach
            has_r = r < s1 and js[r] - j <= reach
            if not (has_l or has_r):
                continue
            if has_l and has_r:
                dl, dr = ds[r - 1], ds[r]
                if abs(dl - dr) > 1.0:
                    continue  # a depth edge between the seeds
                a = (j - js[r - 1]) / max(js[r] - js[r - 1], 1)
                g = dl + a * (dr - dl)
            elif has_l:
                g = ds[r - 1]
            else:
                g = ds[r]
            out_k[c] = k
            out_j[c] = j
            out_g[c] = g
            c += 1
    return c


def candidates_numpy(
    fh1: NDArray,
    thr: float,
    pad: int,
    n_h: int,
    k: NDArray,
    jj: NDArray,
    disp: NDArray,
    reach: int,
) -> tuple[NDArray, NDArray, NDArray]:
    """:func:`candidates` in numpy (its reference form): a dilation of the seeds along
    the lines, then each candidate's nearest seeds by searchsorted."""
    cand = np.abs(fh1) >= thr
    cand[:, :pad] = False
    cand[:, pad + n_h :] = False
    # only samples within ``reach`` columns of a seed on their line can be tried: a
    # dilation of the seeds along the lines cuts the candidates before the search
    seeded = np.zeros(fh1.shape, np.uint8)
    seeded[k, jj] = 1
    cand &= cv2.dilate(seeded, np.ones((1, 2 * reach + 1), np.uint8)).astype(bool)
    cand[k, jj] = False  # the seeds themselves
    ck, cj = np.nonzero(cand)
    if ck.size == 0:
        return ck, cj, np.zeros(0)
    usable, guess = _seed_guess(k, jj, disp, ck, cj, fh1.shape[1], reach)
    return ck[usable], cj[usable], guess[usable]


def smooth_profiles(
    t1: NDArray, k: NDArray, j: NDArray, *, w: int, stride: int, smooth: float
) -> NDArray:
    """Whether each profile of ``t1`` at (k[i], j[i]) (table columns) is smooth over its
    own length: its NCC with the profile of the same table half a profile radius
    (``w * stride // 2`` columns, at least 1) away, on either side that keeps the
    shifted profile inside the table, exceeds ``smooth``.

    Such a profile (a ramp, a slow swell: the plain walls of the rendered
    low_texture scene) correlates almost as well with image 2 a quarter of the
    profile away as at the truth, so a short search at a seed's disparity places it
    wherever the seed was: on low_texture 48 densified matches at NCC > 0.9 with
    themselves half a radius away, all 13-15 px off (docs/decisions/dense_mode.md).
    A profile neither side of which fits is not smooth.
    """
    k = np.asarray(k, dtype=np.int64)
    j = np.asarray(j, dtype=np.int64)
    if k.size == 0:
        return np.zeros(0, dtype=bool)
    lag = max(1, (w * stride) // 2)
    lo, hi = w * stride, t1.shape[1] - 1 - w * stride  # columns whose profile fits
    cols = j[:, None] + np.array([-lag, lag])
    fits = (cols >= lo) & (cols <= hi)
    S = np.empty(cols.shape)
    t = np.ascontiguousarray(t1, np.float32)
    ncc_offsets(t, t, k, j, np.clip(cols, lo, hi), int(w), int(stride), S)
    return np.any(fits & (S > smooth), axis=1)


def grown_from(
    k: NDArray, j: NDArray, seed_k: NDArray, seed_j: NDArray, flags: NDArray, reach: int
) -> NDArray:
    """Whether each densified match at (line k[i], column j[i]) grew from a flagged seed.

    :func:`densify` guesses a candidate's disparity from the nearest seed within
    ``reach`` columns on each side of it on its line (interpolated between the two
    where both exist); a match is placed by its seeds, so it carries their flag: True
    where either of those seeds has ``flags`` set. Columns of matches and seeds are
    counted alike (both table columns or both core columns).
    """
    k = np.asarray(k, dtype=np.int64)
    j = np.asarray(j, dtype=np.int64)
    seed_k = np.asarray(seed_k, dtype=np.int64)
    seed_j = np.asarray(seed_j, dtype=np.int64)
    flags = np.asarray(flags, dtype=bool)
    if k.size == 0 or not flags.any():
        return np.zeros(k.size, dtype=bool)
    span = int(max(j.max(), seed_j.max())) + 1
    order = np.lexsort((seed_j, seed_k))
    key = seed_k[order] * span + seed_j[order]
    right = np.searchsorted(key, k * span + j)  # the first seed at or right of the match
    left = right - 1
    li, ri = np.clip(left, 0, key.size - 1), np.clip(right, 0, key.size - 1)
    has_l = (left >= 0) & (seed_k[order][li] == k) & (j - seed_j[order][li] <= reach)
    has_r = (right < key.size) & (seed_k[order][ri] == k) & (seed_j[order][ri] - j <= reach)
    return (has_l & flags[order][li]) | (has_r & flags[order][ri])


def densify(
    tab: TableGeometry,
    fh1: NDArray,
    t1: NDArray,
    t2: NDArray,
    seeds: tuple[NDArray, NDArray, NDArray],
    thr: float,
    *,
    w: int,
    stride: int,
    min_score: float,
    reach: int,
    search: int = 2,
    flatness: float = 0.0,
    smooth: float = 1.0,
) -> tuple[NDArray, NDArray, NDArray, NDArray, int]:
    """Match the textured samples near each seed match at the seed's disparity.

    Parameters
    ----------
    tab : TableGeometry
    fh1 : ndarray, (n_theta, n_cols)
        df1/dh_1 on image 1's polar table (padded columns).
    t1, t2 : ndarray, (n_theta, n_cols)
        The (blurred) polar tables of f of both units.
    seeds : (k, j1, c2)
        The matches to grow from: line, image 1 column and sub-pixel image 2
        column, both counted from the first core column (as the robust rule
        returns them).
    thr : float
        Candidates have |df1/dh_1| >= thr.
    w, stride : int
        The profile of :class:`~omniflow.matching.robust.Descriptors`.
    min_score, flatness : float
        Acceptance, as for the robust rule.
    reach : int
        Candidates lie within this many columns of a seed on their line.
    search : int
        Columns searched either side of the seed's disparity.
    smooth : float
        Drop a match whose image-1 profile has an NCC above this with itself half a
        profile radius away (:func:`smooth_profiles`); >= 1 disables the test.

    Returns
    -------
    (k, j1, c2, score, n_tried) : the new matches (columns from the first
    core column, c2 sub-pixel), and the number of candidates tried.
    """
    pad, n_h = tab.pad, tab.n_h
    k, j1, c2 = (np.asarray(a) for a in seeds)
    jj = j1.astype(np.int64) + pad
    empty = (np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros(0), np.zeros(0), 0)
    if k.size == 0:
        return empty
    ck, cj, guess = candidates(fh1, thr, pad, n_h, k, jj, c2 - j1, reach)
    if ck.size == 0:
        return empty
    base = np.rint(guess).astype(np.intp)
    offs = np.arange(-search - 1, search + 2)  # one more each side for the parabola
    cols = np.clip(cj[:, None] + base[:, None] + offs, w * stride, t2.shape[1] - 1 - w * stride)
    # the NCC of the robust rule's profiles (Descriptors), summed from the tables
    S = np.empty(cols.shape)
    t1c, t2c = np.ascontiguousarray(t1, np.float32), np.ascontiguousarray(t2, np.float32)
    ck64, cj64, cols64 = ck.astype(np.int64), cj.astype(np.int64), cols.astype(np.int64)

    def rows(r0: int, r1: int) -> None:  # each share fills its own rows of S
        ncc_offsets(t1c, t2c, ck64[r0:r1], cj64[r0:r1], cols64[r0:r1], int(w), int(stride),
                    S[r0:r1])  # fmt: skip

    # two shares on omniflow.parallel's threads (the pool's is free by then when the
    # first pass densifies while the second pass has finished)
    map_tasks(rows, (0, ck.size // 2), (ck.size // 2, ck.size))
    b = np.argmax(S[:, 1:-1], axis=1) + 1
    r = np.arange(ck.size)
    s_m, s_0, s_p = S[r, b - 1], S[r, b], S[r, b + 1]
    off = parabola_offset(s_m, s_0, s_p)
    peak = s_0 + 0.25 * (s_p - s_m) * off  # the parabola's vertex value
    # a peak on the searched range's border may continue outside it: not a peak
    ok = (s_0 >= s_m) & (s_0 >= s_p) & (peak >= min_score)
    ok &= sharp_peak(peak, s_m, s_0, s_p, flatness)
    if smooth < 1.0:
        idx = np.nonzero(ok)[0]  # only the matches the other tests kept
        ok[idx[smooth_profiles(t1, ck[idx], cj[idx], w=w, stride=stride,
                               smooth=smooth)]] = False  # fmt: skip
    col2 = cj + base + offs[b] + off
    return (ck[ok], (cj - pad)[ok], (col2 - pad)[ok], np.clip(peak[ok], 0.0, 1.0),
            int(ck.size))  # fmt: skip
