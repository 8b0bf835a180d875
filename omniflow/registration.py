"""omniflow on a registered rig: each image rectified to the ideal unit of eq. (1).

A rig whose units carry errors (``[rig.errors.camN]``, e.g. from ``omniflow calibrate``)
does not image by eq. (1). Rather than carrying per-pixel rays through matching and
triangulation, each image is resampled onto the ideal unit's pixels once
(:func:`rectify_map`): ideal pixel (h_i, theta) looks along eq. (1)'s ray; its point at
range ``depth`` from the axis is projected by the traced model
(:func:`omniflow.geometry.rig_errors.traced_project`) into the real image, which is
sampled there (linear interpolation, :data:`RESAMPLE_ORDER`). The pipeline then runs
unchanged on the ideal rig, and the results' pixel columns are mapped back to the real
images (:meth:`Rectifier.result`), so they are scored where the camera saw them. The
range r and height h of eq. (5) are the rig frame's already.

The real image of a point depends on its depth wherever a mirror offset or tilt moves
the viewpoint ring, so the rectification is exact at ``depth`` only; the residual
against depth is measured in docs/decisions/registration.md (``python3 -m
benchmarks.registration_residual``).
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from omniflow.conventions import wrap_angle
from omniflow.geometry.rig import Rig, Unit
from omniflow.geometry.rig_errors import traced_project

__all__ = ["DEFAULT_DEPTH", "Rectifier", "has_errors", "rectify_map"]

#: The range (m from the axis) at which the rectification is exact: the walls of the
#: shipped scenes lie 1-3.3 m from the axis (docs/decisions/registration.md).
DEFAULT_DEPTH = 2.0
#: Spline order of the resampling (scipy.ndimage.map_coordinates): linear. On the default
#: scene with errors it gave the lower flow EPE (0.027 / 0.047 px against 0.029 / 0.049
#: for cubic and 0.030 / 0.050 for order 5) at a third of cubic's cost
#: (docs/decisions/registration.md).
RESAMPLE_ORDER = 1


def has_errors(rig: Rig) -> bool:
    """True when a unit of ``rig`` carries errors (so eq. 1 does not hold)."""
    return any(u.errors is not None and not u.errors.ideal for u in (rig.cam1, rig.cam2))


def ideal_points(unit: Unit, x: NDArray, y: NDArray, depth: float) -> NDArray:
    """Rig points (..., 3) at range ``depth`` on the ideal rays of pixels (x, y), eq. (1)."""
    h_i, theta = unit.polar_of_pixel(x, y)
    h = h_i * (unit.d + depth) / unit.v  # eq. (1) solved for h
    return np.stack([depth * np.cos(theta), depth * np.sin(theta), unit.tip_h + h], axis=-1)


@lru_cache(maxsize=8)
def rectify_map(unit: Unit, depth: float = DEFAULT_DEPTH) -> tuple[NDArray, NDArray]:
    """Real-image pixel (x, y), each (H, W), of every ideal pixel centre of ``unit``.

    Ideal pixels outside the rim keep their own position; ideal pixels whose point no
    real pixel sees (beyond the real rim) are NaN.
    """
    x, y = unit.pixel_centres()
    q = ideal_points(unit, x, y, depth)
    inside = np.hypot(x - unit.x_c, y - unit.y_c) <= unit.r_m
    xr, yr = x.copy(), y.copy()
    xa, ya, seen = traced_project(unit, q[inside])
    xr[inside] = np.where(seen, xa, np.nan)
    yr[inside] = np.where(seen, ya, np.nan)
    xr.flags.writeable = yr.flags.writeable = False
    return xr, yr


def _rectify(image: NDArray, mp: tuple[NDArray, NDArray]) -> NDArray:
    """``image`` resampled at the real pixels ``mp`` (:data:`RESAMPLE_ORDER`; 0 where NaN)."""
    xr, yr = mp
    bad = ~np.isfinite(xr)
    coords = [np.where(bad, 0.0, yr - 0.5), np.where(bad, 0.0, xr - 0.5)]
    img = np.asarray(image, dtype=np.float64)
    out = ndimage.map_coordinates(img, coords, order=RESAMPLE_ORDER, mode="nearest")
    out[bad] = 0.0
    return out.astype(np.asarray(image).dtype if np.asarray(image).dtype.kind == "f" else float)


def _at(mp: tuple[NDArray, NDArray], x: NDArray, y: NDArray) -> tuple[NDArray, NDArray]:
    """The map at continuous ideal pixels (x, y), bilinear (NaN where the map is)."""
    coords = [np.asarray(y, dtype=float) - 0.5, np.asarray(x, dtype=float) - 0.5]
    return tuple(ndimage.map_coordinates(m, coords, order=1, mode="nearest") for m in mp)


class Rectifier:
    """Rectify the images of a rig with errors and map results back (see the module)."""

    def __init__(self, rig: Rig, depth: float = DEFAULT_DEPTH):
        self.rig, self.depth = rig, float(depth)
        self.ideal = Rig(cam1=replace(rig.cam1, errors=None), cam2=replace(rig.cam2, errors=None),
                         s=rig.s)  # fmt: skip
        self.maps = {}

    def _map(self, cam: str):
        if cam not in self.maps:
            unit = getattr(self.rig, cam)
            ideal = unit.errors is None or unit.errors.ideal
            self.maps[cam] = None if ideal else rectify_map(unit, self.depth)
        return self.maps[cam]

    def image(self, image: NDArray, cam: str) -> NDArray:
        """One real image of ``cam`` resampled onto the ideal unit's pixels."""
        mp = self._map(cam)
        img = np.asarray(image)
        if mp is None or img.shape != mp[0].shape:  # a wrong shape: the pipeline's check says so
            return img
        return _rectify(img, mp)

    def frames(self, frames1, frames2) -> tuple[list, list]:
        return [self.image(f, "cam1") for f in frames1], [self.image(f, "cam2") for f in frames2]

    def columns(self, cols: dict, cam: str, names: tuple[str, ...]) -> dict:
        """Pixel columns ``names`` = (x, y, dx, dy, h, dh_dt[, theta, dtheta_dt]) mapped from
        the ideal unit's pixels to the real image (positions, flow, polar ones about x_c,
        y_c); the rest unchanged."""
        mp = self._map(cam)
        if mp is None or names[0] not in cols or len(cols[names[0]]) == 0:
            return cols
        cols = dict(cols)
        unit = getattr(self.rig, cam)
        x, y, dx, dy = (np.asarray(cols[k], dtype=np.float64) for k in names[:4])
        xa, ya = _at(mp, x, y)
        xb, yb = _at(mp, x + dx, y + dy)
        cols[names[0]], cols[names[1]], cols[names[2]], cols[names[3]] = xa, ya, xb - xa, yb - ya
        h0, t0 = unit.polar_of_pixel(xa, ya)
        h1, t1 = unit.polar_of_pixel(xb, yb)
        cols[names[4]], cols[names[5]] = h0, h1 - h0
        if len(names) > 6:
            cols[names[6]], cols[names[7]] = t0, wrap_angle(t1 - t0)
        return cols

    def result(self, res):
        """An :class:`~omniflow.result.OmniFlowResult` of the rectified images, its pixel
        columns in the real images (cam1: x, y, theta, h1, flow; cam2: x2, y2, h2, flow)."""
        if res is None:
            return None
        cam1 = ("x", "y", "dx", "dy", "h1", "dh1_dt", "theta", "dtheta_dt")
        res.columns = self.columns(res.columns, "cam1", cam1)
        res.columns = self.columns(res.columns, "cam2", ("x2", "y2", "dx2", "dy2", "h2", "dh2_dt"))
        if res.monocular:
            res.monocular = self.columns(res.monocular, "cam1", cam1)
        return res
