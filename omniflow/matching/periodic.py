"""The periodic-alias test of the robust matcher: is there an alias a period away?

On a texture with a strong period along the radial lines, image 1's radial
profile at an edge recurs on its own line a period P away, and an alias P
(or 2P, ...) away in image 2 can score as well as the true match or better;
the uniqueness test, the left-right check and the consistency vote then all
confirm a consistent alias.

A recurrence in image 1 alone is not enough to drop a match: on low texture a
profile holding one step edge correlates with another lone step of its line,
and dropping every such match dropped nine in ten good matches on the
low-texture render (docs/decisions/matching.md).
:func:`not_periodic` therefore looks for the alias itself: where
image 1's profile recurs at lag L, the match is dropped only when image 2
holds the same profile at j_2 + L or j_2 - L (one of them is the truth if the
match is an alias). Where those columns lie in the disparity window but past
image 2's rim (or centre), the alias cannot be looked at; the match is then
dropped only when image 1 shows a period (recurrences at two lags at least).

Profiles are compared only at the edges of image 1 (local maxima of
|df/dh_1| along the line), as the matcher does.
"""

from __future__ import annotations

import itertools

import numpy as np
from numpy.typing import NDArray

from omniflow.matching.ncc import EdgeProfiles, alias_lines
from omniflow.matching.robust import Descriptors

__all__ = ["line_edges", "not_periodic", "not_periodic_numpy", "profiles"]


def profiles(table: NDArray, k: NDArray, j: NDArray, *, w: int, stride: int) -> NDArray:
    """Zero-mean, unit-norm radial profiles of a polar table; shape k.shape + (L,).

    The profile at (line k, column j) holds columns j - w stride .. j + w
    stride, every ``stride``-th, on line k: L = 2 w + 1 values, the matcher's descriptors
    (:class:`omniflow.matching.robust.Descriptors`, whose whole profile must
    lie inside the table).
    """
    return Descriptors(table, w, stride)(np.asarray(k), np.asarray(j))


def line_edges(edges: NDArray, k: NDArray) -> tuple[NDArray, NDArray]:
    """Columns of the True entries of ``edges`` (n_lines, n_cols) on lines ``k`` (M,).

    Returns (cols (M, c), exists (M, c)): each row's edge columns ascending,
    left-aligned, padded with column 0 and exists False.
    """
    ek, ej = np.nonzero(edges)
    counts = np.bincount(ek, minlength=edges.shape[0])
    start = np.concatenate([[0], np.cumsum(counts)])
    c = max(int(counts.max()) if counts.size else 0, 1)
    slot = np.arange(c)
    exists = slot[None, :] < counts[k][:, None]
    idx = np.minimum(start[k][:, None] + slot[None, :], max(ej.size - 1, 0))
    cols = np.where(exists, ej[idx] if ej.size else 0, 0)
    return cols, exists


def not_periodic(
    table: NDArray,
    edges: NDArray,
    k: NDArray,
    j: NDArray,
    *,
    w: int,
    stride: int,
    lags: tuple[int, int],
    alias_score: float,
    table2: NDArray | None = None,
    j2: NDArray | None = None,
    window: tuple[int, int] | None = None,
    alias2_score: float = 0.9,
    confirm_score: float = 0.8,
    columns2: tuple[int, int] | None = None,
    threads: int = 1,
    per_range=None,
) -> NDArray:
    """Whether each match's image-1 profile does NOT recur with an alias; bool (M,).

    Compiled (:func:`omniflow.matching.ncc.alias_lines`): each match walks the
    edges of its line outward, and image 2 is looked at only where image 1's
    profile recurs. :func:`not_periodic_numpy` is the same rule in numpy.

    Parameters
    ----------
    table : ndarray, shape (n_lines, n_cols)
        Image 1's polar table (as matched: blurred across the lines).
    edges : ndarray of bool, same shape
        Image 1's edges (the profiles compared with).
    k, j : ndarray of int, shape (M,)
        Line and table column of each match's edge.
    w, stride : int
        The profile (:func:`profiles`).
    lags : (int, int)
        Columns: a recurrence counts at lags[0] <= |lag| <= lags[1] (half the
        profile to the disparity window's width: an alias further away cannot
        be inside the window).
    alias_score : float
        A recurrence: NCC above this after the NCC fell below 0 at a smaller
        lag on the same side (a smooth ramp correlates with itself at every
        lag without falling; it is left to the other tests). >= 1 disables
        the test (all True).
    table2, j2, window : optional
        Image 2's polar table (same columns), each match's image-2 column
        (sub-pixel) and the disparity window (j2 - j in [window[0],
        window[1]]). Given, a recurrence at lag L drops the match only when
        image 2 holds the alias too: NCC of the image-1 profile with image
        2's at j2 + L or j2 - L (+-1 column, inside the window) above
        ``alias2_score`` (the truth is a period away from an alias on either
        side).
        Not given, any recurrence drops the match.
    alias2_score : float
        See ``table2``.
    columns2 : (int, int), optional
        Image 2's table columns whose whole profile lies inside the image
        (between the centre and the rim); default: the whole table.
    confirm_score : float
        Where image 2 cannot be looked at, a match is dropped only when its
        image-1 profile recurs at two lags at least (one above
        ``alias_score``, the other above this): a period, not a lone
        recurrence.
    threads, per_range : optional
        With ``threads`` > 1 the matches are split into ranges run by
        ``per_range`` (:func:`omniflow.parallel.map_tasks`); the result does
        not depend on it.
    """
    reach = w * stride
    if np.shape(edges) != np.shape(table) or np.any(
        edges[:, :reach] | edges[:, edges.shape[1] - reach :]
    ):
        raise ValueError("not_periodic: every edge's profile must lie inside the table")
    use2 = table2 is not None and j2 is not None and window is not None
    return alias_lines(
        EdgeProfiles.from_mask(table, edges, w, stride), k, j, lags=lags,
        alias_score=alias_score, t2=table2 if use2 else None, j2=j2 if use2 else None,
        window=window if use2 else (0, 0), alias2_score=alias2_score,
        confirm_score=confirm_score, columns2=columns2, threads=threads, per_range=per_range,
    )  # fmt: skip


def not_periodic_numpy(
    table: NDArray,
    edges: NDArray,
    k: NDArray,
    j: NDArray,
    *,
    w: int,
    stride: int,
    lags: tuple[int, int],
    alias_score: float,
    table2: NDArray | None = None,
    j2: NDArray | None = None,
    window: tuple[int, int] | None = None,
    alias2_score: float = 0.9,
    confirm_score: float = 0.8,
    columns2: tuple[int, int] | None = None,
    desc1: Descriptors | None = None,
    desc2: Descriptors | None = None,
) -> NDArray:
    """:func:`not_periodic` in numpy (its reference form): every match's NCC with
    every edge of its line by one batched float32 product per line, then the
    walk outward as cumulative minima. The same decisions as :func:`not_periodic`
    but where an NCC lies within a float32 ulp or two of a threshold (the
    products sum in a different order).

    Parameters
    ----------
    table, edges, k, j, w, stride, lags, alias_score, table2, j2, window, \
    alias2_score, confirm_score, columns2
        As :func:`not_periodic`.
    desc1, desc2 : Descriptors, optional
        The matcher's descriptors of ``table`` and ``table2`` with the same
        (w, stride), if it has them (saves building them again).
    """
    m = np.asarray(k).size
    if alias_score >= 1.0 or m == 0:
        return np.ones(m, dtype=bool)
    k = np.asarray(k, dtype=np.intp)
    j = np.asarray(j, dtype=np.intp)
    desc1 = Descriptors(table, w, stride) if desc1 is None else desc1
    d1 = desc1(k, j)  # (M, L)
    # NCC of each match's profile with every edge of its line: the matches and
    # the edges laid out per line, one batched product per line
    used, row = np.unique(k, return_inverse=True)  # the lines with matches
    ecols, eexists = line_edges(edges, used)  # (lines used, c)
    safe = np.where(eexists, ecols, w * stride)  # padding slots: any whole profile
    P = desc1(np.broadcast_to(used[:, None], ecols.shape), safe)
    P[~eexists] = 0.0
    order = np.argsort(row, kind="stable")
    counts = np.bincount(row, minlength=used.size)
    slot = np.empty(m, dtype=np.intp)
    slot[order] = np.arange(m) - np.concatenate([[0], np.cumsum(counts)[:-1]])[row[order]]
    Dm = np.zeros((used.size, int(counts.max()), d1.shape[1]), dtype=np.float32)
    Dm[row, slot] = d1
    A = np.matmul(Dm, P.transpose(0, 2, 1))[row, slot].astype(float)  # (M, c)
    cols, exists = ecols[row], eexists[row]
    lag = cols - j[:, None]
    A[~exists | (np.abs(lag) > lags[1])] = np.nan
    fallen = np.zeros(A.shape, dtype=bool)  # the NCC fell below 0 nearer j, that side
    for side in (1, -1):
        order = slice(None) if side > 0 else slice(None, None, -1)  # walk outward from j
        a = np.where(side * lag > 0, A, np.nan)[:, order]
        low = np.fmin.accumulate(np.where(np.isnan(a), np.inf, a), axis=1)
        f = np.zeros(a.shape, dtype=bool)
        f[:, 1:] = low[:, :-1] < 0.0
        fallen |= f[:, order]
    with np.errstate(invalid="ignore"):
        rec = fallen & (np.abs(lag) >= lags[0]) & (A > alias_score)  # (M, c)
    if table2 is None or j2 is None or window is None:
        return ~np.any(rec, axis=1)
    # image 2 at the recurrence's lag from the match: is the alias there?
    mi, ci = np.nonzero(rec)
    if mi.size == 0:
        return np.ones(m, dtype=bool)
    at = np.rint(np.asarray(j2, dtype=float)[mi]).astype(np.intp)
    best = np.full(mi.size, -np.inf)
    lo_col, hi_col = w * stride, table2.shape[1] - 1 - w * stride
    if columns2 is not None:
        lo_col, hi_col = max(lo_col, columns2[0]), min(hi_col, columns2[1])
    desc2 = Descriptors(table2, w, stride) if desc2 is None else desc2
    hidden = np.zeros(mi.size, dtype=bool)  # in the window, but no whole profile there
    for sign, dj in itertools.product((1, -1), (-1, 0, 1)):
        c2 = at + sign * lag[mi, ci] + dj
        in_window = (c2 - j[mi] >= window[0]) & (c2 - j[mi] <= window[1])
        usable = (c2 >= lo_col) & (c2 <= hi_col)
        hidden |= in_window & ~usable
        p2 = desc2(k[mi], np.clip(c2, lo_col, hi_col))
        ncc = np.einsum("nl,nl->n", d1[mi], p2)
        best = np.where(in_window & usable, np.maximum(best, ncc), best)
    # a period away lies in the window but past the rim (or the centre): the
    # truth may be there, unseen, and the match an alias; dropped where image 1
    # shows a period (recurrences at two lags at least)
    with np.errstate(invalid="ignore"):
        second = fallen & (np.abs(lag) >= lags[0]) & (A > confirm_score)
    period = np.count_nonzero(second, axis=1) >= 2
    hidden &= period[mi]
    alias = np.zeros(m, dtype=bool)
    alias[mi[(best > alias2_score) | hidden]] = True
    return ~alias
