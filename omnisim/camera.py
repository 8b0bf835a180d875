"""Re-export of :mod:`omniflow.camera`, the camera model's home (kept for old imports)."""

from omniflow.camera import (
    BITS,
    MAX_DEFOCUS,
    MAX_FULL_WELL,
    POISSON_EXACT_BELOW,
    RESPONSES,
    CameraError,
    CameraModel,
    camera_image,
    parse_camera_overrides,
    srgb_encode,
)

__all__ = [
    "BITS",
    "MAX_DEFOCUS",
    "MAX_FULL_WELL",
    "POISSON_EXACT_BELOW",
    "RESPONSES",
    "CameraError",
    "CameraModel",
    "camera_image",
    "parse_camera_overrides",
    "srgb_encode",
]
