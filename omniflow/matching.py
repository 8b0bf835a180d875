"""Radial stereo matching of a coaxial pair (paper section 5.2).

Epipolar lines of a coaxial rig are the radial lines: a scene point at
azimuth theta is imaged at (h_1, theta) by cam1 and (h_2, theta) by cam2 with
h_2 / v_2 - h_1 / v_1 = s / (d + r) > 0 (eq. 3-5). Both fitted images are
sampled once into polar tables (one row per theta, one column per radius)
with :func:`cv2.remap`; the search then runs on the tables with numpy, for all
radial lines at once.

The tables use a common normalised radius u = h_i / v_i: column j of cam1's
table is at h_1 = h_min + j * h_step and column j of cam2's at
h_2 = (v_2 / v_1) (h_min + j * h_step). The disparity window of a range
interval [r_min, r_max] is then the same on every line and at every radius:
j_2 - j_1 in [v_1 s / ((d + r_max) h_step), v_1 s / ((d + r_min) h_step)].

Two methods:

``"paper"``
    The paper's rule. Significant points of image 1 are the samples where
    |df1/dh_1| passes a threshold (a percentile of |df1/dh_1| over the
    annulus); the candidates are the significant samples of image 2 on the
    same radial line inside the disparity window (the window's far end is the
    paper's minimum disparity); the best match has the most similar polar
    gradient vector (df/dh_i, (1/h_i) df/dtheta_i); h_2 is refined to
    sub-pixel by a parabola through the gradient distance of the neighbouring
    samples. Ambiguous on real texture; kept to be measured.

``"robust"``
    Both tables of f are first blurred across the lines (``tangential_blur``,
    Gaussian in theta): at one scene point cam1 (at h_1) resolves theta
    h_2 / h_1 times more coarsely than cam2 (at h_2 > h_1), so the same
    point looks different in the two units until both are brought to one
    angular resolution (without it an isotropic texture gave almost no match
    above the NCC floor). Significant points are the local maxima of
    |df/dh_i| along each radial line (edges across the line; central
    differences of the blurred table) above the threshold; candidates are the
    edges of image 2 inside the disparity window. The score is the normalised
    cross-correlation (NCC) of the radial intensity profiles, +-
    ``patch_radius`` px around each edge (on 2 ``patch_lines`` + 1 lines). A
    match must have the same edge polarity, score at least ``min_score``, be
    unique ((1 - NCC) of the best at most ``uniqueness`` times that of the
    second best edge) and pass a left-right check (matching image 2's edge
    back to image 1 finds the same edge). h_2 is refined to sub-pixel by a
    parabola through the NCC at the neighbouring samples. Last, a disparity
    consistency vote (``consistency``) keeps a match only where enough of
    its neighbours in (theta, h_1) agree with its disparity. The profiles
    compare equal radial scales, which is exact for vertical surfaces (both
    units map dh to dh_i = v dh / (d + r)); on inclined surfaces the scales
    differ by up to h_2 / h_1 and the NCC drops.

    Vectorised: the edges of each line are laid out left-aligned in
    (n_theta, c) arrays, so the NCC of every pair of edges on every line is
    one batched matrix product; the window is a contiguous range of slots
    per row.

Measured on closed-form scenes (``omniflow.synthetic``, see
``tests/omniflow/test_matching.py``): see that file's module docstring for the
figures and the command.

On rendered frames (omnisim, path traced) the robust matcher's outliers
(|h_2 - gt.stereo.h_other| > 1 px) are mostly small: on the default scene at
512 x 512, 16 spp, with the earlier defaults (tangential_blur 0.06, profiles
of 9 samples, no vote) 20.6 % of 1208 matches, of which 215 of 249 within
3 px and unbiased (median signed error 0.0 px, no trend with theta or h_1);
0.5 % of the matches see a point cam2 does not (gt.stereo.valid = 0), 13 %
of the outliers (6 % of all matches) lie within 6 px of an object boundary,
and no match lies beyond 0.85 r_m (the rim is not the cause).
The outliers follow the render noise (256 x 256: 22.8 % at 4 spp, 6.7 % at
64 spp) and the score (33 % below NCC 0.97, 12.5 % above 0.99). Added
Gaussian noise on closed-form frames does not reproduce them (0 % at 5 %
noise): path-traced frames differ between the units by more than white
noise. Three changes, measured on that frame (``match_radial`` on the
frame's 8-bit grey image, as ``omnivalidate`` feeds it): a narrower
tangential blur (0.03: 14.9 %), profiles of 17 samples either side
(``profile_step`` patch_radius / 16: 13.7 % alone, 7.8 % with the blur,
as many matches) and the consistency vote (5.0 % of 1036 matches).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import lru_cache

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from omniflow.dct import DCTFit
from omniflow.rig import Rig, Unit

__all__ = [
    "MATCH_METHODS",
    "Matches",
    "PolarGrids",
    "match_radial",
    "polar_grids",
    "polar_sample",
]

MATCH_METHODS = ("robust", "paper")

_REMAP_CHUNK = 32000  # cv2.remap needs both map dimensions below SHRT_MAX


@dataclass(frozen=True)
class Matches:
    """Stereo matches along radial lines; all arrays 1-D of equal length N.

    Attributes
    ----------
    x, y : ndarray, shape (N,)
        Continuous pixel coordinates of the point in cam1's image.
    theta : ndarray, shape (N,)
        Azimuth of the radial line, radians (theta_1 = theta_2).
    h1, h2 : ndarray, shape (N,)
        Image radii in cam1 and cam2, pixels; h2 is sub-pixel.
    score : ndarray, shape (N,)
        Match quality in [0, 1], higher is better (NCC for ``"robust"``;
        1 - |g1 - g2| / (|g1| + |g2|) for ``"paper"``).
    n_significant : int
        Number of significant points of image 1 that were tried (the
        denominator of a match rate).
    method : str
        ``"robust"`` or ``"paper"``.
    """

    x: NDArray
    y: NDArray
    theta: NDArray
    h1: NDArray
    h2: NDArray
    score: NDArray
    n_significant: int = 0
    method: str = ""

    def __len__(self) -> int:
        return int(self.x.size)

    def subset(self, keep: NDArray) -> Matches:
        """The matches selected by a boolean mask or index array."""
        return replace(
            self, **{k: getattr(self, k)[keep] for k in ("x", "y", "theta", "h1", "h2", "score")}
        )

    @classmethod
    def from_polar(
        cls, rig: Rig, theta: NDArray, h1: NDArray, h2: NDArray, score: NDArray | None = None, **kw
    ) -> Matches:
        """Matches given by (theta, h1, h2), e.g. the true ones of a synthetic scene."""
        theta = np.asarray(theta, dtype=float).ravel()
        h1 = np.asarray(h1, dtype=float).ravel()
        h2 = np.asarray(h2, dtype=float).ravel()
        x, y = rig.cam1.pixel_of_polar(h1, theta)
        score = np.ones_like(h1) if score is None else np.asarray(score, dtype=float).ravel()
        return cls(x=x, y=y, theta=theta, h1=h1, h2=h2, score=score, **kw)


@dataclass(frozen=True)
class PolarGrids:
    """Per-pixel grids of one fitted image that matching samples from.

    ``f`` is the fitted image (eq. 18), ``f_h`` and ``f_theta`` the polar
    gradient (eq. 19-20) on every pixel centre, all (H, W) float32. The
    paper's rule needs all three; the robust matcher reads only ``f``.
    """

    f: NDArray
    f_h: NDArray
    f_theta: NDArray | None = None
    extra: dict = field(default_factory=dict)


def polar_grids(fit: DCTFit, unit: Unit, *, gradient: bool = True) -> PolarGrids:
    """Evaluate a fit (and its polar gradient) on the pixel grid (fast transform path)."""
    f = np.asarray(fit.grid(), dtype=np.float32)
    if not gradient:
        return PolarGrids(f=f, f_h=None)
    f_h, f_th = polar_gradient_fast(fit, unit)
    return PolarGrids(f=f, f_h=f_h, f_theta=f_th)


@lru_cache(maxsize=8)
def _polar_basis(unit: Unit) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Per-pixel (cos theta_i, sin theta_i, x - x_c, y - y_c), float32 (H, W); 0 at h_i = 0."""
    x, y = unit.pixel_centres()
    dx, dy = x - unit.x_c, y - unit.y_c
    h_i = np.hypot(dx, dy)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(h_i > 0, dx / h_i, 0.0)
        s = np.where(h_i > 0, dy / h_i, 0.0)
    out = tuple(np.ascontiguousarray(a, dtype=np.float32) for a in (c, s, dx, dy))
    for a in out:
        a.setflags(write=False)
    return out


def polar_gradient_fast(fit: DCTFit, unit: Unit) -> tuple[NDArray, NDArray]:
    """(df/dh_i, df/dtheta_i) on the pixel grid, float32, eq. (19)-(20).

    The same as :func:`omniflow.edges.polar_gradient_grid` (with 0 instead of
    NaN for f_h at h_i = 0), using cached per-pixel cos/sin grids.
    """
    if (fit.width, fit.height) != (unit.width, unit.height):
        raise ValueError(
            f"fit is {fit.width}x{fit.height} but unit {unit.name} is "
            f"{unit.width}x{unit.height}: expected the same image size"
        )
    f_x, f_y = fit.grid_gradient()
    f_x = np.asarray(f_x, dtype=np.float32)
    f_y = np.asarray(f_y, dtype=np.float32)
    c, s, dx, dy = _polar_basis(unit)
    f_h = c * f_x
    f_h += s * f_y  # eq. (19)
    f_th = dx * f_y
    f_th -= dy * f_x  # eq. (20)
    return f_h, f_th


def polar_sample(
    image: NDArray, unit: Unit, h_i: NDArray, theta: NDArray, *, interpolation: str = "linear"
) -> NDArray:
    """Sample a per-pixel grid at polar image points (h_i, theta), eq. (6)-(7).

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Grid on pixel centres (x = j + 0.5, y = i + 0.5).
    unit : Unit
        Supplies (x_c, y_c).
    h_i, theta : array_like
        Polar points; broadcast together.
    interpolation : {"linear", "cubic"}
        OpenCV interpolation; points outside the image read 0.

    Returns
    -------
    ndarray, the broadcast shape, float32
    """
    h_i, theta = np.broadcast_arrays(
        np.asarray(h_i, dtype=np.float64), np.asarray(theta, dtype=np.float64)
    )
    x, y = unit.pixel_of_polar(h_i, theta)
    return sample_xy(image, x, y, interpolation=interpolation)


def sample_xy(image: NDArray, x: NDArray, y: NDArray, *, interpolation: str = "linear") -> NDArray:
    """Sample a grid on pixel centres at continuous (x, y) with cv2.remap; float32."""
    flag = {"linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC}[interpolation]
    x = np.asarray(x)
    shape = x.shape
    src = np.ascontiguousarray(image, dtype=np.float32)
    mx = (np.asarray(x, dtype=np.float64) - 0.5).astype(np.float32).reshape(-1)
    my = (np.asarray(y, dtype=np.float64) - 0.5).astype(np.float32).reshape(-1)
    n = mx.size
    if len(shape) == 2 and shape[0] < _REMAP_CHUNK and shape[1] < _REMAP_CHUNK:
        return cv2.remap(
            src,
            mx.reshape(shape),
            my.reshape(shape),
            flag,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
    cols = min(max(n, 1), 4096)
    rows = -(-n // cols)
    pad = rows * cols - n
    if pad:
        mx = np.concatenate([mx, np.zeros(pad, np.float32)])
        my = np.concatenate([my, np.zeros(pad, np.float32)])
    out = cv2.remap(
        src,
        mx.reshape(rows, cols),
        my.reshape(rows, cols),
        flag,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
    return out.reshape(-1)[:n].reshape(shape)


# ---------------------------------------------------------------------------
# polar tables


@lru_cache(maxsize=16)
def _polar_maps(
    unit: Unit, n_theta: int, h0: float, step: float, n: int
) -> tuple[NDArray, NDArray]:
    """cv2.remap maps (float32, shape (n_theta, n)) of the polar grid of one unit.

    Row k is theta_k = -pi + 2 pi (k + 1/2) / n_theta, column j is
    h_i = h0 + j step; map values are pixel indices (x - 1/2, y - 1/2).
    """
    theta = -np.pi + (2.0 * np.pi / n_theta) * (np.arange(n_theta) + 0.5)
    h_i = h0 + step * np.arange(n)
    mx = (unit.x_c - 0.5) + np.cos(theta)[:, None] * h_i[None, :]
    my = (unit.y_c - 0.5) + np.sin(theta)[:, None] * h_i[None, :]
    mx, my = mx.astype(np.float32), my.astype(np.float32)
    mx.setflags(write=False)
    my.setflags(write=False)
    return mx, my


def _table(image: NDArray, maps: tuple[NDArray, NDArray]) -> NDArray:
    return cv2.remap(
        np.ascontiguousarray(image, dtype=np.float32),
        maps[0],
        maps[1],
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )


def _blur_lines(table: NDArray, sigma: float) -> NDArray:
    """Gaussian blur across the radial lines (theta, wrapping around), sigma in lines."""
    half = int(np.ceil(3 * sigma))
    if half < 1:
        return table
    padded = np.concatenate([table[-half:], table, table[:half]], axis=0)
    out = cv2.GaussianBlur(
        padded, (1, 2 * half + 1), sigmaX=0, sigmaY=sigma, borderType=cv2.BORDER_REPLICATE
    )
    return np.ascontiguousarray(out[half:-half])


def _radial_derivative(table: NDArray, step: float) -> NDArray:
    """Central difference along the columns (radius) of a polar table."""
    out = np.empty_like(table)
    np.subtract(table[:, 2:], table[:, :-2], out=out[:, 1:-1])
    out[:, 1:-1] *= 0.5 / step
    out[:, 0] = out[:, 1]
    out[:, -1] = out[:, -2]
    return out


def _local_maxima(a: NDArray) -> NDArray:
    """Local maxima along axis 1 (a plateau counts once, at its right end)."""
    m = np.zeros(a.shape, dtype=bool)
    m[:, 1:-1] = (a[:, 1:-1] >= a[:, :-2]) & (a[:, 1:-1] > a[:, 2:])
    return m


def _parabola_offset(s_m: NDArray, s_0: NDArray, s_p: NDArray) -> NDArray:
    """Vertex offset in [-1, 1] of the parabola through (-1, s_m), (0, s_0), (1, s_p)."""
    den = s_m - 2.0 * s_0 + s_p
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(np.abs(den) > 1e-12, 0.5 * (s_m - s_p) / den, 0.0)
    return np.clip(off, -1.0, 1.0)


class _Descriptors:
    """Zero-mean, unit-norm polar patches of one table.

    A patch at (line k, column j) holds the radial profile at columns
    j - w stride .. j + w stride, every ``stride``-th, on lines
    k - lines .. k + lines (wrapping around theta); L = (2 lines + 1)(2 w + 1)
    values. The table is split by column parity into ``stride`` decimated
    copies so each profile is a contiguous run, and each window's mean and
    norm come from cumulative sums.
    """

    def __init__(self, table: NDArray, w: int, stride: int, lines: int):
        self.w, self.stride, self.lines = w, stride, lines
        self.n_lines, n_cols = table.shape
        m = 2 * w + 1
        width = -(-n_cols // stride)
        dec = np.zeros((stride, self.n_lines, width), dtype=np.float32)
        for par in range(stride):
            part = table[:, par::stride]
            dec[par, :, : part.shape[1]] = part
        self.view = sliding_window_view(dec, m, axis=2)  # (stride, lines, width - m + 1, m)
        # the same windows by the flat index of their first sample (one
        # index array gathers faster than three; windows never cross a row)
        self.width = width
        self.flat = sliding_window_view(dec.reshape(-1), m)

        # per window: sum and sum of squares over the (2 lines + 1) x m patch
        # (box filters anchored at the window's first sample)
        def window_sum(a):
            out = []
            for par in range(stride):
                x = a[par]
                if lines:  # wrap around theta
                    x = np.concatenate([x[-lines:], x, x[:lines]], axis=0)
                y = cv2.boxFilter(x, -1, (m, 2 * lines + 1), anchor=(0, 0), normalize=False,
                                  borderType=cv2.BORDER_CONSTANT)  # fmt: skip
                out.append(y[: self.n_lines])
            return np.stack(out)

        s1 = window_sum(dec)
        s2 = window_sum(dec * dec)
        length = (2 * lines + 1) * m
        self.length = length
        self.mean = s1 / np.float32(length)
        var = np.maximum(s2 - s1 * self.mean, np.float32(0.0))
        self.inv_norm = np.float32(1.0) / np.maximum(np.sqrt(var), np.float32(1e-12))

    def __call__(self, k: NDArray, j: NDArray) -> NDArray:
        """Patches at (k, j) of any equal shapes S; returns S + (L,), float32."""
        start = j - self.w * self.stride
        par, col = start % self.stride, start // self.stride
        n = self.n_lines
        # flat index of (par, k, col) in the (stride, lines, width) arrays
        fi = (par * n + k) * self.width + col
        if self.lines == 0:
            p = self.flat[fi]  # a copy: fancy indexing
        else:
            m = 2 * self.w + 1
            p = np.empty((*np.shape(k), self.length), dtype=np.float32)
            for i, dk in enumerate(range(-self.lines, self.lines + 1)):
                p[..., i * m : (i + 1) * m] = self.flat[(par * n + (k + dk) % n) * self.width + col]
        p -= self.mean.reshape(-1)[fi][..., None]
        p *= self.inv_norm.reshape(-1)[fi][..., None]
        return p


def _window_slots(
    cols: NDArray, exists: NDArray, line: NDArray, lo: NDArray, hi: NDArray
) -> tuple[NDArray, NDArray]:
    """Slots [first, stop) of the edges of ``line`` whose column lies in [lo, hi].

    ``cols``/``exists`` are a left-aligned layout from :func:`_per_line` (each
    row's edges ascending), so the slots in range are contiguous. ``line``,
    ``lo`` and ``hi`` have any one shape; so do the results.
    """
    n_lines, c = cols.shape
    big = np.int64(1) << 40
    key = np.where(exists, cols, big - 1).astype(np.int64)
    key += np.arange(n_lines, dtype=np.int64)[:, None] * big
    key = key.ravel()
    base = np.asarray(line, dtype=np.int64) * big
    first = np.searchsorted(key, (base + lo).ravel(), side="left").reshape(base.shape)
    stop = np.searchsorted(key, (base + hi).ravel(), side="right").reshape(base.shape)
    offset = np.asarray(line, dtype=np.int64) * c
    return first - offset, stop - offset


def _per_line(mask: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """The True columns of each row of ``mask``, left-aligned and padded.

    Returns (cols (n, c), exists (n, c), rank) where c is the largest count
    in a row, padded entries hold column 0, and rank is each True entry's
    position in its row (row-major order, as np.nonzero).
    """
    k, j = np.nonzero(mask)
    counts = np.bincount(k, minlength=mask.shape[0])
    c = max(int(counts.max()) if counts.size else 0, 1)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.arange(k.size) - starts[k]
    cols = np.zeros((mask.shape[0], c), dtype=np.intp)
    exists = np.zeros((mask.shape[0], c), dtype=bool)
    cols[k, rank] = j
    exists[k, rank] = True
    return cols, exists, rank


# ---------------------------------------------------------------------------


def match_radial(
    fit1: DCTFit | None,
    fit2: DCTFit | None,
    rig: Rig,
    *,
    method: str = "robust",
    threshold_percentile: float = 80.0,
    min_gradient: float = 1e-4,
    r_min: float | None = None,
    r_max: float = 10.0,
    n_theta: int = 360,
    h_step: float = 1.0,
    h_min: float = 16.0,
    rim_margin: float = 4.0,
    patch_radius: float | None = None,
    patch_lines: int = 0,
    profile_step: float | None = None,
    min_score: float = 0.95,
    uniqueness: float = 0.5,
    left_right: bool = True,
    candidate_fraction: float = 0.5,
    tangential_blur: float = 0.03,
    consistency: float = 1.0,
    consistency_support: int = 2,
    self_similarity: float = 1.0,
    grids: tuple[PolarGrids, PolarGrids] | None = None,
) -> Matches:
    """Match cam1's significant points along radial lines in cam2 (section 5.2).

    Parameters
    ----------
    fit1, fit2 : DCTFit
        The fitted images of cam1 and cam2 (eq. 17). May be None when
        ``grids`` is given.
    rig : Rig
        The coaxial pair (v_1, v_2, s, d, image centres, rims).
    method : {"robust", "paper"}
        See the module docstring.
    threshold_percentile : float
        Significant points have |df1/dh_1| above this percentile of
        |df1/dh_1| over the annulus h_min <= h_1 <= r_m - rim_margin.
    min_gradient : float
        ... and at least this, grey levels per pixel (for images scaled to
        [0, 1]), so a textureless image has no significant point.
    r_min, r_max : float
        Range interval searched, metres; gives the disparity window
        (:meth:`Rig.disparity_window`). r_max sets the paper's minimum
        disparity. r_min defaults to :attr:`Rig.min_common_range`, the
        nearest range both units can see.
    n_theta : int
        Number of radial lines, evenly spaced in theta (360: one per degree,
        about the angular resolution left by ``tangential_blur``).
    h_step : float
        Sample spacing along cam1's radial lines, pixels.
    h_min, rim_margin : float
        Radii searched: h_min <= h_i <= r_m - rim_margin, pixels. Near the
        centre cam1 resolves much less of the scene tangentially than cam2
        (h_2 / h_1 times less), so its patches look different there.
    patch_radius : float, optional
        ``robust``: half-length of the radial profile compared, pixels;
        default r_m / 8 (16 px at 256 x 256), so the profile covers the same
        part of the scene at every image size. Longer profiles are less
        ambiguous on periodic texture and match fewer points.
    patch_lines : int
        ``robust``: neighbouring radial lines on each side in the patch.
    profile_step : float, optional
        ``robust``: spacing of the profile's samples along the radial line,
        pixels (rounded to a multiple of h_step); default patch_radius / 16,
        33 samples (at most one per h_step). On rendered frames (path-tracing
        noise) the denser profile halved the outliers at 512 x 512 (16 spp:
        13.7 % instead of 20.6 % alone, 7.8 % instead of 14.9 % with
        tangential_blur 0.03); patch_radius / 8 was as good on noise-free
        closed-form frames.
    min_score : float
        ``robust``: smallest NCC accepted.
    uniqueness : float
        ``robust``: accept when (1 - NCC_best) <= uniqueness (1 - NCC_second);
        1 disables the test.
    left_right : bool
        ``robust``: require the left-right consistency check.
    candidate_fraction : float
        ``robust``: edges of either image count as candidates down to this
        fraction of the significance threshold.
    self_similarity : float
        ``robust``: uniqueness against image 1's own line: accept a match
        only when (1 - NCC_best) <= self_similarity (1 - NCC_self), NCC_self
        being the best NCC of the edge's radial profile with another edge of
        its own line at a lag between the profile's length and the disparity
        window's width. On a periodic texture the profile recurs a period
        away, and so does an alias in image 2 that can score as well as the
        truth (the uniqueness test, the left-right check and the consistency
        vote then all confirm a consistent alias); the stereo match must be
        clearly better than the texture's own recurrence. 1 disables it.
    tangential_blur : float
        ``robust``: Gaussian blur (sigma, radians) across the radial lines of
        both polar tables before matching. cam1 resolves the scene h_2 / h_1
        times more coarsely in theta than cam2 at the same point, so the
        same patch looks different in the two units unless both are blurred
        to a common angular resolution. 0 disables it. Default 0.03 (1.7
        lines of 360): on rendered frames it matched more points with fewer
        outliers than 0.06 (default scene, 512 x 512, 16 spp: 14.9 % instead
        of 20.6 %; 256 x 256, 64 spp: 2.5 % instead of 6.7 %; 0.02 and 0.04
        were as good or worse); on closed-form frames it matched as well
        (0.2 % outliers in all, 0.3 % with 0.06) but fewer points on the
        room texture (704 / 1525 instead of 893 / 1893).
    consistency : float
        ``robust``: disparity consistency vote, pixels of cam2 (0 disables).
        A surface's disparity h_2 - (v_2 / v_1) h_1 varies smoothly, so a
        match is kept only when at least ``consistency_support`` of its
        neighbouring matches (within +-0.05 rad in theta and +-r_m / 16 in
        h_1), and at least half of them, have a disparity within
        ``consistency`` of its own. On rendered frames most outliers are
        1-3 px errors of isolated matches (path-tracing noise); measured on
        the default scene, 512 x 512, 16 spp: 7.8 % -> 5.2 % outliers for
        18 % fewer matches (see ``tests/omniflow/test_matching.py``).
    consistency_support : int
        ``robust``: the agreeing neighbours a match needs.
    grids : (PolarGrids, PolarGrids), optional
        Precomputed grids of the two fits (saves re-evaluating them).

    Returns
    -------
    Matches
    """
    if method not in MATCH_METHODS:
        raise ValueError(f"method = {method!r}: expected one of {MATCH_METHODS}")
    if not (0.0 <= threshold_percentile < 100.0):
        raise ValueError(f"threshold_percentile = {threshold_percentile!r}: expected [0, 100)")
    cam1, cam2 = rig.cam1, rig.cam2
    if patch_radius is None:
        patch_radius = cam1.r_m / 8.0
    if profile_step is None:
        profile_step = patch_radius / 16.0
    if not (h_step > 0 and n_theta >= 8 and patch_radius > 0 and patch_lines >= 0):
        raise ValueError("expected h_step > 0, n_theta >= 8, patch_radius > 0, patch_lines >= 0")
    r_min = rig.min_common_range if r_min is None else float(r_min)
    if not (0 <= r_min < r_max):
        raise ValueError(f"r_min = {r_min!r}, r_max = {r_max!r}: expected 0 <= r_min < r_max")
    if grids is None:
        if fit1 is None or fit2 is None:
            raise ValueError("match_radial needs fit1 and fit2, or grids")
        grids = (
            polar_grids(fit1, cam1, gradient=method == "paper"),
            polar_grids(fit2, cam2, gradient=method == "paper"),
        )
    g1, g2 = grids

    scale2 = cam2.v / cam1.v  # cam2 table radius per cam1 table radius
    h_top = min(cam1.r_m - rim_margin, (cam2.r_m - rim_margin) / scale2)
    n_h = int(np.floor((h_top - h_min) / h_step)) + 1
    if n_h < 8:
        raise ValueError("the annulus h_min .. r_m - rim_margin is too narrow to match")
    # disparity window in table columns (the same everywhere, see module doc)
    d_lo = cam1.v * rig.s / ((rig.d + r_max) * h_step)
    d_hi = cam1.v * rig.s / ((rig.d + r_min) * h_step)
    win = (int(np.floor(d_lo)) - 1, int(np.ceil(d_hi)) + 1)

    stride = max(1, round(profile_step / h_step))  # patch profile spacing, in columns
    w = int(np.ceil(patch_radius / (h_step * stride)))
    pad = w * stride + 2 if method == "robust" else 1
    h0 = h_min - pad * h_step
    n_cols = n_h + 2 * pad
    maps1 = _polar_maps(cam1, n_theta, h0, h_step, n_cols)
    maps2 = _polar_maps(cam2, n_theta, scale2 * h0, scale2 * h_step, n_cols)
    tab = _Tables(maps1, maps2, pad, n_h, h0, h_step, scale2, n_theta, win)
    t1 = t2 = None
    if method == "robust":
        t1, t2 = _table(g1.f, maps1), _table(g2.f, maps2)
        if tangential_blur > 0:
            sigma = tangential_blur * n_theta / (2.0 * np.pi)  # in lines
            t1, t2 = _blur_lines(t1, sigma), _blur_lines(t2, sigma)
    # df/dh_i along the lines. The paper's rule reads the polar edge finder's
    # grid (eq. 19); the robust matcher finds its edges on the same blurred
    # profiles it compares, by central differences of the table (it needs
    # only where |df/dh_i| peaks and its sign, not its exact value)
    if method == "robust":
        fh1 = _radial_derivative(t1, h_step)
        fh2 = _radial_derivative(t2, scale2 * h_step)
    else:
        if g1.f_h is None or g2.f_h is None or g1.f_theta is None or g2.f_theta is None:
            raise ValueError("the paper's rule needs f_h and f_theta grids")
        fh1, fh2 = _table(g1.f_h, maps1), _table(g2.f_h, maps2)
    core = slice(pad, pad + n_h)
    # the percentile of every other line is the same to well within a percent
    thr = float(np.percentile(np.abs(fh1[::2, core]), threshold_percentile))
    thr = max(thr, float(min_gradient))

    if method == "paper":
        res = _match_paper(tab, fh1, fh2, _table(g1.f_theta, maps1), _table(g2.f_theta, maps2), thr)
    else:
        res = _match_robust(
            tab,
            fh1,
            fh2,
            t1,
            t2,
            thr,
            w=w,
            stride=stride,
            patch_lines=patch_lines,
            min_score=min_score,
            uniqueness=uniqueness,
            left_right=left_right,
            candidate_fraction=candidate_fraction,
            self_similarity=self_similarity,
        )
    k1, j1, c2, score, n_sig = res
    theta = -np.pi + (2.0 * np.pi / n_theta) * (k1 + 0.5)
    h1 = h_min + h_step * j1  # j1, c2: columns from the first core column
    h2 = scale2 * (h_min + h_step * c2)
    lo, hi = rig.disparity_window(h1, r_min, r_max)
    ok = (h2 >= lo) & (h2 <= hi) & np.isfinite(h2)
    if method == "robust" and consistency > 0 and np.any(ok):
        idx = np.nonzero(ok)[0]
        agree = _consistent(
            theta[idx], h1[idx], h2[idx] - scale2 * h1[idx],
            half_theta=0.05, half_h=cam1.r_m / 16.0, tol=consistency,
            support=consistency_support,
        )  # fmt: skip
        ok[idx[~agree]] = False
    return Matches.from_polar(
        rig, theta[ok], h1[ok], h2[ok], score[ok], n_significant=n_sig, method=method
    )


def _consistent(
    theta: NDArray, h1: NDArray, disparity: NDArray, *, half_theta: float, half_h: float,
    tol: float, support: int,
) -> NDArray:  # fmt: skip
    """Matches whose disparity agrees (within ``tol``) with at least ``support``
    of their neighbours (|d theta| <= half_theta, wrapping; |d h1| <= half_h),
    and with at least half of them; bool (N,)."""
    n = theta.size
    scale = half_h / half_theta  # theta in pixels, so the window is a square
    t = np.mod(theta, 2.0 * np.pi) * scale
    box = (2.0 * np.pi * scale, 4.0 * (float(h1.max()) + half_h) + 1.0)
    pts = np.column_stack([np.minimum(t, np.nextafter(box[0], 0)), h1 - h1.min()])
    pairs = cKDTree(pts, boxsize=box).query_pairs(half_h, p=np.inf, output_type="ndarray")
    i = np.concatenate([pairs[:, 0], pairs[:, 1]])
    j = np.concatenate([pairs[:, 1], pairs[:, 0]])
    near = np.bincount(i, minlength=n)
    agree = np.bincount(i, weights=np.abs(disparity[i] - disparity[j]) <= tol, minlength=n)
    return (agree >= support) & (agree >= 0.5 * near)


@dataclass(frozen=True)
class _Tables:
    """Geometry of the two polar tables (columns include ``pad`` on each side)."""

    maps1: tuple
    maps2: tuple
    pad: int
    n_h: int
    h0: float
    h_step: float
    scale2: float
    n_theta: int
    win: tuple[int, int]  # column offsets j2 - j1 that can hold the match


def _match_robust(
    tab: _Tables,
    fh1,
    fh2,
    t1,
    t2,
    thr,
    *,
    w,
    stride,
    patch_lines,
    min_score,
    uniqueness,
    left_right,
    candidate_fraction,
    self_similarity=1.0,
):
    """NCC of radial profiles between the edges of both images, line by line.

    The edges (local maxima of |f_h| along a line above candidate_fraction *
    thr) of each line are laid out left-aligned in (n_theta, c) arrays, so
    the NCC of every pair of edges on every line is one batched matrix
    product: first the significant edges of image 1 against all edges of
    image 2, then, for the left-right check, the chosen edges of image 2
    against all edges of image 1.
    """
    n_theta, pad, n_h = tab.n_theta, tab.pad, tab.n_h
    lo, hi = tab.win
    low = candidate_fraction * thr
    layout = []
    for fh in (fh1, fh2):
        a = np.abs(fh)
        m = _local_maxima(a)
        m &= a > low
        m[:, :pad] = False
        m[:, pad + n_h :] = False
        cols, exists, _ = _per_line(m)
        rows = np.broadcast_to(np.arange(n_theta)[:, None], cols.shape)
        layout.append((cols, exists, rows, fh[rows, cols]))
    (c1, e1, rows1, g1), (c2, e2, rows2, g2) = layout
    # the significant edges of image 1, as slots of its edge layout
    sslot, es, _ = _per_line(e1 & (np.abs(g1) > thr))
    n_sig = int(np.count_nonzero(es))
    if n_sig == 0 or not e2.any():
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0), np.zeros(0), n_sig
    rows_s = np.broadcast_to(np.arange(n_theta)[:, None], sslot.shape)
    desc2 = _Descriptors(t2, w, stride, patch_lines)
    D1 = _Descriptors(t1, w, stride, patch_lines)(rows1, c1)  # (n_theta, c1, L)
    D2 = desc2(rows2, c2)  # (n_theta, c2, L)
    # padding slots get zero descriptors, hence NCC 0 with everything: never a
    # match (min_score > 0), never a left-right winner over a real edge
    D1[~e1] = 0.0
    D2[~e2] = 0.0
    D1s = _rows_take(D1, rows_s, sslot)  # D1[rows_s, sslot]
    D1s[~es] = 0.0

    # forward: each significant edge of image 1 takes its best edge of image 2
    # inside the disparity window
    j1 = c1[rows_s, sslot]
    S = np.matmul(D1s, D2.transpose(0, 2, 1))  # (n_theta, cs, c2) NCC
    _mask_outside(S, *_window_slots(c2, e2, rows_s, j1 + lo, j1 + hi))
    best_c = np.argmax(S, axis=2)
    best = np.take_along_axis(S, best_c[..., None], axis=2)[..., 0]
    # the NCC at whole columns can sit below its peak between them by up to
    # ~(1 - peak) (h_step / correlation length)^2; take a looser floor here
    # and apply min_score to the interpolated peak below
    floor = min_score - 0.5 * (1.0 - min_score)
    ok = es & np.isfinite(best) & (best >= floor)
    # the same edge polarity (an edge of the other polarity falls where this
    # one rises: NCC near -1, so it seldom wins anyway)
    ok &= (g1[rows_s, sslot] > 0) == (g2[rows_s, best_c] > 0)
    if uniqueness < 1.0 and S.shape[2] > 1:
        np.put_along_axis(S, best_c[..., None], -np.inf, axis=2)
        second = np.maximum(S.max(axis=2), -1.0)
        ok &= (1.0 - best) <= uniqueness * (1.0 - second)
    if self_similarity < 1.0 and ok.any():
        # periodic aliases: image 1's own profile recurs on its line within a
        # window's width (at a lag of at least half the profile), so an
        # equally good match sits a period away in image 2 whatever it scores
        A = np.matmul(D1s, D1.transpose(0, 2, 1))  # (n_theta, cs, c1)
        lag = np.abs(c1[:, None, :] - j1[:, :, None])
        far = (lag < (w * stride) // 2) | (lag > hi - lo) | ~e1[:, None, :]
        A[far] = -np.inf
        self_best = np.maximum(A.max(axis=2), -1.0)
        ok &= (1.0 - best) <= self_similarity * (1.0 - self_best)
    if left_right and ok.any():
        # the best image-1 edge of each chosen image-2 edge, in its window
        oslot, eo, _ = _per_line(ok)
        rows_o = np.broadcast_to(np.arange(n_theta)[:, None], oslot.shape)
        b2 = best_c[rows_o, oslot]
        D2o = _rows_take(D2, rows_o, b2)  # D2[rows_o, b2]
        D2o[~eo] = 0.0
        Sb = np.matmul(D2o, D1.transpose(0, 2, 1))  # (n_theta, co, c1)
        j2 = c2[rows_o, b2]
        _mask_outside(Sb, *_window_slots(c1, e1, rows_o, j2 - hi, j2 - lo))
        back = np.argmax(Sb, axis=2)
        agree = eo & (back == sslot[rows_o, oslot])
        ok = np.zeros_like(ok)
        ok[rows_o[agree], oslot[agree]] = True
    ks, si = np.nonzero(ok)
    rs = sslot[ks, si]
    best = best[ks, si]
    jj1 = c1[ks, rs]
    jj2 = c2[ks, best_c[ks, si]]
    dd1 = _rows_take(D1, ks, rs)  # D1[ks, rs]

    # sub-sample h_2: parabola through the NCC at the neighbouring columns,
    # after moving one column if a neighbour scores higher
    lo_col, hi_col = w * stride, t2.shape[1] - 1 - w * stride

    def ncc(jj):
        return np.einsum("nl,nl->n", dd1, desc2(ks, np.clip(jj, lo_col, hi_col)))

    s0, sm, sp = best, ncc(jj2 - 1), ncc(jj2 + 1)
    step = np.where((sp > s0) & (sp >= sm), 1, np.where(sm > s0, -1, 0))
    moved = step != 0
    if np.any(moved):
        far = ncc(jj2 + 2 * step)
        sm, s0, sp = (
            np.where(step > 0, s0, np.where(moved, far, sm)),
            np.where(moved, np.maximum(sp, sm), s0),
            np.where(step > 0, far, np.where(moved, s0, sp)),
        )
        jj2 = jj2 + step
    off = _parabola_offset(sm, s0, sp)
    peak = s0 + 0.25 * (sp - sm) * off  # the parabola's vertex value
    keep = peak >= min_score
    return (ks[keep], (jj1 - pad)[keep], (jj2 + off - pad)[keep],
            np.clip(peak[keep], 0.0, 1.0), n_sig)  # fmt: skip


def _rows_take(a: NDArray, k: NDArray, j: NDArray) -> NDArray:
    """a[k, j] for a C-contiguous (n, c, L) array: np.take of flat rows (the
    same values, gathered several times faster than by two index arrays)."""
    n, c, length = a.shape
    return np.take(a.reshape(n * c, length), np.asarray(k) * c + j, axis=0)


def _mask_outside(S: NDArray, first: NDArray, stop: NDArray) -> None:
    """Set S[..., m] = -inf outside first <= m < stop (in place)."""
    # int16 slots where they fit and an in-place or: less memory traffic on
    # the (lines, c, c) masks
    it = np.int16 if S.shape[-1] < np.iinfo(np.int16).max else np.int32
    slot = np.arange(S.shape[-1], dtype=it)
    out = np.less(slot, first[..., None].astype(it))
    out |= slot >= stop[..., None].astype(it)
    S[out] = -np.inf


def _match_paper(tab: _Tables, fh1, fh2, ft1, ft2, thr):
    """Section 5.2 as written: most similar polar gradient vector along the line."""
    pad, n_h = tab.pad, tab.n_h
    h1_cols = tab.h0 + tab.h_step * np.arange(fh1.shape[1])
    g1t = ft1 / h1_cols  # (1/h_i) df/dtheta_i, eq. (8)
    g2t = ft2 / (tab.scale2 * h1_cols)
    sig = []
    for f in (fh1, fh2):
        m = np.abs(f) > thr
        m[:, :pad] = False
        m[:, pad + n_h :] = False
        sig.append(m)
    k1, j1 = np.nonzero(sig[0])
    k2, j2 = np.nonzero(sig[1])
    n_sig = int(k1.size)
    if k1.size == 0 or k2.size == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0), np.zeros(0), n_sig
    n_cols = fh1.shape[1]
    key2 = k2 * n_cols + j2
    start = np.searchsorted(key2, k1 * n_cols + j1 + tab.win[0], side="left")
    stop = np.searchsorted(key2, k1 * n_cols + j1 + tab.win[1], side="right")
    count = stop - start
    m = max(int(count.max()), 1)
    ga = np.stack([fh1[k1, j1], g1t[k1, j1]], axis=1)
    gb = np.stack([fh2[k2, j2], g2t[k2, j2]], axis=1)
    best_d = np.full(k1.size, np.inf, np.float32)
    best_i = np.zeros(k1.size, int)
    for s in range(0, k1.size, 8192):  # chunks keep the (n, m, 2) array small
        e = min(s + 8192, k1.size)
        idx = start[s:e, None] + np.arange(m)[None, :]
        ok = np.arange(m)[None, :] < count[s:e, None]
        idx = np.where(ok, idx, 0)
        dist = np.where(ok, np.linalg.norm(ga[s:e, None, :] - gb[idx], axis=2), np.inf)
        bi = np.argmin(dist, axis=1)
        best_d[s:e] = dist[np.arange(e - s), bi]
        best_i[s:e] = idx[np.arange(e - s), bi]
    ok = np.isfinite(best_d)
    k1, j1, ga, best_d = k1[ok], j1[ok], ga[ok], best_d[ok]
    jb = j2[best_i[ok]]

    def dist_at(jj):
        jj = np.clip(jj, 0, n_cols - 1)
        return np.hypot(ga[:, 0] - fh2[k1, jj], ga[:, 1] - g2t[k1, jj])

    off = _parabola_offset(-dist_at(jb - 1), -best_d, -dist_at(jb + 1))
    gnorm = np.hypot(ga[:, 0], ga[:, 1]) + np.hypot(fh2[k1, jb], g2t[k1, jb])
    score = np.clip(1.0 - best_d / np.maximum(gnorm, 1e-12), 0.0, 1.0)
    return k1, j1 - pad, jb + off - pad, score, n_sig
