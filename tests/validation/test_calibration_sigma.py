"""The harness's calibration figures (validation.calibration_sigma) against hand-computed
values, and the leaderboard's 2-sigma columns."""

from __future__ import annotations

import math

import numpy as np

from validation.calibration_sigma import calibration, calibration_block, sigma_errors, within
from validation.leaderboard import scene_rows


def test_within_hand_computed():
    err = np.array([0.5, 1.0, 1.5, 2.5, 4.0])
    sigma = np.ones(5)
    assert within(err, sigma, 1.0) == 2 / 5  # 0.5 and 1.0 (at the bound counts)
    assert within(err, sigma, 2.0) == 3 / 5  # and 1.5
    assert math.isnan(within(np.zeros(0), np.zeros(0), 2.0))


def test_block_pools_frames_and_bins_by_sigma():
    # two frames; sigma 1 for the first four points, 10 for the last four
    frames = [
        {"err": np.array([0.5, 3.0, 0.2, 5.0]), "sigma": np.array([1.0, 1.0, 10.0, 10.0])},
        {"err": np.array([1.5, 0.1, 30.0, 12.0]), "sigma": np.array([1.0, 1.0, 10.0, 10.0])},
    ]
    b = calibration_block(frames, bins=2)
    assert b["n"] == 8
    # within 1 sigma: 0.5, 0.1 (sigma 1); 0.2, 5 (sigma 10) -> 4 of 8
    assert b["within1"] == 4 / 8
    # within 2 sigma: 0.5, 1.5, 0.1 (<= 2); 0.2, 5, 12 (<= 20) -> 6 of 8
    assert b["within2"] == 6 / 8
    assert b["sigma_median"] == 5.5
    low, high = b["reliability"]
    assert (low["n"], low["sigma"], high["sigma"]) == (4, 1.0, 10.0)
    # the sigma-1 bin's errors sorted: 0.1, 0.5, 1.5, 3.0; numpy's linear quantile at
    # 0.683: index 0.683 * 3 = 2.049 -> 1.5 + 0.049 * 1.5 = 1.5735
    assert math.isclose(low["q68"], 1.5735, rel_tol=1e-12)
    assert low["within2"] == 3 / 4 and high["within2"] == 3 / 4


def test_sigma_errors_drops_points_without_truth_or_sigma():
    h = w = 8
    ones = np.ones((h, w), np.float32)
    truth = {
        cam: {"gt.valid": ones, "gt.object": ones, "gt.stereo.valid": ones,
              "gt.flow.dx": ones * 0.5, "gt.flow.dy": ones * 0.0, "gt.r": ones * 2.0}
        for cam in ("cam1", "cam2")
    }  # fmt: skip
    cols = {"x": np.array([3.5, 4.5, 5.5]), "y": np.array([3.5, 3.5, 3.5]),
            "dx": np.array([0.5, 1.5, 0.5]), "dy": np.array([0.0, 0.0, 0.0]),
            "x2": np.array([3.5, 4.5, 5.5]), "y2": np.array([3.5, 3.5, 3.5]),
            "dx2": np.array([0.5, 0.5, 0.5]), "dy2": np.array([0.3, 0.4, 0.0]),
            "r": np.array([2.0, 2.5, 1.0])}  # fmt: skip
    sig = {"sigma_flow1": np.array([1.0, np.nan, 1.0]), "sigma_flow2": np.ones(3),
           "sigma_r": np.array([0.1, 1.0, 0.1])}  # fmt: skip
    e = sigma_errors(cols, sig, truth)
    np.testing.assert_allclose(e["cam1"]["err"], [0.0, 0.0])  # the NaN sigma left out
    np.testing.assert_allclose(e["cam2"]["err"], [0.3, 0.4, 0.0], atol=1e-12)
    np.testing.assert_allclose(e["range"]["err"], [0.0, 0.5, 1.0])
    cal = calibration([e])
    assert cal["range"]["within2"] == 2 / 3  # 0 <= 0.2, 0.5 <= 2, 1.0 > 0.2
    assert cal["cam1"]["unit"] == "px" and cal["range"]["sigma"] == "sigma_r"


def test_infinite_sigmas_are_excluded_and_counted():
    """Flagged points carry sigma inf (omniflow.result.confident): scored nowhere, counted
    in ``excluded``. Three points with truth, the second flagged (cam2 and range inf); a
    fourth point without truth (outside the image) is neither scored nor excluded."""
    h = w = 8
    ones = np.ones((h, w), np.float32)
    truth = {
        cam: {"gt.valid": ones, "gt.object": ones, "gt.stereo.valid": ones,
              "gt.flow.dx": ones * 0.5, "gt.flow.dy": ones * 0.0, "gt.r": ones * 2.0}
        for cam in ("cam1", "cam2")
    }  # fmt: skip
    x = np.array([3.5, 4.5, 5.5, 50.0])
    cols = {"x": x, "y": np.full(4, 3.5), "dx": np.array([0.5, 1.5, 0.5, 0.5]),
            "dy": np.zeros(4), "x2": x, "y2": np.full(4, 3.5), "dx2": np.full(4, 0.5),
            "dy2": np.array([0.3, 0.4, 0.0, 0.0]), "r": np.array([2.0, 2.5, 1.0, 2.0])}  # fmt: skip
    inf = np.inf
    sig = {"sigma_flow1": np.ones(4), "sigma_flow2": np.array([1.0, inf, 1.0, inf]),
           "sigma_r": np.array([0.1, inf, 0.1, inf])}  # fmt: skip
    e = sigma_errors(cols, sig, truth)
    assert [e[q]["excluded"] for q in ("cam1", "cam2", "range")] == [0, 1, 1]
    np.testing.assert_allclose(e["cam2"]["err"], [0.3, 0.0], atol=1e-12)
    np.testing.assert_allclose(e["range"]["err"], [0.0, 1.0])
    cal = calibration([e, e])  # two frames: the counts add
    assert (cal["cam1"]["n"], cal["cam1"]["excluded"]) == (6, 0)
    assert (cal["cam2"]["n"], cal["cam2"]["excluded"]) == (4, 2)
    assert (cal["range"]["n"], cal["range"]["excluded"]) == (4, 2)
    assert cal["range"]["within2"] == 2 / 4  # 0 <= 0.2; 1.0 > 0.2; per frame
    assert cal["cam2"]["within2"] == 1.0  # 0.3 and 0 within 2; the inf one not scored


def test_leaderboard_within2_pools_cameras():
    cal = {"cam1": {"n": 30, "within2": 0.9}, "cam2": {"n": 10, "within2": 0.5},
           "range": {"n": 5, "within2": 0.8}}  # fmt: skip
    summary = {"methods": [{"name": "m", "points": "own", "kind": "omniflow",
                            "calibration": cal},
                           {"name": "b", "points": "dense", "kind": "baseline"}]}  # fmt: skip
    rows = {r["method"]: r for r in scene_rows("s", "test", summary)}
    # (30 * 0.9 + 10 * 0.5) / 40 = 0.8
    assert math.isclose(rows["m"]["within2_flow"], 0.8)
    assert rows["m"]["within2_range"] == 0.8
    assert math.isnan(rows["b"]["within2_flow"]) and math.isnan(rows["b"]["within2_range"])


def test_external_sigma_columns_are_read(tmp_path):
    """An external per-point flow.csv may carry any of the sigma columns; the others are
    NaN (no point of theirs is scored), and without any the result has no sigma."""
    from omniflow.geometry.rig import Rig
    from validation.external import ExternalOutput

    rig = Rig.symmetric(d=0.10, R=0.05, s=0.30, size=64)
    for name, header, row in (("with", "x,y,dx,dy,sigma_r", "30.5,20.5,0.1,0.2,0.05"),
                              ("without", "x,y,dx,dy", "30.5,20.5,0.1,0.2")):  # fmt: skip
        frame = tmp_path / name / "frames" / "000000"
        frame.mkdir(parents=True)
        (frame / "flow.csv").write_text(f"# units\n{header}\n{row}\n")
    res = ExternalOutput(tmp_path / "with").points(0, rig)
    assert res.sigma["sigma_r"].tolist() == [0.05]
    assert np.isnan(res.sigma["sigma_flow1"]).all() and np.isnan(res.sigma["sigma_flow2"]).all()
    assert ExternalOutput(tmp_path / "without").points(0, rig).sigma == {}
