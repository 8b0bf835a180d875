"""The pooled solver's test of no motion (``OmniFlowConfig.static_test``).

Checked against closed-form references:

* the statistic's null distribution: eq. (9) and (15) whose temporal derivatives are
  pure independent Gaussian noise (nothing moves), pooled with equal weights over the
  48 nearest points, give a Wald statistic that is chi-squared with 2 degrees of
  freedom, so the share of pools called still at ``static_test = tau`` is
  1 - exp(-tau / 2); measured 0.483 at tau = 2 ln 2 (expected 0.5) and 0.896 at
  tau = 2 ln 10 (0.9) over 3,000 points (constant and linear models alike);
* an exact flow field (dh_1/dt = alpha h_1, dtheta/dt = beta) with the same noise on
  f_t at a tenth of the flow's own f_t: no pool is called still, and the flow is the
  plain solution's;
* ``static_max_px``: on the same still field with the texture's contrast halved on half
  of the image (standard errors 0.1 and 0.2 px), a bound of sqrt(tau) times the median
  standard error keeps the faint half's pools (1.4 % called still against 88.7 %);
* the closed-form motion boundary of test_pooling.py with Gaussian noise (sigma 0.01)
  on the frames: a band turning in front of a static wall, the rig still. At
  ``static_test = 4`` the wall's mean end-point error falls from 0.032 px to 0.014 px
  (78 % of its points exactly still) and the band's mean tangential flow keeps 0.997 of
  the plain solution's (1.2 % of its points called still). Its cost shows at larger
  thresholds: at 8 the band keeps 0.987 (4.3 % still), at 16 0.951 (12 %).

Each check has a mutation that it catches (the tests named ``..._catches_...``).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import omniflow.solve.pooled as flow_module
from omniflow.config import OmniFlowConfig
from omniflow.pipeline import estimate
from omniflow.solve.pooled import neighbourhoods, pooled_solution
from tests.helpers.scenes import band_scene, frames, paper_rig, sparse_true_matches


def _equations(alpha: float, beta: float, noise: float, seed: int = 5, n: int = 3000):
    """Eq. (9) and (15) of the field dh_1/dt = alpha h_1, dtheta/dt = beta at random points
    of a polar image, f_t with independent Gaussian noise of sd ``noise``; equal-weight
    pools of the 48 nearest points."""
    rng = np.random.default_rng(seed)
    h1 = rng.uniform(30.0, 120.0, n)
    theta = rng.uniform(-np.pi, np.pi, n)
    h2 = h1 * rng.uniform(1.3, 1.8, n)
    x, y = 128.0 + h1 * np.cos(theta), 128.0 + h1 * np.sin(theta)
    f1h, f1th, f2h, f2th = (rng.normal(size=n) for _ in range(4))
    f1th, f2th = f1th * h1, f2th * h1  # grey per radian
    a, b = alpha * h1, np.full(n, beta)
    f1t = -(f1h * a + f1th * b) + noise * rng.normal(size=n)  # eq. (9)
    f2t = -((h2 / h1) * f2h * a + f2th * b) + noise * rng.normal(size=n)  # eq. (15)
    idx, w = neighbourhoods(x, y, k=48, radius=1e9)
    w = np.where(idx < n, 1.0, 0.0)  # equal weights: the statistic is chi-squared
    return (f1h, f1th, f1t, f2h, f2th, f2t, h1, h2), idx, w, theta, a, b


def _still_share(tau: float, model: str) -> float:
    args, idx, w, theta, _, _ = _equations(0.0, 0.0, 1.0)
    pa, pb, _ = pooled_solution(*args, idx, w, theta=theta, model=model, scale=16.0,
                                static_test=tau)  # fmt: skip
    return float(np.mean((pa == 0.0) & (pb == 0.0)))


@pytest.mark.parametrize("model", ["constant", "linear"])
@pytest.mark.parametrize("share", [0.5, 0.9])
def test_still_pools_follow_chi_squared_with_two_degrees(model, share):
    tau = -2.0 * math.log(1.0 - share)  # chi-squared(2): P(z < tau) = 1 - exp(-tau / 2)
    got = _still_share(tau, model)
    print(f"{model}: tau {tau:.3f} still {got:.3f} (expected {share})")
    # measured 0.483 / 0.896 (constant and linear); 3,000 points whose pools overlap,
    # so the share scatters by about 0.02 between seeds
    assert got == pytest.approx(share, abs=0.04)


def test_null_distribution_check_catches_a_one_unit_variance(monkeypatch):
    """Mutation: the pool's variance per row over its weight once (one unit's rows, not
    both): the statistic halves and the share called still at the median moves far off."""
    orig = flow_module.motion_statistic

    def wrong(pool, derivs6, sums, wsum, model, h1):
        stat, sd = orig(pool, derivs6, sums, wsum, model, h1)
        return 0.5 * stat, sd

    monkeypatch.setattr(flow_module, "motion_statistic", wrong)
    got = _still_share(2.0 * math.log(2.0), "linear")
    print(f"mutation: still {got:.3f}")
    assert abs(got - 0.5) > 0.04  # measured 0.750


def _moving_field(static_test: float | None):
    args0, *_ = _equations(0.004, -0.003, 0.0)
    f1t_rms = float(np.sqrt(np.mean(args0[2] ** 2)))
    args, idx, w, theta, _, _ = _equations(0.004, -0.003, 0.1 * f1t_rms)
    return pooled_solution(*args, idx, w, theta=theta, model="linear", scale=16.0,
                           static_test=static_test)[:2]  # fmt: skip


def test_a_moving_field_is_never_called_still():
    pa, pb = _moving_field(4.0)
    qa, qb = _moving_field(None)
    still = (pa == 0.0) & (pb == 0.0)
    print(f"still {still.mean():.4f}")
    assert not still.any()  # measured: none of 3,000
    np.testing.assert_array_equal(pa, qa)
    np.testing.assert_array_equal(pb, qb)


def test_moving_field_check_catches_a_reversed_sign(monkeypatch):
    """Mutation: the statistic's sign reversed (every pool below the threshold)."""
    orig = flow_module.motion_statistic
    monkeypatch.setattr(flow_module, "motion_statistic", lambda *a: (-orig(*a)[0], orig(*a)[1]))
    pa, pb = _moving_field(4.0)
    assert np.all((pa == 0.0) & (pb == 0.0))  # measured: all 3,000 still


@pytest.fixture(scope="module")
def noisy_band():
    rig = paper_rig(256)
    scene = band_scene(rig)
    f1, f2 = frames(scene, 2)
    rng = np.random.default_rng(11)
    f1 = [f + rng.normal(0.0, 0.01, f.shape).astype(np.float32) for f in f1]
    f2 = [f + rng.normal(0.0, 0.01, f.shape).astype(np.float32) for f in f2]
    m, gt = sparse_true_matches(scene, 0.1)
    return rig, f1, f2, m, gt


def _band_figures(res, gt):
    c = res.columns
    iy, ix = c["y"].astype(int), c["x"].astype(int)  # the true matches lie on pixel centres
    obj = np.rint(gt["gt.object"][iy, ix])
    tan = c["h1"] * c["dtheta_dt"]
    epe = np.hypot(c["dx"] - gt["gt.flow.dx"][iy, ix], c["dy"] - gt["gt.flow.dy"][iy, ix])
    still = (c["dh1_dt"] == 0.0) & (c["dtheta_dt"] == 0.0)
    wall, band = obj == 1, obj == 2
    return {
        "wall_epe": float(epe[wall].mean()),
        "wall_still": float(still[wall].mean()),
        "band_tan": float(tan[band].mean()),
        "band_still": float(still[band].mean()),
    }


def test_static_test_zeroes_the_still_wall_and_keeps_the_band(noisy_band):
    rig, f1, f2, m, gt = noisy_band
    plain = _band_figures(estimate(f1, f2, rig, OmniFlowConfig(), matches=m), gt)
    tested = _band_figures(
        estimate(f1, f2, rig, OmniFlowConfig(pooling={"static_test": 4.0}), matches=m), gt
    )
    print(f"plain {plain}\ntested {tested}")
    assert tested["wall_epe"] < 0.6 * plain["wall_epe"]  # measured 0.0138 against 0.0323 px
    assert tested["wall_still"] > 0.6  # measured 0.78 (plain: 0)
    assert tested["band_tan"] / plain["band_tan"] == pytest.approx(1.0, abs=0.01)  # 0.997
    assert tested["band_still"] < 0.05  # measured 0.012


def test_band_check_catches_a_test_that_calls_everything_still(noisy_band, monkeypatch):
    """Mutation: the pool's residual not divided by its rows (the statistic ~100 times too
    small): moving pools are called still, and the band checks above fail."""
    rig, f1, f2, m, gt = noisy_band
    orig = flow_module.motion_statistic

    def small(*args):
        stat, sd = orig(*args)
        return stat / 100.0, sd

    monkeypatch.setattr(flow_module, "motion_statistic", small)
    tested = _band_figures(
        estimate(f1, f2, rig, OmniFlowConfig(pooling={"static_test": 4.0}), matches=m), gt
    )
    print(f"mutation {tested}")
    assert tested["band_still"] > 0.05  # measured 1.0: every point still
    assert abs(tested["band_tan"] / 0.2711 - 1.0) > 0.01  # the plain band's 0.2711 px; 0


def _predicted_sd(args, idx) -> np.ndarray:
    """sigma / sqrt(lambda_min) of each equal-weight pool's normal matrix on (a, h_1 b) for
    the constant model, formed by its definition (sigma = 1: the noise of _equations)."""
    f1h, f1th, _, f2h, f2th, _, h1, h2 = args
    n = h1.size
    out = np.empty(n)
    for i in range(n):
        j = idx[i][idx[i] < n]
        rel = h1[j] / h1[i]
        rows = np.concatenate([np.column_stack([f1h[j] * rel, f1th[j] / h1[i]]),
                               np.column_stack([(h2[j] / h1[j]) * f2h[j] * rel,
                                                f2th[j] / h1[i]])])  # fmt: skip
        out[i] = 1.0 / np.sqrt(np.linalg.eigvalsh(rows.T @ rows)[0])
    return out


def _max_px_shares(monkeypatch=None, mutate=None) -> tuple[float, float]:
    """Share of the still field's pools called still at tau = 2 ln 10 (0.9 of them
    without the bound) among the pools whose predicted standard error is below the
    median and among those above it, with static_max_px = sqrt(tau) x that median; the
    texture's contrast halved on one half of the image, so the errors differ by two."""
    args, idx, w, theta, _, _ = _equations(0.0, 0.0, 1.0)
    # half the image (x < 128) with half the texture's contrast: twice the standard error
    faint = np.where(np.cos(theta) < 0.0, 0.5, 1.0)
    args = tuple(v * faint if i in (0, 1, 3, 4) else v for i, v in enumerate(args))
    sd = _predicted_sd(args, idx)
    tau = 2.0 * math.log(10.0)
    if mutate is not None:
        orig = flow_module.motion_statistic
        monkeypatch.setattr(flow_module, "motion_statistic", lambda *a: mutate(*orig(*a)))
    pa, pb, _ = pooled_solution(*args, idx, w, theta=theta, model="constant", scale=16.0,
                                static_test=tau,
                                static_max_px=math.sqrt(tau) * float(np.median(sd)))  # fmt: skip
    still = (pa == 0.0) & (pb == 0.0)
    small = sd < np.median(sd)
    return float(still[small].mean()), float(still[~small].mean())


def test_max_px_keeps_the_pools_that_cannot_see_that_flow():
    low, high = _max_px_shares()
    print(f"still: {low:.3f} of the better-conditioned half, {high:.3f} of the other")
    # measured 0.887 and 0.014 (0.9 and 0 for a known noise: the bound uses the pool's
    # own standard error, estimated from its residuals, within 10 % of the predicted one)
    assert low > 0.8
    assert high < 0.1


def test_max_px_check_catches_a_halved_standard_error(monkeypatch):
    """Mutation: the standard error halved (the residual variance counted over four times
    the pool's weight): the poorly conditioned pools are called still too."""
    low, high = _max_px_shares(monkeypatch, lambda stat, sd: (stat, 0.5 * sd))
    print(f"mutation: {low:.3f} {high:.3f}")
    assert high > 0.1  # measured 0.899
