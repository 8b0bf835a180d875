"""The stereo omni flow step: fit, match, solve (paper section 5).

:func:`estimate` takes the frames of both units, fits the DCT (eq. 17) to the
two frames of each unit, evaluates the fitted images and their polar
gradients (eq. 18-20) on the pixel grid by fast transforms, matches along the
radial lines (section 5.2, :mod:`omniflow.matching`), samples the gradients
and temporal derivatives at the matched points and solves for the flow
(section 5.3, :mod:`omniflow.paper.flow`). Every choice is a field of
:class:`OmniFlowConfig`; :meth:`OmniFlowConfig.paper` gives the paper's.

Output per point (:class:`OmniFlowResult`, columns in :data:`COLUMNS`): cam1
position (x, y, theta, h1), its match h2 and cam2 position (x2, y2), range
and height (r, h; eq. 5), the polar flow (dh1_dt, dtheta_dt;
dh2_dt = (h2/h1) dh1_dt, eq. 14, except where ``coupled`` is 0:
:mod:`omniflow.solve.decoupled`), dr_dt = -(d + r) dh1_dt / h1, the pixel
flow of both units (dx, dy; dx2, dy2), the determinant D of eq. (16), a
confidence in [0, 1] and the derivatives that entered eq. (9) and (15). The
pixel flow is the displacement of the point's image over one frame,
(x_c + (h + dh) cos(theta + dtheta), ...) - (x, y), so it compares directly
with a ground-truth displacement; velocities are per frame interval.

Accuracy of the variants on closed-form scenes (true matches and end to end,
against OpenCV DIS): docs/decisions/paper_preset.md. Eq. (14) assumes no motion along the axis
(tests/omniflow/test_flow.py::test_vertical_motion_bias_matches_prediction).

Where each step lives: the knobs in :mod:`omniflow.config`, the result in
:mod:`omniflow.result`, the per-unit series (fits, bands, noise, rim fill)
in :mod:`omniflow.fit.series`, the stereo matching in :mod:`omniflow.matching`,
reading the series at the points in :mod:`omniflow.fit.sampling` and the solvers
in :mod:`omniflow.solve.at_matches`; this module only runs them in order.

Speed: the two units' fits run in two threads, and the grids the flow step
samples are made on the second thread while the first matches
(:mod:`omniflow.parallel`); in the flow step the grid pools' filters, the
refinement's two units and the two-model test's pool fits share the two
threads too; each is the same computation as in one thread,
so the columns do not change. The stage timings are in
:attr:`OmniFlowResult.timings` (``grids``: the grids matched on; ``match``
overlaps the flow step's grids, whose wait, if any, counts in ``sample``);
benchmarks/bench_omniflow.py compares the whole step with OpenCV DIS.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from omniflow.config import OmniFlowConfig
from omniflow.fit.series import (
    Frame,
    annulus,
    choose_flow_band,
    fill_outside_rim,
    fit_band,
    gradient_noise,
    needs_noise_sigma,
    noise_variance,
    unit_fits,
    unit_frames,
    unit_noise_sigma,
    value_noise_share,
)
from omniflow.geometry.rig import Rig
from omniflow.matching import Matches, PolarGrids, match_radial
from omniflow.parallel import map_tasks, submit
from omniflow.registration import Rectifier, has_errors
from omniflow.result import COLUMNS, NoMatchesWarning, OmniFlowResult, no_points
from omniflow.solve.at_matches import flow_at_matches
from omniflow.solve.monocular import add_monocular
from omniflow.solve.pooled import neighbourhoods
from omniflow.solve.shading import flow_units, where_moving
from omniflow.solve.sigma import model_for, point_noise, sigmas

__all__ = [
    "COLUMNS",
    "NoMatchesWarning",
    "OmniFlowConfig",
    "OmniFlowResult",
    "estimate",
    "fill_outside_rim",
    "flow_at_matches",
    "flow_grids",
    "matching_grid",
    "matching_grids",
    "stereo_matches",
]


def _unit_series(frames, t: int, unit, config: OmniFlowConfig, what: str):
    """One unit's noise level (0 when not read) and series (:func:`unit_fits`)."""
    sigma = unit_noise_sigma(frames[t], unit, config) if needs_noise_sigma(config) else 0.0
    return sigma, unit_fits(frames, t, unit, config, what, fit_band(config))


def flow_grids(cam: dict, config: OmniFlowConfig) -> dict:
    """Make the grids :func:`flow_at_matches` samples in one unit's Frames (``cam``, as
    :func:`unit_frames` gives), so they can be made off the thread that samples them.

    Each is a lazy property of its Frame, made once: making it here changes no value.
    Returns ``cam``.
    """
    if config.fit.sampling != "exact":
        needed = [("g", "grad_xy"), ("t", "f")]
        # grids read off-pixel
        if config.iterations > 0 and config.refinement.iterate_min_px == 0.0:
            needed += [("b", "grad_xy"), ("b", "fine"), ("af", "fine")]
            if config.fit.gradients == "average":
                needed.append(("af", "grad_xy"))
        for key, grid_name in needed:
            getattr(cam[key], grid_name)
    return cam


def _check_inputs(frames1, frames2, rig: Rig, t: int) -> None:
    if len(frames1) != len(frames2):
        raise ValueError(f"frames1 has {len(frames1)} frames but frames2 {len(frames2)}")
    if not (0 <= t and t + 1 < len(frames1)):
        raise ValueError(f"t = {t}: need frames t and t + 1 of {len(frames1)}")
    for name, frames, unit in (("frames1", frames1, rig.cam1), ("frames2", frames2, rig.cam2)):
        shape = np.shape(frames[t])
        if shape != (unit.height, unit.width):
            raise ValueError(
                f"{name}[{t}] has shape {shape}; the rig's {unit.name} is "
                f"{unit.height}x{unit.width} (rows x columns)"
            )


def estimate(
    frames1: Sequence[NDArray],
    frames2: Sequence[NDArray],
    rig: Rig,
    config: OmniFlowConfig | None = None,
    *,
    t: int = 0,
    matches: Matches | None = None,
) -> OmniFlowResult:
    """Stereo omni flow from frame t to t + 1 of both units.

    Parameters
    ----------
    frames1, frames2 : sequence of ndarray, each shape (H, W)
        Grey float frames of cam1 and cam2 (at least t + 2; at least
        ``config.fit.temporal_frames`` for ``temporal="dct3d"``).
    rig : Rig
    config : OmniFlowConfig, optional
        Defaults to ``OmniFlowConfig()``.
    t : int
        The flow is from frame t to frame t + 1.
    matches : Matches, optional
        Use these stereo matches instead of matching (e.g. the true ones).

    Returns
    -------
    OmniFlowResult
        With no stereo match (a dark or constant image, no common view) every
        column has length 0 and a :class:`NoMatchesWarning` is issued.
    """
    config = OmniFlowConfig() if config is None else config
    _check_inputs(frames1, frames2, rig, t)
    if matches is None and has_errors(rig):  # registered: docs/decisions/registration.md
        rect = Rectifier(rig)  # each image rectified to the ideal unit, results mapped back
        f1, f2 = rect.frames(frames1, frames2)
        return rect.result(estimate(f1, f2, rect.ideal, config, t=t))
    timings: dict[str, float] = {}
    t_start = time.perf_counter()

    (s1, fits1), (s2, fits2) = map_tasks(
        _unit_series,
        (frames1, t, rig.cam1, config, "frames1"),
        (frames2, t, rig.cam2, config, "frames2"),
    )
    sigmas, fits = (s1, s2), (fits1, fits2)
    flow_band = choose_flow_band(fits, sigmas, config)
    cam1 = unit_frames(fits[0], rig.cam1, config, flow_band)
    cam2 = unit_frames(fits[1], rig.cam2, config, flow_band)
    flat: tuple = ()  # the flattened units when they are used only where objects move
    if config.brightness.flow_shading is not None:  # the flow step on shading-flattened frames
        units = flow_units(frames1, frames2, t, rig, config, flow_band, (cam1, cam2))
        if config.brightness.flow_shading_where == "moving":
            flat = tuple(units)
        else:
            cam1, cam2 = units
    for cam in (cam1, cam2, *flat):
        cam["noise_var"] = noise_variance(cam["g"].fit, config)
    diagnostics = {"flow_band": flow_band, "noise_sigma1": sigmas[0], "noise_sigma2": sigmas[1]}
    t_fit = time.perf_counter()
    timings["fit"] = t_fit - t_start

    # the flow step's grids do not need the matches: made on the other thread while
    # this one matches (sampling waits for them, or makes those not yet started)
    grid2 = submit(matching_grid, cam2["a"], config) if matches is None else None
    flow = [submit(flow_grids, cam, config) for cam in (cam1, cam2, *flat)]
    n_sig = 0
    try:
        if matches is None:
            grids = (matching_grid(cam1["a"], config), grid2.result())
            timings["grids"] = time.perf_counter() - t_fit
            t_m = time.perf_counter()
            matches = stereo_matches(grids, rig, config)
            n_sig = matches.n_significant
            timings["match"] = time.perf_counter() - t_m
        else:
            timings["grids"] = timings["match"] = 0.0
    except BaseException:
        for task in (grid2, *flow):
            if task is not None:
                task.cancel()  # no task outlives the call
        raise
    t_s = time.perf_counter()
    for f in flow:
        f.result()
    if len(matches.theta) == 0:
        return add_monocular(no_points(timings, t_start, config, n_sig), cam1, rig.cam1)
    t_wait = time.perf_counter() - t_s
    result = flow_at_matches(matches, rig, cam1, cam2, config)
    timings["sample"] = result.pop("_t_sample") + t_wait
    if flat:  # the flattened frames' flow at the moving objects' points only
        other = flow_at_matches(matches, rig, *flat, config)
        timings["sample"] += other.pop("_t_sample")
        result, diagnostics["shading_flattened_points"] = where_moving(result, other, rig)
    timings["solve"] = time.perf_counter() - t_s - timings["sample"]
    timings["total"] = time.perf_counter() - t_start
    result = OmniFlowResult(
        columns=result,
        timings=timings,
        config=config,
        n_significant=n_sig,
        diagnostics=diagnostics,
    )
    frames = (frames1, frames2)
    result.defer_sigma(predicted_sigmas(result.columns, frames, t, rig, (cam1, cam2), config))
    return add_monocular(result, cam1, rig.cam1)  # cam1 alone where no match is near


#: The columns :func:`omniflow.solve.sigma.sigmas` reads.
_SIGMA_READS = ("x", "y", "x2", "y2", "h1", "h2", "r", "dh1_dt", "dtheta_dt", "dx", "dy", "dx2",
                "dy2", "coupled", "score", "f1_h", "f1_theta", "f2_h", "f2_theta")  # fmt: skip


def predicted_sigmas(
    cols: dict, frames: tuple, t: int, rig: Rig, cams: tuple, config: OmniFlowConfig
):
    """The predicted standard deviations of :mod:`omniflow.solve.sigma` for the columns,
    as a function of no argument that makes them (:meth:`OmniFlowResult.defer_sigma`):
    each unit's temporal noise (frames t and t + 1 over its annulus) at the points, the
    flow series' noise shares (taken now, so the function holds the frames t and t + 1
    and the columns only), and the solver's pools (k-d pools of the points kept)."""
    # copies: the sigmas do not change if the caller reuses its buffers before reading
    frames = tuple((np.array(f[t]), np.array(f[t + 1])) for f in frames)
    cols = {k: np.array(cols[k]) for k in _SIGMA_READS if k in cols}
    value_share = tuple(value_noise_share(c["g"].fit, config) for c in cams)
    gradient_var = tuple(gradient_noise(1.0, c["g"].fit, config) for c in cams)
    return lambda: _predicted_sigmas(cols, frames, rig, config, value_share, gradient_var)


def _predicted_sigmas(cols, frames, rig, config, value_share, gradient_var) -> dict:
    h_min, rim_margin = float(config.search.h_min), float(config.search.rim_margin)
    tasks = [
        (frames_u[0], frames_u[1], annulus(unit, h_min, rim_margin), x, y)
        for frames_u, unit, (x, y) in zip(frames, (rig.cam1, rig.cam2),
                                          ((cols["x"], cols["y"]), (cols["x2"], cols["y2"])),
                                          strict=True)
    ]  # fmt: skip
    noise = [level[0] for level in map_tasks(point_noise, *tasks)]  # the two units' threads
    pools = None
    if config.solver == "pooled":
        radius = rig.cam1.r_m / 8.0 if config.pool_radius is None else config.pool_radius
        pools = neighbourhoods(cols["x"], cols["y"], k=config.pooling.pool_k, radius=radius,
                               r=cols["r"], range_tol=config.pooling.pool_range_tol)  # fmt: skip
    return sigmas(
        cols,
        noise=(noise[0], noise[1]),
        value_share=value_share,
        gradient_var=gradient_var,
        d=rig.d,
        s=rig.s,
        v2=rig.cam2.v,
        pools=pools,
        model=model_for(config),
    )


def matching_grids(a1: Frame, a2: Frame, config: OmniFlowConfig) -> tuple[PolarGrids, PolarGrids]:
    """The grids the matcher reads from frame t of each unit (``a`` of :func:`unit_frames`)."""
    return matching_grid(a1, config), matching_grid(a2, config)


def matching_grid(a: Frame, config: OmniFlowConfig) -> PolarGrids:
    """The grids the matcher reads from one unit's frame t."""
    if config.match_method == "paper":  # the polar edge finder's f_h, f_theta
        return PolarGrids(f=a.f, f_h=a.grad[0], f_theta=a.grad[1])
    # the robust matcher differentiates its polar table of f
    return PolarGrids(f=a.f, f_h=None)


def stereo_matches(
    grids: tuple[PolarGrids, PolarGrids], rig: Rig, config: OmniFlowConfig
) -> Matches:
    """The stereo matches of one time step with the configured matcher (section 5.2)."""
    return match_radial(
        None,
        None,
        rig,
        method=config.match_method,
        threshold_percentile=config.threshold_percentile,
        r_min=config.r_min,
        r_max=config.r_max,
        n_theta=config.n_theta,
        patch_radius=config.patch_radius,
        dense_percentile=config.dense_percentile,
        **config.search.as_kwargs(),  # the groups' field names are match_radial's keywords
        **config.matching.as_kwargs(),
        grids=grids,
    )
