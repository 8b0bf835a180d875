"""Reading the fitted series at the matched points.

From the pixel grids of :class:`omniflow.fit.series.Frame` by cv2.remap (cubic
or linear), or by evaluating the series exactly (``sampling="exact"``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from omniflow.fit.series import Frame
from omniflow.matching import sample_xy
from omniflow.paper.edges import polar_from_cartesian

__all__ = ["sample_f", "sample_fine", "sample_polar_grad"]


def sample_polar_grad(
    frame: Frame, x: NDArray, y: NDArray, sampling: str
) -> tuple[NDArray, NDArray]:
    """(f_h, f_theta) at points: f_x, f_y sampled (or evaluated exactly), then eq. (19)-(20)."""
    if sampling == "exact":
        f_x, f_y = frame.fit.gradient(x, y)
    else:
        gx, gy = frame.grad_xy
        f_x = sample_xy(gx, x, y, interpolation=sampling).astype(np.float64)
        f_y = sample_xy(gy, x, y, interpolation=sampling).astype(np.float64)
    f_h, f_th = polar_from_cartesian(f_x, f_y, x - frame.unit.x_c, y - frame.unit.y_c)
    return f_h, f_th


def sample_f(frame: Frame, x: NDArray, y: NDArray, sampling: str) -> NDArray:
    if sampling == "exact":
        return frame.fit.evaluate(x, y)
    return sample_xy(frame.f, x, y, interpolation=sampling).astype(np.float64)


_FINE_INTERP = 4  # lanczos


def sample_fine(frame: Frame, x: NDArray, y: NDArray, sampling: str) -> NDArray:
    """The fitted image at points: Lanczos-4 interpolation of the grid (or exact)."""
    if sampling == "exact":
        return frame.fit.evaluate(x, y)
    import cv2

    mx = (2.0 * np.asarray(x, dtype=np.float64) - 0.5).astype(np.float32).reshape(1, -1)
    my = (2.0 * np.asarray(y, dtype=np.float64) - 0.5).astype(np.float32).reshape(1, -1)
    out = np.empty(mx.size, np.float64)
    for lo in range(0, mx.size, 32000):  # cv2.remap maps are at most 32767 wide
        sl = slice(lo, lo + 32000)
        out[sl] = cv2.remap(
            frame.fine, mx[:, sl], my[:, sl], _FINE_INTERP, borderMode=cv2.BORDER_CONSTANT
        )[0]
    return out.reshape(np.shape(x))
