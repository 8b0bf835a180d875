"""Tests of omniflow.calibration: the rim circle and a Unit from it (eq. 2).

Rim images come from omniflow.synthetic: the textured room seen by one unit,
the rim antialiased by its area coverage in each pixel (synthetic.rim_coverage:
exact chords integrated by Gauss-Legendre quadrature, error < 2e-4 px^2).
Accuracy figures were measured by running these cases (texture seeds 1-5) and
printing the errors.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from omniflow.calibration import RimError, calibrate_unit, find_rim
from omniflow.rig import Rig, Unit
from omniflow.synthetic import SyntheticScene


def _rim_image(width, height, x_c, y_c, r_m, *, noise=0.0, seed=0, outside=0.0):
    cam2 = Unit(
        d=0.1, R=0.05, x_c=x_c, y_c=y_c, r_m=r_m, width=width, height=height, tip_h=0.0, name="cam2"
    )
    rig = Rig(cam1=dataclasses.replace(cam2, tip_h=0.3, name="cam1"), cam2=cam2, s=0.3)
    scene = dataclasses.replace(SyntheticScene.room(rig, texture_seed=seed), outside=outside)
    return scene.render("cam2", 0, noise=noise, seed=seed)


CASES = [
    # width, height, x_c, y_c, r_m, noise, outside grey level
    (128, 128, 64.0, 64.0, 62.0, 0.0, 0.0),
    (160, 128, 81.3, 62.7, 55.4, 0.0, 0.0),
    (200, 180, 97.9, 91.2, 80.15, 0.01, 0.0),
    (128, 128, 60.55, 66.2, 50.3, 0.0, 0.0),
    (160, 150, 77.3, 73.9, 70.2, 0.05, 0.0),
    (160, 150, 77.3, 73.9, 70.2, 0.02, 0.9),  # bright surround
    (128, 120, 60.3, 58.2, 63.5, 0.01, 0.0),  # rim cut by the image border
]


@pytest.mark.parametrize("case", CASES)
def test_rim_found_to_a_tenth_of_a_pixel(case):
    width, height, x_c, y_c, r_m, noise, outside = case
    img = _rim_image(width, height, x_c, y_c, r_m, noise=noise, seed=1, outside=outside)
    rim = find_rim(img)
    err = np.array([rim.x_c - x_c, rim.y_c - y_c, rim.r_m - r_m])
    # Required: 0.1 px (the brief). Measured over these cases with texture seeds 1-5:
    # max |error| 0.021 px (noise 0.1, not tested here: 0.032 px), so a margin of ~5x.
    # The cut rim needs the Otsu-outline candidate: Hough alone misses it for seed 1.
    assert np.abs(err).max() < 0.1, err
    assert rim.residual_px < 0.3  # measured 0.075-0.14 px RMS; bound ~2x
    assert rim.inlier_fraction > 0.9  # measured >= 0.994


def test_calibrate_unit_gives_v_from_eq2():
    img = _rim_image(160, 128, 81.3, 62.7, 55.4)
    unit = calibrate_unit(img, d=0.1, R=0.05, tip_h=0.3, name="cam1")
    assert (unit.width, unit.height, unit.tip_h, unit.name) == (160, 128, 0.3, "cam1")
    assert unit.v == pytest.approx((0.1 / 0.05 + 1) * unit.r_m)  # eq. (2)
    assert unit.v == pytest.approx(3 * 55.4, abs=3 * 0.1)


def test_colour_image_is_reduced_to_grey():
    img = _rim_image(128, 128, 64.0, 64.0, 62.0)
    rim = find_rim(np.stack([img, img, img], axis=-1))
    assert abs(rim.r_m - 62.0) < 0.1


@pytest.mark.parametrize(
    ("image", "match"),
    [
        (np.zeros((64, 64)), "blank"),
        (np.zeros((64, 64, 2)), "expected a grey"),
        (np.full((64, 64), np.nan), "NaN"),
        (np.zeros((8, 8)), "too small"),
        # A bright square: no circle in the default radius range.
        (np.pad(np.ones((60, 60)), 34), "no circle"),
        # Uniform noise: Hough proposes a circle but only ~18 % of the edge points agree.
        (np.random.default_rng(0).random((128, 128)), "no consistent rim"),
    ],
)
def test_bad_input_raises_a_clear_error(image, match):
    with pytest.raises(RimError, match=match):
        find_rim(image)


def test_circle_outside_the_radius_range_is_not_found():
    x, y = np.meshgrid(np.arange(128) + 0.5, np.arange(128) + 0.5)
    small = (np.hypot(x - 64, y - 64) < 15).astype(float)
    with pytest.raises(RimError, match=r"radius in \[32.0, 70.4\]"):
        find_rim(small)
    with pytest.raises(RimError, match="r_min"):
        find_rim(small, r_min=20, r_max=10)
