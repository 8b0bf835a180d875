"""Compiled kernels (Numba) for loops that numpy runs only through large temporaries.

:func:`pooled_sums` forms the weighted sums of the pooled flow solver
(:func:`omniflow.paper.flow.pooled_solution`): for every point, over its K
neighbours, sum_j w_ij u_ij^m (pp, pq, qq, pf, qf)_j. In numpy that is a
dozen (N, K) gathers and products and an (N, K, 5) stack before one batched
product; here it is one pass over the neighbours with nothing stored but
the sums. The arithmetic of each term is numpy's, term by term; only the
order of the additions over the K neighbours differs (a batched matrix
product there, a running sum here), so the sums agree to rounding.

:func:`pooled_solves` solves those sums' 2 x 2 systems (the Schur complement on (a, h_1 b)
for the linear model) per point, numpy's operations in numpy's order, so bit for bit the
answers of the numpy form it replaced, without its (N,) temporaries.

:func:`ncc_offsets` scores a radial profile of table 1 against profiles of table
2 at a few columns (the densification's short search, omniflow.matching.dense):
the normalised cross-correlation of the same profiles as
omniflow.matching.robust.Descriptors, summed straight from the tables instead of
gathering every profile first.

:func:`cos_bases` makes the cosine series' bases at points
(:func:`omniflow.paper.dct.DCTFit.evaluate` and its gradients) as the running product
of a complex exponential, numpy's cumprod value for value, in one pass.

:func:`cos_bases_columns` makes the same products with the loop over the points
innermost, so that the points' independent chains (one dependent complex product per
coefficient each) fill the vector units, and stores them transposed, shape (n_coef, M):
contiguous rows for the stores and for the matrix products of
:meth:`omniflow.paper.dct.DCTFit.value_and_gradient` (``single``), which take them as
``coeffs.T @ bases``. Each product is numpy's, (a c - b d, a d + b c), in the same order,
so the values are :func:`omniflow.paper.dct.bases_numpy`'s, value for value (in float32
output, each rounded once as it is stored).

:func:`grid_scatter` and :func:`grid_read` put the grid pooling's point terms
into a cell image and read filtered images back bilinearly at the points
(:mod:`omniflow.solve.gridpool`), without numpy's (N, C) temporaries per corner.

:func:`cell_knn` finds the k nearest points within a radius
(:func:`omniflow.paper.flow.neighbourhoods`) by binning the points into square cells of
half the radius and visiting the cells around each query point ring by ring,
keeping the nearest so far in a max-heap whose top bounds the cells still worth
visiting. It answers what scipy's k-d tree answers (the same squared distances,
the same strict bound, nearest first) except in how points at exactly the same
distance are ordered, which the tree decides by its traversal; it flags the rows
where that decides which points are in, and the caller asks the tree for those.

:func:`gain_sums` forms the normal equations of the pools with a brightness gain
(:func:`omniflow.solve.gain.gain_solution`): per point the P x P matrix X^T W X, X^T W y
and y^T W y of both units' rows over the pool, in one pass, instead of numpy's
(N, K, 2, P) design and a batched product (the gain fit had been most of the gated
solve's time).

:func:`small_solves` solves those small systems per pool with omniflow.solve.gain's tests
(Gauss-Jordan; a positive-definite test by a Cholesky factorisation and the inverse's
trace, Jacobi rotations only where those bounds leave it open); :func:`nested_fits`
adds the fit without one unknown (the gain's or eq. (14)'s F test) from the same
inverse instead of a second solve.

:func:`decouple_sums` and :func:`decouple_fits` are the two-model test of eq. (14)
(:func:`omniflow.solve.decoupled.model_fits`): the weighted sums of each point's 3x3
normal equations in one pass over its pool, then per point the conditioning test
and the solves of the 3x3 (decoupled) and 2x2 (coupled) systems, without the
(N, K) temporaries, the batched SVD of ``np.linalg.cond`` and the batched LAPACK
solve. The condition number is numpy's (the 2-norm one: the ratio of the largest to
the smallest absolute eigenvalue of a symmetric matrix): from the closed-form
eigenvalues where they put it far below the threshold, else from cyclic Jacobi
rotations, which give every eigenvalue to an absolute error of a few ulps of the
largest as the SVD does (the closed-form cubic loses the small ones to sqrt(eps)
when two are close); the solves are Gaussian elimination with partial pivoting,
LAPACK's ``gesv`` on a 3x3.

The kernels compile on first use; ``cache=True`` keeps the machine code
between runs where the package folder (or Numba's user cache) is writable.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

__all__ = [
    "DECOUPLE_SUMS",
    "cell_knn",
    "cos_bases_columns",
    "decouple_fits",
    "decouple_sums",
    "gain_sums",
    "grid_read",
    "grid_scatter",
    "ncc_offsets",
    "nested_fits",
    "pooled_solves",
    "pooled_sums",
    "small_solves",
]


@numba.njit(cache=True, nogil=True)
def _pooled_sums(idx, w, f1_h, f1_theta, f1_t, kf2_h, f2_theta, f2_t, h1, th, relative,
                 n_powers, scale):  # pragma: no cover - compiled  # fmt: skip
    n, kk = idx.shape
    sums = np.zeros((n, n_powers, 5))
    wsum = np.zeros((n, n_powers))
    two_pi = 2.0 * math.pi
    for i in range(n):
        hi = h1[i]
        for s in range(kk):
            j = idx[i, s]
            ww = w[i, s]
            rel = h1[j] / hi if relative else 1.0
            p1 = f1_h[j] * rel
            p2 = kf2_h[j] * rel
            q1 = f1_theta[j] / hi
            q2 = f2_theta[j] / hi
            t1 = f1_t[j]
            t2 = f2_t[j]
            pp = p1 * p1 + p2 * p2
            pq = p1 * q1 + p2 * q2
            qq = q1 * q1 + q2 * q2
            pf = p1 * t1 + p2 * t2
            qf = q1 * t1 + q2 * t2
            power = ww
            for m in range(n_powers):
                if m == 1:  # the tangential offset u, as numpy's floor-mod wrap
                    u = (((th[j] - th[i]) + math.pi) % two_pi - math.pi) * hi / scale
                    power = ww * u
                elif m == 2:
                    power = ww * u * u
                sums[i, m, 0] += power * pp
                sums[i, m, 1] += power * pq
                sums[i, m, 2] += power * qq
                sums[i, m, 3] += power * pf
                sums[i, m, 4] += power * qf
                wsum[i, m] += power
    return sums, wsum


def pooled_sums(
    idx: NDArray,
    w: NDArray,
    derivs: tuple[NDArray, ...],
    h1: NDArray,
    theta: NDArray | None,
    *,
    relative: bool,
    linear: bool,
    scale: float,
) -> tuple[NDArray, NDArray]:
    """Weighted sums of the pooled normal equations, and of the weights.

    Parameters
    ----------
    idx, w : ndarray, shape (N, K)
        Neighbour indices (N + 1 entries below: index N is the sentinel) and weights.
    derivs : six ndarrays, shape (N + 1,)
        f1_h, f1_theta, f1_t, (h2/h1) f2_h, f2_theta, f2_t, each with a zero
        sentinel at index N.
    h1 : ndarray, shape (N + 1,)
        cam1 image radius, sentinel 1.
    theta : ndarray, shape (N + 1,), optional
        Azimuth (``linear`` only).
    relative, linear : bool
        The local model of :func:`omniflow.paper.flow.pooled_solution`.
    scale : float
        Tangential length that scales u, pixels.

    Returns
    -------
    sums : ndarray, shape (N, 1 or 3, 5)
        sum_j w u^m (pp, pq, qq, pf, qf), m = 0 (and 1, 2 for ``linear``).
    wsum : ndarray, shape (N, 1 or 3)
        sum_j w u^m.
    """
    f = [np.ascontiguousarray(v, dtype=np.float64) for v in derivs]
    th = np.zeros_like(f[0]) if theta is None else np.ascontiguousarray(theta, dtype=np.float64)
    return _pooled_sums(
        np.ascontiguousarray(idx, dtype=np.int64), np.ascontiguousarray(w, dtype=np.float64),
        *f, np.ascontiguousarray(h1, dtype=np.float64), th, bool(relative),
        3 if linear else 1, float(scale),
    )  # fmt: skip


@numba.njit(cache=True, nogil=True)
def _pooled_solves(sums, linear, limit, positive):  # pragma: no cover - compiled
    n = sums.shape[0]
    a = np.full(n, np.nan)
    c = np.full(n, np.nan)
    conf = np.zeros(n)
    explained = np.full(n, np.nan)
    lam_min = np.zeros(n)
    for i in range(n):
        pd = True
        # [[pp_m, pq_m], [pq_m, qq_m]] for the powers m = 0 (on (a, c)), 1 (coupling to the
        # slopes), 2 (on the slopes)
        m11, m12, m22 = sums[i, 0, 0], sums[i, 0, 1], sums[i, 0, 2]
        v0, v1 = -sums[i, 0, 3], -sums[i, 0, 4]
        if linear:  # Schur complement on (a, c): the two slopes solved out
            b11, b12, b22 = sums[i, 2, 0], sums[i, 2, 1], sums[i, 2, 2]
            det_b = b11 * b22 - b12 * b12
            pd = (det_b > 0) and (b11 > 0)
            inv = 1.0 / (det_b if det_b > 0 else np.nan)
            k11, k12, k22 = sums[i, 1, 0], sums[i, 1, 1], sums[i, 1, 2]
            # C = K B^-1, K the coupling block
            c11, c12 = (k11 * b22 - k12 * b12) * inv, (k12 * b11 - k11 * b12) * inv
            c21, c22 = (k12 * b22 - k22 * b12) * inv, (k22 * b11 - k12 * b12) * inv
            m11, m12, m22 = (m11 - (c11 * k11 + c12 * k12), m12 - (c11 * k12 + c12 * k22),
                             m22 - (c21 * k12 + c22 * k22))  # fmt: skip
            v0, v1 = (v0 + (c11 * sums[i, 1, 3] + c12 * sums[i, 1, 4]),
                      v1 + (c21 * sums[i, 1, 3] + c22 * sums[i, 1, 4]))  # fmt: skip
        det = m11 * m22 - m12 * m12
        # lambda_min / lambda_max, NaN to 0 (numpy's maximum keeps a NaN: so does this)
        tr = m11 + m22
        d = 0.25 * tr * tr - det
        disc = math.sqrt(d if not d < 0.0 else 0.0)
        lmax = 0.5 * tr + disc
        lo = 0.5 * tr - disc
        lmin = lo if not lo < 0.0 else 0.0
        ci = lmin / lmax if lmax > 0 else 0.0
        if math.isnan(ci):
            ci = 0.0
        elif math.isinf(ci):
            ci = 1.7976931348623157e308 if ci > 0 else -1.7976931348623157e308
        conf[i] = ci
        ok = (det > 0) and (ci >= limit) and (ci > 0)
        if positive:
            ok = ok and pd and (m11 > 0)
        if ok:
            a[i] = (m22 * v0 - m12 * v1) / det
            c[i] = (m11 * v1 - m12 * v0) / det
        explained[i] = a[i] * v0 + c[i] * v1
        dm = m11 - m22
        lam_min[i] = 0.5 * (m11 + m22) - math.sqrt(0.25 * (dm * dm) + m12 * m12)
    return a, c, conf, explained, lam_min


def pooled_solves(
    sums: NDArray, *, linear: bool, min_conditioning: float, positive: bool = False
) -> tuple[NDArray, ...]:
    """Solve each point's pooled normal equations from :func:`pooled_sums`' sums.

    The 2 x 2 system on (a, h_1 b) (for ``linear``, its Schur complement once the two
    slopes are solved out), per point in one pass, as numpy did it with a dozen (N,)
    temporaries; the same operations in the same order, so the same answers bit for
    bit (numpy's ``maximum`` and ``nan_to_num`` included).

    Parameters
    ----------
    sums : ndarray, shape (N, 1 or 3, 5)
        sum_j w u^m (pp, pq, qq, pf, qf).
    linear : bool
        The linear model (three powers of u).
    min_conditioning : float
        NaN where the confidence is below this.
    positive : bool
        Also NaN where the slopes' block or the (a, a) entry is not positive.

    Returns
    -------
    a, c : ndarray, shape (N,)
        dh_1/dt and h_1 dtheta/dt; NaN where singular or a test fails.
    confidence : ndarray, shape (N,)
        lambda_min / lambda_max of the 2 x 2 system, NaN as 0.
    explained : ndarray, shape (N,)
        x^T v, the squared residual the solution explains (NaN with x).
    lam_min : ndarray, shape (N,)
        The 2 x 2 system's smaller eigenvalue.
    """
    s = np.ascontiguousarray(sums, dtype=np.float64)
    if linear and s.shape[1] < 3:
        raise ValueError(f"pooled_solves: the linear model needs 3 powers, got {s.shape[1]}")
    return _pooled_solves(s, bool(linear), float(min_conditioning), bool(positive))


@numba.njit(cache=True, nogil=True)
def cos_bases(e, w, cos, dsin):  # pragma: no cover - compiled
    """cos[i, k] = Re(e[i]^k) and dsin[i, k] = -w[k] Im(e[i]^k) for k < cos.shape[1], the
    powers as the running product z_k = z_{k-1} e[i] (z_0 = 1), each complex product
    as numpy's, (a c - b d, a d + b c): :func:`omniflow.paper.dct.bases_numpy`'s cumprod
    value for value, without its complex table and the copies of its two parts."""
    n, m = cos.shape
    if m == 0:
        return
    for i in range(n):
        er = e[i].real
        ei = e[i].imag
        zr = 1.0
        zi = 0.0
        cos[i, 0] = 1.0
        dsin[i, 0] = -w[0] * 0.0
        for k in range(1, m):
            r = zr * er - zi * ei
            zi = zr * ei + zi * er
            zr = r
            cos[i, k] = zr
            dsin[i, k] = -w[k] * zi


@numba.njit(cache=True, nogil=True)
def cos_bases_columns(e, w, cos, dsin):  # pragma: no cover - compiled
    """cos[k, i] = Re(e[i]^k) and dsin[k, i] = -w[k] Im(e[i]^k) for k < cos.shape[0]:
    e (M,) complex128, w (n_coef,) float64, cos and dsin (n_coef, M), float64 or float32
    (the running product kept in float64 either way)."""
    m, n = cos.shape
    if m == 0:
        return
    zr = np.ones(n)
    zi = np.zeros(n)
    er = np.empty(n)
    ei = np.empty(n)
    for i in range(n):
        er[i] = e[i].real
        ei[i] = e[i].imag
        cos[0, i] = 1.0
        dsin[0, i] = -w[0] * 0.0
    for k in range(1, m):
        wk = w[k]
        for i in range(n):
            r = zr[i] * er[i] - zi[i] * ei[i]
            zi[i] = zr[i] * ei[i] + zi[i] * er[i]
            zr[i] = r
            cos[k, i] = r
            dsin[k, i] = -wk * zi[i]


@numba.njit(cache=True, nogil=True)
def grid_scatter(img, iy, ix, y0, x0, parts, members):  # pragma: no cover - compiled
    """Add ``parts[i]`` (C,) into ``img[iy[i] - y0, ix[i] - x0]`` (img (H, W, C)) for i in
    ``members``."""
    for t in range(members.size):
        i = members[t]
        for c in range(parts.shape[1]):
            img[iy[i] - y0, ix[i] - x0, c] += parts[i, c]


@numba.njit(cache=True, nogil=True)
def grid_read(f, gx, gy, x0, y0, readers, coef, out):  # pragma: no cover - compiled
    """Add ``coef[t]`` times the bilinear sample of ``f`` (H, W, C), H, W >= 2, at cell
    coordinates (gx[i] - x0, gy[i] - y0) (centres at integers, clamped to the grid) to
    ``out[i]`` (C,) for i = ``readers[t]``."""
    h, w, nc = f.shape
    for t in range(readers.size):
        i = readers[t]
        x = min(max(gx[i] - x0, 0.0), w - 1.0)
        y = min(max(gy[i] - y0, 0.0), h - 1.0)
        xi = min(int(x), w - 2)  # x >= 0: truncation is the floor
        yi = min(int(y), h - 2)
        fx = x - xi
        fy = y - yi
        c = coef[t]
        w00 = (1.0 - fx) * (1.0 - fy) * c
        w01 = fx * (1.0 - fy) * c
        w10 = (1.0 - fx) * fy * c
        w11 = fx * fy * c
        for k in range(nc):
            out[i, k] += (w00 * f[yi, xi, k] + w01 * f[yi, xi + 1, k]
                          + w10 * f[yi + 1, xi, k] + w11 * f[yi + 1, xi + 1, k])  # fmt: skip


@numba.njit(cache=True, nogil=True, inline="always")
def profile_stats(t1, k, j, w, stride, lines):  # pragma: no cover - compiled
    """(mean, 1 / norm of the mean-removed samples) of the profile of ``t1`` at line
    ``k``, column ``j``: the 2 w + 1 samples every ``stride`` columns on the 2 ``lines`` + 1
    lines around k (wrapping in theta), summed in float64 in this order; the norm is
    floored at 1e-12 (a flat profile)."""
    n_lines = t1.shape[0]
    s1 = 0.0
    s2 = 0.0
    for dk in range(-lines, lines + 1):
        row = (k + dk) % n_lines
        for q in range(-w, w + 1):
            v = np.float64(t1[row, j + q * stride])  # float64 products
            s1 += v
            s2 += v * v
    mean1 = s1 / ((2 * w + 1) * (2 * lines + 1))
    return mean1, 1.0 / max(math.sqrt(max(s2 - s1 * mean1, 0.0)), 1e-12)


@numba.njit(cache=True, nogil=True)
def ncc_offsets(t1, t2, k, j, cols, w, stride, lines, out):  # pragma: no cover - compiled
    """NCC of the profile of ``t1`` at (k[i], j[i]) with those of ``t2`` at (k[i], cols[i, s]).

    A profile: the 2 w + 1 samples every ``stride`` columns centred on the column, on
    the 2 ``lines`` + 1 lines around k (wrapping in theta); zero-mean, unit-norm (a
    flat profile has norm 1e-12). Columns must keep the profile inside the table.
    Writes out[i, s].
    """
    n_lines = t1.shape[0]
    length = (2 * w + 1) * (2 * lines + 1)
    for i in range(k.size):
        mean1, inv1 = profile_stats(t1, k[i], j[i], w, stride, lines)
        for s in range(cols.shape[1]):
            c = cols[i, s]
            dot = 0.0
            b1 = 0.0
            b2 = 0.0
            for dk in range(-lines, lines + 1):
                row = (k[i] + dk) % n_lines
                for q in range(-w, w + 1):
                    v2 = np.float64(t2[row, c + q * stride])
                    dot += (np.float64(t1[row, j[i] + q * stride]) - mean1) * v2
                    b1 += v2
                    b2 += v2 * v2
            # sum (v1 - mean1)(v2 - mean2) = sum (v1 - mean1) v2: the first is zero-mean
            inv2 = 1.0 / max(math.sqrt(max(b2 - b1 * (b1 / length), 0.0)), 1e-12)
            out[i, s] = dot * inv1 * inv2


#: Columns of :func:`decouple_sums`: the 3x3 normal matrix of (U, h_1,i W, c) (six
#: distinct entries), its right-hand side (A^T t), t^T t, and the sums of w and w^2.
DECOUPLE_SUMS = ("uu", "uw", "uq", "ww", "wq", "qq", "ut", "wt", "qt", "tt", "w", "w2")


@numba.njit(cache=True, nogil=True)
def _decouple_sums(idx, w, f1_h, f1_th, f1_t, f2_h, f2_th, f2_t, h1, h2):  # pragma: no cover
    n, kk = idx.shape
    out = np.zeros((n, 12))
    for i in range(n):
        s = np.zeros(12)
        for k in range(kk):
            j = idx[i, k]
            ww = w[i, k]
            if j >= n:  # no neighbour (a zero weight still multiplies, as numpy's sums do)
                continue
            a1, a2 = f1_h[j], f2_h[j]
            b1, b2 = a1 * h1[j], a2 * h2[j]  # f_h h_u,j: the W column times -h_1,i
            q1, q2 = f1_th[j], f2_th[j]
            t1, t2 = f1_t[j], f2_t[j]
            s[0] += ww * (a1 * a1 + a2 * a2)
            s[1] += ww * (a1 * b1 + a2 * b2)
            s[2] += ww * (a1 * q1 + a2 * q2)
            s[3] += ww * (b1 * b1 + b2 * b2)
            s[4] += ww * (b1 * q1 + b2 * q2)
            s[5] += ww * (q1 * q1 + q2 * q2)
            s[6] += ww * (a1 * t1 + a2 * t2)
            s[7] += ww * (b1 * t1 + b2 * t2)
            s[8] += ww * (q1 * t1 + q2 * t2)
            s[9] += ww * (t1 * t1 + t2 * t2)
            s[10] += ww
            s[11] += ww * ww
        out[i] = s
    return out


def decouple_sums(
    idx: NDArray, w: NDArray, derivs: tuple[NDArray, ...], h1: NDArray, h2: NDArray
) -> NDArray:
    """Pool sums of the two-model test, before the scaling by the point's own h_1.

    Parameters
    ----------
    idx, w : ndarray, shape (N, K)
        Pools (index N or more: no neighbour; weight 0 is skipped).
    derivs : six ndarrays, shape (N,)
        f1_h, f1_theta, f1_t, f2_h, f2_theta, f2_t.
    h1, h2 : ndarray, shape (N,)
        Image radii.

    Returns
    -------
    ndarray, shape (N, 12)
        Columns :data:`DECOUPLE_SUMS`, each a sum over j of w_ij times a product
        of j's terms a_u = f_h, b_u = f_h h_u, q_u = f_theta, t_u = f_t summed over
        the two units u (aa, ab, aq, bb, bq, qq, at, bt, qt, tt, then w and w^2).
        The point's own h_1,i scales them into the normal equations
        (:func:`decouple_fits`).
    """
    f = [np.ascontiguousarray(v, dtype=np.float64) for v in (*derivs, h1, h2)]
    return _decouple_sums(
        np.ascontiguousarray(idx, dtype=np.int64), np.ascontiguousarray(w, dtype=np.float64), *f
    )


@numba.njit(cache=True, nogil=True)
def _jacobi(a, n):  # pragma: no cover - compiled
    """Diagonalise the symmetric n x n ``a`` in place by cyclic Jacobi rotations: its
    eigenvalues are left on the diagonal, each to an absolute error of a few ulps of the
    largest."""
    for _sweep in range(30):
        off = 0.0
        for p in range(n):
            for q in range(p + 1, n):
                off += a[p, q] * a[p, q]
        scale = 0.0
        for p in range(n):
            scale += a[p, p] * a[p, p]
        if not off > 1e-36 * scale:  # converged (or NaN: the caller's test fails)
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = a[p, q]
                if apq == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for r in range(n):  # A <- A J (columns p, q)
                    arp, arq = a[r, p], a[r, q]
                    a[r, p] = c * arp - s * arq
                    a[r, q] = s * arp + c * arq
                for r in range(n):  # A <- J^T A (rows p, q)
                    apr, aqr = a[p, r], a[q, r]
                    a[p, r] = c * apr - s * aqr
                    a[q, r] = s * apr + c * aqr
                a[p, q] = 0.0
                a[q, p] = 0.0


@numba.njit(cache=True, nogil=True)
def _sym_eig_abs_ratio_ok(a, n, limit):  # pragma: no cover - compiled
    """Whether max|lambda| / min|lambda| < limit for the symmetric n x n ``a`` (n <= 3),
    its eigenvalues by cyclic Jacobi rotations (``a`` is overwritten). False where an
    entry is not finite (numpy's cond is then NaN or inf)."""
    for p in range(n):
        for q in range(n):
            if not math.isfinite(a[p, q]):
                return False
    _jacobi(a, n)
    lo = math.inf
    hi = 0.0
    for p in range(n):
        v = abs(a[p, p])
        lo = min(lo, v)
        hi = max(hi, v)
    return hi < limit * lo  # False for NaN, for a zero eigenvalue and for the zero matrix


@numba.njit(cache=True, nogil=True)
def _cond_below(a, n, limit):  # pragma: no cover - compiled
    """:func:`_sym_eig_abs_ratio_ok` (``a`` overwritten), answered first from the
    closed-form eigenvalues where they leave no doubt: a ratio below 1e5 there. Their
    error is at most ~1e-7 of the largest (sqrt(eps), where two eigenvalues are
    close), so the true ratio is then far below any ``limit`` >= 1e6; otherwise the
    Jacobi rotations decide, as numpy's SVD would."""
    for p in range(n):
        for q in range(n):
            if not math.isfinite(a[p, q]):
                return False
    if limit >= 1e6:
        if n == 2:
            mean = 0.5 * (a[0, 0] + a[1, 1])
            rad = math.hypot(0.5 * (a[0, 0] - a[1, 1]), a[0, 1])
            lo = min(abs(mean - rad), abs(mean + rad))
            hi = max(abs(mean - rad), abs(mean + rad))
            if hi < 1e5 * lo:
                return True
        else:  # the trigonometric solution of the characteristic cubic
            p1 = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
            q = (a[0, 0] + a[1, 1] + a[2, 2]) / 3.0
            d0, d1, d2 = a[0, 0] - q, a[1, 1] - q, a[2, 2] - q
            p = math.sqrt((d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * p1) / 6.0)
            if p > 0.0:
                # det((A - q I) / p) / 2
                det = (d0 * (d1 * d2 - a[1, 2] * a[1, 2])
                       - a[0, 1] * (a[0, 1] * d2 - a[1, 2] * a[0, 2])
                       + a[0, 2] * (a[0, 1] * a[1, 2] - d1 * a[0, 2]))  # fmt: skip
                r = min(max(det / (2.0 * p * p * p), -1.0), 1.0)
                phi = math.acos(r) / 3.0
                e1 = q + 2.0 * p * math.cos(phi)
                e3 = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
                e2 = 3.0 * q - e1 - e3
                lo = min(abs(e1), abs(e2), abs(e3))
                hi = max(abs(e1), abs(e2), abs(e3))
                if hi < 1e5 * lo:
                    return True
    return _sym_eig_abs_ratio_ok(a, n, limit)


@numba.njit(cache=True, nogil=True)
def _gesv(a, b, n):  # pragma: no cover - compiled
    """Solve a x = b in place (b <- x) by Gaussian elimination with partial pivoting."""
    for col in range(n):
        piv = col
        for r in range(col + 1, n):
            if abs(a[r, col]) > abs(a[piv, col]):
                piv = r
        if piv != col:
            for c in range(n):
                a[col, c], a[piv, c] = a[piv, c], a[col, c]
            b[col], b[piv] = b[piv], b[col]
        for r in range(col + 1, n):
            f = a[r, col] / a[col, col]
            for c in range(col, n):
                a[r, c] -= f * a[col, c]
            b[r] -= f * b[col]
    for r in range(n - 1, -1, -1):
        v = b[r]
        for c in range(r + 1, n):
            v -= a[r, c] * b[c]
        b[r] = v / a[r, r]


@numba.njit(cache=True, nogil=True)
def _decouple_fits(sums, h1, limit):  # pragma: no cover - compiled
    n = sums.shape[0]
    x3 = np.full((n, 3), np.nan)
    x2 = np.full((n, 2), np.nan)
    rss = np.full((n, 2), np.nan)
    m = np.empty((3, 3))
    e = np.empty((3, 3))
    g = np.empty(3)
    x = np.empty(3)
    for i in range(n):
        s = sums[i]
        hi = h1[i]
        # unknowns (U, h_1,i W, c = h_1,i dtheta/dt); columns f_h, -f_h h_u,j / h_1,i,
        # f_theta / h_1,i: the sums of j's terms scaled by the point's own h_1,i
        m[0, 0] = s[0]
        m[0, 1] = m[1, 0] = -s[1] / hi
        m[0, 2] = m[2, 0] = s[2] / hi
        m[1, 1] = s[3] / (hi * hi)
        m[1, 2] = m[2, 1] = -s[4] / (hi * hi)
        m[2, 2] = s[5] / (hi * hi)
        g[0] = s[6]
        g[1] = -s[7] / hi
        g[2] = s[8] / hi
        tt = s[9]
        e[:, :] = m
        if _cond_below(e, 3, limit):
            e[:, :] = m
            for r in range(3):
                x[r] = -g[r]
            _gesv(e, x, 3)
            x3[i] = x
            rss[i, 0] = tt + (g[0] * x[0] + g[1] * x[1] + g[2] * x[2])
        e[:2, :2] = m[1:, 1:]
        if _cond_below(e, 2, limit):
            e[:2, :2] = m[1:, 1:]
            x[0] = -g[1]
            x[1] = -g[2]
            _gesv(e, x, 2)
            x2[i, 0] = x[0]
            x2[i, 1] = x[1]
            rss[i, 1] = tt + (g[1] * x[0] + g[2] * x[1])
    return x3, x2, rss


def decouple_fits(sums: NDArray, h1: NDArray, *, limit: float = 1e8) -> tuple[NDArray, ...]:
    """Solve both models of the two-model test from :func:`decouple_sums`.

    Returns ``x3`` (N, 3): (U, h_1 W, h_1 dtheta/dt) of the decoupled model;
    ``x2`` (N, 2): (h_1 W, h_1 dtheta/dt) of the coupled one (U = 0); ``rss``
    (N, 2): the weighted residual sums of both, min sum w (A x + t)^2 = t^T t + g . x.
    NaN rows where a normal matrix's condition number is not below ``limit``.
    """
    return _decouple_fits(
        np.ascontiguousarray(sums, dtype=np.float64),
        np.ascontiguousarray(h1, dtype=np.float64),
        float(limit),
    )


@numba.njit(cache=True, nogil=True, inline="always")
def _heap_push(hd, hj, m, d2, j):  # pragma: no cover - compiled
    """Add (d2, j) to the max-heap hd[:m], hj[:m]."""
    pos = m
    while pos > 0:
        parent = (pos - 1) // 2
        if hd[parent] >= d2:
            break
        hd[pos] = hd[parent]
        hj[pos] = hj[parent]
        pos = parent
    hd[pos] = d2
    hj[pos] = j


@numba.njit(cache=True, nogil=True, inline="always")
def _heap_replace_top(hd, hj, m, d2, j):  # pragma: no cover - compiled
    """Replace the top of the max-heap hd[:m], hj[:m] by (d2, j)."""
    pos = 0
    while True:
        child = 2 * pos + 1
        if child >= m:
            break
        if child + 1 < m and hd[child + 1] > hd[child]:
            child += 1
        if hd[child] <= d2:
            break
        hd[pos] = hd[child]
        hj[pos] = hj[child]
        pos = child
    hd[pos] = d2
    hj[pos] = j


@numba.njit(cache=True, nogil=True)
def _cell_knn(x, y, rows, k, radius, split):  # pragma: no cover - compiled
    n = x.size
    dist = np.full((n, k), np.inf)
    idx = np.full((n, k), n, dtype=np.int64)
    tie = np.zeros(n, np.bool_)
    if n == 0:
        return dist, idx, tie
    cell = radius / split
    x0 = x.min()
    y0 = y.min()
    gw = int((x.max() - x0) / cell) + 1
    gh = int((y.max() - y0) / cell) + 1
    cx = np.empty(n, np.int64)
    cy = np.empty(n, np.int64)
    start = np.zeros(gw * gh + 1, np.int64)
    for j in range(n):
        cx[j] = min(int((x[j] - x0) / cell), gw - 1)
        cy[j] = min(int((y[j] - y0) / cell), gh - 1)
        start[cy[j] * gw + cx[j] + 1] += 1
    for c in range(gw * gh):
        start[c + 1] += start[c]
    order = np.empty(n, np.int64)
    fill = start[:-1].copy()
    for j in range(n):  # points by cell, in index order within a cell
        c = cy[j] * gw + cx[j]
        order[fill[c]] = j
        fill[c] += 1
    xs = x[order]  # the coordinates in cell order: a cell's candidates are contiguous
    ys = y[order]
    r2 = radius * radius
    hd = np.empty(k)  # one row's nearest so far, a max-heap on the squared distance
    hj = np.empty(k, np.int64)
    for t in range(rows.size):
        i = rows[t]
        xi = x[i]
        yi = y[i]
        m = 0
        bound = r2
        ties = 0  # points outside a full heap at its top's squared distance
        # the cells ring by ring around the point's own (nearest first, so the bound
        # shrinks early and prunes the outer cells)
        for ring in range(split + 1):
            for off in range(8 * ring if ring else 1):
                if ring == 0:
                    ox, oy = 0, 0
                else:  # walk the square ring's 8 ring cells
                    side, step = off // (2 * ring), off % (2 * ring)
                    if side == 0:
                        ox, oy = -ring + step, -ring
                    elif side == 1:
                        ox, oy = ring, -ring + step
                    elif side == 2:
                        ox, oy = ring - step, ring
                    else:
                        ox, oy = -ring, ring - step
                gx = cx[i] + ox
                gy = cy[i] + oy
                if gx < 0 or gy < 0 or gx >= gw or gy >= gh:
                    continue
                ex = max(x0 + gx * cell - xi, xi - (x0 + (gx + 1) * cell), 0.0)
                ey = max(y0 + gy * cell - yi, yi - (y0 + (gy + 1) * cell), 0.0)
                if ex * ex + ey * ey > bound:  # nothing in this cell can enter or tie
                    continue
                c = gy * gw + gx
                for s in range(start[c], start[c + 1]):
                    dx = xs[s] - xi
                    dy = ys[s] - yi
                    d2 = dx * dx + dy * dy
                    if d2 < bound:
                        if m < k:
                            _heap_push(hd, hj, m, d2, order[s])
                            m += 1
                        else:  # the top (the k-th) drops out
                            last = hd[0]
                            _heap_replace_top(hd, hj, k, d2, order[s])
                            ties = ties + 1 if last == hd[0] else 0
                        if m == k:
                            bound = hd[0]
                    elif d2 == bound and m == k:
                        ties += 1
        for q in range(m - 1, -1, -1):  # pop the farthest into the last place
            dist[i, q] = math.sqrt(hd[0])
            idx[i, q] = hj[0]
            _heap_replace_top(hd, hj, q, hd[q], hj[q])
        # another point at the same place (which comes first), or one outside the list
        # at the k-th's distance (which of them is in)
        tie[i] = (m >= 2 and dist[i, 1] == 0.0) or ties > 0
    return dist, idx, tie


def cell_knn(
    x: NDArray, y: NDArray, k: int, radius: float, rows: NDArray | None = None, *, split: int = 2
) -> tuple[NDArray, NDArray, NDArray]:
    """The ``k`` nearest of the points (x, y) closer than ``radius`` to each, nearest first.

    As ``scipy.spatial.cKDTree(pts).query(pts[rows], k, distance_upper_bound=radius)``
    for finite coordinates, on the full (N, k) rows (the rows not in ``rows``, and
    the places beyond the neighbours found, hold distance inf and index N), with
    the cells ``radius / split`` wide. Returns (dist, idx, tie): ``tie`` (N,) bool
    marks the rows whose answer depends on how equal distances are ordered, which
    the tree decides by its own traversal: a point left out at the k-th's
    distance (pixel coordinates make equal distances common), or a second point
    at distance 0. Elsewhere the same neighbours at the same distances
    (the order within equal distances aside).
    """
    x = np.ascontiguousarray(x, dtype=np.float64).ravel()
    y = np.ascontiguousarray(y, dtype=np.float64).ravel()
    rows = np.arange(x.size) if rows is None else np.ascontiguousarray(rows, dtype=np.int64)
    return _cell_knn(x, y, rows, int(k), float(radius), int(split))


#: :func:`gain_sums`'s local models: unknowns (a, h_1,i b, beta), (a, h_1,i b, u a, u h_1,i b,
#: beta), the decoupled (U, h_1,i W, h_1,i b, beta) of omniflow.solve.decoupled, the decoupled
#: with a gain varying linearly across the pool (U, h_1,i W, h_1,i b, beta, beta_u, beta_h),
#: and the two coupled models with that gain, (a, h_1,i b, beta, beta_u, beta_h) and
#: (a, h_1,i b, u a, u h_1,i b, beta, beta_u, beta_h).
GAIN_MODELS = {"constant": 0, "linear": 1, "decoupled": 2, "decoupled_linear": 3,
               "constant_lingain": 4, "linear_lingain": 5}  # fmt: skip


@numba.njit(cache=True, nogil=True, inline="always")
def _add_row6(acc, vacc, ww, r0, r1, r2, r3, r4, r5, y):  # pragma: no cover - compiled
    # one weighted row into a 6 x 6 Gram (upper triangle) and X^T W y, unrolled (the
    # generic loop over a run-time P is twice as slow), in the generic loop's order
    wc = ww * r0
    vacc[0] += wc * y
    acc[0, 0] += wc * r0
    acc[0, 1] += wc * r1
    acc[0, 2] += wc * r2
    acc[0, 3] += wc * r3
    acc[0, 4] += wc * r4
    acc[0, 5] += wc * r5
    wc = ww * r1
    vacc[1] += wc * y
    acc[1, 1] += wc * r1
    acc[1, 2] += wc * r2
    acc[1, 3] += wc * r3
    acc[1, 4] += wc * r4
    acc[1, 5] += wc * r5
    wc = ww * r2
    vacc[2] += wc * y
    acc[2, 2] += wc * r2
    acc[2, 3] += wc * r3
    acc[2, 4] += wc * r4
    acc[2, 5] += wc * r5
    wc = ww * r3
    vacc[3] += wc * y
    acc[3, 3] += wc * r3
    acc[3, 4] += wc * r4
    acc[3, 5] += wc * r5
    wc = ww * r4
    vacc[4] += wc * y
    acc[4, 4] += wc * r4
    acc[4, 5] += wc * r5
    wc = ww * r5
    vacc[5] += wc * y
    acc[5, 5] += wc * r5


@numba.njit(cache=True, nogil=True, inline="always")
def _add_row7(acc, vacc, ww, r0, r1, r2, r3, r4, r5, r6, y):  # pragma: no cover - compiled
    # one weighted row into a 7 x 7 Gram (upper triangle) and X^T W y, unrolled as
    # _add_row6 (the coupled linear flow model with the linear gain)
    wc = ww * r0
    vacc[0] += wc * y
    acc[0, 0] += wc * r0
    acc[0, 1] += wc * r1
    acc[0, 2] += wc * r2
    acc[0, 3] += wc * r3
    acc[0, 4] += wc * r4
    acc[0, 5] += wc * r5
    acc[0, 6] += wc * r6
    wc = ww * r1
    vacc[1] += wc * y
    acc[1, 1] += wc * r1
    acc[1, 2] += wc * r2
    acc[1, 3] += wc * r3
    acc[1, 4] += wc * r4
    acc[1, 5] += wc * r5
    acc[1, 6] += wc * r6
    wc = ww * r2
    vacc[2] += wc * y
    acc[2, 2] += wc * r2
    acc[2, 3] += wc * r3
    acc[2, 4] += wc * r4
    acc[2, 5] += wc * r5
    acc[2, 6] += wc * r6
    wc = ww * r3
    vacc[3] += wc * y
    acc[3, 3] += wc * r3
    acc[3, 4] += wc * r4
    acc[3, 5] += wc * r5
    acc[3, 6] += wc * r6
    wc = ww * r4
    vacc[4] += wc * y
    acc[4, 4] += wc * r4
    acc[4, 5] += wc * r5
    acc[4, 6] += wc * r6
    wc = ww * r5
    vacc[5] += wc * y
    acc[5, 5] += wc * r5
    acc[5, 6] += wc * r6
    wc = ww * r6
    vacc[6] += wc * y
    acc[6, 6] += wc * r6


@numba.njit(cache=True, nogil=True)
def _gain_sums(idx, w, rows, f1_h, f1_th, f1_t, f2_h, f2_th, f2_t, f1, f2, h1, h2, th, model,
               scale):  # pragma: no cover - compiled  # fmt: skip
    n, kk = idx.shape
    npt = h1.size
    p = (3, 5, 4, 6, 5, 7)[model]
    M = np.zeros((n, p, p))
    v = np.zeros((n, p))
    yy = np.zeros(n)
    powers = np.zeros((n, 3))
    x0 = np.zeros((n, 2, p))
    y0 = np.zeros((n, 2))
    row = np.zeros(p)
    acc = np.zeros((p, p))  # the decoupled models' sums of one pool (local: faster)
    vacc = np.zeros(p)
    two_pi = 2.0 * math.pi
    for m in range(n):
        i = rows[m]
        hi = h1[i]
        acc[:] = 0.0
        vacc[:] = 0.0
        # sum_j w u^m of the two units' products of p (radial), q (tangential), g (-f,
        # the gain's column) and y (-f_t): the linear model's matrix is made of these
        s_pp0 = s_pp1 = s_pp2 = s_pq0 = s_pq1 = s_pq2 = s_qq0 = s_qq1 = s_qq2 = 0.0
        s_pg0 = s_pg1 = s_qg0 = s_qg1 = s_gg = 0.0
        s_py0 = s_py1 = s_qy0 = s_qy1 = s_gy = s_yy = 0.0
        w0 = w1 = w2 = 0.0
        for s in range(kk):
            j = idx[m, s]
            ww = w[m, s]
            if j >= npt:  # no neighbour: its terms are zero (numpy's zero sentinel)
                continue
            rel = h1[j] / hi  # the radial flow scales with h_1 on one surface
            u = 0.0
            if model != 0 and model != 2:  # the tangential offset, as numpy's floor-mod wrap
                u = (((th[j] - th[i]) + math.pi) % two_pi - math.pi) * hi / scale
            dh = (h1[j] - hi) / scale  # the radial offset (models 3-5)
            if model >= 4:  # eq. (9); eq. (15) with eq. (14); (beta + beta_u u + beta_h dh) f
                g = p - 3
                for unit in range(2):
                    if unit == 0:
                        pr, fq, ft, fu = f1_h[j] * rel, f1_th[j], f1_t[j], f1[j]
                    else:
                        pr = (h2[j] / h1[j]) * f2_h[j] * rel
                        fq, ft, fu = f2_th[j], f2_t[j], f2[j]
                    row[0] = pr
                    row[1] = fq / hi
                    if model == 5:
                        row[2] = pr * u
                        row[3] = row[1] * u
                    row[g] = -fu
                    row[g + 1] = -fu * u
                    row[g + 2] = -fu * dh
                    y = -ft
                    if s == 0:
                        for c in range(p):
                            x0[m, unit, c] = row[c]
                        y0[m, unit] = y
                    s_yy += ww * y * y
                    if model == 5:
                        _add_row7(acc, vacc, ww, row[0], row[1], row[2], row[3], row[4],
                                  row[5], row[6], y)  # fmt: skip
                        continue
                    for c in range(p):
                        wc = ww * row[c]
                        vacc[c] += wc * y
                        for d in range(c, p):
                            acc[c, d] += wc * row[d]
                w0 += ww
                w1 += ww * u
                w2 += ww * u * u
                continue
            if model >= 2:  # the decoupled model: dh_u = U - h_u W
                for unit in range(2):
                    if unit == 0:
                        fh, fq, ft, fu, hu = f1_h[j], f1_th[j], f1_t[j], f1[j], h1[j]
                    else:
                        fh, fq, ft, fu, hu = f2_h[j], f2_th[j], f2_t[j], f2[j], h2[j]
                    row[0] = fh
                    row[1] = -fh * hu / hi
                    row[2] = fq / hi
                    row[3] = -fu  # beta f on the right side
                    if model == 3:  # (beta + beta_u u + beta_h dh) f
                        row[4] = -fu * u
                        row[5] = -fu * dh
                    y = -ft
                    if s == 0:
                        for c in range(p):
                            x0[m, unit, c] = row[c]
                        y0[m, unit] = y
                    s_yy += ww * y * y
                    if model == 3:
                        _add_row6(acc, vacc, ww, row[0], row[1], row[2], row[3], row[4],
                                  row[5], y)  # fmt: skip
                        continue
                    for c in range(p):  # into the pool's own accumulators, same order
                        wc = ww * row[c]
                        vacc[c] += wc * y
                        for d in range(c, p):
                            acc[c, d] += wc * row[d]
                w0 += ww
                continue
            # eq. (9); eq. (15) with eq. (14)
            p1 = f1_h[j] * rel
            p2 = (h2[j] / h1[j]) * f2_h[j] * rel
            q1, q2 = f1_th[j] / hi, f2_th[j] / hi
            g1, g2 = -f1[j], -f2[j]
            y1, y2 = -f1_t[j], -f2_t[j]
            if s == 0:
                x0[m, 0, 0], x0[m, 0, 1], x0[m, 0, p - 1] = p1, q1, g1
                x0[m, 1, 0], x0[m, 1, 1], x0[m, 1, p - 1] = p2, q2, g2
                y0[m, 0], y0[m, 1] = y1, y2
            pp = ww * (p1 * p1 + p2 * p2)
            pq = ww * (p1 * q1 + p2 * q2)
            qq = ww * (q1 * q1 + q2 * q2)
            pg, qg = ww * (p1 * g1 + p2 * g2), ww * (q1 * g1 + q2 * g2)
            py, qy = ww * (p1 * y1 + p2 * y2), ww * (q1 * y1 + q2 * y2)
            s_pp0 += pp
            s_pq0 += pq
            s_qq0 += qq
            s_pg0 += pg
            s_qg0 += qg
            s_py0 += py
            s_qy0 += qy
            s_gg += ww * (g1 * g1 + g2 * g2)
            s_gy += ww * (g1 * y1 + g2 * y2)
            s_yy += ww * (y1 * y1 + y2 * y2)
            w0 += ww
            if model == 1:
                s_pp1 += pp * u
                s_pq1 += pq * u
                s_qq1 += qq * u
                s_pp2 += pp * u * u
                s_pq2 += pq * u * u
                s_qq2 += qq * u * u
                s_pg1 += pg * u
                s_qg1 += qg * u
                s_py1 += py * u
                s_qy1 += qy * u
                w1 += ww * u
                w2 += ww * u * u
        powers[m, 0], powers[m, 1], powers[m, 2] = w0, w1, w2
        if model >= 2:
            for c in range(p):
                v[m, c] = vacc[c]
                for d in range(c, p):
                    M[m, c, d] = acc[c, d]
            yy[m] = s_yy
        else:
            g = p - 1
            M[m, 0, 0], M[m, 0, 1], M[m, 1, 1] = s_pp0, s_pq0, s_qq0
            M[m, 0, g], M[m, 1, g], M[m, g, g] = s_pg0, s_qg0, s_gg
            v[m, 0], v[m, 1], v[m, g] = s_py0, s_qy0, s_gy
            yy[m] = s_yy
            if model == 1:  # unknowns (a, c, u a, u c, beta)
                M[m, 0, 2], M[m, 0, 3], M[m, 1, 2], M[m, 1, 3] = s_pp1, s_pq1, s_pq1, s_qq1
                M[m, 2, 2], M[m, 2, 3], M[m, 3, 3] = s_pp2, s_pq2, s_qq2
                M[m, 2, g], M[m, 3, g] = s_pg1, s_qg1
                v[m, 2], v[m, 3] = s_py1, s_qy1
        for c in range(p):
            for d in range(c):
                M[m, c, d] = M[m, d, c]
    return M, v, yy, powers, x0, y0


def gain_sums(
    idx: NDArray,
    w: NDArray,
    rows: NDArray,
    derivs: tuple[NDArray, ...],
    f: tuple[NDArray, NDArray],
    h1: NDArray,
    h2: NDArray,
    theta: NDArray | None,
    *,
    model: str,
    scale: float,
) -> tuple[NDArray, ...]:
    """The weighted normal equations of eq. (9) and (15) with a gain per pool.

    Parameters
    ----------
    idx, w : ndarray, shape (n, K)
        The pools of the points ``rows`` (index N or more: no neighbour).
    rows : ndarray of int, shape (n,)
        The point each pool belongs to (its own h_1, theta).
    derivs : six ndarrays, shape (N,)
        f1_h, f1_theta, f1_t, f2_h, f2_theta, f2_t.
    f : two ndarrays, shape (N,)
        Each unit's image at the points.
    h1, h2 : ndarray, shape (N,)
    theta : ndarray, shape (N,), optional
        Azimuth (every model but ``"constant"`` and ``"decoupled"``).
    model : {"constant", "linear", "decoupled", "decoupled_linear", "constant_lingain", \
"linear_lingain"}
        The unknowns, :data:`GAIN_MODELS`.
    scale : float
        Length that scales the offsets u (tangential, every model with u) and
        dh = h_1,j - h_1,i (radial, the models with a gain varying linearly), pixels.

    Returns
    -------
    M : ndarray, shape (n, P, P)
        X^T W X over both units' rows of every neighbour (each carrying the
        neighbour's weight); row of unit u at neighbour j, unknowns as
        :data:`GAIN_MODELS`, the gain's column -f_u,j (``decoupled_linear`` and
        ``*_lingain``: then -f_u,j u_j and -f_u,j dh_j).
    v : ndarray, shape (n, P)
        X^T W y, y = -f_t.
    yy : ndarray, shape (n,)
        y^T W y.
    powers : ndarray, shape (n, 3)
        sum_j w, sum_j w u, sum_j w u^2 (the last two 0 but for ``linear`` and the
        ``*_lingain`` models).
    x0, y0 : ndarray, shapes (n, 2, P) and (n, 2)
        Both units' rows and right sides of each pool's neighbour 0.
    """
    f64 = [np.ascontiguousarray(v, dtype=np.float64) for v in (*derivs, *f, h1, h2)]
    th = np.zeros_like(f64[0]) if theta is None else np.ascontiguousarray(theta, dtype=np.float64)
    return _gain_sums(
        np.ascontiguousarray(idx, dtype=np.int64), np.ascontiguousarray(w, dtype=np.float64),
        np.ascontiguousarray(rows, dtype=np.int64), *f64, th, GAIN_MODELS[model], float(scale),
    )  # fmt: skip


@numba.njit(cache=True, nogil=True, inline="always")
def _cholesky_pivots_above(a, p, tiny):  # pragma: no cover - compiled
    """Whether every pivot of the Cholesky factorisation of the symmetric p x p ``a``
    (unit diagonal) exceeds ``tiny``; ``a``'s lower triangle is overwritten by the factor.
    A pivot d_k is the least eigenvalue's upper bound over the leading k x k block, so a
    pivot at or below ``tiny`` (computed to ~1e-14 of a unit diagonal) bounds the least
    eigenvalue of ``a`` below ``tiny`` plus that rounding; all above it: ``a`` is
    positive definite."""
    for k in range(p):
        d = a[k, k]
        for c in range(k):
            d -= a[k, c] * a[k, c]
        if not d > tiny:  # False for NaN too
            return False
        d = math.sqrt(d)
        a[k, k] = d
        for r in range(k + 1, p):
            s = a[r, k]
            for c in range(k):
                s -= a[r, c] * a[k, c]
            a[r, k] = s / d
    return True


@numba.njit(cache=True, nogil=True, inline="always")
def _solve_one(M, v, i, limit, positive, a, inv, sc, x):  # pragma: no cover - compiled
    """Solve pool i of :func:`small_solves` (``a``, ``inv``, ``sc`` workspace): x[i] set
    where every test passes. Returns (confidence, det, formed): ``det`` the determinant
    of the unit-diagonal form D^-1 M D^-1 (D = sqrt(diag M)); ``formed`` whether ``inv``
    now holds M^-1 (the positive test, the determinant's and a finite M passed)."""
    p = M.shape[1]
    for r in range(p):
        for c in range(p):
            if not math.isfinite(M[i, r, c]):
                return 0.0, 0.0, False
    for r in range(p):
        d = math.sqrt(abs(M[i, r, r]))
        sc[r] = d if d > 0.0 else 1.0
    if positive:
        # positive definite: every eigenvalue of the unit-diagonal form above 1e-12 of
        # the largest. Decided by a Cholesky factorisation and the inverse's trace
        # where they leave no doubt, else by Jacobi rotations (below)
        for r in range(p):
            for c in range(p):
                a[r, c] = M[i, r, c] / (sc[r] * sc[c])
        if not _cholesky_pivots_above(a, p, 1e-13):
            return 0.0, 0.0, False  # lambda_min < 1e-12 <= 1e-12 lambda_max (>= 1)
    for r in range(p):
        for c in range(p):
            a[r, c] = M[i, r, c] / (sc[r] * sc[c])  # unit diagonal
    # Gauss-Jordan with partial pivoting: the inverse and the determinant (the
    # product of the eigenvalues of the unit-diagonal matrix, each <= P)
    for r in range(p):
        for c in range(p):
            inv[r, c] = 1.0 if r == c else 0.0
    det = 1.0
    for col in range(p):
        piv = col
        for r in range(col + 1, p):
            if abs(a[r, col]) > abs(a[piv, col]):
                piv = r
        if piv != col:
            det = -det
            for c in range(p):
                a[col, c], a[piv, c] = a[piv, c], a[col, c]
                inv[col, c], inv[piv, c] = inv[piv, c], inv[col, c]
        d = a[col, col]
        det *= d
        if d == 0.0:
            break
        for c in range(p):
            a[col, c] /= d
            inv[col, c] /= d
        for r in range(p):
            if r != col:
                f = a[r, col]
                if f != 0.0:
                    for c in range(p):
                        a[r, c] -= f * a[col, c]
                        inv[r, c] -= f * inv[col, c]
    if positive:
        # positive definite, lambda_min >= 1 / trace(inverse) and lambda_max <= P (the
        # trace of the unit-diagonal form): sure where P / trace > 1e12 ... else the
        # rotations decide, as they did for every pool (the same answers, cheaper)
        tr = 0.0
        for r in range(p):
            tr += inv[r, r]
        if not tr * p * 1e-12 < 1.0:
            for r in range(p):
                for c in range(p):
                    a[r, c] = M[i, r, c] / (sc[r] * sc[c])
            _jacobi(a, p)
            lo, hi = math.inf, -math.inf
            for r in range(p):
                lo = min(lo, a[r, r])
                hi = max(hi, a[r, r])
            if not (lo > 1e-12 * hi and lo > 0.0):
                return 0.0, det, False
    elif not abs(det) > 1e-12:
        return 0.0, det, False
    for r in range(p):
        for c in range(p):
            inv[r, c] /= sc[r] * sc[c]  # M^-1 = D^-1 (D^-1 M D^-1)^-1 D^-1
    # the Schur complement on the first two unknowns is the inverse of M^-1's block:
    # the same eigenvectors, reciprocal eigenvalues
    ci = _pair_ratio(inv[0, 0], inv[1, 0], inv[1, 1])
    if ci >= limit and ci > 0.0:
        for r in range(p):
            acc = 0.0
            for c in range(p):
                acc += inv[r, c] * v[i, c]
            x[i, r] = acc
    return ci, det, True


@numba.njit(cache=True, nogil=True, inline="always")
def _pair_ratio(b00, b10, b11):  # pragma: no cover - compiled
    """lambda_min / lambda_max of the symmetric 2 x 2 [[b00, b10], [b10, b11]], 0 unless
    both are positive."""
    mean = 0.5 * (b00 + b11)
    rad = math.hypot(0.5 * (b00 - b11), b10)
    lo, hi = mean - rad, mean + rad
    return lo / hi if lo > 0.0 else 0.0


@numba.njit(cache=True, nogil=True)
def _small_solves(M, v, limit, positive):  # pragma: no cover - compiled
    n, p, _ = M.shape
    x = np.full((n, p), np.nan)
    conf = np.zeros(n)
    a = np.empty((p, p))
    inv = np.empty((p, p))
    sc = np.empty(p)
    for i in range(n):
        conf[i] = _solve_one(M, v, i, limit, positive, a, inv, sc, x)[0]
    return x, conf


def small_solves(
    M: NDArray, v: NDArray, min_conditioning: float, *, positive: bool = False
) -> tuple[NDArray, NDArray]:
    """Solve M x = v per point (P x P, P >= 2), with omniflow.solve.gain's tests.

    Parameters
    ----------
    M : ndarray, shape (N, P, P)
        Symmetric normal matrices.
    v : ndarray, shape (N, P)
    min_conditioning : float
        The least lambda_min / lambda_max of the information left on the first two
        unknowns once the others are free (the Schur complement).
    positive : bool
        Require M positive definite (its unit-diagonal form's eigenvalues all above
        1e-12 of the largest: a Cholesky factorisation and the inverse's trace bound
        them, Jacobi rotations decide where those bounds leave it open), else that
        form's determinant above 1e-12 in magnitude.

    Returns
    -------
    x : ndarray, shape (N, P)
        NaN where a test fails or an entry of M is not finite.
    confidence : ndarray, shape (N,)
        That Schur complement's lambda_min / lambda_max; 0 where it is not positive
        definite or M failed its test.
    """
    return _small_solves(
        np.ascontiguousarray(M, dtype=np.float64), np.ascontiguousarray(v, dtype=np.float64),
        float(min_conditioning), bool(positive),
    )  # fmt: skip


@numba.njit(cache=True, nogil=True)
def _nested_fits(M, v, yy, limit, drop):  # pragma: no cover - compiled
    n, p, _ = M.shape
    x = np.full((n, p), np.nan)
    conf = np.zeros(n)
    rss = np.full(n, np.nan)
    rss0 = np.full(n, np.nan)
    a = np.empty((p, p))
    inv = np.empty((p, p))
    sc = np.empty(p)
    e0, e1 = (1, 2) if drop == 0 else ((0, 2) if drop == 1 else (0, 1))
    for i in range(n):
        conf[i], det, formed = _solve_one(M, v, i, limit, False, a, inv, sc, x)
        if not (formed and math.isfinite(x[i, 0])):
            continue
        acc = 0.0
        for c in range(p):
            acc += x[i, c] * v[i, c]
        rss[i] = yy[i] - acc  # min of sum w (A x - y)^2 = y^T y - x . v
        # the fit without unknown ``drop``: its unit-diagonal determinant (Cramer:
        # det M_0 / det M = (M^-1)_dd, in the unit-diagonal form) and the Schur
        # complement on its first two unknowns (the inverse of its own inverse's block,
        # M_0^-1 = M^-1 less the rank-one term of unknown ``drop``), tested as its own
        # solve would be
        idd = inv[drop, drop]
        if not abs(det * idd * sc[drop] * sc[drop]) > 1e-12:
            continue
        b00 = inv[e0, e0] - inv[e0, drop] * inv[drop, e0] / idd
        b10 = inv[e1, e0] - inv[e1, drop] * inv[drop, e0] / idd
        b11 = inv[e1, e1] - inv[e1, drop] * inv[drop, e1] / idd
        ci = _pair_ratio(b00, b10, b11)
        if ci >= limit and ci > 0.0:
            rss0[i] = rss[i] + x[i, drop] * x[i, drop] / idd  # the RSS that unknown takes up
    return x, conf, rss, rss0


def nested_fits(
    M: NDArray, v: NDArray, yy: NDArray, min_conditioning: float, *, drop: int
) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """A fit and the fit without one of its unknowns, from one inverse (an F test's RSS).

    The fit is :func:`small_solves`'s (the same x and confidence, bit for bit). Dropping
    unknown k from a least-squares fit raises its residual sum of squares by
    x_k^2 / (M^-1)_kk, so the nested fit needs no second solve: its own tests (the
    determinant of its unit-diagonal form, det M times (M^-1)_kk in that form, and the
    Schur complement on its first two unknowns, from M^-1 less the rank-one term of
    unknown k) are made from the same inverse, to rounding as :func:`small_solves` would
    make them on M without row and column k. The difference of the two RSS then comes
    from x_k itself, not as the small difference of two large sums.

    Parameters
    ----------
    M, v, min_conditioning
        As :func:`small_solves` (not ``positive``).
    yy : ndarray, shape (N,)
        y^T W y of each pool.
    drop : int
        The unknown the nested fit leaves out (P - 1: the gain; 0: the decoupled U).

    Returns
    -------
    x, confidence
        As :func:`small_solves`.
    rss : ndarray, shape (N,)
        y^T W y - x . v; NaN where x is.
    rss_without : ndarray, shape (N,)
        The nested fit's; NaN where either fit fails its tests.
    """
    p = M.shape[1]
    if not 0 <= drop < p or p < 3:
        raise ValueError(f"nested_fits: drop = {drop} of {p} unknowns (P >= 3)")
    return _nested_fits(
        np.ascontiguousarray(M, dtype=np.float64), np.ascontiguousarray(v, dtype=np.float64),
        np.ascontiguousarray(yy, dtype=np.float64), float(min_conditioning), int(drop),
    )  # fmt: skip
