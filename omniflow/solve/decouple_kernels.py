"""Compiled kernels (Numba) of the two-model test of eq. (14): sums, conditioning, solves.

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
    "decouple_fits",
    "decouple_sums",
    "jacobi",
]


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
def jacobi(a, n):  # pragma: no cover - compiled
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
    jacobi(a, n)
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
