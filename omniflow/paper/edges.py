"""The polar edge finder (paper section 5.1, eq. 19-20).

The image gradient in polar image coordinates (h_i, theta_i) about the image
of the axis (x_c, y_c), from the analytic derivatives of the DCT series, so it
is exact for the fitted series at any sub-pixel point and needs no unwarping:

    df/dh_i     = ((x - x_c) f_x + (y - y_c) f_y) / h_i      # eq. (19)
    df/dtheta_i = (x - x_c) f_y - (y - y_c) f_x              # eq. (20)

theta_i = atan2(y - y_c, x - x_c) (:mod:`omniflow.conventions`), so eq. (20)
is the plain derivative in radians with no 1/h_i factor; the polar gradient
of eq. (8) is (f_h, f_theta / h_i). At h_i = 0 f_h is undefined (NaN).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omniflow.geometry.rig import Unit
from omniflow.paper.dct import DCTFit

__all__ = ["polar_from_cartesian", "polar_gradient", "polar_gradient_grid"]


def polar_from_cartesian(
    f_x: NDArray, f_y: NDArray, dx: NDArray, dy: NDArray, *, inv_h: NDArray | None = None
) -> tuple[NDArray, NDArray]:
    """(f_h, f_theta) from (f_x, f_y) at offsets (dx, dy) = (x - x_c, y - y_c), eq. (19)-(20).

    ``inv_h`` (1 / h_i, broadcastable) may be passed when it is already known.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        if inv_h is None:
            inv_h = 1.0 / np.sqrt(dx * dx + dy * dy)
        f_h = (dx * f_x + dy * f_y) * inv_h  # eq. (19); 0 * inf = NaN at h_i = 0
    f_theta = dx * f_y - dy * f_x  # eq. (20)
    return f_h, f_theta


@lru_cache(maxsize=8)
def _offsets(width: int, height: int, x_c: float, y_c: float, dtype: np.dtype):
    """(x - x_c) as (1, W), (y - y_c) as (H, 1) and 1 / h_i as (H, W), read-only."""
    dt = np.dtype(dtype).type
    dx = (np.arange(width, dtype=dtype) + dt(0.5 - x_c))[None, :]
    dy = (np.arange(height, dtype=dtype) + dt(0.5 - y_c))[:, None]
    with np.errstate(divide="ignore"):
        inv_h = 1.0 / np.sqrt(dx * dx + dy * dy)
    for a in (dx, dy, inv_h):
        a.setflags(write=False)
    return dx, dy, inv_h


def polar_gradient(fit: DCTFit, unit: Unit, x: ArrayLike, y: ArrayLike) -> tuple[NDArray, NDArray]:
    """Polar gradient (df/dh_i, df/dtheta_i) of a fitted image at arbitrary points.

    Parameters
    ----------
    fit : DCTFit
        The image's series, eq. (18).
    unit : Unit
        Supplies the image of the axis (x_c, y_c).
    x, y : array_like, any equal shapes
        Continuous pixel coordinates (pixel centres at j + 0.5, i + 0.5).

    Returns
    -------
    f_h : ndarray, the shape of x
        df/dh_i, grey levels per pixel of radius; NaN where h_i = 0.
    f_theta : ndarray, the shape of x
        df/dtheta_i, grey levels per radian (no 1/h_i factor).
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    f_x, f_y = fit.gradient(x, y)
    return polar_from_cartesian(f_x, f_y, x - unit.x_c, y - unit.y_c)


def polar_gradient_grid(fit: DCTFit, unit: Unit) -> tuple[NDArray, NDArray]:
    """Polar gradient (df/dh_i, df/dtheta_i) on every pixel centre, each shape (H, W).

    Uses the fast transform path :meth:`DCTFit.grid_gradient`; the result has
    the fit's working dtype (float32 for a float32 image).
    """
    if (fit.width, fit.height) != (unit.width, unit.height):
        raise ValueError(
            f"fit is {fit.width}x{fit.height} but unit {unit.name or ''} is "
            f"{unit.width}x{unit.height}: expected the same image size"
        )
    f_x, f_y = fit.grid_gradient()
    dx, dy, inv_h = _offsets(fit.width, fit.height, float(unit.x_c), float(unit.y_c), f_x.dtype)
    return polar_from_cartesian(f_x, f_y, dx, dy, inv_h=inv_h)
