"""The pooled solver: eq. (9) and (15) of neighbouring matches in least squares.

A polar Lucas-Kanade over both units (:mod:`omniflow.paper.flow` gives the equations
and why one point's 2x2 solve is ill-conditioned); the confidence column is
lambda_min / lambda_max of each pool's normal matrix.

Pools that respect objects. :func:`neighbourhoods` leaves out neighbours at
another range and, optionally, across a strong image edge
(:func:`edge_between`); :func:`consistent_neighbours` leaves out those whose
own equations reject the point's first-pass flow (another motion), and
:func:`informative_pools` cuts each pool to the nearest neighbours that
condition it well enough (small pools in rich texture). A pool thinned
below a few neighbours keeps them all, as its solve would be near-singular.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from omniflow.config import UNIT_WEIGHTINGS
from omniflow.paper.flow import eig_ratio, flow_residual
from omniflow.solve.gridpool import GridPools
from omniflow.solve.pooled_kernels import cell_knn, pooled_solves, pooled_sums

__all__ = [
    "consistent_neighbours",
    "edge_between",
    "informative_pools",
    "motion_statistic",
    "neighbourhoods",
    "pooled_solution",
]


def neighbourhoods(
    x: ArrayLike,
    y: ArrayLike,
    *,
    k: int = 12,
    radius: float = 4.0,
    r: ArrayLike | None = None,
    range_tol: float | None = 0.1,
    edge_map: NDArray | None = None,
    edge_tol: float | None = None,
    min_count: int = 8,
    query: NDArray | None = None,
) -> tuple[NDArray, NDArray]:
    """The k nearest matched points within ``radius`` px of each (itself included).

    Parameters
    ----------
    x, y : array_like, shape (N,)
        cam1 pixel coordinates of the matches.
    k : int
        Most neighbours per point, the point itself counted.
    radius : float
        Largest distance, pixels; weights are Gaussian with sigma = radius / 2.
    r : array_like, shape (N,), optional
        Triangulated range; with ``range_tol`` neighbours whose range differs
        by more than range_tol * r (another surface) get zero weight.
    edge_map : ndarray, shape (H, W), optional
        Edge strength on the pixel grid (e.g. the gradient magnitude of the
        fitted image); with ``edge_tol``, neighbours separated from the point
        by an edge stronger than edge_tol times the median of ``edge_map`` at
        the points (:func:`edge_between`) get zero weight: an object's
        outline, where it is a stronger edge than the texture on either side,
        bounds the pool.
    edge_tol : float, optional
    min_count : int
        A pool that the edge test would leave with fewer neighbours than
        this keeps them all (its solve would be near-singular).
    query : ndarray of bool, shape (N,), optional
        Search the pools of these points only (the others get none: index
        N, weight 0); :class:`omniflow.solve.gridpool.GridPools` pools the rest.

    Returns
    -------
    idx : ndarray, shape (N, k), int
        Neighbour indices (the point itself first); N where there is none.
    w : ndarray, shape (N, k)
        Weights, 0 for missing or rejected neighbours.
    """
    pts = np.column_stack([np.asarray(x, dtype=float).ravel(), np.asarray(y, dtype=float).ravel()])
    n = pts.shape[0]
    if n == 0:
        return np.zeros((0, k), dtype=np.intp), np.zeros((0, k))
    kk = min(k, n)
    rows = np.arange(n) if query is None else np.flatnonzero(query)
    if np.isfinite(pts).all():  # the k-d tree's answer from a cell search (compiled) ...
        dist, idx, tie = cell_knn(pts[:, 0], pts[:, 1], kk, radius, rows)
        idx = idx.astype(np.intp, copy=False)
        rows = np.flatnonzero(tie)  # ... but where equal distances decide: the tree's
    else:
        dist = np.full((n, kk), np.inf)
        idx = np.full((n, kk), n, dtype=np.intp)
    if rows.size:
        tree = cKDTree(pts, balanced_tree=False, compact_nodes=False)  # faster to build here
        d_q, i_q = tree.query(pts[rows], k=kk, distance_upper_bound=radius)
        dist[rows], idx[rows] = d_q.reshape(rows.size, kk), i_q.reshape(rows.size, kk)
    q = slice(None) if query is None else np.flatnonzero(query)  # the others' weights: 0
    found = idx[q] < n
    sigma = radius / 2.0
    w_q = np.where(found, np.exp(-0.5 * (np.where(found, dist[q], 0.0) / sigma) ** 2), 0.0)
    if r is not None and range_tol is not None:
        rr = np.append(np.asarray(r, dtype=float).ravel(), np.nan)
        with np.errstate(invalid="ignore"):
            same = np.abs(rr[idx[q]] - rr[:n][q, None]) <= range_tol * np.abs(rr[:n][q, None])
        same[:, 0] = True
        w_q = np.where(same, w_q, 0.0)
    if query is None:
        w = w_q
    else:
        w = np.zeros((n, kk))
        w[q] = w_q
    if edge_map is not None and edge_tol is not None:
        strength = edge_between(edge_map, pts[:, 0], pts[:, 1], idx)
        level = np.median(_sample_grid(edge_map, pts[:, 0], pts[:, 1]))
        w = _keep_enough(np.where(strength > edge_tol * level, 0.0, w), w, min_count)
    if kk < k:
        idx = np.pad(idx, ((0, 0), (0, k - kk)), constant_values=n)
        w = np.pad(w, ((0, 0), (0, k - kk)))
    return idx, w


def _sample_grid(grid: NDArray, x: NDArray, y: NDArray) -> NDArray:
    """Bilinear samples of a pixel grid at pixel coordinates (x, y) (centres at j + 1/2)."""
    from scipy.ndimage import map_coordinates

    return map_coordinates(grid, [np.ravel(y) - 0.5, np.ravel(x) - 0.5], order=1,
                           mode="nearest").reshape(np.shape(x))  # fmt: skip


def _keep_enough(w_new: NDArray, w_old: NDArray, min_count: int) -> NDArray:
    """``w_new``, except that a pool left with fewer than ``min_count`` neighbours keeps ``w_old``.

    A pool thinned below the four unknowns of the linear model (plus a margin)
    gives a near-singular solve and a heavy-tailed flow; there the wider
    pool's answer is the better one.
    """
    few = np.count_nonzero(w_new > 0, axis=1) < np.minimum(
        min_count, np.count_nonzero(w_old > 0, axis=1)
    )
    return np.where(few[:, None], w_old, w_new)


def edge_between(
    edge_map: NDArray, x: ArrayLike, y: ArrayLike, idx: NDArray, *, spacing: float = 2.0
) -> NDArray:
    """The strongest edge on the segment from each point to each of its neighbours.

    ``edge_map`` (H, W) is dilated with a square of ``spacing`` + 1 px, so
    samples every ``spacing`` px along the open segment (its end points
    left out: they lie on edges, being significant points) see every peak
    within spacing / 2 of the line.

    Parameters
    ----------
    edge_map : ndarray, shape (H, W)
        Edge strength on the pixel grid.
    x, y : array_like, shape (N,)
        Pixel coordinates of the points.
    idx : ndarray, shape (N, K), int
        Neighbour indices, N for none (as :func:`neighbourhoods` returns).
    spacing : float
        Sample spacing along the segments, pixels.

    Returns
    -------
    ndarray, shape (N, K)
        Largest dilated edge strength between point i and neighbour idx[i, j];
        0 for the point itself, a missing neighbour or one closer than spacing.
    """
    import cv2

    x = np.asarray(x, dtype=np.float64).ravel()
    y = np.asarray(y, dtype=np.float64).ravel()
    n = x.size
    size = 2 * int(np.ceil(spacing / 2.0)) + 1
    dil = cv2.dilate(np.asarray(edge_map, np.float32), np.ones((size, size), np.uint8))
    found = idx < n
    xe, ye = np.append(x, np.nan), np.append(y, np.nan)
    dx, dy = xe[idx] - x[:, None], ye[idx] - y[:, None]
    length = np.where(found, np.hypot(dx, dy), 0.0)
    m = int(np.ceil(np.max(length, initial=0.0) / spacing))  # samples on the longest segment
    out = np.zeros(idx.shape)
    if m < 2:
        return out
    ii, jj = np.nonzero(found & (length >= spacing))
    seg = length[ii, jj]
    for s in range(1, m):
        frac = s * spacing / seg  # a point every ``spacing`` px from point i
        inside = frac < 1.0 - 0.5 * spacing / seg
        if not inside.any():
            break
        a, b = ii[inside], jj[inside]
        f = frac[inside]
        vals = _sample_grid(dil, x[a] + f * dx[a, b], y[a] + f * dy[a, b])
        out[a, b] = np.maximum(out[a, b], vals)
    return out


def consistent_neighbours(
    idx: NDArray,
    w: NDArray,
    f1_h: ArrayLike,
    f1_theta: ArrayLike,
    f1_t: ArrayLike,
    f2_h: ArrayLike,
    f2_theta: ArrayLike,
    f2_t: ArrayLike,
    h1: ArrayLike,
    h2: ArrayLike,
    a: ArrayLike,
    b: ArrayLike,
    *,
    tol: float,
    min_count: int = 8,
) -> NDArray:
    """Pool weights without the neighbours whose own equations reject the point's flow.

    Neighbour j's eq. (9) and (15) are evaluated at point i's first-pass
    flow (a_i h_1,j / h_1,i, b_i) (the relative model of
    :func:`pooled_solution`); where the RMS of the two residuals exceeds
    ``tol`` times their robust scale over all points at their own flow
    (1.4826 times the median absolute residual), j moves differently (or
    is another surface) and gets weight 0. Unlike comparing the
    neighbours' first-pass flows (each already a mixture where its pool
    crossed the outline), this asks j's own data. A point without a
    first-pass flow keeps its neighbours.

    Parameters
    ----------
    idx, w : ndarray, shape (N, K)
        From :func:`neighbourhoods`.
    f1_h ... h2 : array_like, shape (N,)
        As in :func:`pooled_solution`.
    a, b : array_like, shape (N,)
        First-pass dh_1/dt and dtheta/dt at the points.
    tol : float
        Residual allowed, in robust standard deviations.
    min_count : int
        A pool that the test would leave with fewer neighbours than this
        keeps them all.

    Returns
    -------
    ndarray, shape (N, K)
    """
    f1_h, f1_theta, f1_t, f2_h, f2_theta, f2_t, h1, h2 = (
        np.append(np.asarray(v, dtype=np.float64).ravel(), np.nan)
        for v in (f1_h, f1_theta, f1_t, f2_h, f2_theta, f2_t, h1, h2)
    )
    n = f1_h.size - 1
    a = np.asarray(a, dtype=np.float64).ravel()
    b = np.asarray(b, dtype=np.float64).ravel()
    k = h2 / h1  # eq. (14)
    aj = (a / h1[:n])[:, None] * h1[idx]  # the point's radial flow at the neighbour's radius
    bj = b[:, None]
    res1 = flow_residual(f1_h[idx], f1_theta[idx], f1_t[idx], aj, bj)  # eq. (9)
    res2 = flow_residual(k[idx] * f2_h[idx], f2_theta[idx], f2_t[idx], aj, bj)  # eq. (15)
    rms = np.sqrt(0.5 * (res1 * res1 + res2 * res2))
    own = np.abs(np.concatenate([res1[:, 0], res2[:, 0]]))
    own = own[np.isfinite(own)]
    if own.size == 0:
        return w
    scale = 1.4826 * np.median(own)
    with np.errstate(invalid="ignore"):
        same = rms <= tol * scale
    same[:, 0] = True
    same |= ~(np.isfinite(a) & np.isfinite(b))[:, None]
    return _keep_enough(np.where(same, w, 0.0), w, min_count)


def informative_pools(
    idx: NDArray,
    w: NDArray,
    f1_h: ArrayLike,
    f1_theta: ArrayLike,
    f2_h: ArrayLike,
    f2_theta: ArrayLike,
    h1: ArrayLike,
    h2: ArrayLike,
    *,
    target: float,
    min_count: int = 8,
) -> NDArray:
    """Pool weights cut to the nearest neighbours that condition eq. (9) and (15) well enough.

    The pool of point i grows over its neighbours in order of distance (the
    order :func:`neighbourhoods` gives) until the weaker direction of its
    normal matrix on (dh_1/dt, h_1 dtheta/dt) (the ``model="constant"``
    matrix of :func:`pooled_solution`) holds ``target`` times the
    information of a typical single equation pair (the median over the
    points of their own largest eigenvalue); later neighbours get weight 0.
    Rich texture reaches that with a few close neighbours, so the pool stays
    small and crosses fewer object outlines; poor texture keeps the whole
    neighbourhood. At least ``min_count`` neighbours (with non-zero weight
    or not) are kept, so the linear model's four unknowns stay determined.

    Parameters
    ----------
    idx, w : ndarray, shape (N, K)
        From :func:`neighbourhoods`, neighbours sorted by distance.
    f1_h ... h2 : array_like, shape (N,)
        Gradients and radii at the points, as in :func:`pooled_solution`.
    target : float
        Information wanted on the weaker direction, in typical single points.
    min_count : int
        Fewest neighbours kept, the point itself counted.

    Returns
    -------
    ndarray, shape (N, K)
        ``w`` with the neighbours past the informative prefix set to 0.
    """
    f1_h, f1_theta, f2_h, f2_theta, h1, h2 = (
        np.append(np.asarray(v, dtype=np.float64).ravel(), 0.0)
        for v in (f1_h, f1_theta, f2_h, f2_theta, h1, h2)
    )
    n = f1_h.size - 1
    h1[n] = 1.0
    hi = h1[:n, None]
    rel = h1[idx] / hi
    p1, p2 = f1_h[idx] * rel, (h2 / h1 * f2_h)[idx] * rel
    q1, q2 = f1_theta[idx] / hi, f2_theta[idx] / hi
    pp, pq, qq = p1 * p1 + p2 * p2, p1 * q1 + p2 * q2, q1 * q1 + q2 * q2
    own_max = _eig_max(pp[:, 0], pq[:, 0], qq[:, 0])
    level = target * np.median(own_max)
    cpp, cpq, cqq = (np.cumsum(w * v, axis=1) for v in (pp, pq, qq))
    lmin = _eig_max(cpp, cpq, cqq) * eig_ratio(cpp, cpq, cqq)
    enough = lmin >= level
    # first prefix length that is informative enough; K where none is
    count = np.where(enough.any(axis=1), np.argmax(enough, axis=1) + 1, idx.shape[1])
    count = np.maximum(count, min_count)
    keep = np.arange(idx.shape[1])[None, :] < count[:, None]
    return np.where(keep, w, 0.0)


def _eig_max(m11: NDArray, m12: NDArray, m22: NDArray) -> NDArray:
    """lambda_max of symmetric 2x2 matrices [[m11, m12], [m12, m22]]."""
    tr = m11 + m22
    det = m11 * m22 - m12 * m12
    return 0.5 * tr + np.sqrt(np.maximum(0.25 * tr * tr - det, 0.0))


def pooled_solution(
    f1_h: ArrayLike,
    f1_theta: ArrayLike,
    f1_t: ArrayLike,
    f2_h: ArrayLike,
    f2_theta: ArrayLike,
    f2_t: ArrayLike,
    h1: ArrayLike,
    h2: ArrayLike,
    idx: NDArray | None,
    w: NDArray | None,
    *,
    theta: ArrayLike | None = None,
    model: str = "constant",
    scale: float = 4.0,
    relative: bool = True,
    min_conditioning: float = 0.0,
    noise1: float = 0.0,
    noise2: float = 0.0,
    residual_noise: bool = False,
    unit_weighting: str = "equal",
    grid: GridPools | None = None,
    static_test: float | None = None,
    static_max_px: float | None = None,
) -> tuple[NDArray, NDArray, NDArray]:
    """Eq. (9) and (15) of neighbouring matches pooled in weighted least squares.

    For point i with neighbours j (``idx[i]``, weights ``w[i]``), minimise
    sum_j w_ij [(f1_h a_j + f1_theta b_j + f1_t)_j^2
                + ((h_2/h_1) f2_h a_j + f2_theta b_j + f2_t)_j^2]
    where (a_j, b_j) = (dh_1/dt, dtheta/dt) at neighbour j follow a local
    model of the point's own (a, b):

    * ``relative``: a_j = a h_1,j / h_1,i. By eq. (13) at dh = 0,
      dh_1 / h_1 = -dr / (d + r), the same for neighbours on one surface, so
      the radial flow grows in proportion to h_1 (a neighbourhood of 4 px at
      h_1 = 50 px spans 8 % of it). Otherwise a_j = a.
    * ``model="constant"``: b_j = b (rigid motion makes dtheta/dt independent
      of h). ``model="linear"``: both a and h_1 b also vary linearly with the
      tangential offset u = h_1,i (theta_j - theta_i) / scale, two more
      unknowns: a translating robot gives a flow that changes with theta at
      the first order (needs ``theta``).

    Unknowns are scaled to pixels per frame, (a, h_1,i b, ...). Solved per
    point from the small normal equations. With ``noise1``, ``noise2`` the
    errors in the variables are corrected (:func:`_eiv_corrected`).

    Parameters
    ----------
    f1_h ... h2 : array_like, shape (N,)
        As in :func:`direct_solution`, at every match.
    idx, w : ndarray, shape (N, K)
        From :func:`neighbourhoods` (index N = no neighbour, weight 0); None
        with ``grid``.
    theta : array_like, shape (N,), optional
        Azimuth of the matches (for ``model="linear"``).
    model : {"constant", "linear"}
    scale : float
        Tangential length that scales u, pixels (the neighbourhood radius).
    relative : bool
        Pool dh_1/dt / h_1 (True) or dh_1/dt itself (False).
    min_conditioning : float
        NaN where the confidence is below this.
    noise1, noise2 : float
        Variance of unit 1's and unit 2's gradient components, (grey / px)^2;
        0 (the default) solves the plain least squares. With
        ``residual_noise``: that variance per unit variance of the fitted
        image's noise.
    residual_noise : bool
        Measure each unit's image noise from the residuals of eq. (9) and (15)
        at the plain solution (noise in the band the flow step uses, whatever
        its spectrum) and scale ``noise1``, ``noise2`` by it.
    unit_weighting : {"equal", "global", "local"}
        Weight of each unit's equations. "equal": eq. (9) and (15) count
        alike (ordinary least squares). "global": each unit's rows weighted
        by the inverse of that unit's residual variance at the equal-weight
        solution (one figure per unit). "local": by the inverse of the
        unit's residual variance around each neighbour (the weighted mean of
        the squared residuals over that neighbour's own pool), so a unit
        whose equations do not hold in one part of the image (cam1 near its
        centre, where the texture is compressed tangentially and its radial
        derivative carries little but error) gives way there to the other.
        Generalised least squares with the noise measured, not assumed.
    grid : GridPools, optional
        Pool by filtering on a grid (:mod:`omniflow.solve.gridpool`) instead of over
        ``idx``, ``w`` (``relative`` model, ``"equal"`` weighting only); the
        tangential offset u is then the tangential component of the pixel
        offset, equal to h_1,i (theta_j - theta_i) to first order.
    static_test, static_max_px : float, optional
        Report no motion where the pool's equations show none
        (:func:`_zero_where_still`); None (the default): no test, no guard.

    Returns
    -------
    dh1_dt, dtheta_dt : ndarray, shape (N,)
    confidence : ndarray, shape (N,)
        lambda_min / lambda_max of the normal matrix of (a, h_1 b) (for
        ``"linear"``, of its Schur complement: the information left on
        (a, h_1 b) once the slopes are free), in [0, 1].
    """
    _check_pool_args(model, unit_weighting, theta, grid, relative)
    f1_h, f1_theta, f1_t, f2_h, f2_theta, f2_t, h1, h2 = (
        np.append(np.asarray(v, dtype=np.float64).ravel(), 0.0)
        for v in (f1_h, f1_theta, f1_t, f2_h, f2_theta, f2_t, h1, h2)
    )
    n = f1_h.size - 1
    h1[n] = 1.0
    k = h2 / h1
    # Normal equations without forming the design matrix: a row of neighbour j
    # and one unit is (p, q, p u, q u) [ * sqrt(w)] with p = f_h rel (k f2_h
    # for unit 2), q = f_theta / h_1, right side -f_t, so every entry of
    # A^T A and A^T rhs is a weighted sum of pp, pq, qq, pf, qf times 1, u or
    # u^2 (both units share j's weight and u): one compiled pass over the
    # neighbours (omniflow.solve.pooled_kernels.pooled_sums).
    th = np.append(np.asarray(theta, dtype=np.float64).ravel(), 0.0) if theta is not None else None
    derivs6 = (f1_h, f1_theta, f1_t, k * f2_h, f2_theta, f2_t)
    kw = dict(relative=relative, linear=model == "linear", scale=scale)

    def pool(d6):
        if grid is None:
            return pooled_sums(idx, w, d6, h1, th, **kw)
        g_sums, g_wsum = grid.sums(tuple(v[:n] for v in d6), h1[:n], linear=kw["linear"],
                                   scale=scale)  # fmt: skip
        if grid.idx is not None:  # the points whose window mixes ranges: their tree pools
            t_sums, t_wsum = pooled_sums(grid.idx, grid.w, d6, h1, th, **kw)
            g_sums, g_wsum = g_sums + t_sums, g_wsum + t_wsum
        return g_sums, g_wsum

    sums, wsum = pool(derivs6)
    sums0, wsum0 = sums, wsum
    # sums (N, 1 or 3, 5): sum_j w u^m (pp, pq, qq, pf, qf); wsum: sum_j w u^m
    a, c, conf = _solve_sums(sums, model, min_conditioning)
    derivs = (f1_h, f1_theta, f1_t, f2_h, f2_theta, f2_t)
    if residual_noise and (noise1 > 0 or noise2 > 0):
        n1, n2 = _residual_variance(derivs, k, a, c / h1[:n], n)
        noise1, noise2 = noise1 * n1, noise2 * n2
    wsum1 = wsum2 = wsum  # sum_j w u^m times each unit's row weight (1: equal)
    if unit_weighting != "equal":
        v1, v2 = _unit_variances(derivs, k, a, c / h1[:n], n, idx, w, unit_weighting)
        if v1 is not None:
            sums, a, c, conf, wsum1, wsum2 = _unit_weighted(
                (v1, v2), derivs6, idx, w, h1, th, kw, model, scale, min_conditioning
            )
    if noise1 > 0 or noise2 > 0:
        per_row = noise1 * wsum1 + (noise2 * k[:n] ** 2)[:, None] * wsum2  # (N, m)
        a, c, conf = _eiv_corrected(sums, per_row, (a, c, conf), model, min_conditioning)
    if static_test is not None:  # the equal-weight pools' Wald test of no motion
        stat, sd = motion_statistic(pool, derivs6, sums0, wsum0, model, h1[:n])
        a, c = _zero_where_still(stat, sd, static_test, static_max_px, a, c)
    return a, c / h1[:n], conf


def _zero_where_still(stat: NDArray, sd: NDArray, static_test: float,
                      static_max_px: float | None, a: NDArray, c: NDArray):  # fmt: skip
    """(a, c) set to 0 where the pool shows no motion.

    ``stat`` (:func:`motion_statistic`): the squared residual that the flow
    (a, h_1 b) explains, s = x^T S x over the pool (S the normal matrix of
    (a, h_1 b), its Schur complement for ``"linear"``), over the pool's remaining
    residual variance per row (its sum of squared f_t less s, over twice the pool's
    weight: both units' rows). A Wald test of zero flow with the noise measured in
    the pool itself; with independent rows it is chi-squared with 2 degrees of
    freedom where nothing moves: still where below ``static_test``. With
    ``static_max_px``, only where the smallest flow the pool would have detected,
    sqrt(static_test) times the standard error ``sd`` of (a, h_1 b) along its
    weakest direction, is at most this (px per frame): a pool too poor in texture
    to see a small motion keeps its flow.
    """
    still = stat < static_test
    if static_max_px is not None:  # only where the test would have seen that much motion
        still &= np.sqrt(static_test) * sd <= static_max_px
    return np.where(still, 0.0, a), np.where(still, 0.0, c)


def _check_pool_args(model: str, unit_weighting: str, theta, grid, relative: bool) -> None:
    """pooled_solution's choices checked against each other."""
    if model not in ("constant", "linear"):
        raise ValueError(f"model = {model!r}: expected 'constant' or 'linear'")
    if unit_weighting not in UNIT_WEIGHTINGS:
        raise ValueError(f"unit_weighting = {unit_weighting!r}: expected one of {UNIT_WEIGHTINGS}")
    if model == "linear" and theta is None:
        raise ValueError("model='linear' needs theta")
    if grid is not None and (unit_weighting != "equal" or not relative):
        raise ValueError("grid pools need unit_weighting='equal' and relative=True")


def _unit_weighted(variances, derivs6, idx, w, h1, th, kw, model, scale, min_conditioning):
    """The pooled sums and solution with neighbour j's rows of unit u weighted by
    1 / v_u(j) (``variances`` = (v1, v2)): its derivatives scaled by sqrt(1 / v_u(j)),
    so the same compiled sums apply; also each unit's weighted sums of w u^m."""
    r1, r2 = (np.append(1.0 / np.sqrt(v), 0.0) for v in variances)
    scaled = tuple(d * r for d, r in zip(derivs6, (r1, r1, r1, r2, r2, r2), strict=True))
    sums, _ = pooled_sums(idx, w, scaled, h1, th, **kw)
    a, c, conf = _solve_sums(sums, model, min_conditioning)
    n = h1.size - 1
    wsum1, wsum2 = (_weight_sums(w, s[idx], idx, th, h1[:n], model, scale)
                    for s in (r1 * r1, r2 * r2))  # fmt: skip
    return sums, a, c, conf, wsum1, wsum2


def _eiv_corrected(sums: NDArray, per_row: NDArray, plain: tuple, model: str,
                   min_conditioning: float) -> tuple[NDArray, NDArray, NDArray]:  # fmt: skip
    """The errors-in-variables correction of the pooled solve.

    Noise in the gradients adds its variance to the diagonal of the normal matrix
    A^T A (but, being uncorrelated with the temporal derivative at the same point,
    nothing to A^T b on average), so plain least squares shrinks the flow towards
    zero by roughly signal / (signal + noise) power. That expected contribution
    (``per_row``, (N, m): each unit's gradient-noise variance times its weighted
    sums of w u^m, the neighbours' rel, h_1,j / h_1,i and k_j taken as the point's
    own (1, 1, k_i), the pool being small against h_1) is subtracted from the pp
    and qq entries (bias-compensated least squares). Where a diagonal entry is less
    than twice its noise share the ``plain`` (a, c, conf) is kept: there the
    corrected one divides small noisy quantities and is heavy-tailed.
    """
    a, c, conf = plain
    noise = np.zeros_like(sums)
    noise[..., 0] = per_row
    noise[..., 2] = per_row
    ac, cc, confc = _solve_sums(sums - noise, model, min_conditioning, positive=True)
    strong = (sums[:, 0, 0] > 2.0 * per_row[:, 0]) & (sums[:, 0, 2] > 2.0 * per_row[:, 0])
    use = strong & np.isfinite(ac) & np.isfinite(cc)
    return np.where(use, ac, a), np.where(use, cc, c), np.where(use, confc, conf)


def motion_statistic(
    pool, derivs6: tuple, sums: NDArray, wsum: NDArray, model: str, h1: NDArray
) -> tuple[NDArray, NDArray]:
    """The Wald statistic of zero flow over each point's pool (``static_test`` of
    :func:`pooled_solution`): the squared residual the flow (a, h_1 b) explains, over the
    pool's remaining residual variance per row; and the standard error of (a, h_1 b)
    along its weakest direction (px per frame: the residual variance over the smallest
    eigenvalue of the normal matrix). NaN where the pool has no solution.

    ``pool(derivs6)`` forms the pooled sums of six derivative arrays (with the zero
    sentinel) as :func:`pooled_solution` does; ``sums``, ``wsum`` are those of the
    equations themselves. The pool's sum of squared f_t comes from the same sums with
    f_t in the place of f_theta (their qq entry is sum_j w (f1_t^2 + f2_t^2) / h_1,i^2).
    """
    zero = np.zeros_like(derivs6[0])
    ft_sums, _ = pool((zero, derivs6[2], zero, zero, derivs6[5], zero))
    ff = ft_sums[:, 0, 2] * h1 * h1  # sum_j w (f1_t^2 + f2_t^2)
    a, c, _, explained, lam_min = _solve_sums(sums, model, 0.0, explained=True)
    rows = 2.0 * wsum[:, 0]  # both units' equations
    ok = np.isfinite(a) & np.isfinite(c)
    with np.errstate(divide="ignore", invalid="ignore"):
        variance = (ff - explained) / rows
        stat = np.where(ok, explained / variance, np.nan)
        sd = np.where(ok, np.sqrt(np.maximum(variance, 0.0) / lam_min), np.nan)
    return stat, sd


def _weight_sums(
    w: NDArray, s: NDArray, idx: NDArray, th: NDArray | None, hi: NDArray, model: str, scale: float
) -> NDArray:
    """sum_j w_ij s_ij u_ij^m, m = 0 (constant model) or 0, 1, 2 (linear), shape (N, 1 or 3)."""
    ws = w * s
    if model == "constant":
        return ws.sum(axis=1)[:, None]
    n = idx.shape[0]
    u = (((th[idx] - th[:n, None]) + np.pi) % (2 * np.pi) - np.pi) * hi[:, None] / scale
    return np.stack([ws.sum(axis=1), (ws * u).sum(axis=1), (ws * u * u).sum(axis=1)], axis=1)


def _unit_residuals(derivs: tuple, k: NDArray, a: NDArray, b: NDArray, n: int) -> tuple:
    """Residuals of eq. (9) and (15) at each point's own flow (a, b); ``derivs`` carry a
    sentinel at index n."""
    f1_h, f1_theta, f1_t, f2_h, f2_theta, f2_t = derivs
    res1 = flow_residual(f1_h[:n], f1_theta[:n], f1_t[:n], a, b)  # eq. (9)
    res2 = flow_residual(k[:n] * f2_h[:n], f2_theta[:n], f2_t[:n], a, b)  # eq. (15)
    return res1, res2


def _unit_variances(
    derivs: tuple,
    k: NDArray,
    a: NDArray,
    b: NDArray,
    n: int,
    idx: NDArray,
    w: NDArray,
    how: str,
) -> tuple[NDArray | None, NDArray | None]:
    """Residual variance of each unit's equation at each point (for ``unit_weighting``).

    The residual of eq. (9) and (15) of every point at its own solution
    (a, b); "global": one median-based variance per unit for all points;
    "local": the weighted mean of the squared residuals over each point's pool
    (``idx``, ``w``), floored at 1 % of the unit's global figure so that no
    unit's weight runs away where its residuals happen to vanish. (None, None)
    when fewer than 10 points have a solution or a variance is 0.
    """
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 10:
        return None, None
    out = []
    for res in _unit_residuals(derivs, k, a, b, n):
        res2 = np.where(ok, res * res, np.nan)
        glob = float(np.nanmedian(res2)) / 0.455  # median of a squared normal: 0.455 var
        if how == "global":
            out.append(np.full(n, glob))
            continue
        near = np.append(res2, np.nan)[idx]  # (N, K), NaN: no neighbour or no solution
        wr = np.where(np.isfinite(near), w, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            local = (wr * np.nan_to_num(near)).sum(axis=1) / wr.sum(axis=1)
        out.append(np.maximum(np.where(np.isfinite(local), local, glob), 0.01 * glob))
    if not (out[0].min() > 0 and out[1].min() > 0):
        return None, None
    return out[0], out[1]


def _residual_variance(
    derivs: tuple, k: NDArray, a: NDArray, b: NDArray, n: int
) -> tuple[float, float]:
    """Noise variance of each unit's fitted image from the residuals of eq. (9) and (15).

    At the plain solution (a, c = h_1 b) the residual of a point is the noise
    of its f_t (the difference of two fits: twice the fitted value's noise
    variance) plus terms of second order; the median of a squared normal
    variable is 0.455 of its variance.
    """
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 10:
        return 0.0, 0.0
    res1, res2 = _unit_residuals(derivs, k, a, b, n)
    return tuple(float(np.median(res[ok] ** 2)) / 0.455 / 2.0 for res in (res1, res2))


def _solve_sums(
    sums: NDArray,
    model: str,
    min_conditioning: float,
    *,
    positive: bool = False,
    explained: bool = False,
) -> tuple[NDArray, ...]:
    """Solve the pooled normal equations from their weighted sums.

    ``sums`` (N, 1 or 3, 5): sum_j w u^m (pp, pq, qq, pf, qf). Returns
    (a, h_1 b, confidence); NaN where singular, below ``min_conditioning`` or,
    with ``positive``, where the matrix is not positive definite. With
    ``explained`` also x^T v, the squared residual the solution x = (a, h_1 b)
    explains (x^T S x, S the normal matrix on (a, h_1 b) and v its right side,
    both after the slopes are solved out for ``"linear"``), and S's smaller eigenvalue.
    """
    a, c, conf, explained_, lam_min = pooled_solves(
        sums, linear=model != "constant", min_conditioning=min_conditioning, positive=positive
    )  # compiled, numpy's operations in numpy's order (omniflow.solve.pooled_kernels)
    if explained:
        return a, c, conf, explained_, lam_min
    return a, c, conf
