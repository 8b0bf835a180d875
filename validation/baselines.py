"""OpenCV baselines, run on the same 8-bit frames as omniflow.

Each method runs on each camera's raw omni image (the name alone) and, where the
name ends in ``-panorama``, on the unwarped panoramas
(:func:`omniflow.geometry.rig.unwarp`), the panorama flow mapped back to an
image-plane displacement at each point. The paper's method avoids unwarping;
the panorama rows measure what unwarping costs and buys.

* ``DIS-medium``: ``cv2.DISOpticalFlow`` with ``DISOPTICAL_FLOW_PRESET_MEDIUM``;
* ``DIS-fine``: DIS at its finest settings (:func:`dis_fine_flow`): the medium
  preset, then finest scale 0 (full resolution), patch stride 2, 100
  gradient-descent iterations per scale, 10 variational-refinement iterations
  (alpha 20, delta 5, gamma 10, the preset's weights);
* ``Farneback``: ``cv2.calcOpticalFlowFarneback`` (pyramid scale 0.5, 3
  levels, window 15, 3 iterations, poly_n 5, poly_sigma 1.2);
* ``DeepFlow``: ``cv2.optflow.createOptFlow_DeepFlow`` (Weinzaepfel et al.
  2013, the variational energy without the deep matches), OpenCV's defaults;
* ``DualTVL1``: ``cv2.optflow.DualTVL1OpticalFlow_create`` (Zach, Pock and
  Bischof 2007), OpenCV's defaults (5 scales, 5 warps, lambda 0.15);
* ``PCAFlow``: ``cv2.optflow.createOptFlow_PCAFlow`` (Wulff and Black 2015):
  sparse matches fitted by a low-dimensional flow basis, OpenCV's defaults
  (no learned prior);
* ``RLOF``: ``cv2.optflow.calcOpticalFlowDenseRLOF`` (Senst et al.): robust
  local flow on a 6 px grid, interpolated edge-aware (EPIC) and smoothed,
  OpenCV's defaults;
* ``zero-flow``: predicts no motion anywhere. Not a method but the floor a
  method must clearly beat: a method that shrinks its flow towards zero has a
  small median error at sub-pixel motion, and this row shows how small.

Input: every method takes the 8-bit grey frame, except RLOF, whose default
cross-based support region (``SR_CROSS``) needs 8-bit 3-channel images: it gets
the grey frame copied into three channels (``cv2.COLOR_GRAY2BGR``), so it sees
exactly the same intensities as the others.

:data:`DEFAULT_BASELINES` are the cheap ones ``omnivalidate`` runs unless told
otherwise; the rest are chosen by name. Settings, measured accuracy and cost:
``docs/decisions/baselines_contrib.md``.

Each baseline gives a dense field per camera; :class:`DenseFlow` evaluates it
at arbitrary sub-pixel points (bilinear), so baselines are scored at exactly
the points omniflow reports as well as at every valid pixel.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from omniflow.geometry.rig import Unit, unwarp

from .inputs import InputError
from .metrics import polar_components
from .sampling import bilinear

__all__ = [
    "BASELINES",
    "DEFAULT_BASELINES",
    "DIS_MIN_SIDE",
    "METHODS",
    "PANORAMA_METHODS",
    "PANORAMA_SUFFIX",
    "PCAFLOW_MIN_ROWS",
    "RLOF_MIN_SEEDS",
    "ZERO_FLOW",
    "DenseFlow",
    "PanoramaFlow",
    "deepflow_flow",
    "dense_baseline",
    "dis_fine_flow",
    "dis_flow",
    "dual_tvl1_flow",
    "farneback_flow",
    "panorama_flow",
    "panorama_size",
    "pcaflow_flow",
    "rlof_flow",
]

#: The row that predicts no motion (the floor every method is compared with).
ZERO_FLOW = "zero-flow"
#: Appended to a method's name for its run on the unwarped panoramas.
PANORAMA_SUFFIX = "-panorama"
#: The fewest rows OpenCV's PCAFlow takes without writing out of bounds: on
#: opencv-contrib 5.1.0, 55 x 64 px aborts the process (valgrind: invalid writes
#: inside cv2), 56 x 64, 60 x 377 and larger run clean (docs/decisions/baselines_contrib.md).
PCAFLOW_MIN_ROWS = 56
#: The shortest side OpenCV's DIS takes: on opencv-contrib 5.1.0 a 14 x 120 px image
#: (the DIS-medium-panorama of a 32 px render) kills the process with a segmentation
#: fault, 16 x 120 and 16 x 16 px run (its own check only refuses both sides under 12).
DIS_MIN_SIDE = 16
#: Dense RLOF's seed grid step (OpenCV's default ``gridStep``, 6 x 6 px).
RLOF_GRID_STEP = 6
#: The fewest grid seeds dense RLOF is run on. On opencv-contrib 5.1.0 its EPIC
#: interpolation (K = 128 nearest seeds) reads out of bounds (valgrind) at 64 x 64 px
#: (121 seeds) and gives a different flow on each call of the same pair, up to 71 px
#: wrong, or crashes, at 56-72 px square (100-144 seeds); with epicK 64 or grid step
#: 3 the same pairs are repeatable. Twice K, for a margin (docs/decisions/baselines_contrib.md).
RLOF_MIN_SEEDS = 256

#: Columns of circular padding on each side of a panorama, so DIS sees the
#: seam at theta = 0 as continuous image.
PANORAMA_PAD = 16


def _dis_size(a: NDArray) -> None:
    """InputError for an image with a side under :data:`DIS_MIN_SIDE` (DIS would crash)."""
    if min(a.shape[:2]) < DIS_MIN_SIDE:
        raise InputError(
            f"DIS: a {a.shape[0]} x {a.shape[1]} px image; OpenCV's DIS crashes on images "
            f"with a side under {DIS_MIN_SIDE} px (a panorama has about a seventh of the "
            "image size in rows at 32 px): use a larger resolution or leave the row out"
        )


def dis_flow(img0: NDArray, img1: NDArray) -> NDArray:
    """DIS optical flow (medium preset), shape (H, W, 2) as (dx, dy) in pixels."""
    a, b = _u8(img0), _u8(img1)
    _dis_size(a)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return dis.calc(a, b, None)


def farneback_flow(img0: NDArray, img1: NDArray) -> NDArray:
    """Farneback dense flow, shape (H, W, 2) as (dx, dy) in pixels."""
    return cv2.calcOpticalFlowFarneback(_u8(img0), _u8(img1), None, 0.5, 3, 15, 3, 5, 1.2, 0)


def dis_fine_flow(img0: NDArray, img1: NDArray) -> NDArray:
    """DIS at its finest settings with variational refinement, shape (H, W, 2) as (dx, dy).

    The medium preset (patch 8, mean normalisation and spatial propagation on),
    then: finest scale 0 (the medium preset stops at scale 1, half resolution),
    patch stride 2 (medium: 3), 100 gradient-descent iterations per patch
    (medium: 25) and 10 variational-refinement iterations (medium: 5) with the
    preset's weights (alpha 20, delta 5, gamma 10).
    """
    a, b = _u8(img0), _u8(img1)
    _dis_size(a)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    dis.setFinestScale(0)
    dis.setPatchStride(2)
    dis.setGradientDescentIterations(100)
    dis.setVariationalRefinementIterations(10)
    return dis.calc(a, b, None)


def deepflow_flow(img0: NDArray, img1: NDArray) -> NDArray:
    """DeepFlow (``cv2.optflow.createOptFlow_DeepFlow``, OpenCV's defaults), (H, W, 2)."""
    return cv2.optflow.createOptFlow_DeepFlow().calc(_u8(img0), _u8(img1), None)


def dual_tvl1_flow(img0: NDArray, img1: NDArray) -> NDArray:
    """Dual TV-L1 (``cv2.optflow.DualTVL1OpticalFlow_create``, OpenCV's defaults), (H, W, 2)."""
    return cv2.optflow.DualTVL1OpticalFlow_create().calc(_u8(img0), _u8(img1), None)


def pcaflow_flow(img0: NDArray, img1: NDArray) -> NDArray:
    """PCAFlow (``cv2.optflow.createOptFlow_PCAFlow``, OpenCV's defaults), (H, W, 2).

    Images under :data:`PCAFLOW_MIN_ROWS` rows are refused (:class:`InputError`):
    OpenCV's PCAFlow writes out of bounds on them and the process aborts.
    """
    a, b = _u8(img0), _u8(img1)
    if a.shape[0] < PCAFLOW_MIN_ROWS:
        raise InputError(
            f"PCAFlow: a {a.shape[0]} x {a.shape[1]} px image; OpenCV's PCAFlow corrupts memory "
            f"on images under {PCAFLOW_MIN_ROWS} rows (a panorama has about half the image "
            "size in rows): use a larger resolution or leave the row out"
        )
    return cv2.optflow.createOptFlow_PCAFlow().calc(a, b, None)


def rlof_flow(img0: NDArray, img1: NDArray) -> NDArray:
    """Dense RLOF (``cv2.optflow.calcOpticalFlowDenseRLOF``, OpenCV's defaults), (H, W, 2).

    The default support region (cross-based) needs 8-bit 3-channel images: the
    grey frame is copied into three channels, so RLOF sees the same intensities
    as every other baseline. Images giving under :data:`RLOF_MIN_SEEDS` seeds on
    its 6 px grid are refused (:class:`InputError`): there OpenCV's RLOF reads
    out of bounds, and its flow changes from call to call or the process crashes.
    """
    a = _u8(img0)
    seeds = math.ceil(a.shape[0] / RLOF_GRID_STEP) * math.ceil(a.shape[1] / RLOF_GRID_STEP)
    if seeds < RLOF_MIN_SEEDS:
        raise InputError(
            f"RLOF: a {a.shape[0]} x {a.shape[1]} px image gives {seeds} grid seeds; OpenCV's "
            f"dense RLOF reads out of bounds with under about {RLOF_MIN_SEEDS} (its EPIC "
            "interpolator takes the 128 nearest): use a larger resolution or leave the row out"
        )
    bgr0 = cv2.cvtColor(a, cv2.COLOR_GRAY2BGR)
    bgr1 = cv2.cvtColor(_u8(img1), cv2.COLOR_GRAY2BGR)
    return cv2.optflow.calcOpticalFlowDenseRLOF(bgr0, bgr1, None)


def zero_flow(img0: NDArray, img1: NDArray) -> NDArray:
    """No motion anywhere, shape (H, W, 2): the floor every method must beat."""
    return np.zeros((*img0.shape[:2], 2), np.float32)


def _u8(img: NDArray) -> NDArray:
    if img.dtype != np.uint8 or img.ndim != 2:
        raise TypeError(
            f"OpenCV baselines take 2-D uint8 grey images, got {img.dtype} of shape {img.shape}"
        )
    return np.ascontiguousarray(img)


#: The methods by name: a function of two 8-bit grey frames giving (dx, dy) per pixel.
METHODS: dict[str, Callable[[NDArray, NDArray], NDArray]] = {
    "DIS-medium": dis_flow,
    "DIS-fine": dis_fine_flow,
    "Farneback": farneback_flow,
    "DeepFlow": deepflow_flow,
    "DualTVL1": dual_tvl1_flow,
    "PCAFlow": pcaflow_flow,
    "RLOF": rlof_flow,
    ZERO_FLOW: zero_flow,
}
#: Methods that also run on the unwarped panoramas (``NAME-panorama``).
PANORAMA_METHODS = ("DIS-medium", "DIS-fine", "DeepFlow", "DualTVL1", "PCAFlow", "RLOF")
#: Every baseline name ``omnivalidate --baselines`` accepts, in report order.
BASELINES = (
    "DIS-medium",
    "Farneback",
    "DIS-medium-panorama",
    ZERO_FLOW,
    "DIS-fine",
    "DeepFlow",
    "DualTVL1",
    "PCAFlow",
    "RLOF",
    *(m + PANORAMA_SUFFIX for m in PANORAMA_METHODS if m != "DIS-medium"),
)
#: The baselines run unless others are named: cheap enough for CI at 512 px
#: (see ``docs/decisions/baselines_contrib.md`` for each method's time per frame).
DEFAULT_BASELINES = ("DIS-medium", "Farneback", "DIS-medium-panorama", ZERO_FLOW)


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


def panorama_flow(
    img0: NDArray,
    img1: NDArray,
    unit: Unit,
    *,
    method: Callable[[NDArray, NDArray], NDArray] = dis_flow,
) -> PanoramaFlow:
    """Unwarp both frames, pad circularly, run ``method`` (DIS medium by default).

    Timed as a whole, unwarping included.
    """
    t0 = time.perf_counter()
    p0, p1 = unwarp_u8(img0, unit), unwarp_u8(img1, unit)
    pad = PANORAMA_PAD
    p0 = np.ascontiguousarray(np.concatenate([p0[:, -pad:], p0, p0[:, :pad]], axis=1))
    p1 = np.ascontiguousarray(np.concatenate([p1[:, -pad:], p1, p1[:, :pad]], axis=1))
    flow = method(p0, p1)
    seconds = time.perf_counter() - t0
    height, width = p0.shape[0], p0.shape[1] - 2 * pad
    return PanoramaFlow(flow=flow, unit=unit, width=width, height=height, pad=pad, seconds=seconds)


def dense_baseline(name: str, img0: NDArray, img1: NDArray, unit: Unit) -> DenseFlow | PanoramaFlow:
    """Run the baseline ``name`` (one of :data:`BASELINES`) on one camera's frame pair.

    Raises ``ValueError`` with one line listing the choices for an unknown name.
    """
    if name not in BASELINES:
        raise ValueError(f"unknown baseline {name!r}; expected one of {', '.join(BASELINES)}")
    if name.endswith(PANORAMA_SUFFIX):
        return panorama_flow(img0, img1, unit, method=METHODS[name.removesuffix(PANORAMA_SUFFIX)])
    t0 = time.perf_counter()
    flow = METHODS[name](img0, img1)
    return DenseFlow(flow=flow, unit=unit, seconds=time.perf_counter() - t0)
