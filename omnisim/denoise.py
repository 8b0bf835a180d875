"""Denoise a Monte Carlo render with Intel Open Image Denoise (``pyoidn``, CPU).

A path-traced frame at a few samples per pixel carries Monte Carlo noise; the
``RT`` filter of Open Image Denoise removes it, guided by the albedo and the
shading normal of the first hit (Mitsuba's ``aov`` integrator), which carry the
texture and the geometry noise-free: the filter smooths the illumination and
keeps the texture the albedo shows. docs/decisions/denoiser.md
compares the residual error against a converged reference, the
error of the image gradients and the time with the integrators at several spp.

The colour is linear radiance, so the filter runs in HDR mode. Pixels wholly
outside the mirror's rim are black in the render and stay black.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "DENOISERS",
    "GUIDE_AOVS",
    "GUIDE_SPP",
    "QUALITY",
    "guide_integrator_dict",
    "oidn_denoise",
]

#: ``render.denoise`` values: none, or Open Image Denoise's RT filter.
DENOISERS = ("none", "oidn")
#: Mitsuba ``aov`` integrator channels of the guides: albedo (3), shading normal (3).
GUIDE_AOVS = "albedo:albedo,normal:sh_normal"
#: Samples per pixel of the guides (fewer when the colour has fewer). The guides are
#: handed to the filter as clean (``clean_aux``), so they need enough samples to carry
#: the texture averaged over the pixel: with 4 spp guides the residual of direct 64 spp +
#: oidn rose from 0.81 % to 1.32 %, with 64 spp it fell to 0.79 % at 3.5x the guides'
#: cost (docs/decisions/denoiser.md).
GUIDE_SPP = 16
#: Open Image Denoise quality: "balanced" gave 0.79 % residual at 0.8 CPU s per 512 px
#: image, "high" 0.73 % at 2.1 CPU s, "fast" 0.95 % at 0.4 CPU s (direct 64 spp, guides
#: at 64 spp; docs/decisions/denoiser.md).
QUALITY = "balanced"


def guide_integrator_dict() -> dict[str, Any]:
    """Mitsuba integrator rendering the guides: albedo then world shading normal."""
    return {"type": "aov", "aovs": GUIDE_AOVS}


def oidn_denoise(
    color: NDArray[np.float32],
    guides: NDArray[np.float32],
    outside: NDArray[np.bool_] | None = None,
) -> NDArray[np.float32]:
    """Denoised linear RGB (H, W, 3) of ``color`` with ``guides`` (H, W, 6).

    Parameters
    ----------
    color
        Noisy linear radiance (H, W, 3), float32, non-negative.
    guides
        Albedo (channels 0-2, in [0, 1]) and world-space shading normal
        (channels 3-5, in [-1, 1]) of the same pixels, as rendered by
        :func:`guide_integrator_dict` at :data:`GUIDE_SPP`; taken as
        noise-free (``clean_aux``: a prefilter would blur the texture they carry).
    outside
        (H, W) pixels that no sample can reach (wholly outside the rim): the
        guides are zeroed there before filtering and the output is zeroed
        after, so the black surround neither bleeds in nor out.

    Returns
    -------
    numpy.ndarray
        Denoised radiance (H, W, 3), float32. Deterministic: the same input
        gives the same bytes (Open Image Denoise on the CPU).
    """
    import pyoidn

    color = np.ascontiguousarray(color, dtype=np.float32)
    albedo = np.clip(guides[..., 0:3], 0.0, 1.0).astype(np.float32)
    normal = np.clip(guides[..., 3:6], -1.0, 1.0).astype(np.float32)
    if outside is not None:
        albedo[outside] = 0.0
        normal[outside] = 0.0
    out = pyoidn.denoise(
        color,
        np.ascontiguousarray(albedo),
        np.ascontiguousarray(normal),
        hdr=True,
        clean_aux=True,
        quality=QUALITY,
    )
    out = np.maximum(out, 0.0)
    if outside is not None:
        out[outside] = 0.0
    return out
