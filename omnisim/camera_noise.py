"""The noise of omniflow's grey input, predicted from a camera model's parameters.

omniflow reads a camera image as grey (:func:`omniflow.io.dataset.camera_grey`: the
Rec. 709 luma of ``DN / (2^bits - 1)``, rounded to 8 bits again for 8-bit cameras). For a
grey radiance (R = G = B) under a linear response, below saturation, at grey brightness
``I`` (normalised, = gain * exposure * L):

* electrons per channel ``mu = exposure * full_well * L = I full_well / gain``; their
  variance ``mu + read_noise^2`` (Poisson shot noise, Gaussian read noise);
* in normalised units ``(gain / full_well)^2 (mu + read_noise^2)
  = (gain / full_well) I + (gain read_noise / full_well)^2``, plus the quantisation
  step ``q = 1 / (2^bits - 1)``'s ``q^2 / 12``;
* the luma of three channels with independent noise has ``sum w_c^2 = 0.5619`` of one
  channel's variance (w the Rec. 709 weights).

So sigma^2(I) = a I + b with ``a = 0.5619 gain / full_well`` and
``b = 0.5619 ((gain read_noise / full_well)^2 + q^2 / 12)`` (:func:`grey_noise_level`),
exact for 10 to 16 bits. At 8 bits the grey value is rounded a second time; the luma of
whole digital numbers is not spread evenly between grey levels, so that rounding does not
add ``q^2 / 12``; :func:`grey_noise_variance` sums it exactly over the digital numbers'
distribution (Gaussian shot noise, as the model draws it at >= 1000 e-), averaged over
where the clean value falls between two levels (as over a texture).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import special

from omniflow.conventions import LUMA_WEIGHTS
from omniflow.fit.noise import NoiseLevel
from omnisim.camera import CameraModel

__all__ = ["grey_noise_level", "grey_noise_variance"]

#: sum of the squared Rec. 709 weights: the share of one channel's variance the luma keeps.
LUMA_SQUARES = float(sum(w * w for w in LUMA_WEIGHTS))


def grey_noise_level(model: CameraModel) -> NoiseLevel:
    """sigma^2(I) = a I + b of the grey image, from the camera's parameters (module doc).

    Exact for more than 8 bits; at 8 bits the second rounding is counted as ``q^2 / 12``
    (:func:`grey_noise_variance` has the exact figure). Raises ``ValueError`` for the
    sRGB response (its noise is not linear in I).
    """
    _check_linear(model)
    a = LUMA_SQUARES * model.gain / model.full_well
    q = 1.0 / model.max_dn
    b = LUMA_SQUARES * ((model.gain * model.read_noise / model.full_well) ** 2 + q * q / 12.0)
    if model.bits <= 8:
        b += (1.0 / 255.0) ** 2 / 12.0
    return NoiseLevel(a=a, b=b)


def grey_noise_variance(
    model: CameraModel, intensity: ArrayLike, *, offset: float | None = None, steps: int = 32
) -> NDArray[np.float64]:
    """Noise variance of the grey image at grey brightness ``intensity`` (R = G = B).

    More than 8 bits: :func:`grey_noise_level`. At 8 bits: the variance of
    ``round(255 sum_c w_c DN_c / 255)`` with each channel's ``DN_c`` the rounded Gaussian
    of mean ``255 I`` and the channel's standard deviation, summed over all digital numbers
    within 7 sigma. ``offset`` (in [0, 1), DN) puts the clean value at ``floor(255 I) +
    offset``; by default the variance is averaged over ``steps`` offsets spread evenly
    over one level, as a textured image spreads them.
    """
    _check_linear(model)
    level = grey_noise_level(model)
    I = np.asarray(intensity, dtype=np.float64)
    if model.bits > 8:
        return level.a * I + level.b
    out = np.empty(I.shape)
    read = model.gain * model.read_noise / model.full_well
    offsets = [offset] if offset is not None else (np.arange(steps) + 0.5) / steps
    for idx, value in np.ndenumerate(I):
        # one channel's noise, DN: (gain / full_well) I + (gain read_noise / full_well)^2
        s = 255.0 * math.sqrt(model.gain * value / model.full_well + read**2)
        base = math.floor(255.0 * value)
        out[idx] = np.mean([_rounded_luma_variance(base + float(o), s) for o in offsets])
    return out / 255.0**2


def _rounded_luma_variance(mu: float, s: float) -> float:
    """Variance (DN^2) of round(sum_c w_c DN_c), DN_c = round(N(mu, s^2)) independently."""
    k = np.arange(math.floor(mu - 7 * s - 1), math.ceil(mu + 7 * s + 2), dtype=np.float64)
    z = (k[:, None] + np.array([0.5, -0.5])[None, :] - mu) / (s * math.sqrt(2.0))
    p = 0.5 * (special.erf(z[:, 0]) - special.erf(z[:, 1]))
    p /= p.sum()
    w = np.asarray(LUMA_WEIGHTS, dtype=np.float64)
    grey = np.rint(w[0] * k[:, None, None] + w[1] * k[None, :, None] + w[2] * k[None, None, :])
    prob = p[:, None, None] * p[None, :, None] * p[None, None, :]
    mean = float((prob * grey).sum())
    return float((prob * (grey - mean) ** 2).sum())


def _check_linear(model: CameraModel) -> None:
    if model.response != "linear":
        raise ValueError(
            f"camera.response = {model.response!r}: the noise prediction needs 'linear'"
        )
