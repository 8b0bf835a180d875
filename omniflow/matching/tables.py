"""Fitted images on pixel grids and polar tables, and sampling them.

A polar table has one row per radial line theta_k and one column per image
radius; both units' tables are made with one cv2.remap each
(:func:`polar_table`), their geometry is
:class:`omniflow.paper.matching.TableGeometry`. Also the small primitives of the robust
rule (local maxima along a line, the peak's sharpness, percentiles).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

from omniflow.geometry.rig import Unit
from omniflow.paper.dct import DCTFit
from omniflow.paper.edges import polar_gradient_grid

__all__ = [
    "PolarGrids",
    "abs_percentile",
    "blur_lines",
    "local_maxima",
    "polar_gradient_fast",
    "polar_grids",
    "polar_maps",
    "polar_radii",
    "polar_sample",
    "polar_table",
    "radial_derivative",
    "sample_xy",
    "sharp_peak",
]

_REMAP_CHUNK = 32000  # cv2.remap needs both map dimensions below SHRT_MAX


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


def polar_gradient_fast(fit: DCTFit, unit: Unit) -> tuple[NDArray, NDArray]:
    """(df/dh_i, df/dtheta_i) on the pixel grid, float32, eq. (19)-(20).

    :func:`omniflow.paper.edges.polar_gradient_grid` with 0 instead of NaN for f_h at
    h_i = 0 (the matchers compare magnitudes; a NaN would poison percentiles).
    """
    f_h, f_th = polar_gradient_grid(fit, unit)
    f_h = np.nan_to_num(np.asarray(f_h, dtype=np.float32), nan=0.0, copy=False)
    return f_h, np.asarray(f_th, dtype=np.float32)


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
def polar_maps(unit: Unit, n_theta: int, h0: float, step: float, n: int) -> tuple[NDArray, NDArray]:
    """cv2.remap maps (float32, shape (n_theta, n)) of the polar grid of one unit.

    Row k is theta_k = -pi + 2 pi (k + 1/2) / n_theta, column j is
    h_i = h0 + j step; map values are pixel indices (x - 1/2, y - 1/2).
    """
    theta = -np.pi + (2.0 * np.pi / n_theta) * (np.arange(n_theta) + 0.5)
    h_i = polar_radii(h0, step, n)
    mx = (unit.x_c - 0.5) + np.cos(theta)[:, None] * h_i[None, :]
    my = (unit.y_c - 0.5) + np.sin(theta)[:, None] * h_i[None, :]
    mx, my = mx.astype(np.float32), my.astype(np.float32)
    mx.setflags(write=False)
    my.setflags(write=False)
    return mx, my


def polar_radii(h0: float, step: float, n: int) -> NDArray:
    """The image radii of the columns of a polar table, h0 + j step (:func:`polar_maps`):
    two tables whose radii are equal have equal maps, column for column."""
    return h0 + step * np.arange(n)


def polar_table(image: NDArray, maps: tuple[NDArray, NDArray]) -> NDArray:
    return cv2.remap(
        np.ascontiguousarray(image, dtype=np.float32),
        maps[0],
        maps[1],
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )


def blur_lines(table: NDArray, sigma: float) -> NDArray:
    """Gaussian blur across the radial lines (theta, wrapping around), sigma in lines."""
    half = int(np.ceil(3 * sigma))
    if half < 1:
        return table
    padded = np.concatenate([table[-half:], table, table[:half]], axis=0)
    out = cv2.GaussianBlur(
        padded, (1, 2 * half + 1), sigmaX=0, sigmaY=sigma, borderType=cv2.BORDER_REPLICATE
    )
    return np.ascontiguousarray(out[half:-half])


def radial_derivative(table: NDArray, step: float) -> NDArray:
    """Central difference along the columns (radius) of a polar table.

    (t[:, j + 1] - t[:, j - 1]) (0.5 / step), the end columns copied from their
    neighbours; a float32 table is differenced in float32 (compiled), any other
    with numpy, in its dtype.
    """
    if table.dtype == np.float32 and table.ndim == 2 and table.shape[1] >= 3:
        out = np.empty(table.shape, dtype=np.float32)
        _central_difference(np.ascontiguousarray(table), np.float32(0.5 / step), out)
        return out
    out = np.empty_like(table)
    np.subtract(table[:, 2:], table[:, :-2], out=out[:, 1:-1])
    out[:, 1:-1] *= 0.5 / step
    out[:, 0] = out[:, 1]
    out[:, -1] = out[:, -2]
    return out


@numba.njit(cache=True, nogil=True)
def _central_difference(t, half_inv_step, out):  # pragma: no cover - compiled
    n = t.shape[1]
    for k in range(t.shape[0]):
        for j in range(1, n - 1):
            out[k, j] = (t[k, j + 1] - t[k, j - 1]) * half_inv_step
        out[k, 0] = out[k, 1]
        out[k, n - 1] = out[k, n - 2]


def local_maxima(a: NDArray) -> NDArray:
    """Local maxima along axis 1 (a plateau counts once, at its right end)."""
    m = np.zeros(a.shape, dtype=bool)
    m[:, 1:-1] = (a[:, 1:-1] >= a[:, :-2]) & (a[:, 1:-1] > a[:, 2:])
    return m


def sharp_peak(peak: NDArray, s_m: NDArray, s_0: NDArray, s_p: NDArray, flatness: float) -> NDArray:
    """Whether an NCC peak is sharp enough to place its vertex to sub-pixel.

    The vertex of the parabola through the NCC at three neighbouring columns
    moves with the noise by about (1 - NCC) / curvature columns: a match is
    kept when (1 - peak) <= ``flatness`` (2 s_0 - s_m - s_p). ``flatness``
    <= 0 keeps everything. Bool, the broadcast shape.
    """
    if flatness <= 0:
        return np.ones(np.broadcast(peak, s_0).shape, dtype=bool)
    return (1.0 - peak) <= flatness * (2.0 * s_0 - s_m - s_p)


@numba.njit(cache=True, nogil=True)
def _abs_order_stats(a, lo, out):  # pragma: no cover - compiled
    """The lo-th and (lo + 1)-th smallest of |a| (2-D float32) into out[0], out[1]: a
    radix select on the bit patterns of |a| (as unsigned integers they sort as the
    values do), a histogram of their top 16 bits, then a sort of the bins it needs.
    Returns False (nothing written) where |a| holds a NaN or an infinity."""
    bits = np.abs(a.ravel()).view(np.uint32)
    n = bits.size
    hist = np.zeros(65537, dtype=np.int64)
    for i in range(n):
        if bits[i] >= 0x7F800000:
            return False
        hist[(bits[i] >> 16) + 1] += 1
    for b in range(65536):
        hist[b + 1] += hist[b]  # hist[b]: how many lie in the bins below b
    for r in range(2):
        rank = lo + r
        b = np.searchsorted(hist, rank, side="right") - 1  # the bin holding that rank
        m = hist[b + 1] - hist[b]
        sel = np.empty(m, dtype=np.uint32)
        c = 0
        for i in range(n):
            if (bits[i] >> 16) == b:
                sel[c] = bits[i]
                c += 1
        sel.sort()
        out[r] = sel[rank - hist[b] : rank - hist[b] + 1].view(np.float32)[0]
    return True


def abs_percentile(a: NDArray, q: float) -> float:
    """``float(np.percentile(np.abs(a), q))``, faster for a 2-D float32 array.

    The two order statistics np.percentile interpolates between come from a
    compiled radix select (no copy, no partition) and are interpolated as numpy
    does for a Python-scalar q (method "linear", in float32); any other input
    goes to np.percentile itself.
    """
    a = np.asarray(a)
    if type(q) not in (int, float) or a.dtype != np.float32 or a.ndim != 2 or a.size < 2:
        return float(np.percentile(np.abs(a), q))
    n = a.size
    v = (n - 1) * np.true_divide(q, 100)  # numpy's virtual index of method "linear"
    if not (0.0 <= v < n - 1):
        return float(np.percentile(np.abs(a), q))
    lo = math.floor(v)
    out = np.empty(2, dtype=np.float32)
    if not _abs_order_stats(np.ascontiguousarray(a), lo, out):
        return float(np.percentile(np.abs(a), q))
    prev, nxt = out[0], out[1]
    gamma = float(v - lo)
    diff = nxt - prev  # numpy's _lerp, in float32
    if gamma >= 0.5:
        return float(nxt - diff * (1 - gamma))
    return float(prev + diff * gamma)
