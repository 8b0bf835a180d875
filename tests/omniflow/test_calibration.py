"""Tests of omniflow.geometry.calibration: the rim circle and a Unit from it (eq. 2).

Rim images come from omnisim.synthetic: the textured room seen by one unit,
the rim antialiased by its area coverage in each pixel (synthetic.rim_coverage:
exact chords integrated by Gauss-Legendre quadrature, error < 2e-4 px^2).
A real rig's lit, textured surround is pasted outside the rim with the same
coverage weights (textured_surround_image). Accuracy figures were measured by
running these cases and printing the errors; ``python tests/omniflow/test_calibration.py``
prints the surround table of docs/decisions/rim_calibration.md.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest
from scipy import ndimage

from omniflow.geometry.calibration import RimError, calibrate_unit, find_rim
from omniflow.geometry.rig import Rig, Unit
from omnisim.synthetic import SyntheticScene, rim_coverage


def _unit(width, height, x_c, y_c, r_m) -> Unit:
    return Unit(
        d=0.1, R=0.05, x_c=x_c, y_c=y_c, r_m=r_m, width=width, height=height, tip_h=0.0, name="cam2"
    )


def _rim_image(width, height, x_c, y_c, r_m, *, noise=0.0, seed=0, outside=0.0):
    cam2 = _unit(width, height, x_c, y_c, r_m)
    rig = Rig(cam1=dataclasses.replace(cam2, tip_h=0.3, name="cam1"), cam2=cam2, s=0.3)
    scene = dataclasses.replace(SyntheticScene.room(rig, texture_seed=seed), outside=outside)
    return scene.render("cam2", 0, noise=noise, seed=seed)


def surround_texture(shape, *, mean, amplitude, seed, scale=2.0):
    """A lit, textured surround: Gaussian-filtered noise at 0.7, ``scale`` and 4 ``scale`` px."""
    rng = np.random.default_rng(seed)
    tex = np.zeros(shape)
    for sigma, weight in ((scale, 1.0), (4 * scale, 1.0), (0.7, 0.3)):
        layer = ndimage.gaussian_filter(rng.standard_normal(shape), sigma)
        tex += weight * layer / layer.std()
    return mean + amplitude * tex / tex.std()


def textured_surround_image(size, dx, dy, r_frac, *, mean, amplitude, noise, seed):
    """The room seen by one unit, the surround outside its rim pasted in, plus noise.

    The rim is antialiased exactly: image = (room) * coverage + surround * (1 - coverage),
    with the pixel's area inside the rim from synthetic.rim_coverage. The room's texture
    near the rim has mean 0.50 and standard deviation 0.06.
    """
    unit = _unit(size, size, size / 2 + dx, size / 2 + dy, r_frac * size)
    rig = Rig(cam1=dataclasses.replace(unit, tip_h=0.3, name="cam1"), cam2=unit, s=0.3)
    inside = SyntheticScene.room(rig, texture_seed=seed).render("cam2", 0)  # 0 outside
    tex = surround_texture((size, size), mean=mean, amplitude=amplitude, seed=seed + 100)
    img = inside + (1 - rim_coverage(unit)) * tex
    img += noise * np.random.default_rng(seed + 7).standard_normal(img.shape)
    return img, (unit.x_c, unit.y_c, unit.r_m)


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
    # max |error| 0.019 px, so a margin of ~5x.
    assert np.abs(err).max() < 0.1, err
    assert rim.residual_px < 0.3  # measured <= 0.015 px RMS (smoothed along the circle)
    assert rim.inlier_fraction > 0.9  # measured 1.0


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
        # A bright square: its edges are not a circle (296 of 720 rays agree, 0.5 needed).
        (np.pad(np.ones((60, 60)), 34), "no consistent rim circle|no rim circle"),
        # Uniform noise: no circular edge stands out.
        (np.random.default_rng(0).random((128, 128)), "no consistent rim circle|no rim circle"),
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


def test_rim_near_a_known_circle():
    """``near``: the coarse search skipped. From a start 1.5 px off the rim is found to
    0.0025 px (measured; bound 0.1 px as above); a start whose 3 px band misses the rim
    (5.4 px small: 198 of 720 rays agree) and a bad circle are refused."""
    img = _rim_image(160, 128, 81.3, 62.7, 55.4)
    rim = find_rim(img, near=(79.8, 63.9, 56.0))
    assert np.abs([rim.x_c - 81.3, rim.y_c - 62.7, rim.r_m - 55.4]).max() < 0.1
    with pytest.raises(RimError):
        find_rim(img, near=(81.3, 62.7, 50.0))
    with pytest.raises(RimError, match="near"):
        find_rim(img, near=(float("nan"), 62.7, 55.4))


# -- a lit, textured surround (issue 11 item 10) ---------------------------------------------
# size, centre offset (dx, dy), r_m / size, surround mean and texture amplitude, noise.
SURROUND_CASES = [
    (256, 3.3, -2.7, 0.47, 0.8, 0.10, 0.01),  # bright surround
    (256, -6.6, 4.1, 0.45, 0.3, 0.10, 0.01),  # dark surround
    (256, 6.6, -2.7, 0.47, 0.65, 0.20, 0.03),  # strong texture, noisy
    (512, 3.3, -2.7, 0.47, 0.8, 0.10, 0.01),
    (512, -9.9, 5.4, 0.44, 0.3, 0.10, 0.02),
    (512, 6.6, -2.7, 0.47, 0.65, 0.20, 0.03),
    (512, 1.7, 0.9, 0.49, 0.75, 0.15, 0.05),  # noise 0.05
]


def _timed_find_rim(img):
    t = time.perf_counter()
    rim = find_rim(img)
    return rim, time.perf_counter() - t


@pytest.mark.parametrize("case", SURROUND_CASES)
@pytest.mark.parametrize("seed", [1, 2])
def test_rim_with_a_lit_textured_surround(case, seed):
    size, dx, dy, r_frac, mean, amplitude, noise = case
    img, truth = textured_surround_image(
        size, dx, dy, r_frac, mean=mean, amplitude=amplitude, noise=noise, seed=seed
    )
    rim, seconds = _timed_find_rim(img)
    err = np.array([rim.x_c, rim.y_c, rim.r_m]) - truth
    # Required: 0.1 px. Measured over these cases, seeds 1-2
    # (python tests/omniflow/test_calibration.py):
    # max |error| 0.049 px (seeds 1-3: also 0.049); the table is in
    # docs/decisions/rim_calibration.md.
    assert np.abs(err).max() < 0.1, err
    assert rim.inlier_fraction > 0.85  # measured >= 0.91
    # Required: under 1 s per 512 x 512 image. Measured 0.4-0.8 s per image on the shared
    # 2-core machine under load; bounded at 3 s here so that a loaded CI runner does not
    # fail it (the 1 s figure is checked by the table, docs/decisions/rim_calibration.md).
    assert seconds < 3.0


@pytest.mark.parametrize(
    "case",
    [
        # width, height, x_c, y_c, r_m, surround mean, texture amplitude, noise
        (128, 120, 60.3, 58.2, 63.5, 0.8, 0.1, 0.01),  # rim cut by the image border
        (640, 480, 322.4, 236.1, 200.3, 0.3, 0.1, 0.02),  # not square
        (512, 512, 250.2, 262.7, 270.0, 0.8, 0.1, 0.01),  # rim cut by the image border
        (1024, 1024, 515.5, 509.9, 480.2, 0.8, 0.15, 0.02),
    ],
)
def test_rim_cut_or_not_square_with_a_lit_surround(case):
    width, height, x_c, y_c, r_m, mean, amplitude, noise = case
    unit = _unit(width, height, x_c, y_c, r_m)
    rig = Rig(cam1=dataclasses.replace(unit, tip_h=0.3, name="cam1"), cam2=unit, s=0.3)
    img = SyntheticScene.room(rig, texture_seed=1).render("cam2", 0)
    tex = surround_texture((height, width), mean=mean, amplitude=amplitude, seed=101)
    img += (1 - rim_coverage(unit)) * tex + noise * np.random.default_rng(1).standard_normal(
        img.shape
    )
    rim = find_rim(img)
    # Measured (seeds 1-2): max |error| 0.025 px; 0.33-0.48 s each. Required 0.1 px.
    assert np.abs(np.array([rim.x_c - x_c, rim.y_c - y_c, rim.r_m - r_m])).max() < 0.1


@pytest.mark.parametrize("seed", [1, 2])
def test_rim_hidden_in_texture_is_refused_or_right(seed):
    # A surround with the same mean as the scene and 2.5 times its texture: the rim is
    # barely visible. Measured: refused (RimError) for seed 1, found within 0.027 px for
    # seed 2 at 256 px. Never a wrong circle silently: either it raises or it is right.
    img, truth = textured_surround_image(
        256, 3.3 * seed, -2.7, 0.47, mean=0.5, amplitude=0.15, noise=0.02, seed=seed
    )
    try:
        rim = find_rim(img)
    except RimError:
        return
    assert np.abs(np.array([rim.x_c, rim.y_c, rim.r_m]) - truth).max() < 0.1


def test_rim_search_fails_without_smoothing_along_the_circle():
    # The mutation the surround cases catch: with no smoothing along the circle
    # (arc_sigma=0) the texture's own edges win on some rays; measured on the strong-texture
    # 512 px case: error 0.1-0.4 px or a RimError, against 0.05 px with the default.
    img, truth = textured_surround_image(
        512, 6.6, -2.7, 0.47, mean=0.65, amplitude=0.2, noise=0.03, seed=1
    )
    try:
        rim = find_rim(img, arc_sigma=0.0)
        worse = np.abs(np.array([rim.x_c, rim.y_c, rim.r_m]) - truth).max() >= 0.1
    except RimError:
        worse = True
    assert worse


def main() -> None:
    """Print the error and time table of the surround cases (docs/decisions/rim_calibration.md)."""
    print("| size | centre offset | r_m | surround mean, texture | noise | seed | "
          "max abs error x_c, y_c, r_m (px) | inliers | time (s) |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    worst, times = 0.0, []
    cases = [*SURROUND_CASES, (256, 3.3, -2.7, 0.47, 0.5, 0.15, 0.02)]
    for size, dx, dy, r_frac, mean, amplitude, noise in cases:
        for seed in (1, 2):
            img, truth = textured_surround_image(
                size, dx, dy, r_frac, mean=mean, amplitude=amplitude, noise=noise, seed=seed
            )
            try:
                rim, seconds = _timed_find_rim(img)
            except RimError as exc:
                text, inl, seconds = f"RimError ({str(exc)[:40]}...)", "", float("nan")
            else:
                e = np.abs(np.array([rim.x_c, rim.y_c, rim.r_m]) - truth)
                worst = max(worst, e.max()) if mean != 0.5 else worst
                text, inl = " ".join(f"{v:.3f}" for v in e), f"{rim.inlier_fraction:.2f}"
                if size == 512:
                    times.append(seconds)
            print(f"| {size} | ({dx:+.1f}, {dy:+.1f}) | {r_frac * size:.1f} | {mean}, {amplitude} "
                  f"| {noise} | {seed} | {text} | {inl} | {seconds:.2f} |")  # fmt: skip
    print(f"worst error (lit surround cases): {worst:.3f} px; 512 px time median "
          f"{np.median(times):.2f} s, max {np.max(times):.2f} s")  # fmt: skip


if __name__ == "__main__":  # python tests/omniflow/test_calibration.py
    main()
