"""Confident answers (omniflow.result.confident): eq. (14) kept and every sigma finite.

Closed-form truth: the rising pillar of tests/omniflow/test_decoupled.py
(validation.synthdata.vertical_scene at 256 px, 2 mm per frame along the axis in front
of the static room, the true stereo matches at a seeded 10 % of cam1's pixels). Its
points that fail the eq. (14) test (``coupled`` = 0; 25 of the pillar's 30 and 4 of the
room's 2,103 there) must carry an infinite ``sigma_flow2`` and ``sigma_r`` and a finite
``sigma_flow1``, and are no confident answer; every coupled point keeps finite sigmas.
"""

from __future__ import annotations

import numpy as np
import pytest

from omniflow.config import OmniFlowConfig
from omniflow.pipeline import estimate
from omniflow.result import SIGMA_COLUMNS, confident
from tests.helpers.scenes import frames, sparse_true_matches
from validation.synthdata import vertical_scene


@pytest.fixture(scope="module")
def pillar_result():
    scene = vertical_scene(256, vz=0.002)
    f1, f2 = frames(scene, 2)
    m, gt = sparse_true_matches(scene, 0.1)
    res = estimate(f1, f2, scene.rig, OmniFlowConfig(decouple_tol=20.0), matches=m)
    iy, ix = res["y"].astype(int), res["x"].astype(int)  # true matches on pixel centres
    return res, gt["gt.object"][iy, ix] == 3


def test_flagged_points_have_infinite_cam2_and_range_sigma(pillar_result):
    res, on = pillar_result
    flagged = res["coupled"] == 0
    assert flagged[on].sum() >= 20  # the rising pillar is flagged (25 of 30 measured)
    s = res.sigma
    assert np.isposinf(s["sigma_flow2"][flagged]).all()
    assert np.isposinf(s["sigma_r"][flagged]).all()
    assert np.isfinite(s["sigma_flow1"]).all()  # cam1's flow does not rest on eq. (14)
    for k in SIGMA_COLUMNS:  # every coupled point keeps a finite, positive sigma
        assert (np.isfinite(s[k][~flagged]) & (s[k][~flagged] > 0)).all(), k


def test_confident_is_coupled_with_finite_sigmas(pillar_result):
    res, _ = pillar_result
    np.testing.assert_array_equal(res.confident, res["coupled"] == 1)
    # defined once: a finite sigma missing makes a coupled point not confident either
    sig = {k: v.copy() for k, v in res.sigma.items()}
    sig["sigma_r"][0] = np.nan
    want = res["coupled"] == 1
    want[0] = False
    np.testing.assert_array_equal(confident(res.columns, sig), want)
    assert not confident(res.columns, {}).any()  # no sigma predicted: none confident


def test_flow_csv_writes_inf_and_says_so(pillar_result, tmp_path):
    res, _ = pillar_result
    lines = res.to_csv(tmp_path / "flow.csv").read_text().splitlines()
    assert "sigma_r: m, predicted standard deviation of r; inf where coupled = 0" in lines[0]
    header = lines[1].split(",")
    rows = np.genfromtxt(lines[2:], delimiter=",")
    flagged = rows[:, header.index("coupled")] == 0
    assert flagged.any()
    assert np.isposinf(rows[flagged, header.index("sigma_flow2")]).all()
    assert np.isposinf(rows[flagged, header.index("sigma_r")]).all()
