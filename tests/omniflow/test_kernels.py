"""omniflow.solve.pooled_kernels: the compiled pooled-solver sums equal numpy's, and so does
the flow."""

from __future__ import annotations

import numpy as np
import pytest

import omniflow.solve.pooled
from omniflow.pipeline import OmniFlowConfig, estimate
from omniflow.solve.pooled import neighbourhoods
from omniflow.solve.pooled_kernels import pooled_sums
from omnisim.synthetic import Motion
from tests.helpers.scenes import frames, paper_rig, wall_scene


def numpy_pooled_sums(idx, w, derivs, h1, theta, *, relative, linear, scale):
    """The sums as omniflow.solve.pooled.pooled_solution formed them before the kernel (numpy)."""
    f1_h, f1_theta, f1_t, kf2_h, f2_theta, f2_t = derivs
    n = h1.size - 1
    hi = h1[:n, None]
    rel = h1[idx] / hi if relative else 1.0
    p1, p2 = f1_h[idx] * rel, kf2_h[idx] * rel
    q1, q2 = f1_theta[idx] / hi, f2_theta[idx] / hi
    t1, t2 = f1_t[idx], f2_t[idx]
    prods = np.stack([p1 * p1 + p2 * p2, p1 * q1 + p2 * q2, q1 * q1 + q2 * q2,
                      p1 * t1 + p2 * t2, q1 * t1 + q2 * t2], axis=-1)  # fmt: skip
    if linear:
        u = (((theta[idx] - theta[:n, None]) + np.pi) % (2 * np.pi) - np.pi) * hi / scale
        powers = np.stack([w, w * u, w * u * u], axis=1)
    else:
        powers = w[:, None, :]
    return powers @ prods, powers.sum(axis=-1)


def _problem(n: int, seed: int):
    """Matches on an annulus (theta wrapping at -pi), their pools and random derivatives."""
    rng = np.random.default_rng(seed)
    h = rng.uniform(20, 120, n)
    th = rng.uniform(-np.pi, np.pi, n)
    x, y = 128 + h * np.cos(th), 128 + h * np.sin(th)
    idx, w = neighbourhoods(x, y, k=24, radius=16.0, r=rng.uniform(1, 3, n), range_tol=0.3)
    derivs = tuple(
        np.append(rng.standard_normal(n) * s, 0.0) for s in (0.01, 1, 0.01, 0.01, 1, 0.005)
    )
    return idx, w, derivs, np.append(h, 1.0), np.append(th, 0.0)


# Largest |kernel - numpy| relative to the largest |sum| of that entry over all
# points, measured on these problems: 2.9e-16 to 4.0e-16 over the four models (the
# sums are added in another order: a running sum against a batched matrix product).
# 1e-13 leaves 250x room.
SUM_TOL = 1e-13


@pytest.mark.parametrize("linear", [True, False])
@pytest.mark.parametrize("relative", [True, False])
def test_sums_equal_numpy(linear, relative):
    idx, w, derivs, h1, th = _problem(2000, seed=5)
    kw = dict(relative=relative, linear=linear, scale=16.0)
    sums, wsum = pooled_sums(idx, w, derivs, h1, th, **kw)
    ref, ref_w = numpy_pooled_sums(idx, w, derivs, h1, th, **kw)
    assert sums.shape == ref.shape == (2000, 3 if linear else 1, 5)
    scale = np.max(np.abs(ref), axis=0, keepdims=True)
    assert np.max(np.abs(sums - ref) / scale) <= SUM_TOL
    np.testing.assert_allclose(wsum, ref_w, rtol=1e-13, atol=1e-13)


def test_sum_check_catches_an_unwrapped_angle():
    """The comparison above fails for sums whose u is not wrapped at theta = +-pi."""
    idx, w, derivs, h1, th = _problem(2000, seed=5)
    sums, _ = pooled_sums(idx, w, derivs, h1, th, relative=True, linear=True, scale=16.0)
    ref, _ = numpy_pooled_sums(idx, w, derivs, h1, th, relative=True, linear=True, scale=16.0)
    wrong = _unwrapped_sums(idx, w, derivs, h1, th, scale=16.0)
    scale = np.max(np.abs(ref), axis=0, keepdims=True)
    assert np.max(np.abs(sums - ref) / scale) <= SUM_TOL
    assert np.max(np.abs(sums - wrong) / scale) > 1e6 * SUM_TOL


def _unwrapped_sums(idx, w, derivs, h1, theta, *, scale):
    """numpy_pooled_sums (relative, linear) with u = (theta_j - theta_i) h_i / scale, unwrapped."""
    f1_h, f1_theta, f1_t, kf2_h, f2_theta, f2_t = derivs
    n = h1.size - 1
    hi = h1[:n, None]
    rel = h1[idx] / hi
    p1, p2 = f1_h[idx] * rel, kf2_h[idx] * rel
    q1, q2 = f1_theta[idx] / hi, f2_theta[idx] / hi
    t1, t2 = f1_t[idx], f2_t[idx]
    prods = np.stack([p1 * p1 + p2 * p2, p1 * q1 + p2 * q2, q1 * q1 + q2 * q2,
                      p1 * t1 + p2 * t2, q1 * t1 + q2 * t2], axis=-1)  # fmt: skip
    u = (theta[idx] - theta[:n, None]) * hi / scale
    return np.stack([w, w * u, w * u * u], axis=1) @ prods


def test_empty_pool():
    idx = np.zeros((0, 4), np.intp)
    derivs = tuple(np.zeros(1) for _ in range(6))
    sums, wsum = pooled_sums(
        idx,
        np.zeros((0, 4)),
        derivs,
        np.ones(1),
        np.zeros(1),
        relative=True,
        linear=True,
        scale=1.0,
    )
    assert sums.shape == (0, 3, 5) and wsum.shape == (0, 3)


# -- before / after: the flow columns with the kernel against those with numpy's sums ----

# Largest |kernel - numpy| over a column relative to the column's largest |value|,
# measured on these frames (128 px closed-form): 8.7e-14 (default), 6.4e-14 (eiv="none";
# earlier 7.5e-14 with a second pooled pass, since retired); on the rendered
# default scene at 512 px,
# 7 configs, the columns against the code before the kernel differed by 1.4e-13. 1e-10 leaves room
# for the solver's amplification on other frames; a real change of the sums (see the
# mutation test below) moves the flow by far more.
FLOW_TOL = 1e-10

CONFIGS = {
    "default": OmniFlowConfig(),
    "no noise correction": OmniFlowConfig(pooling={"eiv": "none"}),
}


@pytest.fixture(scope="module")
def pair():
    rig = paper_rig(128)
    f1, f2 = frames(wall_scene(rig, robot=Motion(velocity=(0.01, 0.005), yaw_rate=0.002)), 2)
    return f1, f2, rig


def _worst(a, b) -> float:
    worst = 0.0
    for k, v in b.columns.items():
        scale = float(np.max(np.abs(v))) if v.size else 0.0
        if scale > 0:
            worst = max(worst, float(np.max(np.abs(a[k] - v))) / scale)
    return worst


@pytest.mark.parametrize("name", list(CONFIGS))
def test_flow_columns_unchanged_by_the_kernel(name, pair, monkeypatch):
    f1, f2, rig = pair
    config = CONFIGS[name]
    fast = estimate(f1, f2, rig, config)
    monkeypatch.setattr(omniflow.solve.pooled, "pooled_sums", numpy_pooled_sums)
    before = estimate(f1, f2, rig, config)
    assert len(fast) == len(before) > 100
    assert _worst(fast, before) <= FLOW_TOL, name


def test_flow_check_catches_a_changed_sum(pair, monkeypatch):
    """Sums off by one part in 1e6 (a dropped term would be far more) fail FLOW_TOL."""
    f1, f2, rig = pair
    fast = estimate(f1, f2, rig)

    def perturbed(*args, **kw):
        sums, wsum = numpy_pooled_sums(*args, **kw)
        sums[..., 3] *= 1 + 1e-6  # the pf sums
        return sums, wsum

    monkeypatch.setattr(omniflow.solve.pooled, "pooled_sums", perturbed)
    assert _worst(fast, estimate(f1, f2, rig)) > 100 * FLOW_TOL


def numpy_solve_sums(sums, model, min_conditioning, *, positive=False, slopes_test=True):
    """omniflow.solve.pooled._solve_sums as it was in numpy (before
    omniflow.solve.pooled_kernels.pooled_solves);
    ``slopes_test`` False: the mutation of the check below (``positive`` without the test
    of the slopes' block)."""
    pp, pq, qq, pf, qf = (sums[:, :, c] for c in range(5))
    pd = np.ones(sums.shape[0], bool)
    m11, m12, m22 = pp[:, 0], pq[:, 0], qq[:, 0]
    v = [-pf[:, 0], -qf[:, 0]]
    if model != "constant":
        b11, b12, b22 = pp[:, 2], pq[:, 2], qq[:, 2]
        det_b = b11 * b22 - b12 * b12
        if slopes_test:
            pd &= (det_b > 0) & (b11 > 0)
        inv = 1.0 / np.where(det_b > 0, det_b, np.nan)
        k11, k12, k22 = pp[:, 1], pq[:, 1], qq[:, 1]
        c11, c12 = (k11 * b22 - k12 * b12) * inv, (k12 * b11 - k11 * b12) * inv
        c21, c22 = (k12 * b22 - k22 * b12) * inv, (k22 * b11 - k12 * b12) * inv
        m11 = m11 - (c11 * k11 + c12 * k12)
        m12 = m12 - (c11 * k12 + c12 * k22)
        m22 = m22 - (c21 * k12 + c22 * k22)
        v = [v[0] + (c11 * pf[:, 1] + c12 * qf[:, 1]), v[1] + (c21 * pf[:, 1] + c22 * qf[:, 1])]
    det = m11 * m22 - m12 * m12
    with np.errstate(all="ignore"):
        tr = m11 + m22
        disc = np.sqrt(np.maximum(0.25 * tr * tr - det, 0.0))
        lmax = 0.5 * tr + disc
        lmin = np.maximum(0.5 * tr - disc, 0.0)
        ratio = np.where(lmax > 0, lmin / lmax, 0.0)
        conf = np.nan_to_num(ratio)
        ok = (det > 0) & (conf >= min_conditioning) & (conf > 0)
        if positive:
            ok &= pd & (m11 > 0)
        a = np.where(ok, (m22 * v[0] - m12 * v[1]) / det, np.nan)
        c = np.where(ok, (m11 * v[1] - m12 * v[0]) / det, np.nan)
        lam_min = 0.5 * (m11 + m22) - np.sqrt(0.25 * (m11 - m22) ** 2 + m12 * m12)
    return a, c, conf, a * v[0] + c * v[1], lam_min


def _solve_cases(linear):
    """Pooled sums of random equations, random (mostly indefinite) ones, and the edge
    cases: a zero pool, a NaN entry, a singular slopes block, an infinite entry."""
    rng = np.random.default_rng(2)
    n = 500
    sums = rng.standard_normal((n, 3 if linear else 1, 5)) * rng.uniform(1e-3, 1e3, (n, 1, 1))
    # half of them true pooled sums of random equations (their blocks positive definite)
    half, k = n // 2, 24
    p, q, t = (rng.standard_normal((half, k)) * rng.uniform(0.1, 10.0, (half, 1)) for _ in "pqt")
    u, w = rng.uniform(-1.0, 1.0, (half, k)), rng.uniform(0.1, 1.0, (half, k))
    prods = np.stack([p * p, p * q, q * q, p * t, q * t], axis=-1)
    powers = [w * u**m for m in range(sums.shape[1])]
    sums[:half] = np.stack([(pw[..., None] * prods).sum(axis=1) for pw in powers], axis=1)
    sums[0] = 0.0
    sums[1, 0, 1] = np.nan
    sums[2, -1, :3] = 0.0
    sums[3, 0, 0] = np.inf
    return sums


@pytest.mark.parametrize("positive", [False, True])
@pytest.mark.parametrize("linear", [False, True])
def test_pooled_solves_equal_numpy_bit_for_bit(linear, positive):
    """omniflow.solve.pooled._solve_sums (the compiled omniflow.solve.pooled_kernels.pooled_solves)
    against its
    numpy form: every output identical, NaN for NaN."""
    from omniflow.solve.pooled import _solve_sums

    sums = _solve_cases(linear)
    model = "linear" if linear else "constant"
    got = _solve_sums(sums, model, 1e-3, positive=positive, explained=True)
    want = numpy_solve_sums(sums, model, 1e-3, positive=positive)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
    assert np.isfinite(got[0]).sum() > 100 and np.isnan(got[0]).sum() > 100


def test_pooled_solves_check_catches_a_missing_slopes_test():
    """The mutation: the corrected solve (``positive``) without the test that the slopes'
    block is positive definite: pools with an indefinite slopes block get a flow."""
    from omniflow.solve.pooled import _solve_sums

    sums = _solve_cases(True)
    got = _solve_sums(sums, "linear", 1e-3, positive=True)
    bad = numpy_solve_sums(sums, "linear", 1e-3, positive=True, slopes_test=False)
    assert (np.isnan(got[0]) & np.isfinite(bad[0])).sum() > 5  # measured 13
