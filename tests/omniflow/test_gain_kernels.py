"""The compiled pieces of the gain fit (omniflow.solve.gain_kernels.gain_sums, small_solves) against
numpy written out from their definitions: the design of every pool built row by row and
solved with ``np.linalg`` (det, inv, eigvalsh), as omniflow.solve.gain did before the kernels.

Tolerances (measured with these seeds): the sums, in a different order, agree to 3e-16
of each pool's largest entry (tolerance 1e-13); the solves by Gauss-Jordan against
LAPACK's LU to 8e-14 relative (x) and 7e-12 (the confidence, a ratio of eigenvalues of the
inverse) on random systems scaled over four decades (tolerance 1e-9).
On the rendered approach, independent_movers and crossing pairs the whole gain fit agreed
with the numpy one to 1.8e-8 relative (F) and 1.4e-12 (flow), with the same NaN pattern
(/tmp/lead/s19/eq_gain.py, stop 19; docs/decisions/brightness_model.md).
"""

from __future__ import annotations

import numpy as np
import pytest

from omniflow.solve.gain_kernels import gain_sums, small_solves

N, K = 40, 12


def _pools(rng, n=N, k=K):
    idx = np.stack([np.arange(n)] + [rng.integers(0, n + 1, n) for _ in range(k - 1)], axis=1)
    w = rng.uniform(0.1, 1.0, (n, k))
    w[idx == n] = 0.0  # index n: no neighbour
    return idx, w


def _data(rng, n=N):
    derivs = tuple(rng.standard_normal(n) * s for s in (0.02, 2.0, 0.01, 0.03, 3.0, 0.01))
    f = (rng.uniform(0.2, 0.8, n), rng.uniform(0.2, 0.8, n))
    h1 = rng.uniform(40.0, 120.0, n)
    h2 = h1 * rng.uniform(1.5, 1.9, n)
    theta = rng.uniform(-np.pi, np.pi, n)  # pools straddle +-pi: the wrap matters
    return derivs, f, h1, h2, theta


def _numpy_design(derivs, f, h1, h2, theta, idx, i, s, model, scale):
    """Both units' rows and right sides of neighbour s of point i, from the definitions."""
    j = idx[i, s]
    if j >= h1.size:
        return None
    hi = h1[i]
    rel = h1[j] / hi
    u = np.angle(np.exp(1j * (theta[j] - theta[i]))) * hi / scale  # wrapped to (-pi, pi]
    rows, ys = [], []
    for unit, (fh, fq, ft), fu, hu in ((1, derivs[:3], f[0], h1), (2, derivs[3:], f[1], h2)):
        q = fq[j] / hi
        if model == "decoupled":
            cols = [fh[j], -fh[j] * hu[j] / hi, q]
        else:
            p = fh[j] * rel * (1.0 if unit == 1 else h2[j] / h1[j])  # eq. (9), eq. (15)
            cols = [p, q] + ([p * u, q * u] if model == "linear" else [])
        rows.append([*cols, -fu[j]])
        ys.append(-ft[j])
    return np.array(rows), np.array(ys), u


@pytest.mark.parametrize("model", ["constant", "linear", "decoupled"])
def test_gain_sums_equal_the_written_out_design(model):
    rng = np.random.default_rng(3)
    derivs, f, h1, h2, theta = _data(rng)
    idx, w = _pools(rng)
    scale = 20.0
    M, v, yy, powers, x0, y0 = gain_sums(idx, w, np.arange(N), derivs, f, h1, h2, theta,
                                         model=model, scale=scale)  # fmt: skip
    worst = 0.0
    for i in range(N):
        Mi, vi, yi, pw = np.zeros_like(M[i]), np.zeros_like(v[i]), 0.0, np.zeros(3)
        for s in range(K):
            d = _numpy_design(derivs, f, h1, h2, theta, idx, i, s, model, scale)
            if d is None:
                continue
            X, y, u = d
            Mi += w[i, s] * X.T @ X
            vi += w[i, s] * X.T @ y
            yi += w[i, s] * y @ y
            uu = u if model == "linear" else 0.0
            pw += w[i, s] * np.array([1.0, uu, uu * uu])
            if s == 0:
                np.testing.assert_allclose(x0[i], X, rtol=1e-12, atol=0)
                np.testing.assert_allclose(y0[i], y, rtol=1e-12, atol=0)
        for got, want in ((M[i], Mi), (v[i], vi), (yy[i], yi), (powers[i], pw)):
            err = np.max(np.abs(got - want) / (np.abs(want) + 1e-300 + np.abs(want).max()))
            worst = max(worst, err)
    assert worst < 1e-13, worst  # measured 2.5e-16


def test_gain_sums_check_catches_an_unwrapped_angle():
    """The mutation: u from theta_j - theta_i without the wrap (pools across +-pi) changes
    the linear model's sums far beyond rounding."""
    rng = np.random.default_rng(3)
    derivs, f, h1, h2, theta = _data(rng)
    idx, w = _pools(rng)
    args = (idx, w, np.arange(N), derivs, f, h1, h2)
    M, *_ = gain_sums(*args, theta, model="linear", scale=20.0)
    # the same angles shifted by 2 pi at half the points: the wrap must undo it
    shifted = theta + 2 * np.pi * (np.arange(N) % 2)
    M2, *_ = gain_sums(*args, shifted, model="linear", scale=20.0)
    np.testing.assert_allclose(M2, M, rtol=1e-10, atol=1e-12)
    # the mutation, written out: u without the wrap on the shifted angles
    hi = h1[:, None]
    u_plain = (np.append(shifted, 0.0)[idx] - shifted[:, None]) * hi / 20.0
    u_plain[idx == N] = 0.0
    wrapped = np.angle(np.exp(1j * (np.append(theta, 0.0)[idx] - theta[:, None]))) * hi / 20.0
    wrapped[idx == N] = 0.0
    # sum_j w u^2 of the power sums: without the wrap it is far off
    _, _, _, powers, _, _ = gain_sums(*args, shifted, model="linear", scale=20.0)
    np.testing.assert_allclose(powers[:, 2], (w * wrapped**2).sum(axis=1), rtol=1e-12)
    assert np.abs((w * u_plain**2).sum(axis=1) - powers[:, 2]).max() > 10.0


def _numpy_solve(M, v, limit, positive):
    """omniflow.solve.gain._solve as it was in numpy (stop 18)."""
    scale = np.sqrt(np.abs(np.einsum("npp->np", M)))
    scale = np.where(scale > 0, scale, 1.0)
    Ms = M / scale[:, :, None] / scale[:, None, :]
    with np.errstate(invalid="ignore"):
        if positive:
            lam = np.linalg.eigvalsh(np.nan_to_num(Ms))
            ok = (lam[:, 0] > 1e-12 * lam[:, -1]) & (lam[:, 0] > 0)
        else:
            ok = np.abs(np.linalg.det(np.nan_to_num(Ms))) > 1e-12
    ok &= np.isfinite(M).all(axis=(1, 2))
    Mi = np.linalg.inv(np.where(ok[:, None, None], M, np.eye(M.shape[1])))
    li = np.linalg.eigvalsh(Mi[:, :2, :2])
    with np.errstate(divide="ignore", invalid="ignore"):
        conf = np.where(li[:, 0] > 0, np.nan_to_num(li[:, 0] / li[:, 1]), 0.0)
    conf = np.where(ok, conf, 0.0)
    ok &= (conf >= limit) & (conf > 0)
    return np.where(ok[:, None], np.einsum("npq,nq->np", Mi, v), np.nan), conf


@pytest.mark.parametrize("positive", [False, True])
@pytest.mark.parametrize("p", [3, 4, 5])
def test_small_solves_equal_numpy(p, positive):
    rng = np.random.default_rng(p)
    n = 200
    A = rng.standard_normal((n, 3 * p, p)) * rng.uniform(0.01, 100.0, (n, 1, p))
    M = np.einsum("nkp,nkq->npq", A, A)
    v = rng.standard_normal((n, p))
    M[0] = 0.0  # the empty pool
    M[1, :, -1] = M[1, -1, :] = 0.0  # a singular one: the gain column all zero
    M[2, 0, 0] = np.nan  # a NaN entry
    M[3] = np.diag(np.r_[np.ones(p - 1), -1.0])  # indefinite, well conditioned on (a, c)
    M[4, 0, 1] = M[4, 1, 0] = np.sqrt(M[4, 0, 0] * M[4, 1, 1]) * (1 - 1e-9)  # (a, c) degenerate
    limit = 1e-3
    x, conf = small_solves(M, v, limit, positive=positive)
    xn, confn = _numpy_solve(M, v, limit, positive)
    assert np.array_equal(np.isnan(x), np.isnan(xn))
    fin = np.isfinite(xn).all(axis=1)
    assert fin.sum() > 150  # most random systems pass the tests
    np.testing.assert_allclose(x[fin], xn[fin], rtol=1e-9, atol=0)  # measured 8e-14
    np.testing.assert_allclose(conf, confn, rtol=1e-9, atol=1e-15)  # measured 7e-12
    assert np.isnan(x[:3]).all() and np.isnan(x[4]).all()
    assert np.isnan(x[3]).all() == positive  # only the positive test refuses it


def _random_systems(rng, n, p):
    A = rng.standard_normal((n, 3 * p, p)) * rng.uniform(0.01, 100.0, (n, 1, p))
    return np.einsum("nkp,nkq->npq", A, A), rng.standard_normal((n, p))


def _nearly_singular(rng, lam_min, p):
    """Symmetric positive semi-definite systems whose least eigenvalue is ``lam_min`` of a
    unit largest one (before small_solves scales them to a unit diagonal)."""
    out = []
    for lo in lam_min:
        q, _ = np.linalg.qr(rng.standard_normal((p, p)))
        lam = np.r_[lo, rng.uniform(0.2, 1.0, p - 2), 1.0]
        out.append((q * lam) @ q.T)
    return np.array(out)


def test_positive_test_equals_the_eigenvalues_near_its_threshold():
    """small_solves(positive=True) refuses exactly the systems whose unit-diagonal form has
    an eigenvalue at or below 1e-12 of the largest (numpy's eigvalsh as the reference):
    least eigenvalues from 1e-15 to 1e-9 of the largest, where the Cholesky pivots and the
    inverse's trace leave it open and the Jacobi rotations decide, and indefinite ones."""
    rng = np.random.default_rng(11)
    p = 5
    lam = np.r_[np.geomspace(1e-15, 1e-9, 120), -np.geomspace(1e-15, 1e-3, 30)]
    M = _nearly_singular(rng, lam, p)
    v = rng.standard_normal((M.shape[0], p))
    x, _ = small_solves(M, v, 0.0, positive=True)
    xn, _ = _numpy_solve(M, v, 0.0, True)
    sc = np.sqrt(np.einsum("npp->np", M))
    ev = np.linalg.eigvalsh(M / sc[:, :, None] / sc[:, None, :])
    ratio = ev[:, 0] / ev[:, -1]
    clear = np.abs(np.log(np.abs(ratio) / 1e-12)) > 0.05  # not within 5 % of the threshold
    assert clear.sum() > 140
    refused = np.isnan(x).all(axis=1)
    assert np.array_equal(refused[clear], np.isnan(xn).all(axis=1)[clear])
    # both sides of the threshold are there
    assert (~refused & (ratio < 1e-10)).sum() > 10 and (refused & (ratio > 0)).sum() > 10


def test_positive_test_check_catches_a_missing_jacobi_fallback(monkeypatch):
    """The mutation: the Cholesky pivots (all above 1e-13) taken as the whole test, without
    the rotations where the inverse's trace leaves it open: systems whose least eigenvalue
    is 1e-13 to 1e-12 of the largest then pass."""
    import omniflow.solve.gain_kernels as kernels

    rng = np.random.default_rng(11)
    p = 5
    M = _nearly_singular(rng, np.geomspace(2e-13, 5e-13, 5), p)
    v = rng.standard_normal((M.shape[0], p))

    def solve_py(M, v):  # the kernel run as Python, with the module's helpers
        x = np.full((M.shape[0], p), np.nan)
        a, inv, sc = np.empty((p, p)), np.empty((p, p)), np.empty(p)
        for i in range(M.shape[0]):
            kernels._solve_one.py_func(M, v, i, 0.0, True, a, inv, sc, x)
        return x

    assert np.isnan(small_solves(M, v, 0.0, positive=True)[0]).all()
    assert np.isnan(solve_py(M, v)).all()  # the Python run agrees with the compiled one
    monkeypatch.setattr(kernels, "jacobi", lambda a, n: None)  # rotations skipped
    assert np.isfinite(solve_py(M, v)).all()


def _nested_reference(M, v, yy, limit, drop):
    """The nested fit solved on its own: M and v without unknown ``drop``."""
    keep = np.delete(np.arange(M.shape[1]), drop)
    x0, _ = small_solves(M[:, keep][:, :, keep], v[:, keep], limit)
    return yy - np.einsum("np,np->n", x0, v[:, keep])


def _pools_with_conditioning_cases(rng, p):
    M, v = _random_systems(rng, 300, p)
    # the full fit conditioned on its first two unknowns, the fit without the last not:
    # unknown 0 nearly repeats the last (removing the last takes from unknown 0's
    # information) ... and with the first two nearly equal in the nested fit only
    M[5] = np.eye(p)
    M[5, 1, 1] = 0.01
    M[5, 0, -1] = M[5, -1, 0] = 0.99
    M[6] = np.eye(p)
    M[6, 0, 1] = M[6, 1, 0] = 0.9999  # both fits ill-conditioned on (a, c)
    M[7] = np.eye(p)
    M[7, 2, 2] = 0.001  # drop = 0: the nested fit's first two are (1, 2), the full's (0, 1)
    yy = np.einsum("np,np->n", v, v) * 10.0 + rng.uniform(1.0, 2.0, M.shape[0])
    return M, v, yy


@pytest.mark.parametrize("drop", ["last", 0])
@pytest.mark.parametrize("p", [3, 5, 6])
def test_nested_fits_equal_a_second_solve(p, drop):
    """nested_fits: the fit bit for bit small_solves's, the nested fit's RSS as solving it
    on its own (measured 4.7e-16 of the largest y^T W y; tolerance 1e-11), NaN exactly where
    that solve fails its tests, including a nested fit ill-conditioned on its first two
    unknowns where the full fit is not."""
    from omniflow.solve.gain_kernels import nested_fits

    rng = np.random.default_rng(p)
    M, v, yy = _pools_with_conditioning_cases(rng, p)
    k = p - 1 if drop == "last" else 0
    limit = 0.05
    x, conf, rss, rss0 = nested_fits(M, v, yy, limit, drop=k)
    xs, confs = small_solves(M, v, limit)
    assert np.array_equal(x, xs, equal_nan=True) and np.array_equal(conf, confs)
    want = np.where(np.isfinite(xs).all(axis=1), _nested_reference(M, v, yy, limit, k), np.nan)
    assert np.array_equal(np.isnan(rss0), np.isnan(want))
    assert np.isfinite(rss0).sum() > 100
    fin = np.isfinite(want)
    np.testing.assert_allclose(rss0[fin], want[fin], rtol=0, atol=1e-11 * yy[fin].max())
    np.testing.assert_allclose(rss, yy - np.einsum("np,np->n", xs, v), rtol=1e-13)
    if k == p - 1:
        assert np.isfinite(x[5]).all() and np.isnan(rss0[5])  # the nested test refuses
    else:
        assert np.isfinite(x[7]).all() and np.isnan(rss0[7])


def test_nested_fits_check_catches_a_missing_nested_test(monkeypatch):
    """The mutation: the nested fit's conditioning test left out (its RSS always taken):
    the system whose nested fit is ill-conditioned on (a, c) gets a finite RSS."""
    import omniflow.solve.gain_kernels as kernels

    p = 5
    M, v, yy = _pools_with_conditioning_cases(np.random.default_rng(p), p)
    M, v, yy = M[:10], v[:10], yy[:10]
    args = (M, v, yy, 0.05, p - 1)
    want = _nested_reference(M, v, yy, 0.05, p - 1)
    assert np.array_equal(np.isnan(kernels._nested_fits.py_func(*args)[3]), np.isnan(want))
    # the Python run calls the compiled full solve (its own test intact) and, for the
    # nested fit's test only, the module's _pair_ratio: every nested fit passes
    monkeypatch.setattr(kernels, "_pair_ratio", lambda b00, b10, b11: 1.0)
    got = kernels._nested_fits.py_func(*args)[3]
    assert np.isnan(want[5]) and np.isfinite(got[5])
