"""One more Gauss-Newton step, only at the points that move far.

The first-order step of eq. (8) reads the temporal derivative as the
difference of frames t + 1 and t, and (``gradients="average"``) the gradient
as their mean. For one texture component of wavenumber k (rad/px) displaced
by d pixels, that pair of finite differences answers (2 / k) tan(k d / 2)
instead of d: too long by about (k d)^2 / 12, a fraction that grows with the
square of the motion. Below half a pixel it is lost in the noise; an object
crossing at 0.7 px per frame in cam1 (1.2 px in cam2, whose radial flow is
h_2 / h_1 times cam1's, eq. 14) comes out 8-9 % too fast in both components
(docs/decisions/refinement.md).

:func:`refine_moving` re-linearises eq. (8) at the displaced points, as
``OmniFlowConfig.iterations`` always did, but only where the first step's
displacement in either unit is at least ``OmniFlowConfig.refinement.iterate_min_px``
pixels, and only where at least ``MIN_NEIGHBOURS`` other fast points lie within
the pool radius, so that a lone wrong match whose first step happens to be fast
is left as it is. At so few points the fitted series are evaluated exactly
(:meth:`omniflow.paper.dct.DCTFit.evaluate`) rather than read off pixel grids, so the
step builds no grid. Static points keep the first-order answer, which the extra
step only makes noisier where the motion is small (the same page).

Each point's equation is linearised about its own first-step flow and the pools
are solved for the total flow, not for an increment: an increment pooled over
neighbours that each moved by their own (noisy) first estimate adds the
difference between a point's first estimate and its neighbours' to the answer,
the first step's noise passed through a high-pass filter (on the rendered
scenes the refined points' error rose by 10-140 % that way; docs/decisions/refinement.md).
For the same reason a fast point pools with the neighbours of its first solve
(``pools``, the k-d tree's), slow ones included, each linearised about its own
flow: pools of the fast points alone are thin where few points move fast.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from omniflow.config import OmniFlowConfig
from omniflow.geometry.rig import Rig
from omniflow.paper.edges import polar_from_cartesian
from omniflow.parallel import map_tasks

__all__ = ["moving_far", "refine_moving"]

_BLAS: list = []  # the process's threadpoolctl controller, made on first use


def _one_blas_thread():
    """A context in which BLAS runs on the calling thread only.

    The exact evaluation is a few small matrix products; OpenBLAS would spread
    each over every core and its workers then spin for a while after the call,
    taking a core from omniflow's own threads and from whatever runs next
    (measured: DIS medium's time in the same process doubled).
    """
    if not _BLAS:
        from threadpoolctl import ThreadpoolController

        _BLAS.append(ThreadpoolController())
    return _BLAS[0].limit(limits=1, user_api="blas")


MIN_NEIGHBOURS = 8  # other fast points within the pool radius: a moving surface, not a stray
SINGLE = True  # the exact evaluations' products in float32 (DCTFit.value_and_gradient)


def moving_far(a: NDArray, b: NDArray, h1: NDArray, h2: NDArray, min_px: float) -> NDArray:
    """Points whose polar flow moves them at least ``min_px`` pixels in cam1 or cam2.

    The displacement is |(dh_i, h_i dtheta)| per unit, with dh_2 = (h_2 / h_1) dh_1
    (eq. 14); a NaN flow is never selected.
    """
    with np.errstate(invalid="ignore"):
        d1 = np.hypot(a, h1 * b)
        d2 = np.hypot((h2 / h1) * a, h2 * b)
        return np.isfinite(d1 + d2) & (np.maximum(d1, d2) >= min_px)


def refine_moving(
    a: NDArray,
    b: NDArray,
    conf: NDArray,
    *,
    cam1: dict,
    cam2: dict,
    rig: Rig,
    x1: NDArray,
    y1: NDArray,
    x2: NDArray,
    y2: NDArray,
    theta: NDArray,
    h1: NDArray,
    h2: NDArray,
    r: NDArray,
    config: OmniFlowConfig,
    make_solver: Callable,
    noise: tuple[float, float] = (0.0, 0.0),
    pools: tuple[NDArray, NDArray] | None = None,
    brightness: tuple[NDArray, NDArray] | None = None,
) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """``config.iterations`` Gauss-Newton steps at the points :func:`moving_far` selects.

    ``cam1``, ``cam2`` are the per-unit frames of :func:`omniflow.fit.series.unit_frames`
    (``b``: frame t + 1, ``af``: frame t, both at the flow band);
    ``make_solver(rig, config, x1, y1, theta, h1, h2, r, noise)`` builds the
    configured solver for a subset (:func:`omniflow.solve.at_matches.make_solver`, passed
    in so that this module does not import the module that calls it).
    ``pools``: the first solve's (idx, w) (:func:`omniflow.solve.pooled.neighbourhoods`),
    when it pooled over k-d tree neighbours; the refined points' pool members are
    then solved with them (each linearised about its own first flow, a NaN one
    about zero motion), else the fast points pool among themselves.
    ``brightness``: each unit's image at the points, passed on to ``make_solver`` for
    the gain term (``config.brightness_gate``, :mod:`omniflow.solve.gain`): the refined
    pools with a brightness change solve with it as the first solve did.

    Returns
    -------
    a, b, conf : ndarray
        dh_1/dt, dtheta/dt and confidence, refined where selected.
    refined : ndarray of bool
        The points that took the refinement.
    """
    sel = moving_far(a, b, h1, h2, config.refinement.iterate_min_px)
    # pooled solves only: the direct solution's fast points are mostly its ill-conditioned
    # failures, and a Gauss-Newton step from them diverges (default scene: mean EPE at
    # those points 5.4 -> 30 px; docs/decisions/refinement.md)
    if config.iterations == 0 or config.solver != "pooled" or sel.sum() <= MIN_NEIGHBOURS:
        return a, b, conf, np.zeros_like(sel)
    # only where the fast points form a surface: a point whose first step alone is
    # fast (a wrong match, a stray equation) has no pool of fast neighbours to refine in
    radius = rig.cam1.r_m / 8.0 if config.pool_radius is None else config.pool_radius
    xy = np.column_stack([x1[sel], y1[sel]])
    near = cKDTree(xy).query_ball_point(xy, radius, return_length=True) - 1
    sel[np.flatnonzero(sel)[near < MIN_NEIGHBOURS]] = False
    if not sel.any():
        return a, b, conf, sel
    group = sel.copy()  # the points solved: the fast ones and their first pools
    if pools is not None:
        idx, w = pools
        members = idx[sel][w[sel] > 0]
        group[members[members < sel.size]] = True
    i = np.flatnonzero(group)
    out = sel[i]  # the solved points whose flow is replaced
    th, g1, g2 = theta[i], h1[i], h2[i]
    kw = {} if brightness is None else {"brightness": tuple(f[i] for f in brightness)}
    solve = make_solver(rig, config, x1[i], y1[i], th, g1, g2, r[i], noise, **kw)
    ai = np.nan_to_num(a[i], nan=0.0, posinf=0.0, neginf=0.0)  # where each is linearised
    bi = np.nan_to_num(b[i], nan=0.0, posinf=0.0, neginf=0.0)
    ci = conf[i].copy()
    k = g2 / g1  # eq. (14)
    with _one_blas_thread():
        for _ in range(config.iterations):
            # the two units' exact evaluations (a few BLAS products each) on the two
            # threads of omniflow.parallel: the same products either way
            (q1_h, q1_th, e1), (q2_h, q2_th, e2) = map_tasks(
                _unit_rows,
                (cam1, x1[i], y1[i], g1, ai, th, bi, config),
                (cam2, x2[i], y2[i], g2, k * ai, th, bi, config),
            )
            # eq. (8) linearised about each point's own flow, for the total flow:
            # f_h (a - a_i) + f_theta (b - b_i) + residual = 0
            e1 = e1 - q1_h * ai - q1_th * bi
            e2 = e2 - q2_h * (k * ai) - q2_th * bi
            an, bn, cc = solve(q1_h, q1_th, e1, q2_h, q2_th, e2)
            step = np.isfinite(an) & np.isfinite(bn)
            ai = np.where(step, an, ai)
            bi = np.where(step, bn, bi)
            ci = np.where(step, cc, ci)
    keep = out & np.isfinite(a[i]) & np.isfinite(b[i])  # a fast point had a first flow
    ai, bi, ci = np.where(keep, ai, a[i]), np.where(keep, bi, b[i]), np.where(keep, ci, conf[i])
    a, b, conf = a.copy(), b.copy(), conf.copy()
    a[i], b[i], conf[i] = ai, bi, ci
    return a, b, conf, sel


def _unit_rows(
    fr: dict,
    x: NDArray,
    y: NDArray,
    h_i: NDArray,
    dh: NDArray,
    th: NDArray,
    db: NDArray,
    config: OmniFlowConfig,
) -> tuple[NDArray, NDArray, NDArray]:
    """One unit's eq. (8) linearised about the flow (dh, db) at its points (x, y) = (h_i, th):
    the polar gradient (f_h, f_theta) of frame t + 1 at the displaced point (averaged
    with frame t's at the point for ``gradients="average"``) and brightness constancy's
    residual f_{t+1}(displaced) - f_t(point) (eq. 8), the series evaluated exactly.

    The products run in float32 (``SINGLE``; about half the float64 time): the residual,
    a difference of two grey levels of ~0.3, comes out within 2e-7 of float64's, over
    four orders below its own spread, and the refined flow within 4e-6 px
    (docs/decisions/refinement.md)."""
    unit = fr["a"].unit  # polar gradients below: eq. (19)-(20)
    xd, yd = unit.pixel_of_polar(h_i + dh, th + db)
    fb, g_x, g_y = fr["b"].fit.value_and_gradient(xd, yd, single=SINGLE)  # t + 1, displaced
    fa, a_x, a_y = fr["af"].fit.value_and_gradient(x, y, single=SINGLE)  # frame t, at the point
    g_h, g_th = polar_from_cartesian(g_x, g_y, xd - unit.x_c, yd - unit.y_c)
    if config.fit.gradients == "average":
        a_h, a_th = polar_from_cartesian(a_x, a_y, x - unit.x_c, y - unit.y_c)
        g_h, g_th = 0.5 * (g_h + a_h), 0.5 * (g_th + a_th)
    return g_h, g_th, fb - fa  # brightness constancy's residual (eq. 8)
