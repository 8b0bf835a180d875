"""The pooled solver: eq. (9) and (15) of neighbouring matches in least squares.

A polar Lucas-Kanade over both units (:mod:`omniflow.paper.flow` gives the equations
and why one point's 2x2 solve is ill-conditioned); the confidence column is
lambda_min / lambda_max of each pool's normal matrix.

Pools that respect objects: :func:`neighbourhoods` leaves out neighbours at another
range (docs/decisions/pooling.md: at the robust matcher's points this keeps movers'
pools on the movers; the other object-aware tests measured were retired,
docs/decisions/retired_knobs.md).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from omniflow.paper.flow import flow_residual
from omniflow.solve.gridpool import GridPools
from omniflow.solve.pooled_kernels import cell_knn, pooled_solves, pooled_sums

__all__ = [
    "POOL_MODEL",
    "motion_statistic",
    "neighbourhoods",
    "pooled_solution",
]

#: The local flow model the pipeline's pools fit: linear in theta across the pool
#: (docs/decisions/pooling.md; the constant model, ``model="constant"`` here, lost:
#: docs/decisions/retired_knobs.md, ``pool_model``).
POOL_MODEL = "linear"


def neighbourhoods(
    x: ArrayLike,
    y: ArrayLike,
    *,
    k: int = 12,
    radius: float = 4.0,
    r: ArrayLike | None = None,
    range_tol: float | None = 0.1,
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
    if kk < k:
        idx = np.pad(idx, ((0, 0), (0, k - kk)), constant_values=n)
        w = np.pad(w, ((0, 0), (0, k - kk)))
    return idx, w


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
    grid : GridPools, optional
        Pool by filtering on a grid (:mod:`omniflow.solve.gridpool`) instead of over
        ``idx``, ``w`` (``relative`` model only); the
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
    _check_pool_args(model, theta, grid, relative)
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
    # sums (N, 1 or 3, 5): sum_j w u^m (pp, pq, qq, pf, qf); wsum: sum_j w u^m
    a, c, conf = _solve_sums(sums, model, min_conditioning)
    derivs = (f1_h, f1_theta, f1_t, f2_h, f2_theta, f2_t)
    if residual_noise and (noise1 > 0 or noise2 > 0):
        n1, n2 = _residual_variance(derivs, k, a, c / h1[:n], n)
        noise1, noise2 = noise1 * n1, noise2 * n2
    if noise1 > 0 or noise2 > 0:
        per_row = noise1 * wsum + (noise2 * k[:n] ** 2)[:, None] * wsum  # (N, m)
        a, c, conf = _eiv_corrected(sums, per_row, (a, c, conf), model, min_conditioning)
    if static_test is not None:  # the equal-weight pools' Wald test of no motion
        stat, sd = motion_statistic(pool, derivs6, sums, wsum, model, h1[:n])
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


def _check_pool_args(model: str, theta, grid, relative: bool) -> None:
    """pooled_solution's choices checked against each other."""
    if model not in ("constant", "linear"):
        raise ValueError(f"model = {model!r}: expected 'constant' or 'linear'")
    if model == "linear" and theta is None:
        raise ValueError("model='linear' needs theta")
    if grid is not None and not relative:
        raise ValueError("grid pools need relative=True")


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


def _unit_residuals(derivs: tuple, k: NDArray, a: NDArray, b: NDArray, n: int) -> tuple:
    """Residuals of eq. (9) and (15) at each point's own flow (a, b); ``derivs`` carry a
    sentinel at index n."""
    f1_h, f1_theta, f1_t, f2_h, f2_theta, f2_t = derivs
    res1 = flow_residual(f1_h[:n], f1_theta[:n], f1_t[:n], a, b)  # eq. (9)
    res2 = flow_residual(k[:n] * f2_h[:n], f2_theta[:n], f2_t[:n], a, b)  # eq. (15)
    return res1, res2


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
