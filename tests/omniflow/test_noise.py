"""Tests of omniflow.fit.noise: Immerkaer's estimate, the fitted gradient's noise, the band choice.

Every bound was measured by printing the figure on these inputs (seeds fixed in
each test) and is written next to it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from omniflow.fit.noise import (
    BAND_CANDIDATES,
    choose_band,
    gradient_noise_variance,
    immerkaer_sigma,
    predicted_gain,
)
from omniflow.paper.dct import band_window, fit_dct


def _smooth(size: int, seed: int, cutoff: float = 0.1) -> np.ndarray:
    """A random image band-limited to ``cutoff`` of each axis (in [0, 1] roughly)."""
    rng = np.random.default_rng(seed)
    spec = np.zeros((size, size))
    k = int(cutoff * size)
    spec[:k, :k] = rng.normal(0, 1, (k, k)) / (1 + np.arange(k)[:, None] + np.arange(k)[None, :])
    import scipy.fft

    img = scipy.fft.idctn(spec, norm="ortho")
    return 0.5 + 0.2 * img / img.std()


@pytest.mark.parametrize("sigma", [0.005, 0.02])
def test_immerkaer_recovers_white_noise_on_a_smooth_image(sigma):
    img = _smooth(256, seed=1) + np.random.default_rng(2).normal(0, sigma, (256, 256))
    # measured estimate / sigma: whole image 0.995 at both levels (bound 6 %); 16 px tiles,
    # 10th percentile, calibrated on white noise: 0.988 (bound 15 %)
    assert immerkaer_sigma(img, block=None) == pytest.approx(sigma, rel=0.06)
    assert immerkaer_sigma(img) == pytest.approx(sigma, rel=0.15)


def test_tiles_ignore_fine_texture():
    """A textured closed-form room: the whole-image estimate counts texture as noise."""
    from omnisim.synthetic import SyntheticScene
    from tests.helpers.scenes import frames, paper_rig

    rig = paper_rig(256)
    scene = SyntheticScene.room(rig, wall_radius=3.0, ceiling=None, texture_seed=7)
    img = np.round(frames(scene, 1)[0][0] * 255) / 255  # 8-bit rounding: sigma 0.0011
    h_i, _ = rig.cam1.polar_of_pixel(*rig.cam1.pixel_centres())
    mask = (h_i > 16) & (h_i < rig.cam1.r_m - 4)
    # measured: whole annulus 0.0154, 16 px tiles (10th percentile) 0.0029
    assert immerkaer_sigma(img, mask, block=None) > 0.01
    assert immerkaer_sigma(img, mask) < 0.004


def test_immerkaer_uses_only_the_mask():
    rng = np.random.default_rng(3)
    img = _smooth(128, seed=4)
    img[:, 64:] += rng.normal(0, 0.05, (128, 64))  # noisy right half
    mask = np.zeros((128, 128), bool)
    mask[:, :60] = True
    # measured 1.5e-5 (the smooth texture alone); the noisy half would give 0.05
    assert immerkaer_sigma(img, mask, block=None) < 0.002
    assert immerkaer_sigma(img, mask, block=8) < 0.002
    assert np.isnan(immerkaer_sigma(img, np.zeros((128, 128), bool)))


@pytest.mark.parametrize("band", [0.25, 0.5])
def test_gradient_noise_variance_matches_fitted_white_noise(band):
    rng = np.random.default_rng(5)
    size, sigma = 128, 0.01
    var = []
    for _ in range(8):
        fx, fy = fit_dct(rng.normal(0, sigma, (size, size)), band=band).grid_gradient()
        inner = slice(8, -8)  # away from the borders, where the cosine basis is even
        var.append(0.5 * (np.var(fx[inner, inner]) + np.var(fy[inner, inner])))
    P = round(band * size)
    pred = gradient_noise_variance(sigma, P, P, size, size)
    # measured ratio empirical / predicted: 1.007 (band 0.25), 0.992 (band 0.5); bound 5 %
    assert np.mean(var) == pytest.approx(pred, rel=0.05)


@pytest.mark.parametrize("taper", [0.5, 1.0])
def test_gradient_noise_variance_with_a_band_window(taper):
    """The rolled-off series (omniflow.paper.dct.band_window) keeps less gradient noise: the
    prediction with the window's weights matches fitted white noise."""
    rng = np.random.default_rng(5)
    size, sigma, band = 128, 0.01, 0.5
    var = []
    for _ in range(8):
        fit = fit_dct(rng.normal(0, sigma, (size, size)), band=band)
        fit = replace(fit, coeffs=fit.coeffs * band_window(fit.Q, fit.P, taper))
        fx, fy = fit.grid_gradient()
        inner = slice(8, -8)
        var.append(0.5 * (np.var(fx[inner, inner]) + np.var(fy[inner, inner])))
    P = round(band * size)
    window = band_window(P, P, taper)
    pred = gradient_noise_variance(sigma, P, P, size, size, window)
    box = gradient_noise_variance(sigma, P, P, size, size)
    # measured ratio empirical / predicted: 0.972 (taper 0.5), 0.973 (taper 1); bound 5 %;
    # the window keeps 0.151 (taper 0.5) and 0.032 (taper 1) of the box's gradient noise
    assert np.mean(var) == pytest.approx(pred, rel=0.05)
    assert pred < 0.2 * box
    assert gradient_noise_variance(sigma, P, P, size, size, np.ones((P, P))) == pytest.approx(box)


def test_predicted_gain_is_the_signal_share_of_the_gradient_power():
    size, sigma = 256, 0.01
    clean = _smooth(size, seed=6, cutoff=0.3)
    noisy = clean + np.random.default_rng(7).normal(0, sigma, clean.shape)
    bands = (0.125, 0.25, 0.5, 0.75)
    pred = predicted_gain(fit_dct(noisy, band=0.75), sigma, bands)
    inner = slice(8, -8)
    for b, g in zip(bands, pred, strict=True):
        cx, cy = fit_dct(clean, band=b).grid_gradient()
        nx, ny = fit_dct(noisy, band=b).grid_gradient()
        share = np.sum(cx[inner, inner] ** 2 + cy[inner, inner] ** 2) / np.sum(
            nx[inner, inner] ** 2 + ny[inner, inner] ** 2
        )
        # measured: predicted 1.000 0.999 0.989 0.947, empirical 1.001 0.999 0.989 0.945
        # (bands 0.125 .. 0.75); bound 0.02
        assert g == pytest.approx(share, abs=0.02)
    assert np.all(np.diff(pred) < 0)  # wider bands keep more noise than signal here


def test_choose_band_narrows_with_noise():
    clean = _smooth(256, seed=8, cutoff=0.3)
    rng = np.random.default_rng(9)
    chosen = []
    bands = (*BAND_CANDIDATES, 0.625, 0.75)
    for sigma in (0.0, 0.01, 0.05, 0.1, 0.2):
        img = clean + rng.normal(0, sigma, clean.shape)
        chosen.append(choose_band(fit_dct(img, band=0.75), sigma, min_gain=0.9, bands=bands))
    # measured: 0.75, 0.75, 0.375, 0.25, 0.125 (texture up to band 0.3, std 0.2)
    assert chosen == [0.75, 0.75, 0.375, 0.25, 0.125]
    # averaging two frames halves the noise: measured 0.4375 instead of 0.375 at sigma 0.05
    fit = fit_dct(clean + rng.normal(0, 0.05, clean.shape), band=0.75)
    assert choose_band(fit, 0.05, frames=2) > choose_band(fit, 0.05, frames=1)
    # the default candidates stop at 1/2; a series narrower than a candidate excludes it
    assert choose_band(fit_dct(clean, band=0.75), 0.0) == 0.5
    assert choose_band(fit_dct(clean, band=0.25), 0.0) == 0.25
