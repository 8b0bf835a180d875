"""omniflow.solve.monocular: cam1's flow alone where no stereo match is near.

Closed-form case: a textured wall (r = 2 m) turning about the rig's axis at
0.006 rad per frame in front of the still rig, 256 px; the true stereo matches
at 10 % of cam1's pixels (seeded), kept only on the half 0 <= theta < pi, so
the monocular solve answers on the other half. Tangential flow h_1 dtheta/dt
is 0.56 px per frame on average over the monocular points, radial 0.
Measured (``python -m pytest tests/omniflow/test_monocular.py -s`` prints
them): 1,739 points; mean estimated over mean true tangential flow 1.018;
mean radial flow 0.004 px; median end-point error 0.013 px (zero flow's:
0.56). The bounds below are about three times those figures' distance from
the truth; frozen frames (t + 1 = t) give a ratio near 0 and fail them.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from omniflow.config import OmniFlowConfig
from omniflow.matching import Matches
from omniflow.pipeline import estimate
from omniflow.result import MONOCULAR_COLUMNS
from tests.helpers.scenes import frames, paper_rig, sparse_true_matches, turning_wall_scene

YAW = 0.006  # rad per frame
GAP = 12.0  # px


@pytest.fixture(scope="module")
def half_matched_wall():
    rig = paper_rig(256)
    scene = turning_wall_scene(rig, YAW)
    f1, f2 = frames(scene, 2)
    m, gt = sparse_true_matches(scene, 0.1)
    half = np.sin(m.theta) >= 0.0
    m = Matches.from_polar(rig, m.theta[half], m.h1[half], m.h2[half])
    return rig, f1, f2, m, gt


def _figures(res, gt):
    mono = res.monocular
    iy, ix = mono["y"].astype(int), mono["x"].astype(int)  # points lie on pixel centres
    true_tan, true_rad = gt["gt.flow.hdtheta"][iy, ix], gt["gt.flow.dh"][iy, ix]
    est_tan = mono["h1"] * mono["dtheta_dt"]
    epe = np.hypot(est_tan - true_tan, mono["dh1_dt"] - true_rad)
    return {
        "n": int(mono["x"].size),
        "tangential_ratio": float(est_tan.mean() / true_tan.mean()),
        "radial_mean": float(mono["dh1_dt"].mean()),
        "epe_median": float(np.median(epe)),
        "true_tan_mean": float(true_tan.mean()),
    }


def test_monocular_flow_where_no_match_is_near(half_matched_wall):
    rig, f1, f2, m, gt = half_matched_wall
    res = estimate(f1, f2, rig, OmniFlowConfig(monocular_gap=GAP), matches=m)
    fig = _figures(res, gt)
    print(fig)
    mono = res.monocular
    dist, _ = cKDTree(np.column_stack([res["x"], res["y"]])).query(
        np.column_stack([mono["x"], mono["y"]])
    )
    assert np.all(dist > GAP)
    assert fig["n"] > 500
    assert fig["tangential_ratio"] == pytest.approx(1.0, abs=0.05)
    assert abs(fig["radial_mean"]) < 0.02
    assert fig["epe_median"] < 0.05


def test_frozen_frames_give_no_monocular_flow(half_matched_wall):
    """The mutation the tangential check must catch: frame t + 1 = frame t."""
    rig, f1, f2, m, gt = half_matched_wall
    frozen = estimate([f1[0], f1[0]], [f2[0], f2[0]], rig, OmniFlowConfig(monocular_gap=GAP),
                      matches=m)  # fmt: skip
    fig = _figures(frozen, gt)
    print(fig)
    assert abs(fig["tangential_ratio"]) < 0.05  # the 0.95-1.05 check above fails on it


def test_off_by_default(half_matched_wall):
    rig, f1, f2, m, _ = half_matched_wall
    res = estimate(f1, f2, rig, matches=m)
    assert res.monocular == {} and "monocular" not in res.timings


def test_no_point_is_an_empty_answer():
    """A constant frame has no significant point: every column empty, no error (the crash
    this caught: OpenCV's remap on an empty point list)."""
    rig = paper_rig(128)
    flat = np.full((128, 128), 0.3)
    with pytest.warns(UserWarning, match="no stereo matches"):
        res = estimate([flat, flat], [flat, flat], rig, OmniFlowConfig(monocular_gap=8.0))
    assert list(res.monocular) == list(MONOCULAR_COLUMNS)
    assert all(v.size == 0 for v in res.monocular.values())
