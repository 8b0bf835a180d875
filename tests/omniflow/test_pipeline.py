"""omniflow.pipeline: OmniFlowConfig, estimate, OmniFlowResult on closed-form scenes.

End to end (matching included), 256 x 256, robot driving (0.01, 0.005)
m/frame and turning 0.002 rad/frame, measured with
``python -m pytest tests/omniflow/test_pipeline.py -s`` (printed)::

    scene            config  matches  stereo outliers  r error  EPE cam1  DIS same pts  EPE cam2
    striped wall 2 m default    1134       0 %          0.02 %   0.0040     0.0324       0.010
    room texture 3 m default    1505       0 %          0.07 %   0.0021     0.1001       0.0036
    striped wall 2 m paper      4247      59 %          5.4 %    0.254      0.0448       0.494
    room texture 3 m paper      2510      95 %         47 %      0.604      0.0786       0.974

(Re-measured for the flow band chosen from the images, the errors-in-variables
correction and the paper's configuration as written, i.e. without rim fill and with
exact evaluation; before: EPE 0.0049 / 0.0115, cam2 0.012 / 0.019; paper 54 % / 92 %
outliers, 0.248 / 0.732 px. Before the flow series was rolled off towards its band's
edge (flow_taper): EPE 0.0038 / 0.0081, cam2 0.010 / 0.013.)
(EPE: median endpoint error in pixels per frame against the exact
displacement, true motion 0.20-0.25 px; r error: median relative error of
the range.) dr/dt of the default: median error 4e-5 and 5e-5 m/frame for
0.008 m/frame of motion. The more confident half of the points (by the
``confidence`` column) has 0.0032 / 0.0021 px median EPE.
"""

from __future__ import annotations

import numpy as np
import pytest

from omniflow.matching import sample_xy
from omniflow.pipeline import COLUMNS, OmniFlowConfig, OmniFlowResult, estimate
from omnisim.synthetic import Motion, SyntheticScene
from tests.helpers.scenes import dis_flow, frames, paper_rig, true_h_other, wall_scene

DRIVE_AND_TURN = Motion(velocity=(0.01, 0.005), yaw_rate=0.002)


@pytest.fixture(scope="module")
def rig256():
    return paper_rig(256)


@pytest.fixture(scope="module")
def moving_frames(rig256):
    scene = wall_scene(rig256, robot=DRIVE_AND_TURN)
    f1, f2 = frames(scene)
    return scene, f1, f2


def _true_motion(scene: SyntheticScene, unit, h_i, theta):
    """Exact displacement (dx, dy) over one frame of what ``unit`` sees at (h_i, theta)."""
    hit = scene.trace(unit, 0, h_i, theta)
    X1, Y1, Z1 = (np.full(h_i.shape, np.nan) for _ in range(3))
    for i, body in enumerate(scene.bodies):
        sel = hit.index == i
        X1[sel], Y1[sel], Z1[sel] = body.to_world(1, *body.to_local(0, hit.X[sel], hit.Y[sel],
                                                                    hit.Z[sel]))  # fmt: skip
    r1, th1, z1 = scene.world_to_rig(1, X1, Y1, Z1)
    x1, y1 = unit.project(r1, th1, z1)
    x0, y0 = unit.pixel_of_polar(h_i, theta)
    return x1 - x0, y1 - y0, r1 - hit.r


def test_estimate_columns_and_csv(moving_frames, rig256, tmp_path):
    _, f1, f2 = moving_frames
    res = estimate(f1, f2, rig256)
    assert isinstance(res, OmniFlowResult)
    assert set(COLUMNS) == set(res.columns)
    n = len(res)
    assert n > 100
    assert all(np.asarray(v).shape == (n,) for v in res.columns.values())
    assert {"fit", "grids", "match", "sample", "solve", "total"} <= set(res.timings)
    assert res.n_significant >= n
    path = res.to_csv(tmp_path / "out.csv")
    lines = path.read_text().splitlines()
    # the columns, then the predicted sigmas (omniflow.solve.sigma)
    assert lines[0].startswith("#") and lines[1].split(",") == [*res.columns, *res.sigma]
    assert list(res.sigma) == ["sigma_flow1", "sigma_flow2", "sigma_r"]
    back = np.loadtxt(path, delimiter=",", skiprows=2)
    assert back.shape == (n, len(res.columns) + len(res.sigma))
    np.testing.assert_allclose(back[:, 0], res["x"], rtol=1e-8)
    assert not list(tmp_path.glob(".*partial*"))  # written atomically, nothing left over


@pytest.mark.parametrize(
    "config",
    [
        OmniFlowConfig(),
        OmniFlowConfig.paper(),
        OmniFlowConfig(fit={"temporal": "dct3d"}),
        OmniFlowConfig(solver="direct", fit={"gradients": "first", "sampling": "exact"}),
        OmniFlowConfig(
            band=0.25,
            fit={"rim_fill": "none", "sampling": "linear"},
        ),
    ],
)
def test_every_variant_runs(moving_frames, rig256, config):
    _, f1, f2 = moving_frames
    res = estimate(f1, f2, rig256, config)
    assert len(res) > 50
    c = res.columns
    assert np.all(np.isfinite(c["dx"])) and np.all(np.isfinite(c["dh1_dt"]))
    assert np.all((c["confidence"] >= 0) & (c["confidence"] <= 1))


@pytest.fixture(scope="module")
def e2e_table(rig256):
    scenes = {
        "striped wall 2 m": (wall_scene(rig256, robot=DRIVE_AND_TURN), 2.0),
        "room texture 3 m": (
            SyntheticScene.room(
                rig256, wall_radius=3.0, ceiling=None, texture_seed=7, robot=DRIVE_AND_TURN
            ),
            3.0,
        ),
    }
    rows = {}
    for name, (scene, radius) in scenes.items():
        f1, f2 = frames(scene)
        dis = dis_flow(f1[0], f1[1])
        for cname, config in (("default", OmniFlowConfig()), ("paper", OmniFlowConfig.paper())):
            c = estimate(f1, f2, rig256, config)
            tdx, tdy, tdr = _true_motion(scene, rig256.cam1, c["h1"], c["theta"])
            t2x, t2y, _ = _true_motion(scene, rig256.cam2, c["h2"], c["theta"])
            h2_true, _ = true_h_other(scene, c["h1"], c["theta"])
            epe = np.hypot(c["dx"] - tdx, c["dy"] - tdy)
            dis_epe = np.hypot(sample_xy(dis[..., 0], c["x"], c["y"]) - tdx,
                               sample_xy(dis[..., 1], c["x"], c["y"]) - tdy)  # fmt: skip
            top = c["confidence"] >= np.median(c["confidence"])
            rows[(name, cname)] = {
                "n": len(c),
                "stereo_outliers": float(np.mean(~(np.abs(c["h2"] - h2_true) <= 1))),
                "r_error": float(np.median(np.abs(c["r"] / radius - 1))),
                "epe": float(np.median(epe)),
                "epe_confident_half": float(np.median(epe[top])),
                "dis": float(np.median(dis_epe)),
                "epe2": float(np.median(np.hypot(c["dx2"] - t2x, c["dy2"] - t2y))),
                "dr_error": float(np.median(np.abs(c["dr_dt"] - tdr))),
                "motion": float(np.median(np.hypot(tdx, tdy))),
            }
    print()
    for key, row in rows.items():
        print(key, {k: round(v, 5) for k, v in row.items()})
    return rows


def test_default_pipeline_end_to_end(e2e_table):
    for name in ("striped wall 2 m", "room texture 3 m"):
        row = e2e_table[(name, "default")]
        assert row["n"] > 700  # measured 1134, 1505
        assert row["stereo_outliers"] < 0.05  # measured 0
        assert row["r_error"] < 0.01  # measured 0.0003, 0.0008
        assert row["epe"] <= 0.5 * row["dis"]  # measured 0.12 and 0.021 of DIS
        assert row["epe"] < 0.03  # measured 0.0040, 0.0021
        assert row["epe2"] < 0.05  # measured 0.0098, 0.0036 (cam2 moves 0.36-0.52 px)
        assert row["dr_error"] < 0.15 * 0.0078  # measured 4e-5, 5e-5 m/frame
    # The confidence ranks the points on the striped wall: the more confident
    # half is more accurate (measured 0.0032 against 0.0040 px). On the room
    # texture it does not with the default pooling (48 neighbours within
    # r_m / 8: 0.0021 against 0.0021 px); with the earlier 24 within r_m / 16
    # it barely did (0.01136 against 0.01149 px). Not asserted there; see
    # tests/omniflow/test_outputs_vs_truth.py for the ranking on another room scene.
    row = e2e_table[("striped wall 2 m", "default")]
    assert row["epe_confident_half"] < row["epe"]


def test_paper_pipeline_end_to_end_is_measured(e2e_table):
    """The paper's choices end to end: most matches wrong, flow errors ~1.4-4.7x
    the motion; recorded (see the module docstring), bounded loosely."""
    for name in ("striped wall 2 m", "room texture 3 m"):
        row = e2e_table[(name, "paper")]
        assert 0.3 < row["stereo_outliers"] < 0.99
        assert row["epe"] > row["dis"]


def test_bad_inputs(moving_frames, rig256):
    _, f1, f2 = moving_frames
    with pytest.raises(ValueError, match="t = 2"):
        estimate(f1, f2, rig256, t=2)
    with pytest.raises(ValueError, match="shape"):
        estimate([f[:, :-1] for f in f1], f2, rig256)
    with pytest.raises(ValueError, match="dct3d"):
        estimate(f1[:2], f2[:2], rig256, OmniFlowConfig(fit={"temporal": "dct3d"}))
    with pytest.raises(ValueError, match="solver"):
        OmniFlowConfig(solver="magic")
    with pytest.raises(ValueError, match="band"):
        OmniFlowConfig(band=0.0)
    with pytest.raises(ValueError, match="frames1 has 3 frames but frames2 2"):
        estimate(f1, f2[:2], rig256)
    bad = f1.copy()
    bad[0, 100, 100] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        estimate(bad, f2, rig256)


def test_config_paper_and_replace():
    p = OmniFlowConfig.paper()
    assert (p.band, p.match_method, p.fit.gradients, p.fit.temporal, p.solver) == (
        0.25, "paper", "first", "difference", "direct")  # fmt: skip
    assert OmniFlowConfig.paper(solver="pooled").solver == "pooled"
    c = OmniFlowConfig().replace(n_theta=360)
    assert c.n_theta == 360 and c.to_dict()["n_theta"] == 360


def test_float64_and_float32_frames_agree(moving_frames, rig256):
    _, f1, f2 = moving_frames
    a = estimate(f1, f2, rig256)
    b = estimate(f1.astype(np.float64), f2.astype(np.float64), rig256)
    np.testing.assert_array_equal(a["h1"], b["h1"])
    np.testing.assert_allclose(a["dx"], b["dx"], atol=1e-6)
