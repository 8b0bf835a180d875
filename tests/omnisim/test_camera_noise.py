"""Tests of omnisim.camera_noise: the grey image's noise predicted from a camera's parameters.

The prediction is checked against what the camera model makes of a flat grey radiance
(512 x 512 pixels, so the measured sigma has a standard error of 0.14 %), read as
omniflow reads a camera image. Every bound was measured on these inputs and is written
next to it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnisim.camera import CameraModel
from omnisim.camera_noise import LUMA_SQUARES, grey_noise_level, grey_noise_variance
from tests.helpers.noise_frames import camera_frames

CAMERAS = [{}, {"read_noise": 20.0}, {"bits": 12}, {"full_well": 80000.0}, {"full_well": 5000.0}]


@pytest.mark.parametrize("params", CAMERAS)
@pytest.mark.parametrize("brightness", [0.1, 0.3, 0.4, 0.8])
def test_prediction_is_the_flat_fields_noise(params, brightness):
    model = CameraModel(**params)
    grey = camera_frames(model, np.full((512, 512), brightness / model.exposure), 0)
    offset = 255 * brightness - math.floor(255 * brightness)  # where the value falls (8 bits)
    exact = math.sqrt(float(grey_noise_variance(model, brightness, offset=offset)))
    # measured flat / predicted over these 20 cases: 0.9979-1.0014; bound 1 %
    assert grey.std() == pytest.approx(exact, rel=0.01)


def test_linear_formula_by_hand():
    """Default camera at I = 0.5: a = 0.5619 / 20000, b = 0.5619 (5 / 20000)^2 + q^2 / 12."""
    level = grey_noise_level(CameraModel(bits=12))
    q = 1 / 4095
    assert LUMA_SQUARES == pytest.approx(0.2126**2 + 0.7152**2 + 0.0722**2)
    assert level.a == pytest.approx(0.56192 / 20000, rel=1e-4)
    assert level.b == pytest.approx(0.56192 * ((5 / 20000) ** 2 + q * q / 12), rel=1e-4)
    # 12 bits: no second rounding, so the exact variance is the linear one
    assert float(grey_noise_variance(CameraModel(bits=12), 0.5)) == pytest.approx(
        level.a * 0.5 + level.b
    )


def test_eight_bit_second_rounding_is_not_a_twelfth():
    """At 8 bits the grey value is rounded twice; the linear formula errs by a few %."""
    model = CameraModel()
    ratio = math.sqrt(float(grey_noise_variance(model, 0.1))) / grey_noise_level(model).sigma_at(
        0.1
    )
    # measured exact (averaged over the sub-level offset) / linear: 1.088 at I = 0.1
    assert 1.05 < ratio < 1.12


def test_srgb_is_refused():
    with pytest.raises(ValueError, match="response = 'srgb'"):
        grey_noise_level(CameraModel(response="srgb"))
