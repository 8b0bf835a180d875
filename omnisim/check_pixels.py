"""The per-pixel helpers of :mod:`omnisim.check`: angle wrapping, remapping, the
interior of an object, the noise estimate, the traced image polar coordinates, luma,
the Lambertian test and the flow masks' consistency."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from omniflow.io.dataset import grey_of

__all__ = [
    "image_polar",
    "interior",
    "is_lambertian",
    "luma",
    "mask_consistency",
    "noise_sigma",
    "remap",
    "wrap",
]


def wrap(a: NDArray) -> NDArray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def remap(img: NDArray, mx: NDArray, my: NDArray, cubic: bool = False) -> NDArray:
    import cv2

    return cv2.remap(
        np.ascontiguousarray(img, dtype=np.float32),
        mx.astype(np.float32),
        my.astype(np.float32),
        interpolation=cv2.INTER_CUBIC if cubic else cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )


def interior(ch: dict[str, NDArray]) -> NDArray:
    """Valid pixels whose 3x3 neighbourhood is valid and shows the same object."""
    from scipy import ndimage

    valid = ch["gt.valid"] > 0.5
    obj = np.where(valid, ch["gt.object"], -1.0)
    same = ndimage.minimum_filter(obj, 3, mode="nearest") == ndimage.maximum_filter(
        obj, 3, mode="nearest"
    )
    return valid & ndimage.binary_erosion(valid, np.ones((3, 3)), border_value=0) & same


def noise_sigma(img: NDArray, mask: NDArray) -> tuple[float, int]:
    """Immerkaer (1996) noise estimate on ``mask`` (needs the 3x3 support inside it)."""
    from scipy import ndimage

    k = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float64)
    lap = ndimage.convolve(img.astype(np.float64), k, mode="nearest")
    m = ndimage.binary_erosion(mask, np.ones((3, 3)), border_value=0)
    n = int(m.sum())
    if n == 0:
        return math.nan, 0
    return math.sqrt(math.pi / 2.0) / 6.0 * float(np.mean(np.abs(lap[m]))), n


def image_polar(unit, r: NDArray, th: NDArray, h: NDArray, mask: NDArray):
    """(h_i, theta_i) at which ``unit`` images the rig points (r, th, h), (H, W) each.

    Eq. (1) (theta_i = th) for an ideal unit; for one with rig errors
    (``Unit.errors``) the traced model's pixel
    (:func:`omniflow.geometry.rig_errors.traced_project`) on ``mask``, its polar
    coordinates about (x_c, y_c), NaN where no pixel sees the point (counted as
    non-finite: a failure).
    """
    if getattr(unit, "errors", None) is None:
        return unit.image_radius(r, h), th
    from omniflow.geometry.rig_errors import traced_project

    h_out = np.full(r.shape, np.nan)
    th_out = np.full(r.shape, np.nan)
    q = np.stack([r * np.cos(th), r * np.sin(th), h], axis=-1)[mask]
    x, y, _ = traced_project(unit, q)
    h_out[mask] = np.hypot(x - unit.x_c, y - unit.y_c)
    th_out[mask] = np.arctan2(y - unit.y_c, x - unit.x_c)
    return h_out, th_out


def luma(ch: dict[str, NDArray]) -> NDArray:
    """The frame's Rec. 709 luma (the project's one: omniflow.io.dataset.grey_of), float64."""
    return grey_of(ch).astype(np.float64)


def is_lambertian(material) -> bool:
    if material is None:
        return True
    if isinstance(material, str):
        return material.lower() in ("diffuse", "lambertian")
    if isinstance(material, dict):
        kind = material.get("type", material.get("kind", "diffuse"))
        return str(kind).lower() in ("diffuse", "lambertian")
    return "diffuse" in str(material).lower()


def mask_consistency(ch: dict[str, NDArray], k: int) -> tuple[int, int]:
    """Version 2 flow masks: (pixels where they break the contract, pixels looked at).

    Per direction (``gt.flow``, ``gt.bflow``): valid, occluded, outside are 0/1, disjoint
    and 0 where ``gt.valid`` is 0; frame 0's backward masks and flow are all 0.
    """
    valid = ch["gt.valid"] > 0.5
    bad = np.zeros(valid.shape, bool)
    for key in ("gt.flow", "gt.bflow"):
        masks = [ch[f"{key}.{m}"] for m in ("valid", "occluded", "outside")]
        total = np.zeros(valid.shape)
        for m in masks:
            bad |= (m != 0) & (m != 1)
            total += m
        bad |= (total > 1) | ((total > 0) & ~valid)
        if key == "gt.bflow" and k == 0:
            for c in ("dx", "dy", "dh", "hdtheta"):
                bad |= ch[f"{key}.{c}"] != 0
            bad |= total != 0
    return int(bad.sum()), bad.size
