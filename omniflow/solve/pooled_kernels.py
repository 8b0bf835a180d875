"""Compiled kernels (Numba) of the pooled solver: its sums, its 2 x 2 solves, the neighbours.

:func:`pooled_sums` forms the weighted sums of the pooled flow solver
(:func:`omniflow.solve.pooled.pooled_solution`): for every point, over its K
neighbours, sum_j w_ij u_ij^m (pp, pq, qq, pf, qf)_j. In numpy that is a
dozen (N, K) gathers and products and an (N, K, 5) stack before one batched
product; here it is one pass over the neighbours with nothing stored but
the sums. The arithmetic of each term is numpy's, term by term; only the
order of the additions over the K neighbours differs (a batched matrix
product there, a running sum here), so the sums agree to rounding.

:func:`pooled_solves` solves those sums' 2 x 2 systems (the Schur complement on (a, h_1 b)
for the linear model) per point, numpy's operations in numpy's order, so bit for bit the
answers of the numpy form it replaced, without its (N,) temporaries.

:func:`cell_knn` finds the k nearest points within a radius
(:func:`omniflow.solve.pooled.neighbourhoods`) by binning the points into square cells of
half the radius and visiting the cells around each query point ring by ring,
keeping the nearest so far in a max-heap whose top bounds the cells still worth
visiting. It answers what scipy's k-d tree answers (the same squared distances,
the same strict bound, nearest first) except in how points at exactly the same
distance are ordered, which the tree decides by its traversal; it flags the rows
where that decides which points are in, and the caller asks the tree for those.

The kernels compile on first use; ``cache=True`` keeps the machine code
between runs where the package folder (or Numba's user cache) is writable.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

__all__ = [
    "cell_knn",
    "pooled_solves",
    "pooled_sums",
]


@numba.njit(cache=True, nogil=True)
def _pooled_sums(idx, w, f1_h, f1_theta, f1_t, kf2_h, f2_theta, f2_t, h1, th, relative,
                 n_powers, scale):  # pragma: no cover - compiled  # fmt: skip
    n, kk = idx.shape
    sums = np.zeros((n, n_powers, 5))
    wsum = np.zeros((n, n_powers))
    two_pi = 2.0 * math.pi
    for i in range(n):
        hi = h1[i]
        for s in range(kk):
            j = idx[i, s]
            ww = w[i, s]
            rel = h1[j] / hi if relative else 1.0
            p1 = f1_h[j] * rel
            p2 = kf2_h[j] * rel
            q1 = f1_theta[j] / hi
            q2 = f2_theta[j] / hi
            t1 = f1_t[j]
            t2 = f2_t[j]
            pp = p1 * p1 + p2 * p2
            pq = p1 * q1 + p2 * q2
            qq = q1 * q1 + q2 * q2
            pf = p1 * t1 + p2 * t2
            qf = q1 * t1 + q2 * t2
            power = ww
            for m in range(n_powers):
                if m == 1:  # the tangential offset u, as numpy's floor-mod wrap
                    u = (((th[j] - th[i]) + math.pi) % two_pi - math.pi) * hi / scale
                    power = ww * u
                elif m == 2:
                    power = ww * u * u
                sums[i, m, 0] += power * pp
                sums[i, m, 1] += power * pq
                sums[i, m, 2] += power * qq
                sums[i, m, 3] += power * pf
                sums[i, m, 4] += power * qf
                wsum[i, m] += power
    return sums, wsum


def pooled_sums(
    idx: NDArray,
    w: NDArray,
    derivs: tuple[NDArray, ...],
    h1: NDArray,
    theta: NDArray | None,
    *,
    relative: bool,
    linear: bool,
    scale: float,
) -> tuple[NDArray, NDArray]:
    """Weighted sums of the pooled normal equations, and of the weights.

    Parameters
    ----------
    idx, w : ndarray, shape (N, K)
        Neighbour indices (N + 1 entries below: index N is the sentinel) and weights.
    derivs : six ndarrays, shape (N + 1,)
        f1_h, f1_theta, f1_t, (h2/h1) f2_h, f2_theta, f2_t, each with a zero
        sentinel at index N.
    h1 : ndarray, shape (N + 1,)
        cam1 image radius, sentinel 1.
    theta : ndarray, shape (N + 1,), optional
        Azimuth (``linear`` only).
    relative, linear : bool
        The local model of :func:`omniflow.solve.pooled.pooled_solution`.
    scale : float
        Tangential length that scales u, pixels.

    Returns
    -------
    sums : ndarray, shape (N, 1 or 3, 5)
        sum_j w u^m (pp, pq, qq, pf, qf), m = 0 (and 1, 2 for ``linear``).
    wsum : ndarray, shape (N, 1 or 3)
        sum_j w u^m.
    """
    f = [np.ascontiguousarray(v, dtype=np.float64) for v in derivs]
    th = np.zeros_like(f[0]) if theta is None else np.ascontiguousarray(theta, dtype=np.float64)
    return _pooled_sums(
        np.ascontiguousarray(idx, dtype=np.int64), np.ascontiguousarray(w, dtype=np.float64),
        *f, np.ascontiguousarray(h1, dtype=np.float64), th, bool(relative),
        3 if linear else 1, float(scale),
    )  # fmt: skip


@numba.njit(cache=True, nogil=True)
def _pooled_solves(sums, linear, limit, positive):  # pragma: no cover - compiled
    n = sums.shape[0]
    a = np.full(n, np.nan)
    c = np.full(n, np.nan)
    conf = np.zeros(n)
    explained = np.full(n, np.nan)
    lam_min = np.zeros(n)
    for i in range(n):
        pd = True
        # [[pp_m, pq_m], [pq_m, qq_m]] for the powers m = 0 (on (a, c)), 1 (coupling to the
        # slopes), 2 (on the slopes)
        m11, m12, m22 = sums[i, 0, 0], sums[i, 0, 1], sums[i, 0, 2]
        v0, v1 = -sums[i, 0, 3], -sums[i, 0, 4]
        if linear:  # Schur complement on (a, c): the two slopes solved out
            b11, b12, b22 = sums[i, 2, 0], sums[i, 2, 1], sums[i, 2, 2]
            det_b = b11 * b22 - b12 * b12
            pd = (det_b > 0) and (b11 > 0)
            inv = 1.0 / (det_b if det_b > 0 else np.nan)
            k11, k12, k22 = sums[i, 1, 0], sums[i, 1, 1], sums[i, 1, 2]
            # C = K B^-1, K the coupling block
            c11, c12 = (k11 * b22 - k12 * b12) * inv, (k12 * b11 - k11 * b12) * inv
            c21, c22 = (k12 * b22 - k22 * b12) * inv, (k22 * b11 - k12 * b12) * inv
            m11, m12, m22 = (m11 - (c11 * k11 + c12 * k12), m12 - (c11 * k12 + c12 * k22),
                             m22 - (c21 * k12 + c22 * k22))  # fmt: skip
            v0, v1 = (v0 + (c11 * sums[i, 1, 3] + c12 * sums[i, 1, 4]),
                      v1 + (c21 * sums[i, 1, 3] + c22 * sums[i, 1, 4]))  # fmt: skip
        det = m11 * m22 - m12 * m12
        # lambda_min / lambda_max, NaN to 0 (numpy's maximum keeps a NaN: so does this)
        tr = m11 + m22
        d = 0.25 * tr * tr - det
        disc = math.sqrt(d if not d < 0.0 else 0.0)
        lmax = 0.5 * tr + disc
        lo = 0.5 * tr - disc
        lmin = lo if not lo < 0.0 else 0.0
        ci = lmin / lmax if lmax > 0 else 0.0
        if math.isnan(ci):
            ci = 0.0
        elif math.isinf(ci):
            ci = 1.7976931348623157e308 if ci > 0 else -1.7976931348623157e308
        conf[i] = ci
        ok = (det > 0) and (ci >= limit) and (ci > 0)
        if positive:
            ok = ok and pd and (m11 > 0)
        if ok:
            a[i] = (m22 * v0 - m12 * v1) / det
            c[i] = (m11 * v1 - m12 * v0) / det
        explained[i] = a[i] * v0 + c[i] * v1
        dm = m11 - m22
        lam_min[i] = 0.5 * (m11 + m22) - math.sqrt(0.25 * (dm * dm) + m12 * m12)
    return a, c, conf, explained, lam_min


def pooled_solves(
    sums: NDArray, *, linear: bool, min_conditioning: float, positive: bool = False
) -> tuple[NDArray, ...]:
    """Solve each point's pooled normal equations from :func:`pooled_sums`' sums.

    The 2 x 2 system on (a, h_1 b) (for ``linear``, its Schur complement once the two
    slopes are solved out), per point in one pass, as numpy did it with a dozen (N,)
    temporaries; the same operations in the same order, so the same answers bit for
    bit (numpy's ``maximum`` and ``nan_to_num`` included).

    Parameters
    ----------
    sums : ndarray, shape (N, 1 or 3, 5)
        sum_j w u^m (pp, pq, qq, pf, qf).
    linear : bool
        The linear model (three powers of u).
    min_conditioning : float
        NaN where the confidence is below this.
    positive : bool
        Also NaN where the slopes' block or the (a, a) entry is not positive.

    Returns
    -------
    a, c : ndarray, shape (N,)
        dh_1/dt and h_1 dtheta/dt; NaN where singular or a test fails.
    confidence : ndarray, shape (N,)
        lambda_min / lambda_max of the 2 x 2 system, NaN as 0.
    explained : ndarray, shape (N,)
        x^T v, the squared residual the solution explains (NaN with x).
    lam_min : ndarray, shape (N,)
        The 2 x 2 system's smaller eigenvalue.
    """
    s = np.ascontiguousarray(sums, dtype=np.float64)
    if linear and s.shape[1] < 3:
        raise ValueError(f"pooled_solves: the linear model needs 3 powers, got {s.shape[1]}")
    return _pooled_solves(s, bool(linear), float(min_conditioning), bool(positive))


@numba.njit(cache=True, nogil=True, inline="always")
def _heap_push(hd, hj, m, d2, j):  # pragma: no cover - compiled
    """Add (d2, j) to the max-heap hd[:m], hj[:m]."""
    pos = m
    while pos > 0:
        parent = (pos - 1) // 2
        if hd[parent] >= d2:
            break
        hd[pos] = hd[parent]
        hj[pos] = hj[parent]
        pos = parent
    hd[pos] = d2
    hj[pos] = j


@numba.njit(cache=True, nogil=True, inline="always")
def _heap_replace_top(hd, hj, m, d2, j):  # pragma: no cover - compiled
    """Replace the top of the max-heap hd[:m], hj[:m] by (d2, j)."""
    pos = 0
    while True:
        child = 2 * pos + 1
        if child >= m:
            break
        if child + 1 < m and hd[child + 1] > hd[child]:
            child += 1
        if hd[child] <= d2:
            break
        hd[pos] = hd[child]
        hj[pos] = hj[child]
        pos = child
    hd[pos] = d2
    hj[pos] = j


@numba.njit(cache=True, nogil=True)
def _cell_knn(x, y, rows, k, radius, split):  # pragma: no cover - compiled
    n = x.size
    dist = np.full((n, k), np.inf)
    idx = np.full((n, k), n, dtype=np.int64)
    tie = np.zeros(n, np.bool_)
    if n == 0:
        return dist, idx, tie
    cell = radius / split
    x0 = x.min()
    y0 = y.min()
    gw = int((x.max() - x0) / cell) + 1
    gh = int((y.max() - y0) / cell) + 1
    cx = np.empty(n, np.int64)
    cy = np.empty(n, np.int64)
    start = np.zeros(gw * gh + 1, np.int64)
    for j in range(n):
        cx[j] = min(int((x[j] - x0) / cell), gw - 1)
        cy[j] = min(int((y[j] - y0) / cell), gh - 1)
        start[cy[j] * gw + cx[j] + 1] += 1
    for c in range(gw * gh):
        start[c + 1] += start[c]
    order = np.empty(n, np.int64)
    fill = start[:-1].copy()
    for j in range(n):  # points by cell, in index order within a cell
        c = cy[j] * gw + cx[j]
        order[fill[c]] = j
        fill[c] += 1
    xs = x[order]  # the coordinates in cell order: a cell's candidates are contiguous
    ys = y[order]
    r2 = radius * radius
    hd = np.empty(k)  # one row's nearest so far, a max-heap on the squared distance
    hj = np.empty(k, np.int64)
    for t in range(rows.size):
        i = rows[t]
        xi = x[i]
        yi = y[i]
        m = 0
        bound = r2
        ties = 0  # points outside a full heap at its top's squared distance
        # the cells ring by ring around the point's own (nearest first, so the bound
        # shrinks early and prunes the outer cells)
        for ring in range(split + 1):
            for off in range(8 * ring if ring else 1):
                if ring == 0:
                    ox, oy = 0, 0
                else:  # walk the square ring's 8 ring cells
                    side, step = off // (2 * ring), off % (2 * ring)
                    if side == 0:
                        ox, oy = -ring + step, -ring
                    elif side == 1:
                        ox, oy = ring, -ring + step
                    elif side == 2:
                        ox, oy = ring - step, ring
                    else:
                        ox, oy = -ring, ring - step
                gx = cx[i] + ox
                gy = cy[i] + oy
                if gx < 0 or gy < 0 or gx >= gw or gy >= gh:
                    continue
                ex = max(x0 + gx * cell - xi, xi - (x0 + (gx + 1) * cell), 0.0)
                ey = max(y0 + gy * cell - yi, yi - (y0 + (gy + 1) * cell), 0.0)
                if ex * ex + ey * ey > bound:  # nothing in this cell can enter or tie
                    continue
                c = gy * gw + gx
                for s in range(start[c], start[c + 1]):
                    dx = xs[s] - xi
                    dy = ys[s] - yi
                    d2 = dx * dx + dy * dy
                    if d2 < bound:
                        if m < k:
                            _heap_push(hd, hj, m, d2, order[s])
                            m += 1
                        else:  # the top (the k-th) drops out
                            last = hd[0]
                            _heap_replace_top(hd, hj, k, d2, order[s])
                            ties = ties + 1 if last == hd[0] else 0
                        if m == k:
                            bound = hd[0]
                    elif d2 == bound and m == k:
                        ties += 1
        for q in range(m - 1, -1, -1):  # pop the farthest into the last place
            dist[i, q] = math.sqrt(hd[0])
            idx[i, q] = hj[0]
            _heap_replace_top(hd, hj, q, hd[q], hj[q])
        # another point at the same place (which comes first), or one outside the list
        # at the k-th's distance (which of them is in)
        tie[i] = (m >= 2 and dist[i, 1] == 0.0) or ties > 0
    return dist, idx, tie


def cell_knn(
    x: NDArray, y: NDArray, k: int, radius: float, rows: NDArray | None = None, *, split: int = 2
) -> tuple[NDArray, NDArray, NDArray]:
    """The ``k`` nearest of the points (x, y) closer than ``radius`` to each, nearest first.

    As ``scipy.spatial.cKDTree(pts).query(pts[rows], k, distance_upper_bound=radius)``
    for finite coordinates, on the full (N, k) rows (the rows not in ``rows``, and
    the places beyond the neighbours found, hold distance inf and index N), with
    the cells ``radius / split`` wide. Returns (dist, idx, tie): ``tie`` (N,) bool
    marks the rows whose answer depends on how equal distances are ordered, which
    the tree decides by its own traversal: a point left out at the k-th's
    distance (pixel coordinates make equal distances common), or a second point
    at distance 0. Elsewhere the same neighbours at the same distances
    (the order within equal distances aside).
    """
    x = np.ascontiguousarray(x, dtype=np.float64).ravel()
    y = np.ascontiguousarray(y, dtype=np.float64).ravel()
    rows = np.arange(x.size) if rows is None else np.ascontiguousarray(rows, dtype=np.int64)
    return _cell_knn(x, y, rows, int(k), float(radius), int(split))
