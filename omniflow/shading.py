"""Shading that stays put while the texture moves: flatten it for the flow step.

Brightness constancy (eq. 8) assumes the image pattern moves with the scene.
On a rotating curved body lit from a fixed light (a rolling ball, a pillar
turning about its own axis) the texture moves but the shading does not: the
image is S(x) T(x - u t), its gradient S' T + S T', of which only S T' moves,
so the flow along the shading gradient comes out short (radially on a ball lit
from above, tangentially on a turning pillar; docs/measurements.md, "Movers:
decoupled radial flow"). Dividing each frame by its local mean removes a
shading that varies slowly against the texture (a ratio image, I / (G * I)).
The matcher keeps the frames as given (its normalised cross-correlation does
not need this); only the flow step's series are fitted to the flattened frames.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from omniflow.config import OmniFlowConfig
from omniflow.rig import Rig, Unit

__all__ = ["flatten_shading", "flow_units"]


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
    (``config.flow_shading`` px), each keeping the matcher's frame ``a`` of ``cams``."""
    from omniflow.series import fit_band, unit_fits, unit_frames

    out = []
    for frames, unit, cam, what in ((frames1, rig.cam1, cams[0], "frames1"),
                                    (frames2, rig.cam2, cams[1], "frames2")):  # fmt: skip
        rim = unit if config.rim_fill == "reflect" else None
        flat = _Flattened(frames, config.flow_shading, rim)
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
            from omniflow.series import fill_outside_rim

            frame = fill_outside_rim(np.asarray(frame, dtype=np.float32), self.unit)
        return flatten_shading(frame, self.sigma)
