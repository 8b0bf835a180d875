"""Tests of omniflow.paper.dct: eq. (17)-(18), the fast grid paths and the 3-D fit.

Tolerances were measured by printing the maxima on these inputs (random images,
40 x 56 with the seed of each test; the figures are repeated next to each
bound) and set with the stated margin.
"""

from __future__ import annotations

import numpy as np
import pytest

from omniflow.paper.dct import DCTFit, band_window, fit_dct, fit_dct3

# Per-dtype bound on reconstruction / path agreement, relative to grey levels in [0, 1].
# Measured max: float64 8e-15 (full-band evaluate), float32 2.7e-7 (full-band grid).
# Margins: float64 x100, float32 x7 (float32 rounding varies with the image size).
TOL = {np.float64: 1e-12, np.float32: 2e-6}


def _random(shape, dtype, seed):
    return np.random.default_rng(seed).random(shape).astype(dtype)


def _centres(width, height):
    return np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_full_band_reproduces_the_image(dtype):
    img = _random((40, 56), dtype, seed=1)
    fit = fit_dct(img, band=1.0)
    x, y = _centres(56, 40)
    assert fit.coeffs.shape == (40, 56) and fit.coeffs.dtype == np.float64
    assert fit.grid().dtype == dtype
    np.testing.assert_allclose(fit.grid(), img, rtol=0, atol=TOL[dtype])
    np.testing.assert_allclose(fit.evaluate(x, y), img, rtol=0, atol=TOL[dtype])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_coefficients_match_eq17_summed_by_hand(dtype):
    img = _random((40, 56), dtype, seed=2)
    fit = fit_dct(img)
    height, width = img.shape
    assert (fit.Q, fit.P) == (10, 14)  # Q = round(40 / 4), P = round(56 / 4)
    q, p = np.arange(fit.Q), np.arange(fit.P)
    cos_x = np.cos(np.pi * np.outer(p, np.arange(width) + 0.5) / width)
    cos_y = np.cos(np.pi * np.outer(q, np.arange(height) + 0.5) / height)
    a = np.where(q[:, None] == 0, 1, 2) * np.where(p[None, :] == 0, 1, 2)
    expected = a / (width * height) * (cos_y @ img.astype(float) @ cos_x.T)  # eq. (17)
    # Measured: float64 2.4e-16, float32 2.8e-8.
    np.testing.assert_allclose(fit.coeffs, expected, rtol=0, atol=TOL[dtype])


def test_hand_computed_coefficients():
    width, height = 32, 24
    x, y = _centres(width, height)
    img = (
        3.0
        + 2.0 * np.cos(np.pi * 2 * x / width) * np.cos(np.pi * y / height)
        - 0.5 * np.cos(np.pi * 5 * y / height)
    )
    fit = fit_dct(img)
    expected = np.zeros((6, 8))
    expected[0, 0], expected[1, 2], expected[5, 0] = 3.0, 2.0, -0.5
    np.testing.assert_allclose(fit.coeffs, expected, rtol=0, atol=1e-13)  # measured 2.4e-16
    assert fit.evaluate(0.0, 0.0) == pytest.approx(3.0 + 2.0 - 0.5, abs=1e-13)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_grid_paths_agree_with_point_paths(dtype):
    img = _random((40, 56), dtype, seed=3)
    fit = fit_dct(img)
    x, y = _centres(56, 40)
    # Measured: float64 5.6e-16 (values) 2.9e-16 (gradients); float32 1.5e-7, 1.9e-8.
    np.testing.assert_allclose(fit.grid(), fit.evaluate(x, y), rtol=0, atol=TOL[dtype])
    gx, gy = fit.grid_gradient()
    px, py = fit.gradient(x, y)
    assert gx.dtype == dtype and gx.shape == (40, 56)
    np.testing.assert_allclose(gx, px, rtol=0, atol=TOL[dtype])
    np.testing.assert_allclose(gy, py, rtol=0, atol=TOL[dtype])


def test_gradient_matches_finite_differences():
    img = _random((40, 56), np.float64, seed=4)
    fit = fit_dct(img)
    rng = np.random.default_rng(5)
    xs, ys = rng.uniform(0, 56, 200), rng.uniform(0, 40, 200)
    gx, gy = fit.gradient(xs, ys)
    e = 1e-4
    fdx = (fit.evaluate(xs + e, ys) - fit.evaluate(xs - e, ys)) / (2 * e)
    fdy = (fit.evaluate(xs, ys + e) - fit.evaluate(xs, ys - e)) / (2 * e)
    # Central differences with e = 1e-4 px: measured max error 6.7e-11 (rounding
    # ~1e-16 / 1e-4 and truncation ~e^2 f'''); bound x15.
    np.testing.assert_allclose(gx, fdx, rtol=0, atol=1e-9)
    np.testing.assert_allclose(gy, fdy, rtol=0, atol=1e-9)


def test_shapes_are_kept_at_arbitrary_points():
    fit = fit_dct(_random((16, 16), np.float64, seed=6))
    x = np.full((3, 4, 2), 7.25)
    assert fit.evaluate(x, x).shape == (3, 4, 2)
    assert all(g.shape == (3, 4, 2) for g in fit.gradient(x, x))
    assert np.ndim(fit.evaluate(3.0, 4.0)) == 0


def test_band_and_explicit_sizes():
    img = _random((30, 50), np.float64, seed=7)
    assert fit_dct(img).coeffs.shape == (8, 12)  # round(7.5) = 8 (banker's), round(12.5) = 12
    assert fit_dct(img, band=0.5).coeffs.shape == (15, 25)
    assert fit_dct(img, P=3, Q=5).coeffs.shape == (5, 3)


@pytest.mark.parametrize(
    ("image", "kwargs", "match"),
    [
        (np.zeros((4, 4, 3)), {}, "2 dimensions"),
        (np.full((8, 8), np.nan), {}, "NaN"),
        (np.zeros((8, 8)), {"band": 0.0}, "band"),
        (np.zeros((8, 8)), {"P": 9}, "P = 9"),
        (np.zeros((8, 8)), {"Q": 0}, "Q = 0"),
        (np.zeros((1, 8)), {}, "at least 2"),
    ],
)
def test_bad_input_raises(image, kwargs, match):
    with pytest.raises(ValueError, match=match):
        fit_dct(image, **kwargs)


def test_evaluate_rejects_unequal_shapes():
    fit = fit_dct(np.zeros((8, 8)))
    with pytest.raises(ValueError, match="equal shapes"):
        fit.evaluate(np.zeros(3), np.zeros(4))


def test_integer_images_are_accepted_as_float64():
    fit = fit_dct(np.arange(64, dtype=np.uint8).reshape(8, 8))
    assert fit.dtype == np.float64 and isinstance(fit, DCTFit)


# -- 3-D fit -----------------------------------------------------------------


def test_dct3_full_band_reproduces_each_frame():
    frames = _random((5, 24, 32), np.float64, seed=8)
    fit = fit_dct3(frames, band=1.0)
    x, y = _centres(32, 24)
    for k in range(5):  # frame k at t = k; measured 7.4e-15
        np.testing.assert_allclose(fit.evaluate(x, y, k), frames[k], rtol=0, atol=1e-12)


def test_dct3_at_a_frame_equals_the_2d_fit_of_that_frame():
    frames = _random((4, 24, 32), np.float64, seed=9)
    fit3 = fit_dct3(frames)
    # With K = T the time series interpolates the frames, so the spatial
    # coefficients at t = k are eq. (17) of frame k. Measured 1.1e-16.
    np.testing.assert_allclose(fit3.at_time(2).coeffs, fit_dct(frames[2]).coeffs, atol=1e-13)


def test_dct3_gradient_matches_finite_differences():
    frames = _random((5, 24, 32), np.float64, seed=10)
    fit = fit_dct3(frames)
    rng = np.random.default_rng(11)
    x, y, t = rng.uniform(0, 32, 200), rng.uniform(0, 24, 200), rng.uniform(0, 4, 200)
    grads = fit.gradient(x, y, t)
    e = 1e-4
    for axis, g in enumerate(grads):
        step = [e * (axis == i) for i in range(3)]
        fd = (
            fit.evaluate(x + step[0], y + step[1], t + step[2])
            - fit.evaluate(x - step[0], y - step[1], t - step[2])
        ) / (2 * e)
        # Measured max 5e-11 (x, y) and 3.2e-9 (t: larger curvature per frame); bound x10.
        np.testing.assert_allclose(g, fd, rtol=0, atol=3e-8)
    np.testing.assert_allclose(
        fit.time_derivative_at(1.3).evaluate(x, y), fit.gradient(x, y, 1.3)[2], atol=1e-13
    )


def test_dct3_time_derivative_of_a_linear_ramp_is_biased_as_derived():
    # Three frames base + g k. The cosine series has zero slope at the ends, so
    # its slope at the middle frame is g pi / (3 cos(pi / 6)) (= 1.2092 g), and
    # g pi / 3 halfway between frames 0 and 1: derived by hand, documented for
    # the "dct3d" temporal variant.
    base = _random((24, 32), np.float64, seed=12)
    g = 0.1
    fit = fit_dct3(np.stack([base + g * k for k in range(3)]))
    assert fit.gradient(16.5, 12.5, 1.0)[2] == pytest.approx(g * np.pi / (3 * np.cos(np.pi / 6)))
    assert fit.gradient(16.5, 12.5, 0.5)[2] == pytest.approx(g * np.pi / 3)


def test_dct3_needs_three_frames():
    with pytest.raises(ValueError, match="T >= 3"):
        fit_dct3(np.zeros((2, 8, 8)))


@pytest.mark.parametrize("frames", [3, 4, 5])
def test_detrended_dct3_is_exact_for_linear_change(frames):
    base = _random((16, 20), np.float64, seed=13)
    g = 0.1
    stack = np.stack([base + g * k for k in range(frames)])
    fit = fit_dct3(stack, band=1.0, detrend=True)
    x, y = _centres(20, 16)
    for t in np.arange(frames - 1) + 0.5:  # measured max error 5.6e-16
        np.testing.assert_allclose(fit.gradient(x, y, t)[2], g, rtol=0, atol=1e-12)
    for k in range(frames):  # still interpolates the frames: measured 2.2e-15
        np.testing.assert_allclose(fit.evaluate(x, y, k), stack[k], rtol=0, atol=1e-12)
    # The plain fit's ends are off by up to 6.3 % (T = 4, t = 0.5: measured 1.063 g).
    plain = fit_dct3(stack, band=1.0).gradient(10.5, 8.5, 0.5)[2]
    assert abs(plain / g - 1) > 0.04


def test_detrended_dct3_derivatives_and_slices_are_consistent():
    frames = _random((4, 16, 20), np.float64, seed=14)
    fit = fit_dct3(frames, detrend=True)
    x, y = _centres(20, 16)
    full = fit_dct3(frames, band=1.0, detrend=True)
    for k in range(4):  # measured 5.2e-15
        np.testing.assert_allclose(full.evaluate(x, y, k), frames[k], rtol=0, atol=1e-12)
    rng = np.random.default_rng(15)
    xs, ys, ts = rng.uniform(0, 20, 100), rng.uniform(0, 16, 100), rng.uniform(0, 3, 100)
    grads = fit.gradient(xs, ys, ts)
    e = 1e-4
    for axis, g in enumerate(grads):
        step = [e * (axis == i) for i in range(3)]
        fd = (
            fit.evaluate(xs + step[0], ys + step[1], ts + step[2])
            - fit.evaluate(xs - step[0], ys - step[1], ts - step[2])
        ) / (2 * e)
        # Measured max 3.7e-11 (x, y) and 2.6e-9 (t); bound as for the plain fit.
        np.testing.assert_allclose(g, fd, rtol=0, atol=3e-8)
    # 2-D slices agree with the 3-D series (measured <= 8.9e-16).
    np.testing.assert_allclose(
        fit.at_time(1.3).evaluate(xs, ys), fit.evaluate(xs, ys, 1.3), atol=1e-13
    )
    np.testing.assert_allclose(
        fit.time_derivative_at(1.3).evaluate(xs, ys), fit.gradient(xs, ys, 1.3)[2], atol=1e-13
    )


def test_band_window_rolls_off_to_the_band_edge():
    """omniflow.paper.dct.band_window: 1 inside (1 - taper) of the band, 0 from its edge on,
    cos^2 between, radial; taper 0 is the sharp truncation (all ones)."""
    assert np.array_equal(band_window(8, 6, 0.0), np.ones((8, 6)))
    w = band_window(64, 64, 0.5)
    rho = np.hypot(np.arange(64)[:, None] / 64, np.arange(64)[None, :] / 64)
    assert np.all(w[rho <= 0.5] == 1.0) and np.all(w[rho >= 1.0] == 0.0)
    assert w[0, 48] == pytest.approx(0.5)  # rho 0.75: halfway down
    assert w[0, 40] == pytest.approx(np.cos(0.5 * np.pi * 0.25) ** 2)  # rho 0.625: 0.854, cos^2
    ramp = w[0, 32:]
    assert np.all(np.diff(ramp) <= 0)  # monotone along an axis
    assert np.allclose(w, w.T)  # radial: the same along both axes
    with pytest.raises(ValueError, match="taper"):
        band_window(4, 4, 1.5)


def test_compiled_bases_equal_the_numpy_form():
    """omniflow.paper.dct_kernels.cos_bases (through dct._bases) gives dct.bases_numpy's cumprod
    bases value for value, at any point and number of coefficients (1 included)."""
    from omniflow.paper.dct import _bases, bases_numpy

    rng = np.random.default_rng(7)
    for n_coef, n in ((256, 512), (37, 100), (1, 8), (2, 8)):
        c = np.concatenate([rng.uniform(-5.0, n + 5.0, 300), [0.0, 0.5, n - 0.5]])
        got, want = _bases(c, n_coef, n), bases_numpy(c, n_coef, n)
        for g, w in zip(got, want, strict=True):
            assert g.shape == w.shape
            np.testing.assert_array_equal(g, w)
        assert got[0].strides == want[0].strides  # the layout the products downstream see


def test_contiguous_bases_give_the_same_products():
    """dct._bases(contiguous=True): the same cosines as a plain array, and the matrix
    product the fits take of them is the strided view's, bit for bit."""
    from omniflow.paper.dct import _bases

    rng = np.random.default_rng(3)
    c = rng.uniform(0.0, 512.0, 500)
    coeffs = rng.standard_normal((256, 256))
    strided, _ = _bases(c, 256, 512)
    plain, _ = _bases(c, 256, 512, contiguous=True)
    assert plain.flags.c_contiguous and not strided.flags.c_contiguous
    np.testing.assert_array_equal(plain, strided)
    np.testing.assert_array_equal(plain @ coeffs, strided @ coeffs)


def test_single_precision_evaluation_agrees_with_double():
    """DCTFit.value_and_gradient(single=True): float32 bases and products, float64 sums
    over p and constant term, returned as float64, near the float64 evaluation; and the
    difference of two nearly equal frames' values (the refinement's residual, eq. 8) too.

    Frames like the rendered ones: grey 0.25 +- 0.08 of smooth texture (|f| <= 0.49,
    |f_x| <= 0.11), the next frame that plus 1e-3 noise (residual rms 3.1e-4; the
    rendered approach pairs': 1e-3), fitted and rolled off as the flow step's series
    (band 0.5, taper 0.5) at 400 points, about the refinement's count.
    """
    from scipy.ndimage import gaussian_filter

    from omniflow.fit.series import truncate

    rng = np.random.default_rng(11)
    tex = gaussian_filter(rng.standard_normal((256, 256)), 1.5)
    img = 0.25 + 0.08 * tex / tex.std()
    nxt = img + 1e-3 * rng.standard_normal(img.shape)
    fits = [truncate(fit_dct(f.astype(np.float32), band=0.5), 0.5, 0.5) for f in (img, nxt)]
    x, y = rng.uniform(2.0, 254.0, (2, 400))
    double = [f.value_and_gradient(x, y) for f in fits]
    single = [f.value_and_gradient(x, y, single=True) for f in fits]
    for got in single:
        assert all(v.dtype == np.float64 and v.shape == (400,) for v in got)
    # Measured (this seed): values 6.1e-8, gradients 2.7e-8, residual 9.8e-8; bounds 2x.
    # With the constant term inside the float32 products: values 2.6e-7, residual 3.5e-7;
    # with the coefficients rounded to float16: 5.3e-5, 8.1e-5 (both fail).
    for d, s in zip(double, single, strict=True):
        np.testing.assert_allclose(s[0], d[0], rtol=0, atol=1.2e-7)
        np.testing.assert_allclose(s[1:], d[1:], rtol=0, atol=5.5e-8)
    residual = [b[0] - a[0] for a, b in (double, single)]
    np.testing.assert_allclose(residual[1], residual[0], rtol=0, atol=2e-7)


def test_column_bases_equal_the_numpy_form_transposed():
    """omniflow.paper.dct_kernels.cos_bases_columns (through dct._bases_columns): dct.bases_numpy's
    cumprod bases transposed, value for value in float64, and those rounded once in
    float32 (mutations caught: the imaginary part updated from the new real part; the
    running product kept in the output's float32)."""
    from omniflow.paper.dct import _bases_columns, bases_numpy

    rng = np.random.default_rng(5)
    for n_coef, n in ((256, 512), (37, 100), (1, 8), (2, 8)):
        c = np.concatenate([rng.uniform(-5.0, n + 5.0, 300), [0.0, 0.5, n - 0.5]])
        want = bases_numpy(c, n_coef, n)
        for dtype in (np.float64, np.float32):
            got = _bases_columns(c, n_coef, n, dtype)
            for g, w in zip(got, want, strict=True):
                assert g.dtype == dtype and g.shape == (n_coef, c.size)
                np.testing.assert_array_equal(g, w.T.astype(dtype))
