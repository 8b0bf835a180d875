"""validation: truth sampling, metrics, motion truth and the baselines' geometry.

Every expected value here is computed by hand or from a closed form.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from omniflow.geometry.rig import Rig
from validation import baselines as bl
from validation.metrics import (
    bin_label,
    flow_errors,
    flow_summary,
    polar_components,
    stats,
    stereo_errors,
    stereo_summary,
)
from validation.motion import point_motion, robot_motion
from validation.sampling import bilinear, sample_truth


def _frame(h=8, w=10):
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    return {
        "gt.valid": np.ones((h, w)),
        "gt.object": np.ones((h, w)),
        "gt.flow.valid": (xx > 5).astype(float),
        "gt.r": 2.0 * xx + 3.0 * yy,  # linear: bilinear interpolation is exact
        "gt.theta": np.full((h, w), math.pi - 0.01),
    }


# -- sampling ----------------------------------------------------------------------


def test_bilinear_exact_on_linear_field_and_nearest_for_flags():
    f = _frame()
    x = np.array([1.0, 2.25, 5.5, 6.1])
    y = np.array([1.0, 3.7, 4.5, 2.0])
    s = sample_truth(f, x, y)
    np.testing.assert_allclose(s["gt.r"], 2 * x + 3 * y, rtol=0, atol=1e-12)
    assert s["bilinear_ok"].all()
    # Nearest pixel centre: the pixel that contains the point (x = 5.5 is in column 5,
    # whose centre 5.5 is not > 5 ... column 5 has centre 5.5 > 5, so flag 1).
    np.testing.assert_array_equal(s["gt.flow.valid"], [0, 0, 1, 1])


def test_bilinear_refuses_mixed_objects_and_invalid_neighbours():
    f = _frame()
    f["gt.object"][:, 5:] = 2.0  # object boundary between columns 4 and 5 (x = 5.0)
    f["gt.valid"][0, 0] = 0.0
    s = sample_truth(f, np.array([4.9, 5.2, 6.5, 0.9, 3.0]), np.array([3.0, 3.0, 3.0, 0.9, 3.0]))
    # 4.9 and 5.2: neighbours at centres 4.5 and 5.5 straddle the boundary.
    np.testing.assert_array_equal(s["bilinear_ok"], [False, False, True, False, True])
    assert np.isnan(s["gt.r"][[0, 1, 3]]).all()
    assert np.isfinite(s["gt.r"][[2, 4]]).all()
    # Discrete channels are still given (nearest pixel).
    np.testing.assert_array_equal(s["gt.object"], [1, 2, 2, 1, 1])


def test_outside_the_image_has_no_truth():
    f = _frame()
    s = sample_truth(f, np.array([-1.0, 0.2, 9.9, np.nan]), np.array([1.0, 1.0, 1.0, 1.0]))
    assert not s["bilinear_ok"].any()
    np.testing.assert_array_equal(s["gt.valid"], [0, 1, 1, 0])
    assert np.isnan(bilinear(f["gt.r"], np.array([0.2]), np.array([1.0]))).all()


def test_theta_is_interpolated_on_the_circle():
    f = _frame()
    f["gt.theta"][:, 3:] = -math.pi + 0.01  # wraps between columns 2 and 3
    s = sample_truth(f, np.array([3.0]), np.array([2.0]))  # halfway between centres 2.5, 3.5
    assert abs(abs(s["gt.theta"][0]) - math.pi) < 1e-9


# -- metrics -------------------------------------------------------------------------


def test_stats_of_nothing_is_nan_without_warnings():
    s = stats([])
    assert s["n"] == 0 and math.isnan(s["median"])
    s = stats([np.nan, 1.0, 3.0])
    assert s == {"n": 2, "median": 2.0, "mean": 2.0, "p90": pytest.approx(2.8)}


def test_flow_errors_hand_values():
    est = {
        "dx": np.array([1.0, 0.0]),
        "dy": np.array([0.0, 0.0]),
        "dh": np.array([0.5, 0.0]),
        "hdtheta": np.array([0.0, -1.0]),
    }
    gt = {
        "dx": np.array([0.0, 0.0]),
        "dy": np.array([1.0, 0.0]),
        "dh": np.array([0.0, 0.0]),
        "hdtheta": np.array([0.0, 0.0]),
    }
    e = flow_errors(est, gt)
    np.testing.assert_allclose(e["epe"], [math.sqrt(2), 0.0])
    np.testing.assert_allclose(e["err_dh"], [0.5, 0.0])
    np.testing.assert_allclose(e["err_hdtheta"], [0.0, 1.0])
    # Barron's angular error between (1, 0, 1) and (0, 1, 1): arccos(1/2) = 60 degrees.
    np.testing.assert_allclose(e["ae"], [60.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(e["speed"], [1.0, 0.0])


def test_flow_summary_splits_and_outlier_rates():
    epe = np.array([0.1, 0.2, 2.0, 5.0, 0.3])
    err = {
        "epe": epe,
        "err_dh": epe,
        "err_hdtheta": epe,
        "ae": epe,
        "speed": np.array([0.2, 0.7, 2.0, 4.0, 0.1]),
        "gt_dh": np.array([0.1, -0.5, 1.0, 2.0, 0.3]),
        "gt_hdtheta": np.array([1.0, 0.5, -1.0, 0.2, 0.3]),
    }
    err["est_dh"] = 2.0 * err["gt_dh"]  # radial gain 2
    err["est_hdtheta"] = err["gt_hdtheta"] + 0.1  # tangential offset 0.1
    noc = np.array([True, True, True, False, True])
    s = flow_summary(err, noc)
    assert s["all"]["radial"]["gain"] == pytest.approx(2.0)
    assert s["all"]["tangential"]["intercept"] == pytest.approx(0.1)
    assert s["speed"]["0-0.25px"]["radial"]["gain"] == pytest.approx(2.0)
    assert s["all"]["n"] == 5 and s["noc"]["n"] == 4 and s["occ"]["n"] == 1
    assert s["all"]["out1"] == pytest.approx(2 / 5)
    assert s["all"]["out3"] == pytest.approx(1 / 5)
    assert s["occ"]["epe"]["median"] == 5.0
    # Speed bins over non-occluded points only.
    assert s["speed"]["0-0.25px"]["n"] == 2
    assert s["speed"]["0.25-0.5px"]["n"] == 0
    assert s["speed"]["0.5-1px"]["n"] == 1
    assert s["speed"]["1-3px"]["n"] == 1
    assert s["speed"][">=3px"]["n"] == 0
    assert bin_label(3, math.inf, "px") == ">=3px"


def test_polar_components_match_the_truth_definition():
    # A pure rotation about the centre by 0.1 rad at radius 20: dh = 0, h dtheta = 2.
    xc, yc, h, a = 50.0, 40.0, 20.0, 0.3
    x, y = xc + h * math.cos(a), yc + h * math.sin(a)
    x1, y1 = xc + h * math.cos(a + 0.1), yc + h * math.sin(a + 0.1)
    dh, hdth = polar_components(x, y, x1 - x, y1 - y, xc, yc)
    assert abs(dh) < 1e-12 and hdth == pytest.approx(2.0)
    # A radial move outward by 1.5 px.
    dh, hdth = polar_components(x, y, 1.5 * math.cos(a), 1.5 * math.sin(a), xc, yc)
    assert dh == pytest.approx(1.5) and abs(hdth) < 1e-12
    # Across theta = +-pi the angle change is wrapped.
    dh, hdth = polar_components(xc - 10, yc + 0.01, 0.0, -0.02, xc, yc)
    assert hdth == pytest.approx(0.02, rel=1e-3)


def test_stereo_metrics():
    est = {
        "h2": np.array([10.0, 20.0, 31.5]),
        "r": np.array([1.1, 2.0, 5.0]),
        "h": np.array([0.5, 0.6, 0.7]),
    }
    gt = {
        "h_other": np.array([10.5, 20.0, 30.0]),
        "r": np.array([1.0, 2.0, 4.0]),
        "h": np.array([0.4, 0.6, 0.7]),
    }
    e = stereo_errors(est, gt)
    np.testing.assert_allclose(e["err_h2"], [0.5, 0.0, 1.5])
    np.testing.assert_allclose(e["rel_r"], [0.1, 0.0, 0.25])
    np.testing.assert_allclose(e["err_h"], [0.1, 0.0, 0.0], atol=1e-12)
    s = stereo_summary(e, n_matched=3, n_significant_valid=6, n_valid_pixels=30)
    assert s["match_rate"] == pytest.approx(0.5) and s["density"] == pytest.approx(0.1)
    assert s["all"]["outliers"] == pytest.approx(1 / 3)
    assert s["range"]["1-2m"]["n"] == 1
    assert s["range"][">=4m"]["n"] == 1
    assert s["range"]["0-1m"]["n"] == 0
    assert math.isnan(
        stereo_summary(e, n_matched=3, n_significant_valid=None, n_valid_pixels=30)["match_rate"]
    )


# -- motion truth ------------------------------------------------------------------------


def _pose(x, y, z, yaw):
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0, x], [s, c, 0, y], [0, 0, 1, z], [0, 0, 0, 1.0]])


def test_robot_motion_in_the_rig_frame():
    # Rig heading +Y in the world (yaw 90 deg) and moving 0.01 m along world +Y: that is
    # +X in its own frame; it also turns by 0.02 rad.
    m = robot_motion(_pose(1, 2, 0.5, math.pi / 2), _pose(1, 2.01, 0.5, math.pi / 2 + 0.02))
    assert m["w"] == pytest.approx(0.02)
    assert m["vx"] == pytest.approx(0.01) and abs(m["vy"]) < 1e-12
    assert m["speed"] == pytest.approx(0.01)


def test_point_motion_static_point_and_moving_object():
    rig0, rig1 = _pose(0, 0, 0, 0), _pose(0.1, 0, 0, 0)  # robot drives 0.1 m along +X
    world = np.array([[2.0, 0.0, 1.0], [0.0, 3.0, 1.0], [-2.0, 0.0, 1.0]])
    ids = np.array([1, 1, 5])
    objs0 = {1: _pose(0, 0, 0, 0), 5: _pose(-2, 0, 0, 0)}
    objs1 = {1: _pose(0, 0, 0, 0), 5: _pose(-1.9, 0, 0.05, 0)}  # object 5 follows the robot
    m = point_motion(world, ids, objs0, objs1, rig0, rig1)
    np.testing.assert_allclose(m["r0"], [2.0, 3.0, 2.0])
    np.testing.assert_allclose(m["dr_dt"], [-0.1, math.hypot(0.1, 3.0) - 3.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(m["dh_dt"], [0.0, 0.0, 0.05], atol=1e-12)
    assert m["ttc"][0] == pytest.approx(20.0) and math.isinf(m["ttc"][2])


# -- baselines ------------------------------------------------------------------------------


def _texture(size, shift=0.0, seed=0):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] + 0.5
    img = np.zeros((size, size))
    for _ in range(12):
        fx, fy = rng.uniform(-0.12, 0.12, 2)
        img += np.sin(2 * np.pi * (fx * (xx - shift) + fy * yy) + rng.uniform(0, 6.3))
    return np.clip(np.rint(127 + 10 * img), 0, 255).astype(np.uint8)


def test_dis_and_farneback_recover_a_translation():
    a, b = _texture(96), _texture(96, shift=1.5)
    rig = Rig.symmetric(d=0.1, R=0.05, s=0.3, size=96)
    for name in ("DIS-medium", "Farneback"):
        f = bl.dense_baseline(name, a, b, rig.cam1)
        est = f.at(np.array([48.0]), np.array([48.0]))
        assert est["dx"][0] == pytest.approx(1.5, abs=0.15), name
        assert abs(est["dy"][0]) < 0.15, name
        assert f.seconds > 0


def test_panorama_flow_maps_back_to_image_displacement():
    rig = Rig.symmetric(d=0.1, R=0.05, s=0.3, size=96)
    unit = rig.cam1
    width, height = bl.panorama_size(unit)
    pad = bl.PANORAMA_PAD
    # A rotation by one panorama column is a constant flow du = 1: in the image, the
    # point turns by 2 pi / width at its own radius.
    flow = np.zeros((height, width + 2 * pad, 2), np.float32)
    flow[..., 0] = 1.0
    pf = bl.PanoramaFlow(flow=flow, unit=unit, width=width, height=height, pad=pad)
    x = np.array([70.0, 30.0, 48.0])
    y = np.array([48.0, 40.0, 20.0])
    est = pf.at(x, y)
    h, _ = unit.polar_of_pixel(x, y)
    np.testing.assert_allclose(est["hdtheta"], h * 2 * np.pi / width, rtol=1e-9)
    np.testing.assert_allclose(est["dh"], 0.0, atol=1e-9)
    # Zero panorama flow is zero image flow, everywhere including near theta = 0.
    pf0 = bl.PanoramaFlow(flow=np.zeros_like(flow), unit=unit, width=width, height=height)
    est0 = pf0.at(np.array([80.0, 80.0]), np.array([47.99, 48.01]))
    np.testing.assert_allclose(np.hypot(est0["dx"], est0["dy"]), 0.0, atol=1e-9)


def test_panorama_dis_sees_a_rotation():
    from omnisim.synthetic import Motion, SyntheticScene

    rig = Rig.symmetric(d=0.1, R=0.05, s=0.3, size=128)
    scene = SyntheticScene.room(rig, wall_radius=3.0, robot=Motion(yaw_rate=0.02))
    imgs = [
        np.clip(np.rint(scene.render("cam1", k) * 255), 0, 255).astype(np.uint8) for k in (0, 1)
    ]
    truth = scene.truth("cam1", 0)
    f = bl.dense_baseline("DIS-medium-panorama", imgs[0], imgs[1], rig.cam1)
    ok = (truth["gt.valid"] > 0.5) & (truth["gt.flow.valid"] > 0.5)
    ii, jj = np.nonzero(ok)
    rad = np.hypot(jj + 0.5 - 64, ii + 0.5 - 64)
    sel = (rad > 25) & (rad < 55)
    est = f.at(jj[sel] + 0.5, ii[sel] + 0.5)
    epe = np.hypot(
        est["dx"] - truth["gt.flow.dx"][ii[sel], jj[sel]],
        est["dy"] - truth["gt.flow.dy"][ii[sel], jj[sel]],
    )
    # The robot turns 0.02 rad/frame: about 1 px at h = 50. Measured median EPE ~0.05 px.
    assert np.median(epe) < 0.2
