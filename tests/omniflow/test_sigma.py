"""The predicted sigmas (omniflow.solve.sigma) against closed-form truth.

The noise part of the prediction is the covariance of the flow equations' least
squares: on a still closed-form wall with white noise of known sigma added, the
predicted flow sigma must match the spread of the estimate over noise realisations,
at the same matches (the true ones), for the direct solution (eq. 16) and the pooled
solver.
"""

from __future__ import annotations

import numpy as np
import pytest

from omniflow.config import OmniFlowConfig
from omniflow.pipeline import estimate
from omniflow.solve import sigma as sigma_mod
from omniflow.solve.sigma import SIGMA_COLUMNS, SigmaModel, flow_covariance
from tests.helpers.scenes import frames, paper_rig, true_matches, wall_scene

NOISE = 0.01  # grey, on images in [0, 1] (about 2.5 levels of 8 bits)
REALISATIONS = 24


@pytest.fixture(scope="module")
def still_wall():
    rig = paper_rig(128)
    scene = wall_scene(rig)
    f1, f2 = frames(scene, 2)
    m, _, _ = true_matches(scene, h_min=16.0)
    return rig, f1, f2, m


def _spread(rig, f1, f2, m, config, monkeypatch):
    """Per point: the predicted raw sigma (every constant neutral) and the RMS endpoint
    error over the realisations (the truth is no motion)."""
    neutral = SigmaModel()
    monkeypatch.setattr(sigma_mod, "MODELS", dict.fromkeys(sigma_mod.MODELS, neutral))
    rng = np.random.default_rng(26)
    sq1, sq2, pred1, pred2, n = 0.0, 0.0, [], [], None
    for _ in range(REALISATIONS):
        g1 = [f + rng.normal(0.0, NOISE, f.shape).astype(np.float32) for f in f1]
        g2 = [f + rng.normal(0.0, NOISE, f.shape).astype(np.float32) for f in f2]
        res = estimate(g1, g2, rig, config, matches=m)
        n = len(res) if n is None else n
        assert len(res) == n == m.theta.size  # every true match keeps its flow
        sq1 = sq1 + res["dx"] ** 2 + res["dy"] ** 2
        sq2 = sq2 + res["dx2"] ** 2 + res["dy2"] ** 2
        pred1.append(res.sigma["sigma_flow1"])
        pred2.append(res.sigma["sigma_flow2"])
    emp = np.sqrt(sq1 / REALISATIONS), np.sqrt(sq2 / REALISATIONS)
    return (np.mean(pred1, axis=0), np.mean(pred2, axis=0)), emp


# Measured (seed 26, 24 realisations, 128 px): the median ratio of the empirical RMS
# endpoint error to the predicted sigma was 0.934 for both units (eq. 14 ties cam2's
# to cam1's), the correlation of their logarithms over the points 0.957. The tolerance
# 0.15 on the ratio is the measured 0.066 with the ratio's sampling spread at 24
# realisations (a chi distribution of 48 degrees of freedom per point: 10 % per point,
# far less for a median over the points) and the noise estimate's own error added.
# The pooled solver's raw prediction is not tested so: its pools' rows share the
# fitted series' correlated noise, which the covariance treats as independent (the
# median ratio measured 2.72 on k-d pools, 1.40 on grid pools), so its scale comes from
# the suite's train split (docs/decisions/confidence.md).
def test_direct_sigma_matches_noise_spread(still_wall, monkeypatch):
    rig, f1, f2, m = still_wall
    config = OmniFlowConfig.paper()
    pred, emp = _spread(rig, f1, f2, m, config, monkeypatch)
    for p, e in zip(pred, emp, strict=True):
        ok = np.isfinite(p) & (p > 0)
        assert ok.mean() > 0.95
        ratio = np.median(e[ok] / p[ok])
        assert abs(ratio - 1.0) < 0.15, ratio
        # and per point, not only on the median: the ranks agree
        assert np.corrcoef(np.log(p[ok]), np.log(e[ok]))[0, 1] > 0.9  # measured 0.957


def test_sigma_columns_in_csv(still_wall, tmp_path):
    rig, f1, f2, m = still_wall
    res = estimate(f1, f2, rig, OmniFlowConfig(), matches=m)
    assert set(res.sigma) == set(SIGMA_COLUMNS)
    assert all(v.shape == res["x"].shape for v in res.sigma.values())
    assert "sigma_flow1" not in res.columns  # the columns stay as they were
    path = res.to_csv(tmp_path / "flow.csv")
    lines = path.read_text().splitlines()
    header = lines[1].split(",")
    assert header[-3:] == list(SIGMA_COLUMNS)
    assert "sigma_r: m, predicted standard deviation of r" in lines[0]


def test_covariance_hand_computed():
    """One point, the direct solution: rows (f1_h, f1_theta / h1), (k f2_h, f2_theta / h1)
    with k = h2 / h1. f1_h = 2, f1_theta = 0 and f2_h = 0, f2_theta = h1 = 10 give
    A = [[2, 0], [0, 1]] (k = 1.5 multiplies f2_h = 0), so Cov = diag(var1 / 4, var2)."""
    values = {"f1_h": 2.0, "f1_theta": 0.0, "f2_h": 0.0, "f2_theta": 10.0, "h1": 10.0, "h2": 15.0}
    cols = {k: np.array([v]) for k, v in values.items()}
    c_aa, c_ab, c_bb = flow_covariance(cols, (np.array([0.04]), np.array([0.09])))
    np.testing.assert_allclose([c_aa[0], c_ab[0], c_bb[0]], [0.01, 0.0, 0.09], atol=1e-15)
    # pooled over two copies of the point (weights 1): half the variance
    two = {k: np.repeat(v, 2) for k, v in cols.items()}
    idx, w = np.array([[0, 1], [1, 0]]), np.ones((2, 2))
    c_aa, _, c_bb = flow_covariance(two, (np.full(2, 0.04), np.full(2, 0.09)), idx, w)
    np.testing.assert_allclose([c_aa[0], c_bb[0]], [0.005, 0.045], atol=1e-15)


def test_stream_gives_the_same_sigmas(still_wall):
    """OmniFlowStream.push equals estimate on the same pair, the sigmas included."""
    from omniflow.stream import OmniFlowStream

    rig, f1, f2, _ = still_wall
    g1 = [
        f + np.float32(0.01) * np.sin(np.arange(f.size, dtype=np.float32)).reshape(f.shape)
        for f in f1
    ]  # fmt: skip  (some texture-free 'noise' so the level is not 0)
    config = OmniFlowConfig()
    ref = estimate(g1, f2, rig, config)
    with OmniFlowStream(rig, config) as stream:
        assert stream.push(g1[0], f2[0]) is None
        res = stream.push(g1[1], f2[1])
    np.testing.assert_array_equal(res["x"], ref["x"])
    for k in SIGMA_COLUMNS:
        np.testing.assert_allclose(res.sigma[k], ref.sigma[k], rtol=1e-12, err_msg=k)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_point_noise_on_stripes_reads_the_added_noise(seed):
    """At 512 px the noise is measured on stripes (a twelfth of the tiles): on a still
    textured image with white noise of sigma 0.01 added to each frame it reads 0.01.
    Measured (seeds 0-4): 0.00989-0.01006 from 90 tiles. Tolerance 5 %: each tile's
    variance has 2 x 98 degrees of freedom (7 rows of 16 less 14 terms, twice), 10 % in
    variance, 5 % in sigma; the median of 90 tiles about 0.7 %, so 5 % is 7 of those."""
    from scipy import ndimage

    from omniflow.solve.sigma import point_noise

    rng = np.random.default_rng(seed)
    base = ndimage.gaussian_filter(rng.random((512, 512)), 3) * 4.0
    base = 0.5 + base - base.mean()
    f0, f1 = (base + rng.normal(0.0, 0.01, base.shape) for _ in range(2))
    sigma, level = point_noise(f0, f1, np.ones(base.shape, bool), np.array([100.5]),
                               np.array([200.5]))  # fmt: skip
    assert level.tiles == 90
    assert sigma[0] == pytest.approx(0.01, rel=0.05)
