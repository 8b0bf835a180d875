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
* :func:`temporal_noise`: the noise from two consecutive frames, as a function
  of brightness (:class:`NoiseLevel`, sigma^2(I) = a I + b): per tile, the
  frame difference less what a local motion explains (see
  :func:`temporal_noise_tiles`), so fine moving texture is not counted as
  noise, as it is by a single-frame estimate (docs/decisions/noise_estimate.md).
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
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omniflow.paper.dct import DCTFit

__all__ = [
    "BAND_CANDIDATES",
    "NoiseLevel",
    "NoiseTiles",
    "choose_band",
    "fit_noise_level",
    "gradient_noise_variance",
    "immerkaer_sigma",
    "predicted_gain",
    "temporal_noise",
    "temporal_noise_tiles",
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


def _pairs(reach: int) -> tuple[tuple[int, int], ...]:
    """Offsets (dx, dy) of the antisymmetric regressors M(x + e) - M(x - e) of
    :func:`temporal_noise_tiles`: one of each pair +-e in the (2 reach + 1)^2 square
    (12 for reach 2; pixels, x right, y down)."""
    r = range(-reach, reach + 1)
    return tuple((dx, dy) for dy in r for dx in r if dy > 0 or (dy == 0 and dx > 0))


@dataclass(frozen=True)
class NoiseLevel:
    """Image noise as a function of brightness: sigma^2(I) = a I + b, in grey units.

    Shot noise gives the term in I (its variance is proportional to the signal); read
    noise and quantisation give the constant ``b``.

    Attributes
    ----------
    a : float
        Variance per unit of brightness (>= 0).
    b : float
        Variance at zero brightness (>= 0).
    reference : float
        A typical brightness (an estimate's median tile brightness); :attr:`sigma` is
        the noise there.
    brightness : (float, float)
        The brightness range the level holds for (an estimate's 5th and 95th tile
        percentiles): outside it ``a`` and ``b`` are extrapolated.
    tiles : int
        Tiles an estimate used (0 for a level from a camera's parameters).
    """

    a: float
    b: float
    reference: float = 0.5
    brightness: tuple[float, float] = (0.0, 1.0)
    tiles: int = 0

    @property
    def sigma(self) -> float:
        """The noise standard deviation at :attr:`reference`."""
        return float(self.sigma_at(self.reference))

    def sigma_at(self, intensity: ArrayLike) -> float | NDArray:
        """The noise standard deviation sqrt(a I + b) at brightness ``intensity``."""
        var = self.a * np.asarray(intensity, dtype=np.float64) + self.b
        out = np.sqrt(np.maximum(var, 0.0))
        return float(out) if out.ndim == 0 else out


@dataclass(frozen=True)
class NoiseTiles:
    """Per-tile noise of a frame pair (:func:`temporal_noise_tiles`).

    Attributes
    ----------
    intensity : ndarray, shape (n,)
        Mean brightness of each tile's fitted rows (the mean of the two frames).
    variance : ndarray, shape (n,)
        Each tile's noise variance estimate (grey units squared).
    dof : int
        Degrees of freedom of each estimate (residual pixels less fitted terms).
    shift : ndarray of int, shape (n, 2)
        The whole-pixel shift (dx, dy) chosen per tile (frame t + 1 against frame t).
    """

    intensity: NDArray
    variance: NDArray
    dof: int
    shift: NDArray


def temporal_noise(
    frame_t: ArrayLike,
    frame_t1: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    block: int = 16,
    search: int = 2,
    reach: int = 2,
    bins: int = 8,
) -> NoiseLevel:
    """The image noise from two consecutive frames, as a function of brightness.

    :func:`temporal_noise_tiles` measures each tile's noise from the frame difference
    less what a local motion explains; :func:`fit_noise_level` fits sigma^2(I) = a I + b
    to the tiles robustly. Unlike :func:`immerkaer_sigma`, fine texture that moves is
    explained by the motion, not counted as noise.

    Parameters
    ----------
    frame_t, frame_t1 : array_like, shape (H, W)
        Grey frames t and t + 1 (the same camera).
    mask : array_like of bool, shape (H, W), optional
        Pixels to estimate over (e.g. the mirror's annulus); all by default.
    block : int
        Tile size, pixels.
    search : int
        Largest whole-pixel motion searched per tile, pixels (the fit then follows the
        remaining sub-pixel motion).
    reach : int
        Reach of the fit's filter, pixels (see :func:`temporal_noise_tiles`).
    bins : int
        Brightness bins of the fit.

    Returns
    -------
    NoiseLevel
        NaN ``a`` and ``b`` if no tile lies wholly inside the mask.
    """
    tiles = temporal_noise_tiles(frame_t, frame_t1, mask, block=block, search=search, reach=reach)
    return fit_noise_level(tiles, bins=bins)


def temporal_noise_tiles(
    frame_t: ArrayLike,
    frame_t1: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    block: int = 16,
    search: int = 2,
    reach: int = 2,
) -> NoiseTiles:
    """Noise variance and brightness of each tile from two consecutive frames.

    In each block x block tile wholly inside the mask (eroded by ``search + reach``,
    the pixels the fit reads), frame t is first shifted by the whole-pixel shift s (|s_x|,
    |s_y| <= ``search``) that minimises the tile's squared difference, then the
    difference d = I_{t+1}(x) - I_t(x - s) is fitted by least squares as

        d = c_0 + c_1 M + sum_e c_e (M(x + e) - M(x - e)),

    M the mean of the two (aligned) frames and e one of each pair of opposite offsets
    in the (2 reach + 1)^2 square (12 for reach 2): a local sub-pixel translation u of
    any texture (against the midpoint frame M the difference is an odd filter of M,
    2 tan(k.u / 2) on each wave of wave vector k, which a general odd 5 x 5 filter
    follows down to wavelengths of about 2.5 pixels; an odd filter cannot follow the
    Nyquist wavelength of 2 pixels), a change of gain (c_1) and of offset (c_0).
    The noise of d (n_{t+1} - n_t) is independent of that of M ((n_t + n_{t+1}) / 2)
    for equal variances, so the residual variance v_r (its sum over n - p degrees of
    freedom, n pixels and p terms) is v_r = 2 sigma^2 + kappa sigma^2 / 2, with
    kappa = c_1^2 + 2 sum c_e^2 the fitted filter's noise gain (estimated from the
    coefficients less their own sampling variance); so sigma^2 = v_r / (2 + kappa / 2).

    The shift is chosen on the tile's top rows and the fit made on its bottom rows, then
    the two swap and the two estimates are averaged. The two bands are ``2 search``
    rows apart, so no pixel of either frame that chose the shift (at any candidate)
    enters the fitted difference: a shift chosen on the noise it is measured on would
    pick the lowest noise where texture does not decide (flat tiles) and err low, and
    interleaved pixel sets (a checkerboard) meet through some candidate shift.

    Parameters
    ----------
    frame_t, frame_t1 : array_like, shape (H, W)
        Grey frames t and t + 1.
    mask : array_like of bool, shape (H, W), optional
        Pixels to estimate over; all by default. Non-finite pixels are left out.
    block : int
        Tile size, pixels (each band of ``(block - 2 search) // 2`` rows must leave at
        least 16 degrees of freedom).
    search : int
        Largest whole-pixel shift searched per axis, pixels (>= 0).
    reach : int
        Reach of the odd filter, pixels (1 to 3): 3 follows texture nearer the Nyquist
        wavelength at many times the cost and with 12 fewer degrees of freedom per band
        (docs/decisions/noise_estimate.md).

    Returns
    -------
    NoiseTiles
        Empty arrays if no tile lies wholly inside the mask.
    """
    from scipy import ndimage

    f0 = np.asarray(frame_t, dtype=np.float64)
    f1 = np.asarray(frame_t1, dtype=np.float64)
    if f0.ndim != 2 or f1.shape != f0.shape:
        raise ValueError(
            f"frames: expected two grey images (H, W) of one shape, got {f0.shape} and {f1.shape}"
        )
    if int(block) != block or block < 4:
        raise ValueError(f"block = {block!r}: expected an integer >= 4 (pixels)")
    if int(search) != search or search < 0:
        raise ValueError(f"search = {search!r}: expected an integer >= 0 (pixels)")
    if int(reach) != reach or not 1 <= reach <= 3:
        raise ValueError(f"reach = {reach!r}: expected an integer 1, 2 or 3 (pixels)")
    block, search, reach = int(block), int(search), int(reach)
    band = (block - 2 * search) // 2
    terms = 2 + len(_pairs(reach))
    if band * block - terms < 16:
        raise ValueError(
            f"block = {block}: expected a tile whose two bands of (block - 2 search) // 2 "
            f"rows leave >= 16 degrees of freedom each for {terms} terms (search {search})"
        )
    finite = np.isfinite(f0) & np.isfinite(f1)
    if mask is not None and np.shape(mask) != f0.shape:
        raise ValueError(f"mask: expected shape {f0.shape}, got {np.shape(mask)}")
    inner = finite if mask is None else finite & np.asarray(mask, bool)
    f0, f1 = np.where(finite, f0, 0.0), np.where(finite, f1, 0.0)
    edge = search + reach
    inner = ndimage.binary_erosion(inner, np.ones((2 * edge + 1,) * 2, bool), border_value=0)
    ty, tx = _whole_tiles(inner, block)
    empty = np.zeros(0)
    if ty.size == 0:
        return NoiseTiles(empty, empty, 0, np.zeros((0, 2), int))
    span = range(-search, search + 1)
    shifts = sorted(
        ((sx, sy) for sy in span for sx in span), key=lambda s: (s[0] ** 2 + s[1] ** 2, s)
    )
    row = np.arange(f0.shape[0]) % block
    bands = ((0, band), (block - band, block))  # top and bottom rows of each tile
    ssd = np.empty((2, len(shifts), ty.size))
    for j, (sx, sy) in enumerate(shifts):
        d2 = (f1 - np.roll(f0, (sy, sx), axis=(0, 1))) ** 2  # f0 at (x - sx, y - sy)
        for k, (lo, hi) in enumerate(bands):
            on = ((row >= lo) & (row < hi))[:, None]
            ssd[k, j] = _tile_sums(np.where(on, d2, 0.0), block)[ty, tx]
    variance = np.zeros(ty.size)
    intensity = np.zeros(ty.size)
    chosen = np.zeros((ty.size, 2), int)
    for k in (0, 1):
        pick = np.asarray(shifts)[np.argmin(ssd[k], axis=0)]  # first = smallest on ties
        var, mean = _tile_fit(f0, f1, ty, tx, pick, block, reach, bands[1 - k])
        variance += 0.5 * var
        intensity += 0.5 * mean
        chosen = pick if k == 0 else chosen
    return NoiseTiles(intensity, variance, 2 * (band * block - terms), chosen)


def _whole_tiles(inner: NDArray, block: int) -> tuple[NDArray, NDArray]:
    """Row and column indices of the block x block tiles wholly inside ``inner``."""
    cover = _tile_sums(inner.astype(np.float64), block)
    return np.nonzero(cover >= block * block - 0.5)


def _tile_sums(image: NDArray, block: int) -> NDArray:
    """Sum of ``image`` over each whole block x block tile (partial tiles dropped)."""
    hb, wb = image.shape[0] // block, image.shape[1] // block
    crop = image[: hb * block, : wb * block]
    return crop.reshape(hb, block, wb, block).sum(axis=(1, 3))


def _tile_fit(
    f0: NDArray,
    f1: NDArray,
    ty: NDArray,
    tx: NDArray,
    shift: NDArray,
    block: int,
    reach: int,
    rows: tuple[int, int],
) -> tuple[NDArray, NDArray]:
    """Per tile: sigma^2 from the fit of :func:`temporal_noise_tiles` on the tile's rows
    ``rows[0] <= row < rows[1]``, and those rows' mean brightness."""
    R, B = reach, block
    lo, hi = rows
    pairs = _pairs(reach)
    ys = ty[:, None] * B + (np.arange(lo - R, hi + R))[None, :]  # (n, band rows + 2R)
    xs = tx[:, None] * B + (np.arange(-R, B + R))[None, :]  # (n, B + 2R)
    p1 = f1[ys[:, :, None], xs[:, None, :]]
    p0 = f0[(ys - shift[:, 1:2])[:, :, None], (xs - shift[:, 0:1])[:, None, :]]
    m = 0.5 * (p0 + p1)
    nr = hi - lo
    centre = (slice(None), slice(R, R + nr), slice(R, R + B))
    d = (p1 - p0)[centre]
    terms = [np.ones_like(d), m[centre]]
    for ex, ey in pairs:
        plus = m[:, R + ey : R + ey + nr, R + ex : R + ex + B]
        minus = m[:, R - ey : R - ey + nr, R - ex : R - ex + B]
        terms.append(plus - minus)
    X = np.stack(terms, axis=-1).reshape(ty.size, nr * B, len(terms))
    y = d.reshape(ty.size, nr * B)
    Xt = X.transpose(0, 2, 1)
    xtx = np.matmul(Xt, X)
    xty = np.matmul(Xt, y[..., None])[..., 0]
    inv = np.linalg.pinv(xtx, hermitian=True)
    beta = np.matmul(inv, xty[..., None])[..., 0]
    rss = np.maximum(np.einsum("nk,nk->n", y, y) - np.einsum("np,np->n", beta, xty), 0.0)
    v_r = rss / (nr * B - len(terms))
    gain = np.array([0.0, 1.0] + [2.0] * len(pairs))  # each term's taps^2 per coefficient^2
    kappa = beta**2 @ gain - v_r * (np.diagonal(inv, axis1=1, axis2=2) @ gain)
    # kappa's own noise is kept (not clipped at 0 per tile: that would bias it up); the
    # floor only guards the division
    var = v_r / (2.0 + 0.5 * np.maximum(kappa, -2.0))
    return var, m[centre].reshape(ty.size, -1).mean(axis=1)  # brightness of the fitted rows


def fit_noise_level(tiles: NoiseTiles, *, bins: int = 8, quantile: float = 0.5) -> NoiseLevel:
    """sigma^2(I) = a I + b fitted robustly to per-tile noise estimates.

    The tiles are split by brightness into up to ``bins`` bins of equal count (at least
    16 tiles each); in each bin the ``quantile`` of the tile variances (the median by
    default: tiles where the motion fit fails, at occlusions and edges of movers, only
    add variance) is divided by the same quantile of a chi-square of the tiles' degrees
    of freedom over its mean, which makes it unbiased for noise alone. A line is fitted
    to the bins' values against their median brightness by least squares weighted by
    count / variance^2 (relative errors), with ``a`` and ``b`` kept >= 0.
    """
    from scipy import stats

    if not 0.0 < quantile < 1.0:
        raise ValueError(f"quantile = {quantile!r}: expected a number in (0, 1)")
    n = tiles.variance.size
    if n == 0:
        return NoiseLevel(math.nan, math.nan, math.nan, (math.nan, math.nan), 0)
    order = np.argsort(tiles.intensity, kind="stable")
    nb = max(1, min(int(bins), n // 16))
    groups = np.array_split(order, nb)
    bias = float(stats.chi2.ppf(quantile, tiles.dof) / tiles.dof) if tiles.dof > 0 else 1.0
    lev = np.array([np.median(tiles.intensity[g]) for g in groups])
    val = np.array([np.quantile(tiles.variance[g], quantile) for g in groups]) / bias
    cnt = np.array([g.size for g in groups], dtype=np.float64)
    a, b = _line_fit(lev, val, cnt)
    lo, hi = np.percentile(tiles.intensity, [5.0, 95.0])
    return NoiseLevel(a, b, float(np.median(tiles.intensity)), (float(lo), float(hi)), n)


def _line_fit(x: NDArray, y: NDArray, n: NDArray) -> tuple[float, float]:
    """y = a x + b by least squares with weights n / y^2 (refined twice), a, b >= 0."""
    fit = np.maximum(y, 1e-30)
    a, b = 0.0, float(np.sum(n * y / fit**2) / np.sum(n / fit**2))
    if x.size < 2 or np.ptp(x) < 1e-6:
        return 0.0, max(b, 0.0)
    for _ in range(3):
        w = n / np.maximum(fit, 1e-30) ** 2
        A = np.stack([x, np.ones_like(x)], axis=1) * np.sqrt(w)[:, None]
        a, b = np.linalg.lstsq(A, y * np.sqrt(w), rcond=None)[0]
        if a < 0:
            a, b = 0.0, float(np.sum(w * y) / np.sum(w))
        elif b < 0:
            a, b = float(np.sum(w * x * y) / np.sum(w * x * x)), 0.0
        fit = a * x + b
    return float(a), float(b)


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
