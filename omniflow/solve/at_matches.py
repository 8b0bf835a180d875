"""The flow at the matches: sample the derivatives, solve eq. (9) and (15).

:func:`flow_at_matches` reads the gradients and temporal derivatives of both
units at the matched points (:mod:`omniflow.fit.sampling`), solves for the polar
flow with the configured solver (:func:`make_solver`: eq. (16) per point, or
the equations of neighbouring matches pooled, :mod:`omniflow.paper.flow`),
optionally iterates (Gauss-Newton), and returns the result columns.

The two-model test of eq. (14) (:mod:`omniflow.solve.decoupled`) pools the
derivatives, not the flow, so its pool fits are made on the other thread of
:mod:`omniflow.parallel` while this one refines the flow; they are used only
where the refinement kept the same points (it does: a refined flow stays
finite), else made again, so the columns do not depend on the threads.
"""

from __future__ import annotations

import time
from functools import partial

import numpy as np
from numpy.typing import NDArray

from omniflow.config import OmniFlowConfig
from omniflow.fit.sampling import sample_f, sample_fine, sample_polar_grad
from omniflow.geometry.rig import Rig, Unit
from omniflow.matching import Matches
from omniflow.paper.flow import conditioning as direct_conditioning
from omniflow.paper.flow import determinant, direct_solution, radial_velocity
from omniflow.parallel import submit
from omniflow.solve.decoupled import decouple, start_pool_fits, tests
from omniflow.solve.gain import gain_solution, gated
from omniflow.solve.gridpool import GridPools
from omniflow.solve.pooled import POOL_MODEL, neighbourhoods, pooled_solution
from omniflow.solve.refine import refine_moving

__all__ = ["flow_at_matches", "make_solver"]


def flow_at_matches(
    matches: Matches, rig: Rig, cam1: tuple, cam2: tuple, config: OmniFlowConfig
) -> dict[str, NDArray]:
    """Sample gradients and temporal derivatives at the matches and solve.

    ``cam1`` and ``cam2`` are the per-unit series as built by :func:`estimate`
    (keys ``a``, ``g``, ``t``; see ``unit_fits``).
    Returns the result columns (plus a private ``_t_sample`` timing).
    """
    t0 = time.perf_counter()
    theta, h1, h2 = matches.theta, matches.h1, matches.h2
    x1, y1 = rig.cam1.pixel_of_polar(h1, theta)
    x2, y2 = rig.cam2.pixel_of_polar(h2, theta)
    derivs = []
    for fr, x, y in ((cam1, x1, y1), (cam2, x2, y2)):
        f_h, f_th = sample_polar_grad(fr["g"], x, y, config.fit.sampling)
        f_t = sample_f(fr["t"], x, y, config.fit.sampling)  # section 5.3
        derivs.append((f_h, f_th, f_t))
    (f1_h, f1_th, f1_t), (f2_h, f2_th, f2_t) = derivs
    t1 = time.perf_counter()
    r, h = rig.triangulate(h1, h2)
    noise = (cam1.get("noise_var", 0.0), cam2.get("noise_var", 0.0))
    brightness = None
    gains = config.brightness_gate is not None or config.brightness.decouple_gain_tol is not None
    if gains and config.solver == "pooled":
        # the image at the points (omniflow.solve.gain): frame t at the matching band, whose
        # grid the matcher has made already (the gradients' series, the mean of frames t
        # and t + 1 at the flow band, would cost a grid per unit; a regressor of the
        # brightness either way: docs/decisions/brightness_model.md)
        brightness = (sample_f(cam1["a"], x1, y1, config.fit.sampling),
                      sample_f(cam2["a"], x2, y2, config.fit.sampling))  # fmt: skip
    solve = make_solver(rig, config, x1, y1, theta, h1, h2, r, noise,
                        static_test=config.pooling.static_test, brightness=brightness)  # fmt: skip
    # the two-model test's pool fits read no flow, only the points that keep one (those
    # of the first solve, a refined point keeps a finite flow: checked below)
    derivs = {"f1_h": f1_h, "f1_theta": f1_th, "f1_t": f1_t,
              "f2_h": f2_h, "f2_theta": f2_th, "f2_t": f2_t}  # fmt: skip
    kept = {"x": x1, "y": y1, "r": r, "h1": h1, "h2": h2, "theta": theta, **derivs}
    speculative = []  # on the grid, every point's: made while the first solve's gain fit runs

    def meanwhile() -> None:
        pools = None if solve.pools is None else (*solve.pools, np.ones(theta.size, bool))
        speculative.append(start_pool_fits(kept, rig, config, pools, brightness))
        speculative[0].take_last()  # the models' fits here if the pool is busy

    ahead = config.grid_pools and tests(config, theta.size)
    try:
        a, b, conf = solve(f1_h, f1_th, f1_t, f2_h, f2_th, f2_t,
                           **({"meanwhile": meanwhile} if ahead else {}))  # fmt: skip
    except BaseException:
        for task in speculative:
            task.cancel()  # no task outlives the call
        raise
    floor = config.matching.edge_smooth_floor if config.solver == "pooled" else None
    if floor is not None and matches.ramp is not None:
        # a smooth-profile match (edge_smooth) whose pool is a ramp in two dimensions
        # too: NCC could not place it, nor can the flow equations be solved there
        ramp = matches.ramp & ~(conf >= floor)
        a, b = np.where(ramp, np.nan, a), np.where(ramp, np.nan, b)
    D = determinant(f1_h, f1_th, f2_h, f2_th, h1, h2)
    k = h2 / h1  # eq. (14)
    # made on the other thread while this one refines (or already, on every point)
    keep0 = np.isfinite(a) & np.isfinite(b)
    if speculative and keep0.all():
        early = speculative[0]
    else:
        for task in speculative:
            task.cancel()  # made for points that lost their flow: again for those kept
        f_kept = brightness
        if not keep0.all():
            kept = {c: v[keep0] for c, v in kept.items()}
            f_kept = None if brightness is None else tuple(f[keep0] for f in brightness)
        pools0 = None if solve.pools is None else (*solve.pools, keep0)
        early = start_pool_fits(kept, rig, config, pools0, f_kept)  # on the pool's thread
    try:
        a, b, conf = _refine(a, b, conf, solve, k, cam1, cam2, rig, x1, y1, x2, y2, theta,
                             h1, h2, r, config, noise, brightness)  # fmt: skip
    except BaseException:
        early.cancel()  # no task outlives the call
        raise
    keep = np.isfinite(a) & np.isfinite(b)
    if not np.all(keep):
        (theta, h1, h2, x1, y1, x2, y2, r, h, a, b, D, conf) = (
            v[keep] for v in (theta, h1, h2, x1, y1, x2, y2, r, h, a, b, D, conf)
        )
        (f1_h, f1_th, f1_t, f2_h, f2_th, f2_t) = (
            v[keep] for v in (f1_h, f1_th, f1_t, f2_h, f2_th, f2_t)
        )
        score = matches.score[keep]
        if brightness is not None:
            brightness = tuple(f[keep] for f in brightness)
    else:
        score = matches.score
    dr_dt = radial_velocity(r, h1, a, d=rig.d)  # -(d + r) dh_1/dt / h_1
    k = h2 / h1
    dx, dy = _displacement(rig.cam1, h1, theta, a, b)
    dx2, dy2 = _displacement(rig.cam2, h2, theta, k * a, b)
    cols = {
        "x": x1,
        "y": y1,
        "theta": theta,
        "h1": h1,
        "h2": h2,
        "r": r,
        "h": h,
        "dh1_dt": a,
        "dtheta_dt": b,
        "dr_dt": dr_dt,
        "dx": dx,
        "dy": dy,
        "x2": x2,
        "y2": y2,
        "dh2_dt": k * a,
        "dx2": dx2,
        "dy2": dy2,
        "score": np.asarray(score, dtype=float),
        "confidence": conf,
        "D": D,
        "f1_h": f1_h,
        "f1_theta": f1_th,
        "f1_t": f1_t,
        "f2_h": f2_h,
        "f2_theta": f2_th,
        "f2_t": f2_t,
        "_t_sample": t1 - t0,
    }
    pools = None if solve.pools is None else (*solve.pools, keep)
    if np.array_equal(keep, keep0):
        fit = early.result()
    else:  # the refinement lost a point's flow: the fits of the points kept
        early.cancel()
        fit = None
    # eq. (14) tested (omniflow.solve.decoupled) over the solver's own pools
    gain = {} if brightness is None else {"brightness": brightness}  # omniflow.solve.gain
    return decouple(cols, rig, config, _displacement, pools=pools, fit=fit, **gain)


def _refine(a, b, conf, solve, k, cam1, cam2, rig, x1, y1, x2, y2, theta, h1, h2, r, config,
            noise, brightness=None):  # fmt: skip
    """The first solve's (a, b, conf) refined: at the points that move far
    (:func:`omniflow.solve.refine.refine_moving`, ``iterate_min_px`` > 0) or at every point
    (``iterations`` Gauss-Newton steps on grids read off-pixel)."""
    if (
        config.refinement.iterate_min_px > 0.0
    ):  # refine only the points that move far (omniflow.solve.refine)
        a, b, conf, _ = refine_moving(
            a, b, conf, cam1=cam1, cam2=cam2, rig=rig, x1=x1, y1=y1, x2=x2, y2=y2,
            theta=theta, h1=h1, h2=h2, r=r, config=config, make_solver=make_solver, noise=noise,
            pools=solve.pools, **({} if brightness is None else {"brightness": brightness}),
        )  # fmt: skip
    for _ in range(config.iterations if config.refinement.iterate_min_px == 0.0 else 0):
        # Gauss-Newton on eq. (8)'s linearisation: the residual of brightness
        # constancy at the displaced points, solved again for the increment.
        ok = np.isfinite(a) & np.isfinite(b)
        da0, db0 = np.where(ok, a, 0.0), np.where(ok, b, 0.0)
        inc = []
        for fr, x, y, h_i, dh in ((cam1, x1, y1, h1, da0), (cam2, x2, y2, h2, k * da0)):
            unit = fr["a"].unit
            xd, yd = unit.pixel_of_polar(h_i + dh, theta + db0)
            g_h, g_th = sample_polar_grad(fr["b"], xd, yd, config.fit.sampling)
            if config.fit.gradients == "average":
                a_h, a_th = sample_polar_grad(fr["af"], x, y, config.fit.sampling)
                g_h, g_th = 0.5 * (g_h + a_h), 0.5 * (g_th + a_th)
            # the residual needs the image itself read off-pixel: cubic
            # interpolation of a series with periods down to 1 / band px is
            # biased by a few per cent, Lanczos (8 taps) much less; both
            # frames at the flow band and taper
            res = sample_fine(fr["b"], xd, yd, config.fit.sampling) - sample_fine(
                fr["af"], x, y, config.fit.sampling
            )
            # linearised about each point's own flow, solved for the total flow (as
            # omniflow.solve.refine: a pooled increment would add the neighbours' noise)
            inc.append((g_h, g_th, res - g_h * dh - g_th * db0))
        (g1_h, g1_th, r1), (g2_h, g2_th, r2) = inc
        an, bn, conf_i = solve(g1_h, g1_th, r1, g2_h, g2_th, r2)
        step = np.isfinite(an) & np.isfinite(bn)
        a = np.where(step, an, a)
        b = np.where(step, bn, b)
        conf = np.where(step, conf_i, conf)
    return a, b, conf


def make_solver(
    rig: Rig,
    config: OmniFlowConfig,
    x1: NDArray,
    y1: NDArray,
    theta: NDArray,
    h1: NDArray,
    h2: NDArray,
    r: NDArray,
    noise: tuple[float, float] = (0.0, 0.0),
    *,
    static_test: float | None = None,
    brightness: tuple[NDArray, NDArray] | None = None,
):
    """The configured solver of eq. (9) and (15) at these matches, as a function
    of the six derivatives returning (dh1_dt, dtheta_dt, confidence).

    ``noise``: the variance of each unit's gradient components, subtracted by
    the pooled solver (``eiv="residual"`` scales it by the residuals). ``static_test``:
    the pooled solver's test of no motion (``config.pooling.static_test``; passed for the
    first solve only: the refinement replaces only the flow of points that move a pixel or
    more).
    ``brightness``: each unit's image f at the points, for the pooled solver's gain
    term (``config.brightness_gate``, :mod:`omniflow.solve.gain`): the pools whose F statistic
    of the gain passes the gate take the answer with it. The gain fit pools over the
    solver's k-d tree pools, or over its grid windows (``pool_grid``).

    The returned function's attribute ``pools``: the (idx, w) of
    :func:`omniflow.solve.pooled.neighbourhoods` where the solver pools over them as
    searched (k-d tree pools), else None."""
    if config.solver == "direct":

        def solve(f1_h, f1_th, f1_t, f2_h, f2_th, f2_t):
            a, b, _ = direct_solution(f1_h, f1_th, f1_t, f2_h, f2_th, f2_t, h1, h2)
            return a, b, direct_conditioning(f1_h, f1_th, f2_h, f2_th, h1, h2)

        solve.pools = None
        return solve

    pool_radius = rig.cam1.r_m / 8.0 if config.pool_radius is None else config.pool_radius
    tree = dict(
        k=config.pooling.pool_k, radius=pool_radius, r=r, range_tol=config.pooling.pool_range_tol
    )
    grid = None
    if config.grid_pools:
        idx = w = None
        eps = 1e-3  # rad: the tangent d(x, y)/dtheta / h_1 by central differences
        xp, yp = rig.cam1.pixel_of_polar(h1, theta + eps)
        xm, ym = rig.cam1.pixel_of_polar(h1, theta - eps)
        tangent = np.column_stack([xp - xm, yp - ym]) / (2.0 * eps * h1[:, None])
        grid = GridPools(
            x1, y1, tangent, (rig.cam1.height, rig.cam1.width), radius=pool_radius,
            cell=config.pooling.pool_grid * pool_radius, r=r,
            range_tol=config.pooling.pool_range_tol,
            tree_pools=lambda mask: neighbourhoods(x1, y1, **tree, query=mask),
        )  # fmt: skip
    else:
        idx, w = neighbourhoods(x1, y1, **tree)

    floor = config.pooling.pool_min_conditioning
    kw = dict(theta=theta, model=POOL_MODEL, scale=pool_radius,
              min_conditioning=floor)  # fmt: skip

    def plain(f1_h, f1_th, f1_t, f2_h, f2_th, f2_t, meanwhile=None):
        if meanwhile is not None:  # nothing to wait for: the caller's work first
            meanwhile()
        return pooled_solution(
            f1_h, f1_th, f1_t, f2_h, f2_th, f2_t, h1, h2, idx, w, **kw, noise1=noise[0],
            noise2=noise[1], residual_noise=config.pooling.eiv == "residual", grid=grid,
            static_test=static_test, static_max_px=config.pooling.static_max_px,
        )  # fmt: skip

    solve = plain
    if config.brightness_gate is not None and brightness is not None:
        gain_kw = dict(model=POOL_MODEL, scale=pool_radius, min_conditioning=floor,
                       noise=noise, residual_noise=config.pooling.eiv == "residual",
                       gate=config.brightness_gate, grid=grid,
                       linear_gain=grid is None and config.brightness.brightness_model == "linear",
                       )  # fmt: skip

        def solve(*derivs, meanwhile=None):
            # the gain fit on the other thread while this one makes the plain solve, then
            # the caller's ``meanwhile()`` (work queued behind the gain fit, or made here)
            task = submit(partial(gain_solution, **gain_kw), derivs, brightness, h1, h2, theta,
                          idx, w)  # fmt: skip
            try:
                a, b, conf = plain(*derivs)
                if meanwhile is not None:
                    meanwhile()
            except BaseException:
                task.cancel()  # no task outlives the call
                raise
            ag, bg, confg, F = task.result()
            use = gated(F, config.brightness_gate, ag, bg)
            return np.where(use, ag, a), np.where(use, bg, b), np.where(use, confg, conf)

    # the plain k-nearest pools, which omniflow.solve.decoupled would search again
    solve.pools = (idx, w) if grid is None else None
    return solve


def _displacement(
    unit: Unit, h_i: NDArray, theta: NDArray, dh: NDArray, dtheta: NDArray
) -> tuple[NDArray, NDArray]:
    """Pixel displacement of the polar point (h_i, theta) moved by (dh, dtheta)."""
    x0, y0 = unit.pixel_of_polar(h_i, theta)
    x1, y1 = unit.pixel_of_polar(h_i + dh, theta + dtheta)
    return x1 - x0, y1 - y0
