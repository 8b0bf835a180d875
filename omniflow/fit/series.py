"""The per-unit DCT series the flow step reads (paper eq. 17-20).

Each unit's two frames are fitted once (:func:`unit_fits`): the image matched
on, frame t + 1, the series whose gradient enters eq. (8) and the series of
f_t, then truncated to the matching band and the flow band
(:func:`unit_frames`). The flow band can be chosen from the images
(:func:`choose_flow_band`, from the noise measured by
:func:`unit_noise_sigma`). Pixels beyond the mirror's rim are filled by
reflection first (:func:`fill_outside_rim`) so the fit does not ring.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from omniflow.config import OmniFlowConfig
from omniflow.fit.noise import (
    BAND_CANDIDATES,
    choose_band,
    gradient_noise_variance,
    immerkaer_sigma,
)
from omniflow.geometry.rig import Unit
from omniflow.matching import polar_gradient_fast
from omniflow.paper.dct import DCTFit, _cos3, band_window, fit_dct, fit_dct3

__all__ = [
    "Frame",
    "choose_flow_band",
    "fill_outside_rim",
    "fit_band",
    "gradient_noise",
    "grey_input",
    "needs_noise_sigma",
    "noise_variance",
    "truncate",
    "unit_fits",
    "unit_frames",
    "unit_noise_sigma",
    "value_noise_share",
]

#: With ``flow_band=None``: the least share of the gradient power that is signal in the
#: band chosen (:func:`omniflow.fit.noise.choose_band`); docs/decisions/flow_band.md.
FLOW_BAND_GAIN = 0.99


def grey_input(frame, what: str, unit: Unit, config: OmniFlowConfig) -> NDArray:
    arr = np.asarray(frame)
    if arr.ndim != 2:
        raise ValueError(f"{what}: expected a grey image (H, W), got shape {arr.shape}")
    if arr.shape != (unit.height, unit.width):
        raise ValueError(
            f"{what} has shape {arr.shape}; the rig's {unit.name} is "
            f"{unit.height}x{unit.width} (rows x columns)"
        )
    arr = np.asarray(arr, dtype=np.float32)
    if config.fit.rim_fill == "reflect":
        arr = fill_outside_rim(arr, unit)
    return arr


_RIM_MAP_WIDTH = 512  # cv2.remap maps are at most 32767 wide: the outside pixels in rows


@lru_cache(maxsize=8)
def _rim_maps(unit: Unit, margin: float) -> tuple[NDArray, NDArray, NDArray]:
    """(flat indices of the pixels beyond r_m - margin, their source x and y maps).

    The maps list only those pixels (padded to whole rows of ``_RIM_MAP_WIDTH``
    with copies of the last one): inside, the mirror map is the identity.
    """
    x, y = unit.pixel_centres()
    h_i, theta = unit.polar_of_pixel(x, y)
    edge = unit.r_m - margin
    index = np.flatnonzero(h_i > edge)
    h_o, th_o = h_i.reshape(-1)[index], theta.reshape(-1)[index]
    xs, ys = unit.pixel_of_polar(np.maximum(2.0 * edge - h_o, 0.0), th_o)
    pad = (-index.size) % _RIM_MAP_WIDTH
    maps = []
    for m in (xs, ys):
        m = np.concatenate([m, np.repeat(m[-1:], pad)]) if index.size else m
        maps.append((m - 0.5).astype(np.float32).reshape(-1, _RIM_MAP_WIDTH))
    for a in (index, *maps):
        a.setflags(write=False)
    return index, maps[0], maps[1]


def fill_outside_rim(image: NDArray, unit: Unit, *, margin: float = 1.0) -> NDArray:
    """The image with every pixel beyond r_m - margin replaced by its radial mirror image.

    A pixel at image radius h_i > e = r_m - margin takes the (bilinear) value
    at radius 2 e - h_i on the same radial line, so the image continues
    smoothly across the rim instead of stepping to the background; the DCT
    fit of eq. (17) then does not ring near the rim. Pixels inside are
    unchanged (only the pixels beyond are interpolated). Returns float32 (H, W).
    """
    import cv2

    index, mx, my = _rim_maps(unit, float(margin))
    out = np.array(image, dtype=np.float32, order="C", copy=True)
    if index.size:
        values = cv2.remap(out, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        out.reshape(-1)[index] = values.reshape(-1)[: index.size]
    return out


class Frame:
    """One unit at one time: its fit, and grids made on demand."""

    def __init__(self, fit: DCTFit, unit: Unit):
        self.fit, self.unit = fit, unit
        self._f = self._grad = self._grad_xy = self._fine = None

    @property
    def f(self) -> NDArray:
        """The fitted image on the pixel grid, eq. (18)."""
        if self._f is None:
            self._f = np.asarray(self.fit.grid(), dtype=np.float32)
        return self._f

    @property
    def fine(self) -> NDArray:
        """The fitted image at twice the resolution: sample j at x = (j + 1/2) / 2."""
        if self._fine is None:
            c = self.fit.coeffs.astype(np.float32, copy=False)
            self._fine = _cos3(_cos3(c, 2 * self.fit.width, axis=1), 2 * self.fit.height, axis=0)
        return self._fine

    @property
    def grad(self) -> tuple[NDArray, NDArray]:
        """(f_h, f_theta) grids, eq. (19)-(20)."""
        if self._grad is None:
            self._grad = polar_gradient_fast(self.fit, self.unit)
        return self._grad

    @property
    def grad_xy(self) -> tuple[NDArray, NDArray]:
        """(f_x, f_y) grids."""
        if self._grad_xy is None:
            self._grad_xy = tuple(np.asarray(g, dtype=np.float32) for g in self.fit.grid_gradient())
        return self._grad_xy


def unit_fits(
    frames: Sequence, t: int, unit: Unit, config: OmniFlowConfig, what: str, band: float
) -> dict[str, DCTFit]:
    """The series one unit needs, fitted at ``band`` (truncated later by :func:`unit_frames`).

    ``a``: the image at frame t (matched on); ``b``: the image at frame
    t + 1 (read at the displaced points by ``iterations``); ``g``: the series whose
    gradient enters eq. (8) (frame t, or the mean of frames t and t + 1, or
    the 3-D series at t + 1/2); ``t``: the series of f_t (the difference of
    the fits of frames t + 1 and t, or the 3-D series' time derivative at
    t + 1/2). Linear in the coefficients, so averaging or differencing the
    coefficients equals doing it to the grids.
    """
    n = len(frames)
    if config.fit.temporal == "dct3d":
        T = config.fit.temporal_frames
        if n < T:
            raise ValueError(f"{what}: temporal='dct3d' needs {T} frames, got {n}")
        t0 = int(np.clip(t + 1 - T // 2, 0, n - T))
        stack = np.stack(
            [grey_input(frames[k], f"{what}[{k}]", unit, config) for k in range(t0, t0 + T)]
        )
        f3 = fit_dct3(stack, band=band)
        tw = t - t0  # frame t in the window's time
        a = _as32(f3.at_time(tw))
        return {
            "a": a,
            "b": _as32(f3.at_time(tw + 1)),
            "g": a if config.fit.gradients == "first" else _as32(f3.at_time(tw + 0.5)),
            "t": _as32(f3.time_derivative_at(tw + 0.5)),
        }
    fa, fb = (
        fit_dct(grey_input(frames[k], f"{what}[{k}]", unit, config), band=band) for k in (t, t + 1)
    )
    g = fa if config.fit.gradients == "first" else replace(fa, coeffs=0.5 * (fa.coeffs + fb.coeffs))
    return {"a": fa, "b": fb, "g": g, "t": replace(fa, coeffs=fb.coeffs - fa.coeffs)}


def truncate(fit: DCTFit, band: float, taper: float = 0.0) -> DCTFit:
    """The series with only the coefficients of ``band`` kept (eq. 18 truncated further),
    rolled off over the outer ``taper`` of the band (omniflow.paper.dct.band_window; 0: sharp)."""
    q = max(1, round(band * fit.height))
    p = max(1, round(band * fit.width))
    if q >= fit.Q and p >= fit.P and taper == 0.0:
        return fit
    coeffs = fit.coeffs[:q, :p]
    if taper > 0.0:
        window = band_window(coeffs.shape[0], coeffs.shape[1], taper)
        coeffs = (coeffs * window).astype(fit.coeffs.dtype, copy=False)
    return replace(fit, coeffs=coeffs)


def unit_frames(
    fits: dict[str, DCTFit], unit: Unit, config: OmniFlowConfig, flow_band: float
) -> dict:
    """Lazy-grid :class:`Frame` s: ``a`` at the matching band, the others at ``flow_band``
    rolled off by ``config.fit.flow_taper`` (``af``: frame t the same way, for the iterations)."""
    out = {"a": Frame(truncate(fits["a"], config.band), unit)}
    for key, src in (("af", "a"), ("b", "b"), ("g", "g"), ("t", "t")):
        out[key] = Frame(truncate(fits[src], flow_band, config.fit.flow_taper), unit)
    return out


@lru_cache(maxsize=8)
def annulus(unit: Unit, h_min: float, margin: float) -> NDArray:
    """Pixels of the unit's annulus h_min + 1 <= h_i <= r_m - margin - 1 (read-only).

    One pixel inside the searched annulus, so the 3x3 noise kernel sees only its pixels.
    """
    x, y = unit.pixel_centres()
    h_i, _ = unit.polar_of_pixel(x, y)
    m = (h_i >= h_min + 1.5) & (h_i <= unit.r_m - margin - 1.5)
    m.setflags(write=False)
    return m


def unit_noise_sigma(frame, unit: Unit, config: OmniFlowConfig) -> float:
    """The image noise of one unit's frame: Immerkaer's estimate over its annulus."""
    mask = annulus(unit, float(config.search.h_min), float(config.search.rim_margin))
    s = immerkaer_sigma(np.asarray(frame, dtype=np.float32), mask, erode=False)
    return 0.0 if not np.isfinite(s) else s


def choose_flow_band(
    fits: Sequence[dict], sigmas: Sequence[float], config: OmniFlowConfig
) -> float:
    """The flow step's band: ``config.flow_band``, or the narrower of the units' choices."""
    if config.flow_band is not None:
        return float(config.flow_band)
    averaged = 1 if config.fit.gradients == "first" else 2
    return min(
        choose_band(f["a"], s, min_gain=FLOW_BAND_GAIN, frames=averaged)
        for f, s in zip(fits, sigmas, strict=True)
    )


def fit_band(config: OmniFlowConfig) -> float:
    """The band each frame is fitted at: the widest that matching or the flow step reads."""
    return max(config.band, config.flow_band or max(BAND_CANDIDATES))


def needs_noise_sigma(config: OmniFlowConfig) -> bool:
    """Whether the configuration reads the image noise (the band choice)."""
    return config.flow_band is None


def noise_variance(g: DCTFit, config: OmniFlowConfig) -> float:
    """The gradient-noise variance the pooled solver subtracts (``config.pooling.eiv``).

    ``"residual"``: per unit of the fitted value's noise variance (the solver scales it
    by the residuals); ``"none"``: 0. ``g`` is the gradient series of the pair.
    """
    if config.pooling.eiv == "residual":
        return gradient_noise(1.0, g, config) / value_noise_share(g, config)
    return 0.0


def gradient_noise(sigma: float, fit: DCTFit, config: OmniFlowConfig) -> float:
    """Variance of the gradient series' f_h (and f_theta / h_i) from pixel noise ``sigma``.

    ``fit`` is the flow series (truncated to the flow band and rolled off by
    ``config.fit.flow_taper``, whose window follows from its shape)."""
    window = band_window(fit.Q, fit.P, config.fit.flow_taper)
    v = gradient_noise_variance(sigma, fit.P, fit.Q, fit.width, fit.height, window)
    # the mean of two frames' fits with independent noise has half the variance
    return v if config.fit.gradients == "first" else 0.5 * v


def value_noise_share(fit: DCTFit, config: OmniFlowConfig) -> float:
    """The share of white pixel noise's variance that the flow series keeps in its values:
    P Q / (X Y) for the sharp truncation, the mean squared window weight times that."""
    window = band_window(fit.Q, fit.P, config.fit.flow_taper)
    return float(np.sum(window**2)) / (fit.width * fit.height)


def _as32(fit: DCTFit) -> DCTFit:
    return replace(fit, dtype=np.dtype(np.float32))
