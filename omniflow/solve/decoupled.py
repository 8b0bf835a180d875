"""Where eq. (14) fails: detect it and solve each unit's radial flow on its own.

The coaxial solution couples the two units' radial flows through
dh_2 = (h_2 / h_1) dh_1 (eq. 14), which holds only for a scene point that
does not move along the axis. Differentiating eq. (3) and (4)::

    dr h_1 + (d + r) dh_1 = v dh                                (eq. 3, d/dt)
    dr h_2 + (d + r) dh_2 = v dh                                (eq. 4, d/dt)

so for dh != 0 (an object rising or falling, or a rolling ball or tumbling
ring whose texture moves vertically) the two radial flows are independent
unknowns, and a solve that ties them answers a wrong radial flow on both
cameras. Solving the two for the flows, dh_i/dt = U - h_i W in either unit
with U = v dh / (d + r) and W = dr / (d + r): U is the axial motion's share,
the same in both units, and W the range's, scaling with each unit's h_i
(U = 0 is eq. (14)). The azimuth is still shared (theta_1 = theta_2 for every
point of a coaxial rig), so the decoupled model has three unknowns,
(U, W, dtheta/dt), in eq. (9) of unit 1 and eq. (10) of unit 2, pooled over
the same neighbours as the coupled solve (U, W and dtheta/dt shared by the
pool, a rigid patch at one range; with ``pool_grid`` the solver's grid windows,
:meth:`omniflow.solve.gridpool.GridPools.decouple_sums`)::

    f1_h (U - h_1 W) + f1_theta b = -f1_t                       # eq. (9)
    f2_h (U - h_2 W) + f2_theta b = -f2_t                       # eq. (10)

Detection (:func:`decouple`). Both models are fitted in weighted least
squares over each point's pool (constant model; with U = 0 the radial flow
scales with the image radius as in :func:`omniflow.solve.pooled.pooled_solution`);
the decoupled one has one more unknown, so its residual sum is never
larger. The F statistic of that one extra unknown,

    F = (RSS_coupled - RSS_decoupled) / (RSS_decoupled / (n_eff - 3)),

is large only where the two units' equations cannot be satisfied with one
radial flow: there the point is reported decoupled (column ``coupled`` =
0) with the three-unknown solution. ``n_eff`` is the pool's effective
number of rows, (sum w)^2 / sum w^2 per unit. The threshold is a knob
(``OmniFlowConfig.decouple_tol``) chosen on the rendered scenes
(docs/decisions/decoupling.md): neighbouring
residuals are correlated by the DCT fit, so F is not F-distributed and the
textbook quantile would switch static points.

A brightness change that varies across a pool (a body turning under fixed
lights) inflates both fits' residuals and hides a failing eq. (14) from that
test. With ``OmniFlowConfig.brightness.decouple_gain_tol`` the test is made again with a
gain varying linearly across the pool in both models
(:func:`omniflow.solve.gain.decoupled_linear_gain`), and the points it passes
(:func:`chained`) take the decoupled model with that gain (without it where
the gain does not matter: :data:`omniflow.solve.gain.MIN_GAIN_F`).

Range rate without eq. (14): subtracting the two differentiated equations
gives dr/dt = -(d + r)(dh_2/dt - dh_1/dt) / (h_2 - h_1)
(:func:`omniflow.paper.flow.radial_velocity_stereo`), exact whatever dh/dt.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from omniflow.config import OmniFlowConfig
from omniflow.geometry.rig import Rig
from omniflow.paper.flow import radial_velocity_stereo
from omniflow.parallel import Task, submit
from omniflow.solve.decouple_kernels import decouple_fits, decouple_sums
from omniflow.solve.gain import decoupled_gain, decoupled_linear_gain, gated
from omniflow.solve.gain_kernels import nested_fits
from omniflow.solve.gridpool import GridPools
from omniflow.solve.pooled import neighbourhoods

__all__ = [
    "EDGE_GATE",
    "EDGE_SHARE",
    "SCREEN_F",
    "SCREEN_RATIO",
    "chained",
    "decouple",
    "fits_from_sums",
    "model_fits",
    "pool_fits",
    "screen",
    "start_pool_fits",
    "tests",
]


def model_fits(
    derivs: tuple[NDArray, ...],
    h1: NDArray,
    h2: NDArray,
    idx: NDArray,
    w: NDArray,
) -> dict[str, NDArray]:
    """Coupled and decoupled pooled least-squares fits at every point.

    Parameters
    ----------
    derivs : six ndarrays, shape (N,)
        f1_h, f1_theta, f1_t, f2_h, f2_theta, f2_t at the matches.
    h1, h2 : ndarray, shape (N,)
        Matched image radii, pixels.
    idx, w : ndarray, shape (N, K)
        Pools as :func:`omniflow.solve.pooled.neighbourhoods` returns them (index N:
        no neighbour, weight 0).

    Returns
    -------
    dict
        ``a1``, ``a2`` (dh_1/dt and dh_2/dt of the decoupled fit, px/frame),
        ``b`` (its dtheta/dt, rad/frame), ``U`` (v dh / (d + r), the axial
        motion's share of either unit's radial flow, px/frame),
        ``coupled_a``, ``coupled_b`` (the fit with U = 0, eq. 14), ``F``
        (the statistic of the extra unknown; NaN where either fit is
        singular), ``n_eff``.
    """
    h1, h2 = (np.asarray(v, dtype=np.float64) for v in (h1, h2))
    return fits_from_sums(decouple_sums(idx, w, derivs, h1, h2), h1, h2)


def fits_from_sums(sums: NDArray, h1: NDArray, h2: NDArray) -> dict[str, NDArray]:
    """:func:`model_fits` from the pools' sums
    (:func:`omniflow.solve.decouple_kernels.decouple_sums`
    or :meth:`omniflow.solve.gridpool.GridPools.decouple_sums`, columns
    :data:`omniflow.solve.decouple_kernels.DECOUPLE_SUMS`).

    Unknowns (U, W, c): dh_i/dt = U - h_i W in either unit (eq. 3-4 differentiated,
    U = v dh / (d + r), W = dr / (d + r), both shared by a pool on one surface), W
    scaled by h_1,i and c = h_1,i dtheta/dt. Unit u's row of neighbour j is
    (f_h, -f_h h_u,j / h_1,i, f_theta / h_1,i) . (U, h_1,i W, c) = -f_t; U = 0 is the
    coupled model (eq. 14), whose W column is pooled_solution's relative radial one.
    Each fit is NaN where its normal matrix's condition number is 1e8 or more.
    """
    h1, h2 = (np.asarray(v, dtype=np.float64) for v in (h1, h2))
    x3, x2, rss = decouple_fits(sums, h1)
    rss3, rss2 = rss[:, 0], rss[:, 1]  # min of sum w (A x + t)^2 = t^T t + g . x
    wsum, w2sum = sums[:, 10], sums[:, 11]
    with np.errstate(divide="ignore", invalid="ignore"):
        n_eff = 2.0 * wsum * wsum / w2sum  # two rows (one per unit) per neighbour
        F = (rss2 - rss3) / (rss3 / (n_eff - 3.0))
    F = np.where((n_eff > 4.0) & (rss3 > 0), F, np.nan)
    k = h2 / h1
    return {
        "a1": x3[:, 0] - x3[:, 1],
        "a2": x3[:, 0] - k * x3[:, 1],
        "b": x3[:, 2] / h1,
        "U": x3[:, 0],
        "coupled_a": -x2[:, 0],
        "coupled_b": x2[:, 1] / h1,
        "F": F,
        "n_eff": n_eff,
    }


def decouple(
    cols: dict[str, NDArray],
    rig: Rig,
    config: OmniFlowConfig,
    displacement: Callable,
    *,
    pools: tuple[NDArray, NDArray, NDArray] | None = None,
    fit: dict[str, NDArray] | None = None,
    brightness: tuple[NDArray, NDArray] | None = None,
) -> dict[str, NDArray]:
    """Add the ``coupled`` column and, where eq. (14) fails, the decoupled flow.

    ``cols`` are the result columns of :func:`omniflow.solve.at_matches.flow_at_matches`
    (the six derivatives, ``x``, ``y``, ``h1``, ``h2``, ``r``, ``theta``
    among them). With ``config.decouple_tol`` None, or the direct solver,
    every point stays coupled and only the column is added. Otherwise the
    points whose F statistic (:func:`model_fits`) exceeds
    ``config.decouple_tol`` get the three-unknown solution: ``dh1_dt``,
    ``dh2_dt`` and ``dtheta_dt`` from their own pool, the displacements
    from those, and ``dr_dt`` from both radial flows
    (:func:`omniflow.paper.flow.radial_velocity_stereo`, eq. (14) not
    assumed). ``displacement(unit, h_i, theta, dh, dtheta)`` gives the pixel
    flow (dx, dy) of a polar flow, the solver's own (passed in, so that this
    module does not import the solver that calls it).

    ``pools``: (idx, w, keep), the solver's own k-d tree pools of the matches
    before the points without a solution were dropped (``keep`` False), from the
    same query (:func:`omniflow.solve.pooled.neighbourhoods` with the same k, radius,
    ranges and no edge test): the pools of the kept points are taken from them
    (:func:`kept_pools`) instead of searched again.

    ``fit``: :func:`pool_fits` of these columns, made beforehand (it reads none of
    the flow columns, so the solver can start it before its last step); None:
    made here.

    ``brightness``: each unit's image at the points (:mod:`omniflow.solve.gain`); with
    ``config.brightness_gate`` the decoupled points whose pool's F statistic of a gain
    passes the gate take the decoupled model with the gain (over the k-d tree pools).
    With ``config.brightness.decouple_gain_tol`` (and ``fit`` made with ``brightness``), eq. (14)
    is then tested again with a gain varying linearly across the pool in both fits
    (:func:`omniflow.solve.gain.decoupled_linear_gain`, over the k-d tree pools): the points
    whose F_U passes :func:`chained`'s gate take the decoupled model with that gain
    and are reported decoupled, whatever the steps before answered.
    """
    n = np.asarray(cols["h1"]).size
    out = dict(cols)
    out["coupled"] = np.ones(n)  # 1.0 / 0.0 like every other column (arithmetic, CSV)
    if not tests(config, n):
        return out
    if fit is None:
        fit = pool_fits(cols, rig, config, pools=pools, brightness=brightness)
    h1, h2 = (np.asarray(cols[c], dtype=np.float64) for c in ("h1", "h2"))
    with np.errstate(invalid="ignore"):
        switch = (fit["F"] > config.decouple_tol) & np.isfinite(fit["a1"] + fit["a2"] + fit["b"])
    a1 = np.where(switch, fit["a1"], cols["dh1_dt"])
    a2 = np.where(switch, fit["a2"], cols["dh2_dt"])
    b = np.where(switch, fit["b"], cols["dtheta_dt"])
    if brightness is not None and config.brightness_gate is not None and switch.any():
        a1, a2, b = _with_gain(cols, rig, config, switch, brightness, a1, a2, b)
    if "gain_F" in fit:  # eq. (14) tested again with a linear gain in both fits
        chain = chained(fit, config.brightness.decouple_gain_tol)
        a1, a2 = np.where(chain, fit["gain_a1"], a1), np.where(chain, fit["gain_a2"], a2)
        b = np.where(chain, fit["gain_b"], b)
        switch = switch | chain
    if not switch.any():
        return out
    theta = np.asarray(cols["theta"], dtype=np.float64)
    dx, dy = displacement(rig.cam1, h1, theta, a1, b)
    dx2, dy2 = displacement(rig.cam2, h2, theta, a2, b)
    dr = radial_velocity_stereo(cols["r"], h1, h2, a1, a2, d=rig.d)
    out.update(
        dh1_dt=a1, dh2_dt=a2, dtheta_dt=b, coupled=np.where(switch, 0.0, 1.0),
        dx=np.where(switch, dx, cols["dx"]), dy=np.where(switch, dy, cols["dy"]),
        dx2=np.where(switch, dx2, cols["dx2"]), dy2=np.where(switch, dy2, cols["dy2"]),
        dr_dt=np.where(switch, dr, cols["dr_dt"]),
    )  # fmt: skip
    return out


def _with_gain(cols, rig, config, switch, brightness, a1, a2, b):
    """(a1, a2, b) with the decoupled model's gain answer
    (:func:`omniflow.solve.gain.decoupled_gain`) at the switched points whose F statistic
    of the gain passes ``config.brightness_gate``."""
    radius = rig.cam1.r_m / 8.0 if config.pool_radius is None else config.pool_radius
    idx, w = neighbourhoods(cols["x"], cols["y"], k=config.pooling.pool_k, radius=radius,
                            r=cols["r"], range_tol=config.pooling.pool_range_tol,
                            query=switch)  # fmt: skip
    derivs = tuple(np.asarray(cols[c], dtype=np.float64) for c in DERIVS)
    h1, h2 = (np.asarray(cols[c], dtype=np.float64) for c in ("h1", "h2"))
    g1, g2, gb, F = decoupled_gain(derivs, brightness, h1, h2, idx, w)
    use = switch & gated(F, config.brightness_gate, g1, g2, gb)
    return np.where(use, g1, a1), np.where(use, g2, a2), np.where(use, gb, b)


#: A pool lies on a range edge (an object whose range differs from its surroundings)
#: when the range test (``pool_range_tol``) drops more than this share of the
#: neighbours within its radius: 64-100 % of independent_movers' movers' points, 7 % of
#: its static ones, 24 % of approach's (docs/decisions/decoupling.md).
#: Never with ``pool_range_tol`` None (no neighbour dropped).
EDGE_SHARE = 0.25

#: :func:`chained`'s gate on range-edge pools, as a share of ``decouple_gain_tol``
#: elsewhere. The probe's "chain L/C U edge>10|20" (the ring's cam1 mean-flow error
#: 64 -> 31 %, static mean error +0-1.5 %); 10 everywhere took the ring to 21 % but
#: cost 3-4 % static mean error on independent_movers, approach and crossing
#: (docs/decisions/decoupling.md).
EDGE_GATE = 0.5


def chained(fit: dict[str, NDArray], tol: float) -> NDArray:
    """Where :func:`decouple` takes the decoupled model with a linear gain: the F_U of
    :func:`omniflow.solve.gain.decoupled_linear_gain` (``fit["gain_F"]``) above ``tol``, or
    above ``EDGE_GATE * tol`` on a range-edge pool (``fit["gain_edge"]``,
    :data:`EDGE_SHARE`), and a finite answer."""
    gate = np.where(fit["gain_edge"], EDGE_GATE * tol, tol)
    return gated(fit["gain_F"], gate, fit["gain_a1"], fit["gain_a2"], fit["gain_b"])


def tests(config: OmniFlowConfig, n: int) -> bool:
    """Whether :func:`decouple` tests eq. (14) at n points: a ``decouple_tol``, the pooled
    solver and at least 10 points."""
    return config.decouple_tol is not None and config.solver == "pooled" and n >= 10


def pool_fits(
    cols: dict[str, NDArray],
    rig: Rig,
    config: OmniFlowConfig,
    pools: tuple[NDArray, NDArray, NDArray] | None = None,
    brightness: tuple[NDArray, NDArray] | None = None,
) -> dict[str, NDArray] | None:
    """Both models' fits over each point's pool (:func:`fits_from_sums`), as
    :func:`decouple` tests them; None where it does not test (:func:`tests`).

    Reads only the columns ``x``, ``y``, ``r``, ``h1``, ``h2``, ``theta`` and the six
    derivatives, none of the solved flow, so the solver can have it made on the
    other thread while it refines the flow (:func:`omniflow.solve.at_matches.flow_at_matches`).
    ``pools`` as for :func:`decouple`.

    With ``config.brightness.decouple_gain_tol`` and ``brightness`` (each unit's image at the
    points) also the decoupled model with a linear gain and its F_U
    (:func:`omniflow.solve.gain.decoupled_linear_gain`) over the k-d tree pools: keys
    ``gain_a1``, ``gain_a2``, ``gain_b``, ``gain_F`` and ``gain_edge`` (the pool on a range
    edge, :data:`EDGE_SHARE`). With grid pools the tree is searched here (the same k,
    radius and range test), at the points :func:`screen` keeps only: the test made first
    on the grid's windows cut at about the tree's ``pool_k`` points
    (:meth:`omniflow.solve.gridpool.GridPools.k_window`), which cannot stand in for the tree's
    (its pools hold other points, and the test's gates were set on the tree's), tells
    where the tree's test may pass; elsewhere ``gain_F`` is NaN (not switched).

    :func:`start_pool_fits` makes the same fits with its two independent parts (both
    models' fits; the linear-gain test) as two tasks of :mod:`omniflow.parallel`.
    """
    return start_pool_fits(cols, rig, config, pools, brightness, spawn=_deferred).result()


def start_pool_fits(
    cols: dict[str, NDArray],
    rig: Rig,
    config: OmniFlowConfig,
    pools: tuple[NDArray, NDArray, NDArray] | None = None,
    brightness: tuple[NDArray, NDArray] | None = None,
    *,
    spawn: Callable = submit,
) -> _Joined:
    """:func:`pool_fits` as a task: its ``result()`` is pool_fits' answer (the same, bit
    for bit), ``cancel()`` drops it.

    The pools are set up here (the grid's, and the k-d tree's where ranges mix), then
    the linear-gain test (``decouple_gain_tol``: the grid's screen, the tree's search
    and test) and both models' fits are handed to ``spawn`` (:func:`omniflow.parallel.
    submit`) in that order, the longer first: the pool's thread takes them in turn, and
    the caller's thread makes the models' fits itself if the pool's thread has not
    started them when it asks (``take_last()``, or ``result()`` after its own work).
    """
    if not tests(config, np.asarray(cols["h1"]).size):
        return _Joined([_deferred(lambda: None)])
    h1, h2 = (np.asarray(cols[c], dtype=np.float64) for c in ("h1", "h2"))
    radius = rig.cam1.r_m / 8.0 if config.pool_radius is None else config.pool_radius
    search = lambda query=None: neighbourhoods(  # noqa: E731
        cols["x"], cols["y"], k=config.pooling.pool_k, radius=radius, r=cols["r"],
        range_tol=config.pooling.pool_range_tol, query=query,
    )  # fmt: skip
    derivs = tuple(np.asarray(cols[c], dtype=np.float64) for c in DERIVS)
    chain = config.brightness.decouple_gain_tol is not None and brightness is not None
    theta = np.asarray(cols["theta"], dtype=np.float64)
    floor = config.pooling.pool_min_conditioning
    grid = idx = w = None
    if config.grid_pools:  # the solver's grid windows, the k-d tree's where ranges mix
        grid = GridPools(
            cols["x"], cols["y"], None, (rig.cam1.height, rig.cam1.width), radius=radius,
            cell=config.pooling.pool_grid * radius, r=cols["r"],
            range_tol=config.pooling.pool_range_tol, tree_pools=lambda mask: search(query=mask),
        )  # fmt: skip
    else:
        idx, w = search() if pools is None else kept_pools(*pools, search)

    def models() -> dict[str, NDArray]:
        if grid is not None:
            return fits_from_sums(grid.decouple_sums(derivs, h1, h2), h1, h2)
        return model_fits(derivs, h1, h2, idx, w)

    def linear_gain() -> dict[str, NDArray]:
        t_idx, t_w = idx, w
        if grid is not None:  # the same Gaussian cut at about the k nearest, as the tree's
            near = GridPools(
                cols["x"], cols["y"], None, (rig.cam1.height, rig.cam1.width), radius=radius,
                cell=config.pooling.pool_grid * radius, r=cols["r"],
                range_tol=config.pooling.pool_range_tol,
                tree_pools=lambda mask: (grid.idx, grid.w),
                window=grid.k_window(config.pooling.pool_k),
            )  # fmt: skip
            sums = near.linear_gain_sums(
                derivs, brightness, h1, h2, theta, scale=radius, single=True
            )
            query = screen(sums, floor, EDGE_GATE * config.brightness.decouple_gain_tol)
            # the tree's test where the grid's may pass; the others' rows get weight 0
            # from the search (neighbourhoods' ``query``): not tested (NaN)
            t_idx, t_w = search(query=query)
        within, kept = (t_idx < h1.size).sum(axis=1), (t_w > 0).sum(axis=1)  # any range; kept
        g = decoupled_linear_gain(derivs, brightness, h1, h2, theta, t_idx, t_w, scale=radius,
                                  min_conditioning=floor)  # fmt: skip
        return dict(gain_a1=g[0], gain_a2=g[1], gain_b=g[2], gain_F=g[3],
                    gain_edge=within - kept > EDGE_SHARE * within)  # fmt: skip

    return _Joined(([spawn(linear_gain)] if chain else []) + [spawn(models)])


class _Joined:
    """Tasks whose dict results make one: ``result()`` asks the last first (the caller
    makes it if the pool has not started it) and adds the others' keys after its own."""

    def __init__(self, parts: list[Task]) -> None:
        self.parts = parts

    def result(self) -> dict[str, NDArray]:
        try:
            fit = self.parts[-1].result()
            for part in self.parts[:-1]:
                fit.update(part.result())
        except BaseException:
            self.cancel()  # no task outlives the call
            raise
        return fit

    def take_last(self) -> None:
        """The last part now, in the caller's thread, if the pool has not started it."""
        self.parts[-1].take()

    def cancel(self) -> None:
        for part in self.parts:
            part.cancel()


def _deferred(fn: Callable, *args) -> Task:
    """``fn(*args)`` as a task run in the caller's thread when its result is asked for."""
    return Task(fn, args, None)


#: :func:`screen`'s least RSS_coupled / RSS_decoupled over the grid's window (the tree's
#: test asks 2, :data:`omniflow.solve.gain.MIN_RESIDUAL_RATIO`, over its own pools). With
#: :data:`SCREEN_F` it keeps 11 % of the dense preset's points on the five rendered scenes
#: (15 pairs) and loses 4 of the 487 the tree's test switched there (grid ratio 1.030-1.073),
#: every omnivalidate figure unchanged; 1.02 keeps 40 % and loses none (the same columns bit
#: for bit) at about 25 ms more a pair (docs/decisions/decoupling.md).
SCREEN_RATIO = 1.1

#: :func:`screen`'s least F_U over the grid's window, as a share of the lowest gate.
SCREEN_F = 0.1


def screen(sums: tuple[NDArray, ...], min_conditioning: float, gate: float) -> NDArray:
    """The points whose linear-gain test (:func:`omniflow.solve.gain.decoupled_linear_gain`) may
    pass ``gate``, from the grid's sums (:meth:`omniflow.solve.gridpool.GridPools.linear_gain_sums`
    over a window of about the tree's pool): the test's F_U over the grid's window above
    :data:`SCREEN_F` ``gate`` with RSS_coupled at least :data:`SCREEN_RATIO` RSS_decoupled,
    and every point where the grid's test is undecided (a fit without a solution, or fewer
    than 4 residual degrees of freedom). The tree's test then runs at these points only."""
    M, v, yy, w1, w2 = sums[:5]
    x, _, rss, rss_c = nested_fits(M, v, yy, min_conditioning, drop=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        dof = 2.0 * w1**2 / w2 - M.shape[1]
        F = (rss_c - rss) / (rss / dof)
        return (
            ~np.isfinite(x[:, :3]).all(axis=1) | ~(dof >= 4.0) | ~(rss > 0)
            | ((rss_c >= SCREEN_RATIO * rss) & (F > SCREEN_F * gate))
        )  # fmt: skip


#: the result columns of the six derivatives, in the order the fits take them
DERIVS = ("f1_h", "f1_theta", "f1_t", "f2_h", "f2_theta", "f2_t")


def kept_pools(
    idx: NDArray, w: NDArray, keep: NDArray, search: Callable
) -> tuple[NDArray, NDArray]:
    """The k-nearest pools of the kept points among themselves, from the pools of all.

    ``idx``, ``w`` (N, K): :func:`omniflow.solve.pooled.neighbourhoods` of N points;
    ``keep`` (N,) bool: the points that stay. The pools :func:`neighbourhoods` would
    give the M kept points on their own: a row keeps its kept neighbours, in the
    same order (nearest first) and with the same weights (a weight depends only on
    the two points' distance and ranges); the row's dropped neighbours leave a gap
    that nearer points cannot fill, since all of them are listed already, except
    where the row was full (K found within the radius): there a farther kept point
    may move in, and those rows are searched again, ``search(query=mask)`` over
    the kept points (mask (M,) bool).
    """
    n = idx.shape[0]
    keep = np.asarray(keep, dtype=bool)
    if keep.all():
        return idx, w
    m = int(keep.sum())
    new_id = np.full(n + 1, m, dtype=np.intp)  # index n (no neighbour) and dropped: m
    new_id[:n][keep] = np.arange(m)
    sub_idx, sub_w = idx[keep], w[keep]
    alive = np.append(keep, False)[sub_idx]
    order = np.argsort(~alive, axis=1, kind="stable")  # kept neighbours first, in order
    sub_idx = np.take_along_axis(sub_idx, order, axis=1)
    alive = np.take_along_axis(alive, order, axis=1)
    out_idx = np.where(alive, new_id[sub_idx], m)
    out_w = np.where(alive, np.take_along_axis(sub_w, order, axis=1), 0.0)
    full = (idx[keep] < n).all(axis=1)
    again = full & ~alive.all(axis=1)
    if again.any():
        a_idx, a_w = search(query=again)
        out_idx[again], out_w[again] = a_idx[again], a_w[again]
    return out_idx, out_w
