"""Procedural and image textures (omnisim.textures)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from omnisim import textures


def _band_power(channel: np.ndarray, f_lo: float, f_hi: float) -> tuple[float, float, float]:
    """(power in the band, power outside it, excluding DC) of a square periodic image."""
    n = channel.shape[0]
    spec = np.abs(np.fft.fft2(channel.astype(np.float64))) ** 2
    f = np.fft.fftfreq(n, d=1.0 / n)
    fr = np.hypot(*np.meshgrid(f, f, indexing="ij"))
    inside = (fr >= f_lo - 1e-9) & (fr <= f_hi + 1e-9)
    dc = fr == 0
    return spec[inside].sum(), spec[~inside & ~dc].sum(), spec[dc].sum()


def test_noise_is_deterministic_for_a_seed():
    kw = dict(tile=2.0, wavelength=(0.05, 0.5), resolution=128)
    a = textures.noise_texture(seed=3, **kw)
    b = textures.noise_texture(seed=3, **kw)
    c = textures.noise_texture(seed=4, **kw)
    assert a.dtype == np.float32 and a.shape == (128, 128, 3)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).mean() > 0.02


@pytest.mark.parametrize("exponent", [0.0, 1.0, 2.0])
def test_noise_is_band_limited(exponent):
    tile, lam = 2.0, (0.05, 0.4)  # 5 .. 40 cycles per tile
    tex = textures.noise_texture(
        tile=tile, wavelength=lam, resolution=256, exponent=exponent, seed=1
    )
    for ch in range(3):
        inside, outside, _ = _band_power(tex[..., ch], tile / lam[1], tile / lam[0])
        assert inside > 0
        # Only float32 rounding outside the band (measured ~1e-13 relative).
        assert outside / inside < 1e-9, (ch, outside / inside)


def test_noise_fills_its_band_and_uses_the_colour_range():
    tile, lam = 1.0, (1 / 40, 1 / 5)
    tex = textures.noise_texture(tile=tile, wavelength=lam, resolution=256, seed=2)
    grey = tex.mean(axis=2).astype(np.float64)
    spec = np.abs(np.fft.fft2(grey - grey.mean())) ** 2
    f = np.fft.fftfreq(256, d=1 / 256)
    fr = np.hypot(*np.meshgrid(f, f, indexing="ij"))
    low = spec[(fr >= 5) & (fr < 10)].sum()
    high = spec[(fr > 30) & (fr <= 40)].sum()
    assert low > 0 and high > 0  # both ends of the band are present
    lo, hi = np.asarray(textures.DEFAULT_COLORS[0]), np.asarray(textures.DEFAULT_COLORS[1])
    assert tex.min() >= lo.min() - 1e-6 and tex.max() <= hi.max() + 1e-6
    assert tex.max() - tex.min() > 0.5 * (hi - lo).max()  # peak normalised: full contrast


def test_noise_tiles_without_a_seam():
    tex = textures.noise_texture(tile=1.0, wavelength=(0.02, 0.2), resolution=256, seed=5)
    g = tex[..., 1].astype(np.float64)
    interior = np.abs(np.diff(g, axis=1)).mean()
    seam = np.abs(g[:, 0] - g[:, -1]).mean()
    assert seam < 2 * interior
    interior_v = np.abs(np.diff(g, axis=0)).mean()
    assert np.abs(g[0] - g[-1]).mean() < 2 * interior_v


def test_noise_band_errors():
    with pytest.raises(ValueError, match="Nyquist"):
        textures.noise_pattern(64, 2.0, 40.0)
    with pytest.raises(ValueError):
        textures.noise_pattern(64, 0.0, 10.0)


def test_grating_is_one_frequency():
    tex = textures.grating_texture(tile=1.0, wavelength=0.1, angle=0.0, resolution=128)
    inside, outside, _ = _band_power(tex[..., 0], 10, 10)
    assert outside / inside < 1e-9
    # Angle 90 degrees varies along v (rows) only.
    tex = textures.grating_texture(tile=1.0, wavelength=0.25, angle=90.0, resolution=64)
    assert np.ptp(tex[0, :, 0]) < 1e-6 and np.ptp(tex[:, 0, 0]) > 0.3


def test_checker_and_solid():
    tex = textures.checker_texture(tile=1.0, size=0.25, resolution=64)
    values = np.unique(tex[..., 0])
    assert len(values) == 2
    assert tex[0, 0, 0] != tex[0, 16, 0] and tex[0, 0, 0] == tex[0, 32, 0]
    solid = textures.solid_texture([0.2, 0.3, 0.4])
    assert solid.dtype == np.float32
    np.testing.assert_allclose(solid[1, 2], [0.2, 0.3, 0.4], rtol=1e-6)


def test_sample_texture_texel_centres_and_wrap():
    rng = np.random.default_rng(0)
    tex = rng.random((8, 16, 3)).astype(np.float32)
    i, j = 3, 11
    u, v = (j + 0.5) / 16, (i + 0.5) / 8
    np.testing.assert_allclose(textures.sample_texture(tex, u, v), tex[i, j], rtol=1e-6)
    np.testing.assert_allclose(textures.sample_texture(tex, u + 2, v - 1), tex[i, j], rtol=1e-6)
    # Half-way between two texels along u: their mean; wrap-around at the right edge.
    mid = textures.sample_texture(tex, 16 / 16, v)  # between column 15 and column 0
    np.testing.assert_allclose(mid, (tex[i, 15] + tex[i, 0]) / 2, rtol=1e-6)
    uu = np.full((2, 3), u)
    assert textures.sample_texture(tex, uu, uu).shape == (2, 3, 3)


def test_load_image_texture_png_srgb_and_16bit(tmp_path):
    img = np.zeros((4, 6, 3), np.uint8)
    img[..., 0] = 255  # OpenCV writes BGR: blue channel
    img[..., 2] = 128  # red channel
    cv2.imwrite(str(tmp_path / "a.png"), img)
    tex = textures.load_image_texture(tmp_path / "a.png")
    assert tex.shape == (4, 6, 3) and tex.dtype == np.float32
    np.testing.assert_allclose(tex[0, 0], [textures.srgb_to_linear(128 / 255), 0, 1], rtol=1e-5)
    raw = textures.load_image_texture(tmp_path / "a.png", srgb=False)
    np.testing.assert_allclose(raw[0, 0], [128 / 255, 0, 1], rtol=1e-5)
    grey16 = np.full((5, 5), 65535, np.uint16)
    cv2.imwrite(str(tmp_path / "b.png"), grey16)
    np.testing.assert_allclose(textures.load_image_texture(tmp_path / "b.png")[2, 2], 1.0)
    (tmp_path / "c.png").write_bytes(b"not an image")
    with pytest.raises(ValueError, match="readable"):
        textures.load_image_texture(tmp_path / "c.png")
