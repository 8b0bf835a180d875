"""The disparity consistency vote of the robust matcher."""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

__all__ = ["consistent", "consistent_kdtree"]


def _points(theta: NDArray, h1: NDArray, half_theta: float, half_h: float):
    """Both forms' coordinates: theta in pixels (the window a square), wrapping at box[0]."""
    scale = half_h / half_theta
    t = np.mod(theta, 2.0 * np.pi) * scale
    box = (2.0 * np.pi * scale, 4.0 * (float(h1.max()) + half_h) + 1.0)
    return np.minimum(t, np.nextafter(box[0], 0)), h1 - h1.min(), box


def consistent(
    theta: NDArray, h1: NDArray, disparity: NDArray, *, half_theta: float, half_h: float,
    tol: float, support: int,
) -> NDArray:  # fmt: skip
    """Matches whose disparity agrees (within ``tol``) with at least ``support``
    of their neighbours (|d theta| <= half_theta, wrapping; |d h1| <= half_h),
    and with at least half of them; bool (N,).

    Compiled: the matches sorted by theta, each compared with those after it
    up to half_theta further on (wrapping), with the distance that
    :func:`consistent_kdtree` (the same vote with scipy's k-d tree) computes.
    """
    n = theta.size
    if n == 0:
        return np.zeros(0, dtype=bool)
    t, h, box = _points(np.asarray(theta, float), np.asarray(h1, float), half_theta, half_h)
    order = np.argsort(t, kind="stable")
    near = np.zeros(n, dtype=np.int64)
    agree = np.zeros(n, dtype=np.int64)
    _vote(t, h, np.asarray(disparity, float), order, float(half_h), float(tol), box[0],
          near, agree)  # fmt: skip
    return (agree >= support) & (agree >= 0.5 * near)


@numba.njit(cache=True, nogil=True)
def _vote(t, h, disp, order, r, tol, box, near, agree):  # pragma: no cover - compiled
    """Count each pair of points within r (Chebyshev, t wrapping at ``box``) once:
    ``near`` the pairs, ``agree`` those whose disparities differ by at most ``tol``.

    The distance is the k-d tree's (scipy's periodic box: a difference beyond
    half the box wraps by the box); ``order`` sorts t, and each point is compared
    with the following ones while their sorted gap could be within r.
    """
    n = t.size
    half = 0.5 * box
    reach = r + 1e-9 * (1.0 + r)  # the sorted gap only bounds the scan: a little wider
    all_pairs = box <= 2.0 * reach  # the window wraps onto itself: compare every pair
    for a in range(n):
        i = order[a]
        steps = n - 1 - a if all_pairs else n - 1
        for s in range(1, steps + 1):
            b = a + s
            if b >= n:
                b -= n
            j = order[b]
            if not all_pairs:
                gap = t[j] - t[i] if b > a else t[j] + box - t[i]
                if gap > reach:
                    break
            dt = t[i] - t[j]
            if dt < -half:
                dt = box + dt
            elif dt > half:
                dt = dt - box
            dh = h[i] - h[j]
            if max(abs(dt), abs(dh)) <= r:
                near[i] += 1
                near[j] += 1
                if abs(disp[i] - disp[j]) <= tol:
                    agree[i] += 1
                    agree[j] += 1


def consistent_kdtree(
    theta: NDArray, h1: NDArray, disparity: NDArray, *, half_theta: float, half_h: float,
    tol: float, support: int,
) -> NDArray:  # fmt: skip
    """:func:`consistent` with scipy's k-d tree (its reference form): the pairs
    within the window by ``cKDTree.query_pairs`` on a periodic box."""
    n = theta.size
    t, h, box = _points(np.asarray(theta, float), np.asarray(h1, float), half_theta, half_h)
    pts = np.column_stack([t, h])
    pairs = cKDTree(pts, boxsize=box).query_pairs(half_h, p=np.inf, output_type="ndarray")
    i = np.concatenate([pairs[:, 0], pairs[:, 1]])
    j = np.concatenate([pairs[:, 1], pairs[:, 0]])
    near = np.bincount(i, minlength=n)
    agree = np.bincount(i, weights=np.abs(disparity[i] - disparity[j]) <= tol, minlength=n)
    return (agree >= support) & (agree >= 0.5 * near)
