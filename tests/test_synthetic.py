"""Tests of the closed-form scene generator (omniflow.synthetic).

Figures measured with ``python /tmp/a_meas_syn.py`` (the fixtures of
tests/conftest.py rebuilt, 128 x 128); each bound states its measured value.
The geometry is closed-form in float64, so the bounds are set at ~1e-9 (px,
m or grey levels), orders above the measured rounding and far below anything
a flow or stereo test could notice.
"""

from __future__ import annotations

import numpy as np
import pytest

from omniflow.synthetic import TRUTH_KEYS, Cylinder, Disc, Motion, SyntheticScene, Texture


def _units(scene, cam):
    rig = scene.rig
    return (rig.cam1, rig.cam2) if cam == "cam1" else (rig.cam2, rig.cam1)


@pytest.mark.parametrize("cam", ["cam1", "cam2"])
def test_truth_has_exactly_the_dataset_channels(busy_scene, cam):
    truth = busy_scene.truth(cam, 0)
    assert tuple(truth) == TRUTH_KEYS
    assert all(v.shape == (128, 128) and v.dtype == np.float64 for v in truth.values())
    valid = truth["gt.valid"] > 0
    assert 0.7 < valid.mean() < 0.8  # the rim disc, r_m = 62: pi 62^2 / 128^2 = 0.737
    assert np.all(np.isfinite(truth["gt.r"][valid])) and np.all(np.isnan(truth["gt.r"][~valid]))
    assert set(np.unique(truth["gt.object"])) == {0.0, 1.0, 3.0}  # ceiling too high to see


@pytest.mark.parametrize("cam", ["cam1", "cam2"])
def test_every_valid_pixel_obeys_eq1(busy_scene, cam):
    unit, _ = _units(busy_scene, cam)
    truth = busy_scene.truth(cam, 0)
    valid = truth["gt.valid"] > 0
    x, y = unit.pixel_centres()
    h_i, theta = unit.polar_of_pixel(x, y)
    err = unit.image_radius(truth["gt.r"], truth["gt.h"])[valid] - h_i[valid]
    assert np.abs(err).max() < 1e-9  # measured 2.8e-14 px; x35
    np.testing.assert_allclose(truth["gt.theta"][valid], theta[valid], rtol=0, atol=0)
    np.testing.assert_array_equal(truth["gt.Z"], truth["gt.h"])


@pytest.mark.parametrize("cam", ["cam1", "cam2"])
def test_stereo_truth_obeys_eq3_to_eq5(busy_scene, cam):
    rig = busy_scene.rig
    unit, other = _units(busy_scene, cam)
    truth = busy_scene.truth(cam, 0)
    sv = truth["gt.stereo.valid"] > 0
    assert sv.mean() > 0.3
    h_i = unit.polar_of_pixel(*unit.pixel_centres())[0]
    h_other = truth["gt.stereo.h_other"]
    h1, h2 = (h_i, h_other) if cam == "cam1" else (h_other, h_i)
    r, h = rig.triangulate(h1[sv], h2[sv])  # eq. (5)
    np.testing.assert_allclose(r, truth["gt.r"][sv], rtol=1e-9)  # measured 8.9e-16 relative
    np.testing.assert_allclose(h, truth["gt.h"][sv], rtol=1e-9)
    # The other unit's ray through h_other sees the same world point.
    hit = busy_scene.trace(other, 0, h_other[sv], truth["gt.theta"][sv])
    np.testing.assert_allclose(hit.X, truth["gt.X"][sv], atol=1e-9)  # measured 0 m
    np.testing.assert_allclose(hit.Z, truth["gt.Z"][sv], atol=1e-9)  # measured 2.2e-16 m


@pytest.mark.parametrize("cam", ["cam1", "cam2"])
def test_flow_carries_brightness_exactly(busy_scene, cam):
    unit, _ = _units(busy_scene, cam)
    truth = busy_scene.truth(cam, 0)
    img0 = busy_scene.render(cam, 0, antialias_rim=False)
    fv = truth["gt.flow.valid"] > 0
    assert fv.mean() > 0.7
    x, y = unit.pixel_centres()
    h1, th1 = unit.polar_of_pixel(x[fv] + truth["gt.flow.dx"][fv], y[fv] + truth["gt.flow.dy"][fv])
    seen = busy_scene.shade(busy_scene.trace(unit, 1, h1, th1), 1)
    assert np.abs(seen - img0[fv]).max() < 1e-9  # measured 4.4e-14 grey levels
    # Polar components describe the same displacement.
    h_i = unit.polar_of_pixel(x, y)[0]
    np.testing.assert_allclose(truth["gt.flow.dh"][fv], h1 - h_i[fv], atol=1e-9)


def test_static_scene_has_zero_flow(room_scene):
    truth = room_scene.truth("cam2", 3)
    valid = truth["gt.valid"] > 0
    for key in ("gt.flow.dx", "gt.flow.dy", "gt.flow.dh", "gt.flow.hdtheta"):
        assert np.abs(truth[key][valid]).max() < 1e-12, key  # measured <= 4.3e-14 px
    np.testing.assert_array_equal(truth["gt.flow.valid"], truth["gt.valid"])


def test_render_is_fast_enough_to_use_and_deterministic(busy_scene):
    a = busy_scene.render("cam1", 2, noise=0.01, seed=3)
    b = busy_scene.render("cam1", 2, noise=0.01, seed=3)
    np.testing.assert_array_equal(a, b)
    assert a.shape == (128, 128) and a.dtype == np.float64
    assert busy_scene.render("cam1", 0, dtype=np.float32).dtype == np.float32


def test_bad_arguments_raise(small_rig):
    with pytest.raises(ValueError, match="ids"):
        SyntheticScene(small_rig, bodies=(Cylinder(id=1), Disc(id=1)))
    with pytest.raises(ValueError, match="cam"):
        SyntheticScene.room(small_rig).render("cam3")
    with pytest.raises(ValueError, match=r"robot\.vz"):
        SyntheticScene(small_rig, robot=Motion(vz=0.1))
    with pytest.raises(ValueError, match="wavelengths"):
        Texture.random(0, wavelengths=(0.5, 0.1))
