"""validation.baselines: the OpenCV contrib methods against closed-form flow, and their names.

Two closed-form pairs: a band-limited texture translated by exactly 1.5 px (every
pixel's true flow is (1.5, 0)), and the synthetic room seen while the robot
turns (``omnisim.synthetic``, exact per-pixel truth). Tolerances are measured
figures with a margin; each says where it comes from.
"""

from __future__ import annotations

import inspect

import numpy as np
import pytest

from omniflow.geometry.rig import Rig
from omnisim.synthetic import Motion, SyntheticScene
from validation import baselines as bl
from validation.cli import _parser, main
from validation.inputs import InputError
from validation.runner import run_validation

#: The methods this module adds (DIS-medium and Farneback: tests/validation/test_metrics.py).
NEW = ("DIS-fine", "DeepFlow", "DualTVL1", "PCAFlow", "RLOF")


def _texture(size: int, shift: float = 0.0, seed: int = 0) -> np.ndarray:
    """12 sinusoids (wavelengths over 8 px), shifted right by ``shift`` px, 8-bit."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] + 0.5
    img = np.zeros((size, size))
    for _ in range(12):
        fx, fy = rng.uniform(-0.12, 0.12, 2)
        img += np.sin(2 * np.pi * (fx * (xx - shift) + fy * yy) + rng.uniform(0, 6.3))
    return np.clip(np.rint(127 + 10 * img), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("name", NEW)
def test_new_method_recovers_a_translation(name):
    rig = Rig.symmetric(d=0.1, R=0.05, s=0.3, size=96)
    a, b = _texture(96), _texture(96, shift=1.5)
    f = bl.dense_baseline(name, a, b, rig.cam1)
    assert isinstance(f, bl.DenseFlow) and f.flow.shape == (96, 96, 2)
    yy, xx = np.mgrid[24:72, 24:72] + 0.5
    est = f.at(xx.ravel(), yy.ravel())
    epe = np.hypot(est["dx"] - 1.5, est["dy"])
    # Median EPE over the central 48 x 48 px, measured on seeds 0-3: DIS-fine <= 0.010,
    # DeepFlow <= 0.003, DualTVL1 <= 0.003, PCAFlow <= 0.039, RLOF <= 0.009 px (DIS-medium
    # 0.048). 0.1 px is twice the worst; a flow 10 % short (0.15 px) fails.
    assert np.median(epe) < 0.1, name
    assert f.seconds > 0


@pytest.mark.parametrize("name", NEW)
def test_identical_frames_give_zero_flow(name):
    rig = Rig.symmetric(d=0.1, R=0.05, s=0.3, size=96)
    a = _texture(96, seed=1)
    flow = bl.dense_baseline(name, a, a.copy(), rig.cam1).flow
    # Measured: exactly 0 everywhere for each of these (Farneback, not tested here, 0.06 px).
    np.testing.assert_allclose(flow, 0.0, atol=1e-6, err_msg=name)


@pytest.fixture(scope="module")
def turning_room():
    """The synthetic room (wall 3 m, 128 px) while the robot turns 0.02 rad per frame:
    about 0.85 px of tangential flow at the ring scored below."""
    rig = Rig.symmetric(d=0.1, R=0.05, s=0.3, size=128)
    scene = SyntheticScene.room(rig, wall_radius=3.0, robot=Motion(yaw_rate=0.02))
    imgs = [
        np.clip(np.rint(scene.render("cam1", k) * 255), 0, 255).astype(np.uint8) for k in (0, 1)
    ]
    truth = scene.truth("cam1", 0)
    ok = (truth["gt.valid"] > 0.5) & (truth["gt.flow.valid"] > 0.5)
    ii, jj = np.nonzero(ok)
    rad = np.hypot(jj + 0.5 - 64, ii + 0.5 - 64)
    sel = (rad > 25) & (rad < 55)
    return rig, imgs, truth, ii[sel], jj[sel]


@pytest.mark.parametrize("name", [*NEW, *(n + bl.PANORAMA_SUFFIX for n in NEW)], ids=lambda n: n)
def test_method_follows_a_turn_on_the_mirror_image_and_the_panorama(name, turning_room):
    rig, imgs, truth, ii, jj = turning_room
    f = bl.dense_baseline(name, imgs[0], imgs[1], rig.cam1)
    assert isinstance(f, bl.PanoramaFlow) == name.endswith("-panorama")
    est = f.at(jj + 0.5, ii + 0.5)
    epe = np.hypot(est["dx"] - truth["gt.flow.dx"][ii, jj], est["dy"] - truth["gt.flow.dy"][ii, jj])
    true_speed = np.median(np.hypot(truth["gt.flow.dx"][ii, jj], truth["gt.flow.dy"][ii, jj]))
    assert true_speed == pytest.approx(0.85, abs=0.02)  # the scene is the one measured
    # Median EPE measured on this scene (texture seeds 0, 1, 2): image rows 0.06-0.25 px
    # (DualTVL1 the worst, 0.248 on seed 1; seed 0 here <= 0.13), panorama rows 0.02-0.15 px;
    # zero flow scores 0.85. 0.3 px: above every measured figure; half the true flow fails.
    assert np.median(epe) < 0.3, name


def test_rlof_takes_the_grey_frame_as_three_equal_channels_and_repeats():
    import cv2

    a, b = _texture(96), _texture(96, shift=1.0)
    direct = cv2.optflow.calcOpticalFlowDenseRLOF(cv2.merge([a, a, a]), cv2.merge([b, b, b]), None)
    np.testing.assert_array_equal(bl.rlof_flow(a, b), direct)
    # 96 px: 256 grid seeds, the fewest allowed. Below that, OpenCV's RLOF gave a different
    # flow on each of 20 calls of one pair (64 and 72 px); here every call is the same.
    np.testing.assert_array_equal(bl.rlof_flow(a, b), bl.rlof_flow(a, b))


def test_rlof_refuses_images_too_small_for_its_interpolator():
    a = _texture(64)  # 11 x 11 = 121 seeds on the 6 px grid
    with pytest.raises(InputError, match=r"RLOF: a 64 x 64 px image gives 121 grid seeds"):
        bl.rlof_flow(a, a)


def test_baselines_refuse_images_that_are_not_8_bit_grey():
    a = _texture(64)
    with pytest.raises(TypeError, match=r"2-D uint8 grey images, got float64"):
        bl.deepflow_flow(a.astype(np.float64), a.astype(np.float64))
    with pytest.raises(TypeError, match=r"shape \(64, 64, 3\)"):
        bl.rlof_flow(np.dstack([a] * 3), np.dstack([a] * 3))


def test_pcaflow_refuses_images_it_would_corrupt_memory_on():
    # 55 rows: OpenCV's PCAFlow aborts the process (docs/decisions/baselines_contrib.md);
    # never call it.
    a = np.zeros((bl.PCAFLOW_MIN_ROWS - 1, 64), np.uint8)
    with pytest.raises(InputError, match=r"PCAFlow: a 55 x 64 px image.*under 56 rows"):
        bl.pcaflow_flow(a, a)
    rig = Rig.symmetric(d=0.1, R=0.05, s=0.3, size=96)  # panorama 46 px high
    img = _texture(96)
    with pytest.raises(InputError, match="PCAFlow"):
        bl.dense_baseline("PCAFlow-panorama", img, img, rig.cam1)


def test_dis_refuses_images_it_would_crash_on():
    # 14 x 120 px (the panorama of a 32 px render): OpenCV's DIS segfaults; never call it.
    a = np.zeros((bl.DIS_MIN_SIDE - 2, 120), np.uint8)
    for fn in (bl.dis_flow, bl.dis_fine_flow):
        with pytest.raises(InputError, match=r"DIS: a 14 x 120 px image.*under 16 px"):
            fn(a, a)
    ok = _texture(64)[: bl.DIS_MIN_SIDE]  # 16 x 64 runs
    assert bl.dis_flow(ok, ok).shape == (bl.DIS_MIN_SIDE, 64, 2)
    rig = Rig.symmetric(d=0.1, R=0.05, s=0.3, size=32)  # panorama 14 px high
    img = _texture(32)
    with pytest.raises(InputError, match="DIS"):
        bl.dense_baseline("DIS-medium-panorama", img, img, rig.cam1)


def test_unknown_baseline_is_one_line_listing_the_choices(capsys):
    rig = Rig.symmetric(d=0.1, R=0.05, s=0.3, size=64)
    a = _texture(64)
    with pytest.raises(ValueError, match="unknown baseline 'RAFT'") as info:
        bl.dense_baseline("RAFT", a, a, rig.cam1)
    msg = str(info.value)
    assert "\n" not in msg and all(n in msg for n in bl.BASELINES)
    # The command line checks the names before anything else (the dataset need not exist).
    assert main(["no-such-dataset", "--out", "no-such-out", "--baselines", "DeepFlow,RAFT"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "unknown ['RAFT']" in err
    assert all(n in err for n in bl.BASELINES)


def test_names_and_the_cheap_default():
    assert set(bl.DEFAULT_BASELINES) <= set(bl.BASELINES)
    assert len(set(bl.BASELINES)) == len(bl.BASELINES)
    for name in NEW:
        assert name in bl.BASELINES and name + bl.PANORAMA_SUFFIX in bl.BASELINES
        assert name not in bl.DEFAULT_BASELINES  # opt-in: seconds per frame at 512 px
    # Both entry points default to the cheap list.
    assert _parser().get_default("baselines") == ",".join(bl.DEFAULT_BASELINES)
    default = inspect.signature(run_validation).parameters["baselines"].default
    assert tuple(default) == bl.DEFAULT_BASELINES
