"""Tests of the polar edge finder, eq. (19)-(20).

Figures measured by printing the maxima on these inputs (same images and
seeds as here); each bound names the measured value and its margin.
"""

from __future__ import annotations

import numpy as np
import pytest

from omniflow.geometry.rig import Unit
from omniflow.paper.dct import fit_dct
from omniflow.paper.edges import polar_gradient, polar_gradient_grid

# Off-centre axis, non-square image, so x/y or row/col mix-ups show.
UNIT = Unit(d=0.1, R=0.05, x_c=60.3, y_c=66.8, r_m=55.0, width=128, height=120)


def _random_fit(dtype=np.float64, seed=0, **kw):
    img = np.random.default_rng(seed).random((UNIT.height, UNIT.width)).astype(dtype)
    return fit_dct(img, **kw)


@pytest.mark.parametrize(
    ("dtype", "atol_h", "atol_theta"),
    [
        # Measured max |grid - point|: float64 8.2e-16 (f_h) and 7.1e-14 (f_theta,
        # which scales with h_i up to ~90 px); float32 1.0e-7 and 1.6e-6. Bounds x10-x100.
        (np.float64, 1e-13, 1e-11),
        (np.float32, 1e-6, 2e-5),
    ],
)
def test_grid_path_agrees_with_point_path(dtype, atol_h, atol_theta):
    fit = _random_fit(dtype)
    x, y = UNIT.pixel_centres()
    gh, gt = polar_gradient_grid(fit, UNIT)
    ph, pt = polar_gradient(fit, UNIT, x, y)
    assert gh.shape == (UNIT.height, UNIT.width) and gh.dtype == dtype
    np.testing.assert_allclose(gh, ph, rtol=0, atol=atol_h)
    np.testing.assert_allclose(gt, pt, rtol=0, atol=atol_theta)


def test_polar_gradient_matches_finite_differences_in_h_and_theta():
    fit = _random_fit()
    rng = np.random.default_rng(1)
    h_i, theta = rng.uniform(5, 50, 300), rng.uniform(-np.pi, np.pi, 300)
    f_h, f_theta = polar_gradient(fit, UNIT, *UNIT.pixel_of_polar(h_i, theta))

    def f(h, t):
        return fit.evaluate(*UNIT.pixel_of_polar(h, t))

    e_h, e_t = 1e-4, 1e-6  # px and rad (e_t h_i <= 5e-5 px)
    fd_h = (f(h_i + e_h, theta) - f(h_i - e_h, theta)) / (2 * e_h)
    fd_t = (f(h_i, theta + e_t) - f(h_i, theta - e_t)) / (2 * e_t)
    # Measured max: 8.0e-11 (f_h, scale 0.13) and 7.2e-10 (f_theta, scale 3.7); bounds x10.
    np.testing.assert_allclose(f_h, fd_h, rtol=0, atol=1e-9)
    np.testing.assert_allclose(f_theta, fd_t, rtol=0, atol=1e-8)


def _ring_image(x, y):
    """f = exp(-(h - 30)^2 / 32) (1 + cos(3 theta) / 2) and its exact polar gradient."""
    dx, dy = x - UNIT.x_c, y - UNIT.y_c
    h, t = np.hypot(dx, dy), np.arctan2(dy, dx)
    ring = np.exp(-((h - 30.0) ** 2) / (2 * 4.0**2))
    f = ring * (1 + 0.5 * np.cos(3 * t))
    return f, -(h - 30.0) / 4.0**2 * f, ring * (-1.5 * np.sin(3 * t))


@pytest.mark.parametrize(
    ("band", "atol_h", "atol_theta"),
    [
        # A Gaussian ring of sigma = 4 px has its spectrum at sigma_f = 0.04 cycles/px.
        # Measured max error (scale of f_h 0.23, of f_theta 1.5):
        # band 0.25 (cut-off 3 sigma_f): 2.0e-3 and 2.5e-2; band 0.5: 2.8e-8 and 1.3e-7
        # (band 0.1875: 2.2e-2 and 0.30). Bounds x2; the band-0.5 bounds show convergence.
        (0.25, 4e-3, 5e-2),
        (0.5, 6e-8, 3e-7),
    ],
)
def test_polar_gradient_approaches_the_analytic_one_inside_the_band(band, atol_h, atol_theta):
    x, y = UNIT.pixel_centres()
    img, f_h, f_theta = _ring_image(x, y)
    gh, gt = polar_gradient_grid(fit_dct(img, band=band), UNIT)
    np.testing.assert_allclose(gh, f_h, rtol=0, atol=atol_h)
    np.testing.assert_allclose(gt, f_theta, rtol=0, atol=atol_theta)


def test_radial_pattern_has_no_angular_gradient_and_vice_versa():
    x, y = UNIT.pixel_centres()
    dx, dy = x - UNIT.x_c, y - UNIT.y_c
    h = np.hypot(dx, dy)
    radial = np.exp(-((h - 30.0) ** 2) / 32.0)
    fit = fit_dct(radial, band=0.5)
    gh, gt = polar_gradient_grid(fit, UNIT)
    # A purely radial pattern: f_theta is 0 up to the fit's error. Measured max |f_theta|
    # 1.1e-7 against max |f_h| h_i ~ 0.15 x 30 = 4.5; bound x10.
    assert np.abs(gt).max() < 1e-6
    assert np.abs(gh).max() > 0.1


def test_centre_gives_nan_radial_derivative():
    fit = _random_fit()
    f_h, f_theta = polar_gradient(fit, UNIT, UNIT.x_c, UNIT.y_c)
    assert np.isnan(f_h) and f_theta == 0.0


def test_grid_rejects_a_unit_of_another_size():
    fit = fit_dct(np.zeros((64, 64)))
    with pytest.raises(ValueError, match="same image size"):
        polar_gradient_grid(fit, UNIT)
