"""Compiled kernels (Numba) of the brightness-gain fits: normal equations and small solves.

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

The kernels compile on first use; ``cache=True`` keeps the machine code
between runs where the package folder (or Numba's user cache) is writable.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

from omniflow.solve.decouple_kernels import jacobi

__all__ = [
    "GAIN_MODELS",
    "gain_sums",
    "nested_fits",
    "small_solves",
]


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
        yy[m] = s_yy
        sums = (s_pp0, s_pq0, s_qq0, s_pg0, s_qg0, s_gg, s_py0, s_qy0, s_gy,
                s_pp1, s_pq1, s_qq1, s_pp2, s_pq2, s_qq2, s_pg1, s_qg1, s_py1, s_qy1)  # fmt: skip
        _store_pool(M[m], v[m], model, p, acc, vacc, sums)
    return M, v, yy, powers, x0, y0


@numba.njit(cache=True, nogil=True)
def _store_pool(Mm, vm, model, p, acc, vacc, sums):  # pragma: no cover - compiled
    """One pool's normal matrix ``Mm`` (both triangles) and right side ``vm`` from
    :func:`_gain_sums`'s accumulators: the pool's own (``acc``, ``vacc``; the decoupled
    and linear-gain models) or the coupled models' sums of products (``sums``)."""
    if model >= 2:
        for c in range(p):
            vm[c] = vacc[c]
            for d in range(c, p):
                Mm[c, d] = acc[c, d]
    else:
        (s_pp0, s_pq0, s_qq0, s_pg0, s_qg0, s_gg, s_py0, s_qy0, s_gy,
         s_pp1, s_pq1, s_qq1, s_pp2, s_pq2, s_qq2, s_pg1, s_qg1, s_py1, s_qy1) = sums  # fmt: skip
        g = p - 1
        Mm[0, 0], Mm[0, 1], Mm[1, 1] = s_pp0, s_pq0, s_qq0
        Mm[0, g], Mm[1, g], Mm[g, g] = s_pg0, s_qg0, s_gg
        vm[0], vm[1], vm[g] = s_py0, s_qy0, s_gy
        if model == 1:  # unknowns (a, c, u a, u c, beta)
            Mm[0, 2], Mm[0, 3], Mm[1, 2], Mm[1, 3] = s_pp1, s_pq1, s_pq1, s_qq1
            Mm[2, 2], Mm[2, 3], Mm[3, 3] = s_pp2, s_pq2, s_qq2
            Mm[2, g], Mm[3, g] = s_pg1, s_qg1
            vm[2], vm[3] = s_py1, s_qy1
    for c in range(p):
        for d in range(c):
            Mm[c, d] = Mm[d, c]


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
            jacobi(a, p)
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
