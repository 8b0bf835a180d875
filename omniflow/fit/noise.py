"""Image noise, and the DCT band of the flow step chosen from it.

The flow step (paper section 5.3) differentiates the truncated DCT series of
eq. (18). Noise in the image passes into the fitted gradient, and gradient
noise shrinks a least-squares flow towards zero (errors in the variables: the
noise adds to the normal matrix A^T A but not to A^T b). A narrower band keeps
less of the noise but also less of the texture, so the band that keeps the
signal above the noise depends on the images; this module measures both.

* :func:`immerkaer_sigma`: the standard deviation of white image noise from
  one image (Immerkaer 1996, "Fast noise variance estimation": the mean
  absolute response of a 3x3 Laplacian difference kernel that cancels smooth
  image structure), taken in the least textured tiles, since fine texture
  also responds.
* :func:`gradient_noise_variance`: the variance of the fitted gradient
  (f_x or f_y of eq. 18) that white pixel noise of that sigma leaves, for a
  given P x Q band (averaged over the image).
* :func:`predicted_gain`: per candidate band, the share of the fitted
  gradient's power that is signal, S / (S + N), from the fit's own
  coefficients: the expected shrink factor of a least-squares flow whose
  gradients carry that noise.
* :func:`choose_band`: the widest candidate band whose predicted gain is at
  least ``min_gain``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omniflow.paper.dct import DCTFit

__all__ = [
    "BAND_CANDIDATES",
    "choose_band",
    "gradient_noise_variance",
    "immerkaer_sigma",
    "predicted_gain",
]

#: Bands :func:`choose_band` picks from by default (fractions of each axis). At most 1/2:
#: wider bands cost fit time and measured worse on noise-free closed-form frames as often
#: as better (tests/omniflow/test_flow.py: band 0.75 0.0019 against 0.0028 px median EPE on the
#: striped wall, 0.0145 against 0.0112 on the room; docs/decisions/flow_band.md).
BAND_CANDIDATES: tuple[float, ...] = (0.125, 0.1875, 0.25, 0.3125, 0.375, 0.4375, 0.5)


def immerkaer_sigma(
    image: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    block: int | None = 16,
    percentile: float = 10.0,
    erode: bool = True,
) -> float:
    """Standard deviation of white noise in ``image`` (Immerkaer 1996, per block).

    sigma = sqrt(pi / 2) / 6 * mean |image * L| with the 3x3 kernel
    L = [[1, -2, 1], [-2, 4, -2], [1, -2, 1]] (the difference of two
    Laplacians, zero on planes and on quadratic ramps along either axis).
    Fine texture also passes L, so the plain estimate over a textured image
    errs high (a noise-free closed-form room, 256 px: 0.0154 against 0.0011
    of 8-bit rounding). With ``block``, the estimate is made in each
    block x block tile that lies wholly inside the mask and the
    ``percentile`` of the tiles is returned: the least textured tiles show
    the noise (the same room: 0.0029; tests/omniflow/test_noise.py).

    Parameters
    ----------
    image : array_like, shape (H, W)
        Grey image.
    mask : array_like of bool, shape (H, W), optional
        Pixels to estimate over (e.g. the mirror's annulus); all by default.
    block : int or None
        Tile size, pixels; None: one estimate over the whole mask.
    percentile : float
        Which tile estimate is returned (with ``block``).
    erode : bool
        Shrink the mask by one pixel first (so the 3x3 kernel sees only masked
        pixels); False when the caller has done so already.

    Returns
    -------
    float
        sigma in the image's grey units; NaN if the mask leaves no pixel (or
        no whole tile).
    """
    import cv2
    from scipy import ndimage

    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 2:
        raise ValueError(f"image: expected a grey image (H, W), got shape {img.shape}")
    k = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float32)
    lap = np.abs(cv2.filter2D(img, -1, k, borderType=cv2.BORDER_REFLECT))
    inner = np.ones(img.shape, bool) if mask is None else np.asarray(mask, bool)
    if erode:
        inner = ndimage.binary_erosion(inner, np.ones((3, 3), bool), border_value=0)
    c = math.sqrt(math.pi / 2.0) / 6.0
    if block is None:
        if not inner.any():
            return math.nan
        return c * float(np.mean(lap[inner], dtype=np.float64))
    est = _tile_means(lap, inner, block)
    if est.size == 0:
        return math.nan
    return c * float(np.percentile(est, percentile)) / _tile_bias(block, float(percentile))


def _tile_means(lap: NDArray, inner: NDArray, block: int) -> NDArray:
    """Mean of ``lap`` in each block x block tile wholly inside ``inner``."""
    import cv2

    hb, wb = lap.shape[0] // block, lap.shape[1] // block
    if hb == 0 or wb == 0:
        return np.zeros(0)
    crop = (slice(0, hb * block), slice(0, wb * block))
    # an area resize by a whole factor is the mean of each tile
    means = cv2.resize(np.ascontiguousarray(lap[crop]), (wb, hb), interpolation=cv2.INTER_AREA)
    cover = cv2.resize(inner[crop].astype(np.float32), (wb, hb), interpolation=cv2.INTER_AREA)
    return means[cover > 1.0 - 1e-6].astype(np.float64)


@lru_cache(maxsize=16)
def _tile_bias(block: int, percentile: float) -> float:
    """The tile percentile over the whole-image mean for pure white noise (below 1).

    The low percentile of noisy tile estimates sits below their mean (16 px
    tiles, 10th percentile: 0.886); measured once on 512 x 512 white noise
    of a fixed seed, so the estimate is unbiased on noise alone.
    """
    import cv2

    noise = np.random.default_rng(0).standard_normal((512, 512)).astype(np.float32)
    k = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float32)
    lap = np.abs(cv2.filter2D(noise, -1, k, borderType=cv2.BORDER_REFLECT))
    est = _tile_means(lap, np.ones(lap.shape, bool), block)
    return float(np.percentile(est, percentile) / np.mean(lap, dtype=np.float64))


def _freq_sums(n_coef: int, n: int) -> NDArray:
    """Running sums over k < K of (pi k / N)^2, for K = 1 .. n_coef (index K - 1)."""
    return np.cumsum((np.pi * np.arange(n_coef) / n) ** 2)


def gradient_noise_variance(
    sigma: float, P: int, Q: int, width: int, height: int, window: NDArray | None = None
) -> float:
    """Variance of the fitted gradient that white pixel noise leaves, per axis.

    With the orthonormal cosine basis phi_k (every coefficient of white noise
    of standard deviation sigma then has variance sigma^2), f_x of the series
    truncated to P x Q has, averaged over the image,
    Var f_x = sigma^2 (Q / Y) (1 / X) sum_{p<P} (pi p / X)^2, and likewise f_y.
    With ``window`` (Q, P) weights on the coefficients (omniflow.paper.dct.band_window)
    each term carries its weight squared. Returned: the mean of the two (the
    variance of each polar component f_h and f_theta / h_i, which are
    rotations of (f_x, f_y)).
    """
    if window is None:
        vx = (Q / height) * (1.0 / width) * _freq_sums(P, width)[-1]
        vy = (P / width) * (1.0 / height) * _freq_sums(Q, height)[-1]
    else:
        w2 = np.asarray(window, dtype=np.float64) ** 2
        wp = (np.pi * np.arange(P) / width) ** 2
        wq = (np.pi * np.arange(Q) / height) ** 2
        vx = float((w2 * wp[None, :]).sum()) / (width * height)
        vy = float((w2 * wq[:, None]).sum()) / (width * height)
    return float(sigma) ** 2 * 0.5 * (vx + vy)


def _orthonormal_power(fit: DCTFit) -> NDArray:
    """|C(q, p)|^2 of the orthonormal DCT from the series' coefficients c(q, p) (eq. 17).

    c = a dctn(f) / (4 X Y) with a = 1, 2 or 4; the orthonormal coefficient is
    dctn(f) s_q s_p with s_0 = 1 / sqrt(4 N), s_k = 1 / sqrt(2 N).
    """
    X, Y = fit.width, fit.height
    sy = np.full(fit.Q, 1.0 / math.sqrt(2 * Y))
    sy[0] = 1.0 / math.sqrt(4 * Y)
    sx = np.full(fit.P, 1.0 / math.sqrt(2 * X))
    sx[0] = 1.0 / math.sqrt(4 * X)
    ay = np.full(fit.Q, 2.0)
    ay[0] = 1.0
    ax = np.full(fit.P, 2.0)
    ax[0] = 1.0
    scale = 4.0 * X * Y * np.outer(sy / ay, sx / ax)
    return (fit.coeffs * scale) ** 2


def predicted_gain(
    fit: DCTFit, sigma: float, bands: Sequence[float] = BAND_CANDIDATES, *, frames: int = 1
) -> NDArray:
    """Expected shrink of a least-squares flow per band: signal / (signal + noise) gradient power.

    For each band B (P = round(B X), Q = round(B Y), at most the fit's own
    size) the gradient power of the series is sum (|C|^2) w^2 with
    w^2 = (pi p / X)^2 + (pi q / Y)^2 over the kept coefficients; white noise
    contributes sigma^2 w^2 to each, so the signal's share is
    S = sum max(|C|^2 - sigma^2, 0) w^2 and the noise's N = sigma^2 sum w^2.
    ``frames`` fitted frames averaged (gradients="average": 2) divide N.

    Returns
    -------
    ndarray, shape (len(bands),)
        S / (S + N / frames), in [0, 1]; 1 for sigma = 0.
    """
    power = _orthonormal_power(fit)
    wq = (np.pi * np.arange(fit.Q) / fit.height) ** 2
    wp = (np.pi * np.arange(fit.P) / fit.width) ** 2
    s2 = float(sigma) ** 2
    sig = np.maximum(power - s2, 0.0)
    out = np.empty(len(bands))
    for i, b in enumerate(bands):
        q = min(fit.Q, max(1, round(b * fit.height)))
        p = min(fit.P, max(1, round(b * fit.width)))
        block = sig[:q, :p]
        S = float(wq[:q] @ block.sum(axis=1) + block.sum(axis=0) @ wp[:p])
        N = s2 * (p * wq[:q].sum() + q * wp[:p].sum()) / max(frames, 1)
        out[i] = S / (S + N) if S + N > 0 else 1.0
    return out


def choose_band(
    fit: DCTFit,
    sigma: float,
    *,
    min_gain: float = 0.9,
    bands: Sequence[float] = BAND_CANDIDATES,
    frames: int = 1,
) -> float:
    """The flow step's band for this image and noise.

    The widest band whose :func:`predicted_gain` is at least ``min_gain`` (the narrowest
    if none). Bands wider than the fit's own are not considered.
    """
    bands = sorted(
        b for b in bands if round(b * fit.width) <= fit.P and round(b * fit.height) <= fit.Q
    )
    if not bands:
        raise ValueError(f"no candidate band fits inside the series' {fit.Q} x {fit.P} terms")
    g = predicted_gain(fit, sigma, bands, frames=frames)
    ok = [b for b, gi in zip(bands, g, strict=True) if gi >= min_gain]
    return max(ok) if ok else bands[0]
