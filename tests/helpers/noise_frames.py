"""Closed-form frame pairs through the camera model, for the noise estimators' tests.

A texture of :class:`omnisim.synthetic.Texture` (a sum of sinusoids) laid on the image
plane in pixel units and translated by a known sub-pixel to few-pixel shift between the
two frames; both frames pass through :class:`omnisim.camera.CameraModel` as grey
radiance (R = G = B) and are read as omniflow reads a camera image
(:func:`omniflow.io.dataset.camera_grey`), frames ``2 seed`` and ``2 seed + 1``.
"""

from __future__ import annotations

import numpy as np

from omniflow.io.dataset import camera_grey
from omnisim.camera import CameraModel
from omnisim.synthetic import Texture

#: Texture wavelengths (pixels) of the tests: fine (where a single-frame estimate counts
#: texture as noise), very fine (down to the Nyquist wavelength) and coarse.
FINE = (2.5, 4.0)
VERY_FINE = (2.0, 3.0)
COARSE = (12.0, 40.0)


def texture_image(
    size: int,
    shift: tuple[float, float],
    seed: int,
    wavelengths: tuple[float, float],
    *,
    mean: float = 0.2,
    contrast: float = 0.15,
) -> np.ndarray:
    """Radiance (size, size) of a random texture moved by ``shift`` (dx, dy) pixels."""
    tex = Texture.random(seed, n=12, wavelengths=wavelengths, contrast=contrast, mean=mean)
    yy, xx = np.mgrid[0:size, 0:size] + 0.5
    return tex(xx - shift[0], yy - shift[1])


def camera_frames(model: CameraModel, radiance: np.ndarray, frame: int) -> np.ndarray:
    """The grey image omniflow reads of a grey ``radiance`` taken by ``model``."""
    rgb = np.repeat(np.asarray(radiance, np.float32)[..., None], 3, axis=2)
    return camera_grey(model.apply(rgb, frame=frame, cam="cam1"), model.bits)


def moving_pair(
    model: CameraModel,
    shift: tuple[float, float],
    seed: int,
    wavelengths: tuple[float, float] = FINE,
    *,
    size: int = 256,
    **texture,
) -> tuple[np.ndarray, np.ndarray]:
    """Grey frames t and t + 1 of a texture moving by ``shift`` pixels per frame."""
    f0 = camera_frames(
        model, texture_image(size, (0.0, 0.0), seed, wavelengths, **texture), 2 * seed
    )
    f1 = camera_frames(
        model, texture_image(size, shift, seed, wavelengths, **texture), 2 * seed + 1
    )
    return f0, f1
