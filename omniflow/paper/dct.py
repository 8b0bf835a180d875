"""Truncated DCT fit of an image and its analytic derivatives (paper section 5, eq. 17-18).

The forward transform keeps the lowest P x Q cosine coefficients,

    c(q, p) = a(q, p) / (X Y) sum_x sum_y cos(pi q y / Y) f(x, y) cos(pi p x / X)   # eq. (17)
    f(x, y) ~ sum_{p<P} sum_{q<Q} cos(pi q y / Y) c(q, p) cos(pi p x / X)           # eq. (18)

with a = 1 for p = q = 0, 2 when exactly one of p, q is 0 and 4 otherwise, and
x, y continuous pixel coordinates (pixel centre j + 0.5, i + 0.5; see
:mod:`omniflow.conventions`), so the paper's ``x + 0.5`` is our ``x``. The
truncation is the smoothing. Eq. (17) is scipy's unnormalised DCT-II of each
axis rescaled: ``c = a * dctn(f) / (4 X Y)``.

Two evaluation paths:

* at arbitrary points (``evaluate``, ``gradient``): cosine/sine tables of the
  points (running products of exp(i pi x / X)) times the coefficient matrix
  (matrix products, no Python loop over coefficients);
* on every pixel centre (``grid``, ``grid_gradient``): the zero-padded
  coefficients through scipy's DCT-III, and for the derivatives the DST-III of
  the frequency-weighted coefficients, since
  d/dx cos(pi p x / X) = -(pi p / X) sin(pi p x / X).

``fit_dct3`` extends this to a stack of T >= 3 frames with a third (time)
axis, so f_t is analytic. Time convention: frame k sits at t = k, and the
time basis is cos(pi k' (t + 1/2) / T), the same half-sample convention as the
pixels (frame k's "centre" is at k + 1/2 in the DCT's own coordinate).
The plain cosine series has zero slope at the window's ends, which biases f_t
(by pi / 3 halfway between the frames of a 3-frame window for linear change);
``detrend=True`` removes a per-pixel straight line first and is exact there.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
import scipy.fft
from numpy.typing import ArrayLike, NDArray

from omniflow.paper.dct_kernels import cos_bases, cos_bases_columns

__all__ = ["DCT3Fit", "DCTFit", "band_window", "fit_dct", "fit_dct3"]


@lru_cache(maxsize=16)
def band_window(Q: int, P: int, taper: float) -> NDArray:
    """Weights (Q, P) that roll a truncated series off smoothly towards its band's edge.

    With rho = hypot(p / P, q / Q) the coefficient's frequency as a fraction of
    the band (1 at the edge of the P x Q block along either axis), the weight is
    1 for rho <= 1 - taper, cos^2(pi / 2 (rho - (1 - taper)) / taper) up to
    rho = 1 and 0 beyond (a radial Tukey window). ``taper = 0`` is the sharp
    truncation of eq. (18), all ones. Why: the sharp truncation is a sinc
    kernel in the image, whose ringing carries texture power at the band's
    edge across the image; near the image centre, where the conical mirror
    compresses the scene tangentially and that power is large, it breaks the
    flow equation's balance of f_t against the gradient (radial flow shrunk
    by 5-10 %; docs/decisions/flow_band.md).
    """
    if not 0.0 <= taper <= 1.0:
        raise ValueError(f"taper = {taper!r}: expected a fraction in [0, 1]")
    if taper == 0.0:
        out = np.ones((Q, P))
    else:
        rho = np.hypot(np.arange(Q)[:, None] / Q, np.arange(P)[None, :] / P)
        ramp = np.clip((rho - (1.0 - taper)) / taper, 0.0, 1.0)
        out = np.where(rho < 1.0, np.cos(0.5 * np.pi * ramp) ** 2, 0.0)
    out.setflags(write=False)  # cached: one array shared by every caller
    return out


def _check_image(image: ArrayLike, name: str = "image", ndim: int = 2) -> NDArray:
    arr = np.asarray(image)
    if arr.ndim != ndim:
        raise ValueError(
            f"{name}: expected a grey image array of {ndim} dimensions, got shape {arr.shape}"
        )
    if not np.issubdtype(arr.dtype, np.floating):
        arr = arr.astype(np.float64)
    if arr.dtype not in (np.float32, np.float64):
        arr = arr.astype(np.float64)
    if min(arr.shape) < 2:
        raise ValueError(f"{name}: every axis needs at least 2 samples, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains NaN or inf values; expected finite grey levels")
    return arr


def _band_size(n: int, band: float, given: int | None, what: str) -> int:
    if given is None:
        if not (0 < band <= 1):
            raise ValueError(f"band = {band!r}: expected a fraction in (0, 1]")
        given = round(band * n)
    if int(given) != given or not (1 <= given <= n):
        raise ValueError(f"{what} = {given!r}: expected an integer in [1, {n}]")
    return int(given)


@lru_cache(maxsize=64)
def _weights(n_coef: int, n: int) -> tuple[NDArray, NDArray]:
    """Per-axis factors: a-factor split (1 for index 0, 2 otherwise) and pi k / N."""
    a = np.full(n_coef, 2.0)
    a[0] = 1.0
    a.setflags(write=False)
    w = np.pi * np.arange(n_coef) / n
    w.setflags(write=False)
    return a, w


def _bases(
    coord: NDArray, n_coef: int, n: int, *, contiguous: bool = False
) -> tuple[NDArray, NDArray]:
    """cos(pi k c / N) and -(pi k / N) sin(pi k c / N) for k < n_coef, shape (M, n_coef).

    Built as the running product of exp(i pi c / N) (one complex exponential per
    point instead of 2 n_coef trigonometric calls; error ~k eps, 1e-13 at k = 256),
    compiled (:func:`omniflow.paper.dct_kernels.cos_bases`): :func:`bases_numpy` value for
    value, about 3 times faster (the refinement's exact evaluations).

    The cosines come as a strided view, the layout of bases_numpy's ``table.real``,
    whose einsum sums downstream add in another order on a contiguous array; with
    ``contiguous`` (for a factor that only enters a matrix product, which numpy makes
    from a contiguous copy of a strided operand: the same product) a plain array,
    without that copy.
    """
    _, w = _weights(n_coef, n)
    e = np.exp((1j * np.pi / n) * np.asarray(coord, dtype=np.float64).reshape(-1))
    cos = np.empty((e.size, n_coef)) if contiguous else np.empty((e.size, n_coef, 2))[:, :, 0]
    dsin = np.empty((e.size, n_coef))
    cos_bases(e, w, cos, dsin)
    return cos, dsin


def _bases_columns(
    coord: NDArray, n_coef: int, n: int, dtype: type = np.float32
) -> tuple[NDArray, NDArray]:
    """:func:`_bases` transposed, shape (n_coef, M), stored as ``dtype``.

    The same running products in float64 (:func:`omniflow.paper.dct_kernels.cos_bases_columns`,
    the points' loop innermost: about 4 times faster than :func:`_bases` at a few
    hundred points), each value rounded once as it is stored (a running product in
    float32 would lose ~k float32 ulps by k = 256).
    """
    _, w = _weights(n_coef, n)
    e = np.exp((1j * np.pi / n) * np.asarray(coord, dtype=np.float64).reshape(-1))
    cos = np.empty((n_coef, e.size), dtype)
    dsin = np.empty((n_coef, e.size), dtype)
    cos_bases_columns(e, w, cos, dsin)
    return cos, dsin


def bases_numpy(coord: NDArray, n_coef: int, n: int) -> tuple[NDArray, NDArray]:
    """:func:`_bases` in numpy (its reference form): a complex table and its cumprod."""
    _, w = _weights(n_coef, n)
    table = np.empty((coord.size, n_coef), np.complex128)
    table[:, 0] = 1.0
    if n_coef > 1:
        table[:, 1:] = np.exp((1j * np.pi / n) * coord.reshape(-1))[:, None]
        np.cumprod(table, axis=1, out=table)
    return table.real, -w * table.imag


def _cos3(c: NDArray, n: int, axis: int) -> NDArray:
    """sum_k c_k cos(pi k (j + 1/2) / N) for j < N along ``axis`` (c zero-padded to N)."""
    # Unnormalised DCT-III: y_j = x_0 + 2 sum_{k>=1} x_k cos(pi k (2j + 1) / 2N).
    half = 0.5 * c
    first = [slice(None)] * c.ndim
    first[axis] = slice(0, 1)
    half[tuple(first)] = c[tuple(first)]
    return scipy.fft.dct(half, type=3, n=n, axis=axis, overwrite_x=True)


def _sin3(b: NDArray, n: int, axis: int) -> NDArray:
    """sum_{k>=1} b_k sin(pi k (j + 1/2) / N) for j < N along ``axis`` (b_0 ignored)."""
    # Unnormalised DST-III: y_j = (-1)^j x_{N-1} + 2 sum_{m<N-1} x_m sin(pi (2j + 1)(m + 1) / 2N),
    # so x_m = b_{m+1} / 2 for m + 1 < N; b_N never exists because the band is < N + 1.
    rest = [slice(None)] * b.ndim
    rest[axis] = slice(1, None)
    return scipy.fft.dst(0.5 * b[tuple(rest)], type=3, n=n, axis=axis, overwrite_x=True)


@dataclass(frozen=True, eq=False)
class DCTFit:
    """The truncated cosine series of one image, eq. (18).

    Attributes
    ----------
    coeffs : ndarray, shape (Q, P), float64
        c(q, p) of eq. (17); row index q (image y), column index p (image x).
    width, height : int
        X and Y, the image size the series is defined on, pixels.
    dtype : numpy dtype
        Working precision of the grid paths (that of the fitted image).
    """

    coeffs: NDArray
    width: int
    height: int
    dtype: np.dtype = field(default=np.dtype(np.float64))

    @property
    def P(self) -> int:
        return self.coeffs.shape[1]

    @property
    def Q(self) -> int:
        return self.coeffs.shape[0]

    def _points(self, x: ArrayLike, y: ArrayLike) -> tuple[NDArray, NDArray, tuple]:
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        if x.shape != y.shape:
            raise ValueError(f"x and y must have equal shapes, got {x.shape} and {y.shape}")
        return x.ravel(), y.ravel(), x.shape

    def evaluate(self, x: ArrayLike, y: ArrayLike) -> NDArray:
        """Eq. (18) at continuous pixel coordinates.

        Parameters
        ----------
        x, y : array_like, any equal shapes
            Column and row coordinates, pixel centres at j + 0.5, i + 0.5.

        Returns
        -------
        ndarray, the shape of x, float64
        """
        xs, ys, shape = self._points(x, y)
        cx, _ = _bases(xs, self.P, self.width)
        cy, _ = _bases(ys, self.Q, self.height, contiguous=True)  # enters a product only
        return np.einsum("np,np->n", cy @ self.coeffs, cx).reshape(shape)

    def gradient(self, x: ArrayLike, y: ArrayLike) -> tuple[NDArray, NDArray]:
        """Analytic (f_x, f_y) of eq. (18) at continuous pixel coordinates.

        Returns
        -------
        f_x, f_y : ndarray, the shape of x, float64, grey levels per pixel
        """
        xs, ys, shape = self._points(x, y)
        cx, dcx = _bases(xs, self.P, self.width)
        cy, dcy = _bases(ys, self.Q, self.height, contiguous=True)  # enter products only
        f_x = np.einsum("np,np->n", cy @ self.coeffs, dcx)
        f_y = np.einsum("np,np->n", dcy @ self.coeffs, cx)
        return f_x.reshape(shape), f_y.reshape(shape)

    def value_and_gradient(
        self, x: ArrayLike, y: ArrayLike, *, single: bool = False
    ) -> tuple[NDArray, NDArray, NDArray]:
        """:meth:`evaluate` and :meth:`gradient` together, sharing the bases: (f, f_x, f_y).

        Parameters
        ----------
        x, y : array_like, any equal shapes
            Column and row coordinates, pixel centres at j + 0.5, i + 0.5.
        single : bool
            Form the bases and the matrix products over q in float32 (the bases from
            float64 ones, rounded once; the coefficients rounded once) and only the
            sums over p in float64: about half the time at a few hundred points,
            since the products over q are most of it and float32 BLAS does twice the
            work per instruction. The constant term c(0, 0), which every basis
            multiplies by exactly 1, stays out of the float32 products and is added
            in float64: it is most of a grey level's magnitude, and its rounding in
            the products would be most of the values' error. Each value then carries
            the rounding of float32 terms (a few float32 ulps of the texture's
            amplitude): for uses where that is far below what they resolve (the
            refinement's residuals, :mod:`omniflow.solve.refine`).

        Returns
        -------
        f, f_x, f_y : ndarray, the shape of x, float64
        """
        xs, ys, shape = self._points(x, y)
        if single:
            return tuple(v.reshape(shape) for v in self._value_and_gradient_single(xs, ys))
        cx, dcx = _bases(xs, self.P, self.width)
        cy, dcy = _bases(ys, self.Q, self.height, contiguous=True)  # enter products only
        coeffs = self.coeffs.astype(np.float64, copy=False)  # a mixed-type matmul skips BLAS
        rows = cy @ coeffs
        f = np.einsum("np,np->n", rows, cx)
        f_x = np.einsum("np,np->n", rows, dcx)
        f_y = np.einsum("np,np->n", dcy @ coeffs, cx)
        return f.reshape(shape), f_x.reshape(shape), f_y.reshape(shape)

    def _value_and_gradient_single(self, xs: NDArray, ys: NDArray) -> tuple[NDArray, ...]:
        """(f, f_x, f_y) at flat points, products in float32 (``value_and_gradient``)."""
        cx, dcx = _bases_columns(xs, self.P, self.width)  # (P, M)
        cy, dcy = _bases_columns(ys, self.Q, self.height)  # (Q, M)
        coeffs_t = self.coeffs.T.astype(np.float32)  # (P, Q), a copy
        coeffs_t[0, 0] = 0.0  # the constant term, 1 in every basis: added in float64
        rows = coeffs_t @ cy  # (P, M): the sums over q, float32
        f = np.einsum("pm,pm->m", rows, cx, dtype=np.float64) + self.coeffs[0, 0]
        f_x = np.einsum("pm,pm->m", rows, dcx, dtype=np.float64)
        f_y = np.einsum("pm,pm->m", coeffs_t @ dcy, cx, dtype=np.float64)
        return f, f_x, f_y

    def grid(self) -> NDArray:
        """Eq. (18) on every pixel centre, shape (H, W), by a DCT-III (fast path)."""
        c = self.coeffs.astype(self.dtype, copy=False)
        along_x = _cos3(c, self.width, axis=1)
        return _cos3(along_x, self.height, axis=0)

    def grid_gradient(self) -> tuple[NDArray, NDArray]:
        """(f_x, f_y) on every pixel centre, each shape (H, W), by DCT-III / DST-III."""
        c = self.coeffs.astype(self.dtype, copy=False)
        _, wx = _weights(self.P, self.width)
        _, wy = _weights(self.Q, self.height)
        cos_x = _cos3(c, self.width, axis=1)  # (Q, W)
        sin_x = _sin3(-wx.astype(self.dtype) * c, self.width, axis=1)  # (Q, W): d/dx
        f_x = _cos3(sin_x, self.height, axis=0)
        f_y = _sin3(-wy.astype(self.dtype)[:, None] * cos_x, self.height, axis=0)
        return f_x, f_y


def fit_dct(
    image: ArrayLike, *, band: float = 0.25, P: int | None = None, Q: int | None = None
) -> DCTFit:
    """Fit the truncated DCT of eq. (17) to a grey image.

    Parameters
    ----------
    image : array_like, shape (H, W), float32 or float64
        Grey image; other real dtypes are converted to float64.
    band : float
        Fraction of each axis's frequencies kept when P or Q is not given:
        P = round(band * W), Q = round(band * H). The paper uses 1/4.
    P, Q : int, optional
        Number of coefficients kept along x (columns) and y (rows).

    Returns
    -------
    DCTFit
        ``coeffs`` of shape (Q, P), float64.
    """
    f = _check_image(image)
    height, width = f.shape
    P = _band_size(width, band, P, "P")
    Q = _band_size(height, band, Q, "Q")
    # eq. (17): DCT-II along x, keep P columns, then along y (same as dctn(f)[:Q, :P]).
    spec = scipy.fft.dct(scipy.fft.dct(f, type=2, axis=1)[:, :P], type=2, axis=0)[:Q]
    ay, _ = _weights(Q, height)
    ax, _ = _weights(P, width)
    coeffs = (ay[:, None] * ax[None, :]) * spec.astype(np.float64) / (4.0 * width * height)
    return DCTFit(coeffs=coeffs, width=width, height=height, dtype=f.dtype)


@dataclass(frozen=True, eq=False)
class DCT3Fit:
    """The truncated cosine series of a stack of frames (x, y and time).

    f(x, y, t) ~ sum_k sum_q sum_p c(k, q, p) cos(pi k (t + 1/2) / T)
    cos(pi q y / Y) cos(pi p x / X): eq. (18) with a time axis; frame k at t = k.
    With ``slope`` (a detrended fit) the series models what remains after a
    per-pixel straight line in time, and (t - (T - 1) / 2) s(x, y) is added,
    s being the 2-D series of eq. (18) with coefficients ``slope``.

    Attributes
    ----------
    coeffs : ndarray, shape (K, Q, P), float64
    width, height, frames : int
        X, Y and T.
    slope : ndarray, shape (Q, P), float64, or None
        Coefficients of the per-pixel least-squares slope (grey levels per frame).
    """

    coeffs: NDArray
    width: int
    height: int
    frames: int
    slope: NDArray | None = None

    @property
    def _t_mid(self) -> float:
        return 0.5 * (self.frames - 1)

    def at_time(self, t: float) -> DCTFit:
        """The 2-D series f(., ., t) at one (continuous) time t."""
        ct, _ = _bases(np.array([t + 0.5]), self.coeffs.shape[0], self.frames)
        c = np.tensordot(ct[0], self.coeffs, axes=1)
        if self.slope is not None:
            c = c + (t - self._t_mid) * self.slope
        return DCTFit(c, self.width, self.height)

    def time_derivative_at(self, t: float) -> DCTFit:
        """The 2-D series of f_t(., ., t), per frame interval."""
        _, dct_ = _bases(np.array([t + 0.5]), self.coeffs.shape[0], self.frames)
        c = np.tensordot(dct_[0], self.coeffs, axes=1)
        if self.slope is not None:
            c = c + self.slope
        return DCTFit(c, self.width, self.height)

    def _points(self, x, y, t):
        x, y, t = (np.asarray(a, dtype=float) for a in (x, y, t))
        x, y, t = np.broadcast_arrays(x, y, t)
        return x.ravel(), y.ravel(), t.ravel(), x.shape

    def evaluate(self, x: ArrayLike, y: ArrayLike, t: ArrayLike) -> NDArray:
        """f at continuous (x, y, t); arrays broadcast together. Returns float64."""
        xs, ys, ts, shape = self._points(x, y, t)
        K, Q, P = self.coeffs.shape
        cx, _ = _bases(xs, P, self.width)
        cy, _ = _bases(ys, Q, self.height)
        ct, _ = _bases(ts + 0.5, K, self.frames)
        out = np.einsum("nk,kqp,nq,np->n", ct, self.coeffs, cy, cx, optimize=True)
        if self.slope is not None:
            out += (ts - self._t_mid) * np.einsum("np,np->n", cy @ self.slope, cx)
        return out.reshape(shape)

    def gradient(
        self, x: ArrayLike, y: ArrayLike, t: ArrayLike
    ) -> tuple[NDArray, NDArray, NDArray]:
        """Analytic (f_x, f_y, f_t) at continuous (x, y, t); f_t per frame interval."""
        xs, ys, ts, shape = self._points(x, y, t)
        K, Q, P = self.coeffs.shape
        cx, dcx = _bases(xs, P, self.width)
        cy, dcy = _bases(ys, Q, self.height)
        ct, dct_ = _bases(ts + 0.5, K, self.frames)
        ein = "nk,kqp,nq,np->n"
        f_x = np.einsum(ein, ct, self.coeffs, cy, dcx, optimize=True)
        f_y = np.einsum(ein, ct, self.coeffs, dcy, cx, optimize=True)
        f_t = np.einsum(ein, dct_, self.coeffs, cy, cx, optimize=True)
        if self.slope is not None:
            tt = ts - self._t_mid
            s_y = cy @ self.slope
            f_x += tt * np.einsum("np,np->n", s_y, dcx)
            f_y += tt * np.einsum("np,np->n", dcy @ self.slope, cx)
            f_t += np.einsum("np,np->n", s_y, cx)
        return f_x.reshape(shape), f_y.reshape(shape), f_t.reshape(shape)


def fit_dct3(
    frames: ArrayLike, *, band: float = 0.25, K: int | None = None, detrend: bool = False
) -> DCT3Fit:
    """Fit a 3-D truncated DCT to T >= 3 frames (the paper's suggested refinement).

    Parameters
    ----------
    frames : array_like, shape (T, H, W)
        Grey frames; frame k is at time t = k.
    band : float
        Spatial band as in :func:`fit_dct` (P = round(band W), Q = round(band H)).
    K : int, optional
        Time coefficients kept; default T (no temporal smoothing).
    detrend : bool
        Fit a per-pixel straight line in time first and the DCT to what is left.
        The plain cosine series has zero slope at both ends of the window (its
        even extension), so for brightness changing linearly in time its f_t is
        off by a factor pi / 3 = 1.047 halfway between the frames of a 3-frame
        window and by up to 1.063 for longer windows (see tests/omniflow/test_dct.py);
        detrending makes f_t exact for linear change and leaves only the
        curvature to the cosines.

    Returns
    -------
    DCT3Fit
        ``coeffs`` of shape (K, Q, P), float64 (and ``slope`` (Q, P) if detrended).
    """
    f = _check_image(frames, "frames", ndim=3)
    T, height, width = f.shape
    if T < 3:
        raise ValueError(f"frames: expected T >= 3 frames for a 3-D fit, got T = {T}")
    K = _band_size(T, 1.0, K, "K")
    P = _band_size(width, band, None, "P")
    Q = _band_size(height, band, None, "Q")
    slope = None
    if detrend:
        tk = (np.arange(T) - 0.5 * (T - 1)).astype(f.dtype)
        b = np.tensordot(tk, f, axes=1) / np.sum(tk * tk)  # least-squares slope, (H, W)
        f = f - tk[:, None, None] * b
        slope = fit_dct(b, P=P, Q=Q).coeffs
    spec = scipy.fft.dctn(f, type=2)[:K, :Q, :P].astype(np.float64)
    at, _ = _weights(K, T)
    ay, _ = _weights(Q, height)
    ax, _ = _weights(P, width)
    a = at[:, None, None] * ay[None, :, None] * ax[None, None, :]
    return DCT3Fit(
        coeffs=a * spec / (8.0 * T * width * height),
        width=width,
        height=height,
        frames=T,
        slope=slope,
    )
