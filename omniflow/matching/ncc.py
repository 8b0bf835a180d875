"""Compiled kernel (Numba) of the robust matcher's edge-to-edge NCC search.

:func:`robust_lines` runs the rule of :func:`omniflow.matching.robust.match_robust`
line by line: the edges of both polar tables, the NCC of each significant
edge of image 1 with the edges of image 2 inside its disparity window only,
the best and second-best candidates, the polarity, uniqueness,
periodic-alias and left-right tests, and the NCC at the
neighbouring columns for the sub-pixel step. In numpy the same rule formed
a dense (lines, edges, edges) NCC array by batched products and then masked
everything outside the window; here nothing outside the window is scored.
:class:`LineSearch` is the same search in ranges of lines a caller schedules,
optionally with each line's sub-pixel step and the periodic-alias test
(:func:`alias_lines`, the rule of :func:`omniflow.matching.periodic.not_periodic`)
in the same call, reusing the image-1 profiles the search made
(:class:`EdgeProfiles`).

The profiles are those of :class:`omniflow.matching.robust.Descriptors`,
value for value: each window's sum and sum of squares are summed in double
and rounded to float32, as OpenCV's box filter does for float32 images, and
the profile is (x - mean) * inv_norm in float32. Only the NCC's own sum
differs: one dot product summed in double here, a float32 BLAS product in
numpy, so an NCC can differ in its last float32 bit or two.

The kernel compiles on first use; ``cache=True`` keeps the machine code
between runs where the package folder (or Numba's user cache) is writable.
"""

from __future__ import annotations

import itertools
import math

import numba
import numpy as np
from numpy.typing import NDArray

__all__ = ["EdgeProfiles", "LineSearch", "alias_lines", "profiles", "robust_lines"]


@numba.njit(cache=True, nogil=True)
def _edges(a, low, pad, n_h, out):  # pragma: no cover - compiled
    """Columns j in [pad, pad + n_h) where |f_h| peaks along the line and exceeds ``low``
    (tables.local_maxima: a plateau counts once, at its right end); returns the count."""
    n = 0
    prev = abs(a[pad - 1])
    cur = abs(a[pad])
    for j in range(pad, pad + n_h):
        nxt = abs(a[j + 1])
        out[n] = j  # kept only when n moves on (no branch to mispredict)
        n += (cur >= prev) & (cur > nxt) & (cur > low)
        prev = cur
        cur = nxt
    return n


@numba.njit(cache=True, nogil=True)
def _profile(t, k, j, w, stride, out, r):  # pragma: no cover - compiled
    """The zero-mean, unit-norm profile of table ``t`` at (line k, column j) into ``out[r]``.

    The sum and sum of float32 squares are summed in double and rounded to float32:
    OpenCV's box filter of a float32 image (Descriptors' mean and norm) sums in double too.
    """
    row = k % t.shape[0]  # an index, not a view: views of the shared tables
    m = 2 * w + 1  # would count references atomically, and the threads would queue on them
    j0 = j - w * stride
    s1 = 0.0
    s2 = 0.0
    for q in range(m):
        x = t[row, j0 + q * stride]
        out[r, q] = x
        s1 += x
        s2 += x * x
    i = m
    s1f = np.float32(s1)
    s2f = np.float32(s2)
    mean = s1f / np.float32(i)
    var = max(s2f - s1f * mean, np.float32(0.0))
    # sqrt in double, then rounded: the float32 square root, correctly rounded
    sd = max(np.float32(math.sqrt(var)), np.float32(1e-12))
    inv = np.float32(1.0) / sd
    for q in range(i):
        out[r, q] = (out[r, q] - mean) * inv


@numba.njit(cache=True, nogil=True)
def profiles(t, k, j, w, stride, out):  # pragma: no cover - compiled
    """The profiles of table ``t`` at (k[i], j[i]) into out[i] (see :func:`_profile`;
    every window must lie inside the table)."""
    for i in range(k.size):
        _profile(t, k[i], j[i], w, stride, out, i)


# reassociation lets the compiler split the double sum into vector lanes (the
# float32 products are exact in double, so only the last bits of the sum move)
@numba.njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def _dot(a, i, b, j):  # pragma: no cover - compiled
    """a[i] . b[j], summed in double (rows by index: no views, whose reference counts
    are atomic operations)."""
    s = 0.0
    for q in range(a.shape[1]):
        s += a[i, q] * b[j, q]
    return np.float32(s)


@numba.njit(cache=True, nogil=True)
def _all_edges(fh1, fh2, low, pad, n_h, cols1, n1, cols2, n2):  # pragma: no cover - compiled
    for k in range(fh1.shape[0]):
        n1[k] = _edges(fh1[k], low, pad, n_h, cols1[k])
        n2[k] = _edges(fh2[k], low, pad, n_h, cols2[k])


@numba.njit(cache=True, nogil=True)
def _robust_lines(t1, t2, fh1, fh2, cols1, n1, cols2, n2, k0, k1, thr, lo, hi, w, stride,
                  floor, uniqueness, alias_score, tests, left_right,
                  ok, j2_out, s_out, n_sig, d1, have1, post, min_score, flatness, pad,
                  periodic, a_score, use2, a_score2, a_confirm, a_lo, a_hi, fin, c2_out,
                  score_out):  # pragma: no cover - compiled  # fmt: skip
    n_cols = t1.shape[1]
    length = 2 * w + 1
    do_uniqueness = tests[0]
    lag_lo = (w * stride) // 2  # the alias test's shortest lag
    lag_hi = hi - lo
    lo_col = w * stride
    hi_col = n_cols - 1 - w * stride
    one = np.float32(1.0)
    # scratch for one line at a time, sized for the longest line of the range
    most1 = max(n1[k0:k1].max(), 1)
    most2 = max(n2[k0:k1].max(), 1)
    per_line = d1.shape[0] // t1.shape[0]  # rows of d1 per line
    d2 = np.empty((most2, length), dtype=np.float32)
    ncc = np.empty((most1, most2), dtype=np.float32)
    scored = np.empty((most1, most2), dtype=np.bool_)
    p = np.empty((1, length), dtype=np.float32)
    own = np.empty((1, length), dtype=np.float32)
    for k in range(k0, k1):
        c1 = cols1[k, : n1[k]]
        c2 = cols2[k, : n2[k]]
        # image 1's profiles are made when first read (the tests of the kept matches
        # read some non-significant edges, most are never read), into rows
        # base .. base + n1[k] of d1, kept for the alias test; image 2's all are
        base = k * per_line
        for m in range(c2.size):
            _profile(t2, k, c2[m], w, stride, d2, m)
        # NCC of edge pairs (image 1, image 2) once scored: the left-right check
        # rereads most of them
        scored[: c1.size, : c2.size] = False
        count = 0
        first = 0  # first edge of image 2 at or after the window's start (columns ascend)
        for i in range(c1.size):
            j1 = c1[i]
            g1 = fh1[k, j1]
            if not abs(g1) > thr:
                continue
            count += 1
            while first < c2.size and c2[first] < j1 + lo:
                first += 1
            stop = first
            while stop < c2.size and c2[stop] <= j1 + hi:
                stop += 1
            if stop == first:
                continue
            if not have1[base + i]:  # made once, when first read
                _profile(t1, k, c1[i], w, stride, d1, base + i)
                have1[base + i] = True
            b = first
            for m in range(first, stop):
                ncc[i, m] = _dot(d1, base + i, d2, m)
                scored[i, m] = True
                if ncc[i, m] > ncc[i, b]:
                    b = m
            best = ncc[i, b]
            if not best >= floor:
                continue
            if (g1 > 0) != (fh2[k, c2[b]] > 0):
                continue
            if do_uniqueness:
                second = np.float32(-1.0)
                for m in range(first, stop):
                    if m != b and ncc[i, m] > second:
                        second = ncc[i, m]
                if not (one - best) <= uniqueness * (one - second):
                    continue
            if tests[1]:
                # walk outward from j1 on each side: the profile recurs when its NCC
                # exceeds alias_score at a lag >= lag_lo after falling below 0 nearer in
                recurs = False
                for direction in (1, -1):
                    low_so_far = np.float32(np.inf)
                    m = i + direction
                    while 0 <= m < c1.size and not recurs:
                        lag = abs(c1[m] - j1)
                        if lag > lag_hi:
                            break
                        if not have1[base + m]:  # made once, when first read
                            _profile(t1, k, c1[m], w, stride, d1, base + m)
                            have1[base + m] = True
                        a = _dot(d1, base + i, d1, base + m)
                        if low_so_far < 0.0 and lag >= lag_lo and a > alias_score:
                            recurs = True
                        if a < low_so_far:
                            low_so_far = a
                        m += direction
                if recurs:
                    continue
            if left_right:
                j2 = c2[b]
                back = -1
                back_s = np.float32(0.0)
                for m in range(c1.size):
                    if c1[m] >= j2 - hi and c1[m] <= j2 - lo:
                        if not scored[m, b]:
                            if not have1[base + m]:  # made once, when first read
                                _profile(t1, k, c1[m], w, stride, d1, base + m)
                                have1[base + m] = True
                            ncc[m, b] = _dot(d1, base + m, d2, b)
                            scored[m, b] = True
                        if back < 0 or ncc[m, b] > back_s:
                            back, back_s = m, ncc[m, b]
                if back != i:
                    continue
            # the NCC at columns j2 - 2 .. j2 + 2 for the sub-pixel step
            j2 = c2[b]
            for q in range(5):
                if q == 2:
                    s_out[k, j1, q] = best
                    continue
                jj = min(max(j2 + q - 2, lo_col), hi_col)
                _profile(t2, k, jj, w, stride, p, 0)
                s_out[k, j1, q] = _dot(d1, base + i, p, 0)
            ok[k, j1] = True
            j2_out[k, j1] = j2
        n_sig[k] = count
        if post:
            _refine_line(t1, t2, k, c1, base, d1, have1, ok, j2_out, s_out, min_score,
                         flatness, pad, periodic, w, stride, lag_lo, lag_hi, a_score,
                         use2, lo, hi, a_score2, a_confirm, a_lo, a_hi, own, p, fin, c2_out,
                         score_out)  # fmt: skip


@numba.njit(cache=True, nogil=True)
def _refine_line(t1, t2, k, c1, base, d1, have1, ok, j2_out, s_out, min_score, flatness, pad,
                 periodic, w, stride, lag_lo, lag_hi, a_score, use2, lo, hi, a_score2,
                 a_confirm, a_lo, a_hi, own, p, fin, c2_out,
                 score_out):  # pragma: no cover - compiled  # fmt: skip
    """The sub-pixel step of :meth:`omniflow.matching.robust.RobustSearch.finish` and the
    periodic-alias test (:func:`_alias_at`) on the matches of line k, in float32 as
    numpy takes them there (a float32 array with a Python float stays float32):
    ``fin`` marks the kept, ``c2_out`` their sub-pixel image-2 column counted from
    the first core column, ``score_out`` the NCC at the vertex, clipped to [0, 1]."""
    f32 = np.float32
    zero, one, two, half, quarter = f32(0.0), f32(1.0), f32(2.0), f32(0.5), f32(0.25)
    tiny = f32(1e-12)
    for i in range(c1.size):
        j1 = c1[i]
        if not ok[k, j1]:
            continue
        jj2 = j2_out[k, j1]
        sm, s0, sp = s_out[k, j1, 1], s_out[k, j1, 2], s_out[k, j1, 3]
        # move one column if a neighbour scores higher (RobustSearch.finish)
        if sp > s0 and sp >= sm:
            sm, s0, sp = s0, max(sp, sm), s_out[k, j1, 4]
            jj2 += 1
        elif sm > s0:
            sm, s0, sp = s_out[k, j1, 0], max(sp, sm), s0
            jj2 -= 1
        den = sm - two * s0 + sp  # tables.parabola_offset
        off = half * (sm - sp) / den if abs(den) > tiny else zero
        off = min(max(off, -one), one)
        peak = s0 + quarter * (sp - sm) * off  # the parabola's vertex value
        keep = peak >= min_score
        if flatness > 0:  # tables.sharp_peak
            keep = keep and (one - peak) <= flatness * (two * s0 - sm - sp)
        if keep and periodic:
            at = np.int64(np.rint(np.float64(jj2) + np.float64(off)))
            keep = not _alias_at(
                t1, t2, k, j1, at, c1, c1.size, d1, have1, base, own, p, w, stride, lag_lo,
                lag_hi, a_score, use2, lo, hi, a_score2, a_confirm, a_lo, a_hi,
            )  # fmt: skip
        fin[k, j1] = keep
        c2_out[k, j1] = np.float64(jj2) + np.float64(off) - pad
        score_out[k, j1] = min(max(peak, zero), one)


class EdgeProfiles:
    """Image 1's edges per line and their profiles, made when first asked for.

    ``cols[k, :n[k]]``: the edge columns of line k, ascending; row
    k * per_line + m of ``d`` holds the profile (:func:`_profile`, with
    ``w``, ``stride``) of edge m of line k once ``have`` marks it.
    :class:`LineSearch` fills it as it searches; :func:`alias_lines` reads
    what is there and makes the rest.
    """

    def __init__(self, t: NDArray, cols: NDArray, n: NDArray, d: NDArray, have: NDArray,
                 w: int, stride: int):  # fmt: skip
        self.t, self.cols, self.n, self.d, self.have = t, cols, n, d, have
        self.w, self.stride = w, stride

    @classmethod
    def from_mask(cls, t: NDArray, edges: NDArray, w: int, stride: int):
        """The edges marked True in ``edges`` (same shape as the table ``t``)."""
        t = np.ascontiguousarray(t, dtype=np.float32)
        ek, ej = np.nonzero(edges)
        n = np.bincount(ek, minlength=t.shape[0]).astype(np.int64)
        per_line = max(int(n.max()) if n.size else 0, 1)
        cols = np.zeros((t.shape[0], per_line), dtype=np.int64)
        start = np.concatenate([[0], np.cumsum(n)[:-1]])
        cols[ek, np.arange(ek.size) - start[ek]] = ej
        d = np.empty((t.shape[0] * per_line, 2 * w + 1), dtype=np.float32)
        return cls(t, cols, n, d, np.zeros(t.shape[0] * per_line, dtype=bool), w, stride)


class LineSearch:
    """The compiled search of :func:`robust_lines`, in pieces a caller can schedule.

    Made with the arguments of :func:`robust_lines` (its edges are found
    here); :meth:`run` searches lines k0 .. k1 - 1 (ranges are independent:
    any order, any thread, the kernel drops the GIL); :meth:`result` returns
    what :func:`robust_lines` returns once every line has been run.

    With ``min_score`` given, each line's matches also take the sub-pixel
    step of :meth:`omniflow.matching.robust.RobustSearch.finish` (``min_score``,
    ``flatness``) and, with ``periodic`` given (the keyword arguments of
    :func:`alias_lines` from ``lags`` on, ``t2`` and ``j2`` excepted; None
    for no image 2: ``{"image2": False, ...}``), the periodic-alias test, in
    the same kernel call; :meth:`refined` returns the kept matches.
    """

    def __init__(
        self, t1: NDArray, t2: NDArray, fh1: NDArray, fh2: NDArray, *, low: float, thr: float,
        pad: int, n_h: int, win: tuple[int, int], w: int, stride: int,
        floor: float, uniqueness: float, alias_score: float,
        left_right: bool, min_score: float | None = None, flatness: float = 0.0,
        periodic: dict | None = None,
    ):  # fmt: skip
        self.n_theta, n_cols = t1.shape
        n_theta = self.n_theta
        self.ok = np.zeros((n_theta, n_cols), dtype=bool)
        # read only where ok: left unset elsewhere (no pages written for them)
        self.j2 = np.empty((n_theta, n_cols), dtype=np.int64)
        self.s = np.empty((n_theta, n_cols, 5), dtype=np.float32)
        self.n_sig = np.zeros(n_theta, dtype=np.int64)
        f32 = np.float32
        t1, t2, fh1, fh2 = (np.ascontiguousarray(a, dtype=f32) for a in (t1, t2, fh1, fh2))
        cols1 = np.empty((n_theta, n_h), dtype=np.int64)
        cols2 = np.empty((n_theta, n_h), dtype=np.int64)
        n1 = np.zeros(n_theta, dtype=np.int64)
        n2 = np.zeros(n_theta, dtype=np.int64)
        _all_edges(fh1, fh2, f32(low), int(pad), int(n_h), cols1, n1, cols2, n2)
        # numpy's rule took the uniqueness test only when some line has two edges in image 2
        tests = (uniqueness < 1.0 and int(n2.max()) > 1, alias_score < 1.0)
        # image 1's edges and their profiles, those the search made (kept for the alias test)
        per_line = max(int(n1.max()), 1)
        self.edges1 = EdgeProfiles(
            t1, cols1, n1, np.empty((n_theta * per_line, 2 * w + 1), f32),
            np.zeros(n_theta * per_line, dtype=bool), int(w), int(stride),
        )  # fmt: skip
        self.pad = int(pad)
        post = min_score is not None
        shape = (n_theta, n_cols) if post else (1, 1)
        self.fin = np.zeros(shape, dtype=bool)
        self.c2 = np.empty(shape, dtype=np.float64)  # read only where fin
        self.score = np.empty(shape, dtype=np.float32)
        a = {} if periodic is None else periodic
        use2 = a.get("image2", True)
        reach = w * stride
        a_lo, a_hi = reach, n_cols - 1 - reach  # whole profiles in image 2
        if a.get("columns2") is not None:
            a_lo, a_hi = max(a_lo, a["columns2"][0]), min(a_hi, a["columns2"][1])
        self._args = (
            t1, t2, fh1, fh2, cols1, n1, cols2, n2, f32(thr), int(win[0]), int(win[1]), int(w),
            int(stride), f32(floor), f32(uniqueness), f32(alias_score), tests,
            bool(left_right), self.ok, self.j2, self.s, self.n_sig,
            self.edges1.d, self.edges1.have, post,
            # numpy compares a float32 array with a Python float in float32
            f32(min_score if post else 0.0), f32(flatness), self.pad,
            periodic is not None and a.get("alias_score", 1.0) < 1.0,
            float(a.get("alias_score", 1.0)), bool(use2), float(a.get("alias2_score", 0.9)),
            float(a.get("confirm_score", 0.8)), int(a_lo), int(a_hi), self.fin, self.c2,
            self.score,
        )  # fmt: skip

    def ranges(self, threads: int) -> list[tuple[int, int]]:
        """The lines in 4 ``threads`` ranges (a few per thread: a thread busy elsewhere
        delays only one), or one range on one thread or with few lines."""
        chunks = 4 * threads
        if threads < 2 or self.n_theta < 2 * chunks:
            return [(0, self.n_theta)]
        cuts = np.linspace(0, self.n_theta, chunks + 1).astype(int).tolist()
        return list(itertools.pairwise(cuts))

    def run(self, k0: int, k1: int) -> None:
        """Search lines k0 .. k1 - 1."""
        a = self._args
        _robust_lines(*a[:8], k0, k1, *a[8:])

    def result(self) -> tuple[NDArray, NDArray, NDArray, int]:
        """(ok, j2, s, n_sig) of :func:`robust_lines`."""
        return self.ok, self.j2, self.s, int(self.n_sig.sum())

    def refined(self) -> tuple[NDArray, NDArray, NDArray, NDArray, int]:
        """With ``min_score`` given: (k, j1, c2, score, n_sig), the kept matches by line
        then column: line, image-1 and sub-pixel image-2 columns counted from the first
        core column, NCC at the vertex (float32, clipped to [0, 1])."""
        ks, jj = np.nonzero(self.fin)
        return ks, jj - self.pad, self.c2[ks, jj], self.score[ks, jj], int(self.n_sig.sum())


def robust_lines(
    t1: NDArray, t2: NDArray, fh1: NDArray, fh2: NDArray, *, low: float, thr: float,
    pad: int, n_h: int, win: tuple[int, int], w: int, stride: int,
    floor: float, uniqueness: float, alias_score: float,
    left_right: bool, threads: int = 1, per_range=None,
) -> tuple[NDArray, NDArray, NDArray, int]:  # fmt: skip
    """The matches of :func:`~omniflow.matching.robust.match_robust` before its sub-pixel step.

    ``t1``, ``t2``: the polar tables (float32, lines x columns); ``fh1``,
    ``fh2``: their radial derivatives; ``low``: the candidate floor
    (candidate_fraction * thr); ``win``: the disparity window in columns;
    the other arguments as in match_robust (``floor``: the whole-column NCC
    floor). The thresholds are compared in float32, as numpy compares a
    float32 array with a Python float.

    Returns (ok, j2, s, n_sig): ok (lines, columns) bool marks the kept
    significant edges of image 1 by their column, j2 the column of their
    match in image 2, s (lines, columns, 5) float32 the NCC at columns
    j2 - 2 .. j2 + 2 (each clipped to the table's profile range; s[..., 2]
    is the best whole-column NCC), and n_sig the significant edges tried.
    With ``threads`` > 1 the lines are split into 4 ``threads`` ranges, run by
    ``per_range(fn, (k0, k1), ...)`` (:func:`omniflow.parallel.map_tasks`);
    :class:`LineSearch` is the same search in pieces.
    """
    search = LineSearch(
        t1, t2, fh1, fh2, low=low, thr=thr, pad=pad, n_h=n_h, win=win, w=w, stride=stride,
        floor=floor, uniqueness=uniqueness, alias_score=alias_score,
        left_right=left_right,
    )  # fmt: skip
    ranges = search.ranges(threads)
    if len(ranges) > 1:
        per_range(search.run, *ranges)
    else:
        search.run(*ranges[0])
    return search.result()


@numba.njit(cache=True, nogil=True)
def _alias_at(t1, t2, line, ji, at, c, n_e, d, have, base, own, p, w, stride, lag_lo,
              lag_hi, alias_score, use2, win_lo, win_hi, alias2, confirm, lo_col,
              hi_col):  # pragma: no cover - compiled  # fmt: skip
    """Whether the match at (line, column ji; image 2's column ``at``) is a periodic
    alias (:func:`alias_lines`); ``c[:n_e]`` the line's edges, their profiles in rows
    base + m of ``d`` (made here where ``have`` is False); ``own``, ``p``: scratch."""
    length = d.shape[1]
    first_right = 0  # the first edge right of the match
    while first_right < n_e and c[first_right] <= ji:
        first_right += 1
    at_edge = first_right > 0 and c[first_right - 1] == ji
    if at_edge:  # the search made it, most likely
        r = base + first_right - 1
        if not have[r]:
            _profile(t1, line, ji, w, stride, d, r)
            have[r] = True
        for q in range(length):
            own[0, q] = d[r, q]
    else:
        _profile(t1, line, ji, w, stride, own, 0)
    alias = False
    hidden = False  # a recurrence whose alias lies in the window but past image 2's rim
    n_confirm = 0  # recurrences above ``confirm`` (a period: two at least)
    for direction in (1, -1):
        # walk outward from j: the NCC must fall below 0 before a recurrence counts
        low = np.inf
        m = first_right if direction > 0 else first_right - 1 - at_edge
        while 0 <= m < n_e and not alias:
            lag = c[m] - ji
            if abs(lag) > lag_hi:
                break
            r = base + m
            if not have[r]:
                _profile(t1, line, c[m], w, stride, d, r)
                have[r] = True
            a = np.float64(_dot(own, 0, d, r))
            if low < 0.0 and abs(lag) >= lag_lo:
                if a > confirm:
                    n_confirm += 1
                if a > alias_score:
                    if not use2:
                        alias = True
                    else:
                        # image 2 a recurrence away from the match (+-1 column, in the
                        # window): does it hold the alias?
                        best = -np.inf
                        for sign in (1, -1):
                            for dj in (-1, 0, 1):
                                c2 = at + sign * lag + dj
                                if c2 - ji < win_lo or c2 - ji > win_hi:
                                    continue
                                if c2 < lo_col or c2 > hi_col:
                                    hidden = True
                                    continue
                                _profile(t2, line, c2, w, stride, p, 0)
                                s = np.float64(_dot(own, 0, p, 0))
                                if s > best:
                                    best = s
                        if best > alias2:
                            alias = True
            if a < low:
                low = a
            m += direction
    return alias or (hidden and n_confirm >= 2)


@numba.njit(cache=True, nogil=True)
def _alias_matches(t1, cols, n, d, have, k, j, j2, i0, i1, w, stride, lag_lo, lag_hi,
                   alias_score, t2, use2, win_lo, win_hi, alias2, confirm, lo_col, hi_col,
                   keep):  # pragma: no cover - compiled  # fmt: skip
    """:func:`alias_lines` for the matches i0 .. i1 - 1 (sorted by line)."""
    length = d.shape[1]
    per_line = d.shape[0] // t1.shape[0]
    own = np.empty((1, length), dtype=np.float32)  # the match's profile
    p = np.empty((1, length), dtype=np.float32)  # image 2's, a recurrence away
    for i in range(i0, i1):
        line = k[i]
        at = np.int64(np.rint(j2[i])) if use2 else np.int64(0)
        keep[i] = not _alias_at(
            t1, t2, line, j[i], at, cols[line], n[line], d, have, line * per_line, own, p, w,
            stride, lag_lo, lag_hi, alias_score, use2, win_lo, win_hi, alias2, confirm,
            lo_col, hi_col,
        )  # fmt: skip


def alias_lines(
    edges1: EdgeProfiles, k: NDArray, j: NDArray, *, lags: tuple[int, int], alias_score: float,
    t2: NDArray | None = None, j2: NDArray | None = None, window: tuple[int, int] = (0, 0),
    alias2_score: float = 0.9, confirm_score: float = 0.8,
    columns2: tuple[int, int] | None = None, threads: int = 1, per_range=None,
) -> NDArray:  # fmt: skip
    """The periodic-alias test of :func:`omniflow.matching.periodic.not_periodic`, compiled.

    ``edges1``: image 1's table, edges and their profiles (those already made
    are reused, the others are made and kept); the other arguments as
    not_periodic's (``t2``: ``table2``); ``t2`` or ``j2`` None: any
    recurrence drops the match. For each match the edges of its line are
    walked outward from it on each side, up to ``lags[1]``; image 2 is looked
    at only where image 1's profile recurs. The NCCs are summed in double and
    rounded to float32 (the matcher's :func:`_dot`). Returns keep, bool (M,),
    in the matches' order. With ``threads`` > 1 the matches are split into
    ``threads`` ranges of whole lines run by ``per_range(fn, (i0, i1), ...)``
    (:func:`omniflow.parallel.map_tasks`).
    """
    k = np.asarray(k, dtype=np.int64)
    j = np.asarray(j, dtype=np.int64)
    m = k.size
    keep = np.ones(m, dtype=bool)
    if alias_score >= 1.0 or m == 0:
        return keep
    e = edges1
    w, stride = e.w, e.stride
    order = np.argsort(k, kind="stable")  # one line's matches together
    ks, js = k[order], j[order]
    use2 = t2 is not None and j2 is not None
    j2s = np.asarray(j2, dtype=np.float64)[order] if use2 else np.zeros(m)
    t1 = e.t
    t2 = np.ascontiguousarray(t2, dtype=np.float32) if use2 else t1
    reach, n_lines, n_cols = w * stride, t1.shape[0], t1.shape[1]
    if k.min() < 0 or k.max() >= n_lines or j.min() < reach or j.max() >= n_cols - reach:
        raise ValueError("alias_lines: every match's profile must lie inside the table")
    lo_col, hi_col = reach, t2.shape[1] - 1 - reach  # whole profiles in image 2
    if columns2 is not None:
        lo_col, hi_col = max(lo_col, columns2[0]), min(hi_col, columns2[1])
    out = np.ones(m, dtype=bool)

    def run(i0: int, i1: int) -> None:
        _alias_matches(
            t1, e.cols, e.n, e.d, e.have, ks, js, j2s, i0, i1, int(w), int(stride),
            int(lags[0]), int(lags[1]), float(alias_score), t2, use2, int(window[0]),
            int(window[1]), float(alias2_score), float(confirm_score), int(lo_col),
            int(hi_col), out,
        )  # fmt: skip

    if threads > 1 and per_range is not None and m >= 64:
        # whole lines per range: a line's edge profiles are made by one thread
        cuts = np.searchsorted(ks, ks[np.linspace(0, m - 1, threads + 1).astype(int)[1:-1]])
        cuts = np.unique(np.concatenate([[0], cuts, [m]])).tolist()
        per_range(run, *itertools.pairwise(cuts))
    else:
        run(0, m)
    keep[order] = out
    return keep
