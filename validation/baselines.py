"""OpenCV baselines, run on the same 8-bit frames as omniflow.

* ``DIS-medium``: ``cv2.DISOpticalFlow`` with ``DISOPTICAL_FLOW_PRESET_MEDIUM``
  on each camera's raw omni image;
* ``Farneback``: ``cv2.calcOpticalFlowFarneback`` (pyramid scale 0.5, 3
  levels, window 15, 3 iterations, poly_n 5, poly_sigma 1.2) on the raw images;
* ``DIS-medium-panorama``: DIS on the unwarped panoramas
  (:func:`omniflow.geometry.rig.unwarp`), the panorama flow mapped back to an
  image-plane displacement at each point. The paper's method avoids unwarping;
  this row measures what unwarping costs and buys;
* ``zero-flow``: predicts no motion anywhere. Not a method but the floor a
  method must clearly beat: a method that shrinks its flow towards zero has a
  small median error at sub-pixel motion, and this row shows how small.

Each baseline gives a dense field per camera; :class:`DenseFlow` evaluates it
at arbitrary sub-pixel points (bilinear), so baselines are scored at exactly
the points omniflow reports as well as at every valid pixel.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from omniflow.geometry.rig import Unit, unwarp

from .metrics import polar_components
from .sampling import bilinear

__all__ = [
    "BASELINES",
    "ZERO_FLOW",
    "DenseFlow",
    "PanoramaFlow",
    "dis_flow",
    "farneback_flow",
    "panorama_flow",
    "panorama_size",
]

#: Names of the baselines, in report order.
BASELINES = ("DIS-medium", "Farneback", "DIS-medium-panorama", "zero-flow")
#: The row that predicts no motion (the floor every method is compared with).
ZERO_FLOW = "zero-flow"

#: Columns of circular padding on each side of a panorama, so DIS sees the
#: seam at theta = 0 as continuous image.
PANORAMA_PAD = 16


def dis_flow(img0: NDArray, img1: NDArray) -> NDArray:
    """DIS optical flow (medium preset), shape (H, W, 2) as (dx, dy) in pixels."""
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return dis.calc(_u8(img0), _u8(img1), None)


def farneback_flow(img0: NDArray, img1: NDArray) -> NDArray:
    """Farneback dense flow, shape (H, W, 2) as (dx, dy) in pixels."""
    return cv2.calcOpticalFlowFarneback(_u8(img0), _u8(img1), None, 0.5, 3, 15, 3, 5, 1.2, 0)


def _u8(img: NDArray) -> NDArray:
    if img.dtype != np.uint8:
        raise TypeError(f"OpenCV baselines take uint8 images, got {img.dtype}")
    return np.ascontiguousarray(img)


@dataclass
class DenseFlow:
    """A dense flow field of one camera, evaluated at points on demand."""

    flow: NDArray  # (H, W, 2) dx, dy
    unit: Unit
    seconds: float = 0.0

    def at(self, x: ArrayLike, y: ArrayLike) -> dict[str, NDArray]:
        """dx, dy, dh, hdtheta (px per frame) at continuous pixel points."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        dx = bilinear(self.flow[..., 0], x, y)
        dy = bilinear(self.flow[..., 1], x, y)
        dh, hdth = polar_components(x, y, dx, dy, self.unit.x_c, self.unit.y_c)
        return {"dx": dx, "dy": dy, "dh": dh, "hdtheta": hdth}


def panorama_size(unit: Unit) -> tuple[int, int]:
    """(width, height) of the panorama: the rim's circumference by r_m pixels."""
    return max(16, round(2 * math.pi * unit.r_m)), max(8, round(unit.r_m))


@dataclass
class PanoramaFlow:
    """Flow computed on the unwarped panorama, mapped back to the image plane.

    Panorama column X (continuous, centres at index + 0.5) is theta = 2 pi X / W
    and row Y is h_i = r_m (1 - Y / H), the inverse of :func:`omniflow.geometry.rig.unwarp`.
    A point (x, y) goes to (X, Y); the panorama flow (du, dv) sampled there
    moves it to (X + du, Y + dv), which maps back to (x', y'); the image-plane
    displacement is (x' - x, y' - y).
    """

    flow: NDArray  # (H_p, W_p + 2 pad, 2), padded circularly
    unit: Unit
    width: int
    height: int
    pad: int = PANORAMA_PAD
    seconds: float = 0.0

    def to_panorama(self, x: NDArray, y: NDArray) -> tuple[NDArray, NDArray]:
        h_i, theta = self.unit.polar_of_pixel(x, y)
        theta = np.mod(theta, 2 * math.pi)
        return theta * self.width / (2 * math.pi), self.height * (1.0 - h_i / self.unit.r_m)

    def at(self, x: ArrayLike, y: ArrayLike) -> dict[str, NDArray]:
        """dx, dy, dh, hdtheta (px per frame) at continuous pixel points."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        px, py = self.to_panorama(x, y)
        du = bilinear(self.flow[..., 0], px + self.pad, py)
        dv = bilinear(self.flow[..., 1], px + self.pad, py)
        theta1 = 2 * math.pi * (px + du) / self.width
        h1 = self.unit.r_m * (1.0 - (py + dv) / self.height)
        x1, y1 = self.unit.pixel_of_polar(h1, theta1)
        dx, dy = x1 - x, y1 - y
        dh, hdth = polar_components(x, y, dx, dy, self.unit.x_c, self.unit.y_c)
        return {"dx": dx, "dy": dy, "dh": dh, "hdtheta": hdth}


def unwarp_u8(img: NDArray, unit: Unit) -> NDArray:
    """The 8-bit panorama of an 8-bit omni image (size from :func:`panorama_size`)."""
    width, height = panorama_size(unit)
    pan = unwarp(img.astype(np.float32), unit, width=width, height=height)
    return np.clip(np.rint(pan), 0, 255).astype(np.uint8)


def panorama_flow(img0: NDArray, img1: NDArray, unit: Unit) -> PanoramaFlow:
    """Unwarp both frames, pad circularly, run DIS medium (timed as a whole)."""
    t0 = time.perf_counter()
    p0, p1 = unwarp_u8(img0, unit), unwarp_u8(img1, unit)
    pad = PANORAMA_PAD
    p0 = np.ascontiguousarray(np.concatenate([p0[:, -pad:], p0, p0[:, :pad]], axis=1))
    p1 = np.ascontiguousarray(np.concatenate([p1[:, -pad:], p1, p1[:, :pad]], axis=1))
    flow = dis_flow(p0, p1)
    seconds = time.perf_counter() - t0
    height, width = p0.shape[0], p0.shape[1] - 2 * pad
    return PanoramaFlow(flow=flow, unit=unit, width=width, height=height, pad=pad, seconds=seconds)


def dense_baseline(name: str, img0: NDArray, img1: NDArray, unit: Unit) -> DenseFlow | PanoramaFlow:
    """Run the baseline ``name`` on one camera's frame pair."""
    if name == "DIS-medium-panorama":
        return panorama_flow(img0, img1, unit)
    fn = {
        "DIS-medium": dis_flow,
        "Farneback": farneback_flow,
        ZERO_FLOW: lambda a, b: np.zeros((*a.shape[:2], 2), np.float32),
    }.get(name)
    if fn is None:
        raise ValueError(f"unknown baseline {name!r}; expected one of {BASELINES}")
    t0 = time.perf_counter()
    flow = fn(img0, img1)
    return DenseFlow(flow=flow, unit=unit, seconds=time.perf_counter() - t0)
