"""Shading that stays put while the texture moves: flatten it for the flow step.

Brightness constancy (eq. 8) assumes the image pattern moves with the scene.
On a rotating curved body lit from a fixed light (a rolling ball, a pillar
turning about its own axis) the texture moves but the shading does not: the
image is S(x) T(x - u t), its gradient S' T + S T', of which only S T' moves,
so the flow along the shading gradient comes out short (radially on a ball lit
from above, tangentially on a turning pillar; docs/decisions/brightness_model.md).
Dividing each frame by its local mean removes a
shading that varies slowly against the texture (a ratio image, I / (G * I)).
The matcher keeps the frames as given (its normalised cross-correlation does
not need this); only the flow step's series are fitted to the flattened frames.

On a static surface under static lights the shading moves with the surface
(a Lambertian surface's brightness is attached to it), so flattening there
only removes signal. ``flow_shading_where = "moving"`` keeps the plain flow
except at the points of independently moving objects (:func:`moving_points`),
where it takes the flattened frames' (:func:`where_moving`).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from omniflow.config import OmniFlowConfig
from omniflow.geometry.rig import Rig, Unit

__all__ = ["MOVING_MIN_POINTS", "flatten_shading", "flow_units", "moving_points", "where_moving"]

#: Smallest group of odometry outliers :func:`moving_points` takes for a moving object.
#: 10: the rolling ball of independent_movers has 14-19 points per pair at the
#: defaults, and the static default scene's outliers form no group this large in
#: two of three pairs (docs/decisions/brightness_model.md).
MOVING_MIN_POINTS = 10


def flatten_shading(frame: NDArray, sigma: float) -> NDArray:
    """``frame`` divided by its Gaussian local mean (``sigma`` px), on the frame's grey scale.

    ``f (m + e) / (G_sigma * f + e)`` with m the mean of the local mean and
    e = 0.1 m (so dark regions are not amplified without bound): a constant
    image is returned unchanged, and a texture under a slowly varying
    multiplicative shading comes out with the shading divided away.
    """
    f = np.asarray(frame, dtype=np.float32)
    local = cv2.GaussianBlur(f, (0, 0), float(sigma), borderType=cv2.BORDER_REFLECT)
    m = float(np.mean(local))
    e = 0.1 * m if m > 0 else 1.0
    return f * np.float32(m + e) / (local + np.float32(e))


def flow_units(
    frames1: Sequence[NDArray],
    frames2: Sequence[NDArray],
    t: int,
    rig: Rig,
    config: OmniFlowConfig,
    flow_band: float,
    cams: tuple[dict, dict],
) -> tuple[dict, dict]:
    """Both units' flow-step series fitted to shading-flattened frames
    (``config.brightness.flow_shading`` px), each keeping the matcher's frame ``a`` of ``cams``."""
    from omniflow.fit.series import fit_band, unit_fits, unit_frames

    out = []
    for frames, unit, cam, what in ((frames1, rig.cam1, cams[0], "frames1"),
                                    (frames2, rig.cam2, cams[1], "frames2")):  # fmt: skip
        rim = unit if config.fit.rim_fill == "reflect" else None
        flat = _Flattened(frames, config.brightness.flow_shading, rim)
        fits = unit_fits(flat, t, unit, config, what, fit_band(config))
        new = unit_frames(fits, unit, config, flow_band)
        new["a"] = cam["a"]
        out.append(new)
    return out[0], out[1]


class _Flattened:
    """A lazy view of a frame sequence, each frame flattened on access."""

    def __init__(self, frames: Sequence[NDArray], sigma: float, unit: Unit | None) -> None:
        self.frames, self.sigma, self.unit = frames, sigma, unit

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, k: int) -> NDArray:
        frame = self.frames[k]
        if self.unit is not None:  # the mirror's outside reflected in first, as the fit will
            from omniflow.fit.series import fill_outside_rim

            frame = fill_outside_rim(np.asarray(frame, dtype=np.float32), self.unit)
        return flatten_shading(frame, self.sigma)


def moving_points(cols: dict[str, NDArray], rig: Rig) -> NDArray:
    """(N,) bool: the points of independently moving objects in a flow result's columns.

    Odometry's outliers (:func:`omniflow.applications.navigation.odometry` on every point's
    dtheta/dt and dr/dt: the points whose flow the robot's own motion does not
    explain), linked in cam1's image within r_m / 10 px (the command's
    ``--auto-link`` default) into groups of at least :data:`MOVING_MIN_POINTS`
    (:func:`omniflow.applications.regions.auto_groups`); a stray outlier on a static surface
    is in no such group. No point where the fit fails (too few points).
    """
    from omniflow.applications.navigation import odometry
    from omniflow.applications.regions import auto_groups

    n = len(cols["x"])
    try:
        fit = odometry(cols["theta"], cols["r"], cols["dtheta_dt"], cols["dr_dt"])
    except ValueError:
        return np.zeros(n, dtype=bool)
    labels = auto_groups(cols["x"], cols["y"], ~fit.inliers, link=rig.cam1.r_m / 10,
                         min_points=MOVING_MIN_POINTS)  # fmt: skip
    return labels > 0


def where_moving(
    plain: dict[str, NDArray], flat: dict[str, NDArray], rig: Rig
) -> tuple[dict[str, NDArray], int]:
    """``plain``'s columns with ``flat``'s values at the moving points (:func:`moving_points`).

    Both are :func:`omniflow.solve.at_matches.flow_at_matches` columns of the same matches; a point
    either solve dropped (non-finite flow) is matched by its cam1 pixel, and one that
    ``flat`` lacks keeps its plain values. Returns the columns and the number of points
    that took the flattened flow.
    """
    moving = moving_points(plain, rig)
    index = {xy: i for i, xy in enumerate(zip(flat["x"].tolist(), flat["y"].tolist(), strict=True))}
    src = np.array([index.get(xy, -1) for xy in zip(plain["x"].tolist(), plain["y"].tolist(),
                                                    strict=True)], dtype=int)  # fmt: skip
    take = moving & (src >= 0)
    n = len(plain["x"])
    out = dict(plain)
    for key, val in plain.items():
        other = flat.get(key)
        if isinstance(val, np.ndarray) and val.shape[:1] == (n,) and isinstance(other, np.ndarray):
            merged = val.copy()
            merged[take] = other[src[take]]
            out[key] = merged
    return out, int(take.sum())
