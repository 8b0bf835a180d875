"""cam1-only flow where the stereo matcher has no answer (``OmniFlowConfig.monocular_gap``).

The stereo solve needs a match in cam2. An object that cam2 does not see, or
sees only at its rim, gets no point: the crossing pillar, 0.85 m from the
axis, covers 8,684 cam1 pixels and 283 of cam2's (docs/decisions/monocular.md).
cam1 alone still has eq. (9),

    f1_h dh_1/dt + f1_theta dtheta/dt + f1_t = 0,

one equation in the two unknowns at a point, which the pooled solver
(:func:`omniflow.solve.pooled.pooled_solution`, the same local model and weights as
the stereo solve, cam2's terms zero) makes determined over a neighbourhood:
the polar form of Lucas-Kanade. There is no range, so no range test in the
pools, no dr/dt and no time to contact.

Points: the strongest-gradient pixel of every :data:`BLOCK` x :data:`BLOCK`
block of cam1's annulus whose gradient magnitude (the flow step's series) is
above the :data:`PERCENTILE`-th percentile of the annulus, and that is
farther than ``monocular_gap`` px from every stereo match, so the two answers
do not overlap. Both constants as measured on the crossing scene
(docs/decisions/monocular.md): 4 px blocks give the pillar about 250
points per frame; the 80th percentile left it 170 points and a mean radial
flow half the truth.

What it is good for: the tangential flow (bearing rate) of an object the rig
cannot range. Its radial flow is weakly determined where the texture varies
little along the radial lines (the pillar's, mean |df/dh| half the walls'),
and overstated on the crossing box by half; the stereo solve, with cam2's
equation, does not have that weakness.
"""

from __future__ import annotations

import time
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from omniflow.config import OmniFlowConfig
from omniflow.fit.sampling import sample_f, sample_polar_grad
from omniflow.geometry.rig import Unit
from omniflow.result import MONOCULAR_COLUMNS, OmniFlowResult
from omniflow.solve.pooled import POOL_MODEL, neighbourhoods, pooled_solution

__all__ = [
    "BLOCK",
    "MONOCULAR_COLUMNS",
    "PERCENTILE",
    "add_monocular",
    "monocular_flow",
    "monocular_points",
]

#: Block size (px) of the point grid: one point per block at most.
BLOCK = 4
#: Percentile of cam1's gradient magnitude over its annulus a point must reach.
PERCENTILE = 70.0


@lru_cache(maxsize=8)
def _inside(unit: Unit, h_min: float, rim_margin: float) -> NDArray:
    """The pixels with h_min <= h_1 <= r_m - rim_margin - 2 (read-only; made once per
    unit: the polar coordinates of every pixel cost about 19 ms at 512 px)."""
    h, _ = unit.polar_of_pixel(*unit.pixel_centres())
    inside = (h >= h_min) & (h <= unit.r_m - rim_margin - 2.0)
    inside.setflags(write=False)
    return inside


def monocular_points(
    grad_xy: tuple[NDArray, NDArray],
    unit: Unit,
    config: OmniFlowConfig,
    stereo_x: NDArray,
    stereo_y: NDArray,
) -> tuple[NDArray, NDArray]:
    """The cam1 pixel centres (x, y) the monocular solve answers at (module docstring)."""
    mag = np.hypot(*grad_xy)
    inside = _inside(unit, config.search.h_min, config.search.rim_margin)
    if not inside.any():
        return np.zeros(0), np.zeros(0)
    rows, cols = (n // BLOCK * BLOCK for n in mag.shape)
    blocks = np.where(inside, mag, -1.0)[:rows, :cols]
    blocks = blocks.reshape(rows // BLOCK, BLOCK, cols // BLOCK, BLOCK).transpose(0, 2, 1, 3)
    blocks = blocks.reshape(rows // BLOCK, cols // BLOCK, BLOCK * BLOCK)
    best, arg = blocks.max(axis=-1), blocks.argmax(axis=-1)
    level = max(float(np.percentile(mag[inside], PERCENTILE)), config.search.min_gradient)
    bi, bj = np.nonzero(best >= level)
    x = (bj * BLOCK + arg[bi, bj] % BLOCK) + 0.5
    y = (bi * BLOCK + arg[bi, bj] // BLOCK) + 0.5
    if len(stereo_x) and x.size:
        dist, _ = cKDTree(np.column_stack([stereo_x, stereo_y])).query(np.column_stack([x, y]))
        far = dist > config.monocular_gap
        x, y = x[far], y[far]
    return x, y


def monocular_flow(
    cam1: dict, unit: Unit, config: OmniFlowConfig, stereo_x: NDArray, stereo_y: NDArray
) -> dict[str, NDArray]:
    """cam1's flow from eq. (9) alone at :func:`monocular_points` (columns in
    :data:`MONOCULAR_COLUMNS`; points without a solution are left out).

    ``cam1``: the unit's series as :func:`omniflow.pipeline.estimate` builds
    them (``g``: the gradients' series, ``t``: f_t's). No noise correction
    (``eiv``): on the crossing pillar it moved the mean radial flow further
    from the truth (0.77 against 0.70, true 0.63 px, pair 1).
    """
    x, y = monocular_points(cam1["g"].grad_xy, unit, config, stereo_x, stereo_y)
    if x.size == 0:  # a constant or dark frame, or matches everywhere: an empty answer
        return {name: np.zeros(0) for name in MONOCULAR_COLUMNS}
    h1, theta = unit.polar_of_pixel(x, y)
    f_h, f_th = sample_polar_grad(cam1["g"], x, y, config.fit.sampling)
    f_t = sample_f(cam1["t"], x, y, config.fit.sampling)
    radius = unit.r_m / 8.0 if config.pool_radius is None else config.pool_radius
    idx, w = neighbourhoods(x, y, k=config.pooling.pool_k, radius=radius, r=None, range_tol=None)
    zero = np.zeros_like(x)
    floor = config.pooling.pool_min_conditioning
    a, b, conf = pooled_solution(
        f_h, f_th, f_t, zero, zero, zero, h1, h1, idx, w, theta=theta,
        model=POOL_MODEL, scale=radius, min_conditioning=floor,
    )  # fmt: skip
    keep = np.isfinite(a) & np.isfinite(b)
    x, y, h1, theta, a, b, conf, f_h, f_th, f_t = (
        v[keep] for v in (x, y, h1, theta, a, b, conf, f_h, f_th, f_t)
    )
    xd, yd = unit.pixel_of_polar(h1 + a, theta + b)
    return {
        "x": x,
        "y": y,
        "theta": theta,
        "h1": h1,
        "dh1_dt": a,
        "dtheta_dt": b,
        "dx": xd - x,
        "dy": yd - y,
        "confidence": conf,
        "f1_h": f_h,
        "f1_theta": f_th,
        "f1_t": f_t,
    }


def add_monocular(result: OmniFlowResult, cam1: dict, unit: Unit) -> OmniFlowResult:
    """Fill ``result.monocular`` where ``result.config.monocular_gap`` is set (timed as
    ``timings["monocular"]``, counted in ``total``); returns ``result``."""
    config = result.config
    if config is None or config.monocular_gap is None:
        return result
    t0 = time.perf_counter()
    cols = result.columns
    result.monocular = monocular_flow(cam1, unit, config, cols["x"], cols["y"])
    seconds = time.perf_counter() - t0
    result.timings["monocular"] = seconds
    result.timings["total"] = result.timings.get("total", 0.0) + seconds
    return result
