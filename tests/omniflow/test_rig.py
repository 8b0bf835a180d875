"""Tests of the rig model omniflow.geometry.rig (eq. 1-7): geometry, stereo, unwarping, files.

Float64 geometry round trips are exact to rounding. Maxima measured by
printing them on the same points: see each bound's comment.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from omniflow.geometry.rig import Rig, RigError, Unit, load_rig, rig_from_dict, unwarp

D, R_MIRROR, S = 0.10, 0.05, 0.30


@pytest.fixture
def rig() -> Rig:
    return Rig.symmetric(d=D, R=R_MIRROR, s=S, size=128)


@pytest.fixture
def odd_rig() -> Rig:
    """Different centres and rim radii per unit, so v_1 != v_2."""
    cam1 = Unit(
        d=D, R=R_MIRROR, x_c=70.3, y_c=61.8, r_m=58.0, width=140, height=120, tip_h=S, name="cam1"
    )
    cam2 = Unit(
        d=D, R=R_MIRROR, x_c=66.9, y_c=59.1, r_m=55.5, width=140, height=120, tip_h=0.0, name="cam2"
    )
    out = Rig(cam1=cam1, cam2=cam2, s=S)
    out.validate()
    return out


def _scene_points(rig: Rig, n: int = 500, seed: int = 0):
    """Random points in the common field of view: r in [1, 10] m, h between the limits."""
    rng = np.random.default_rng(seed)
    r = rng.uniform(1.0, 10.0, n)
    top = (D + r) * R_MIRROR / (D + R_MIRROR)  # cam2's upper limit, eq. (1) at h_i = r_m
    h = rng.uniform(S, top, n)
    theta = rng.uniform(-np.pi, np.pi, n)
    return r, theta, h


# -- one unit: eq. (1), (2), (6), (7) ------------------------------------------------


def test_hand_computed_projection(rig):
    cam2 = rig.cam2
    assert cam2.r_m == 62.0 and cam2.x_c == 64.0
    assert cam2.v == pytest.approx(186.0)  # eq. (2): (0.1 / 0.05 + 1) 62
    # r = 2.9 m, h = 0.6 m: h_i = 186 * 0.6 / 3.0 = 37.2 px (eq. 1).
    assert cam2.image_radius(2.9, 0.6) == pytest.approx(37.2)
    assert rig.cam1.image_radius(2.9, 0.6) == pytest.approx(186.0 * 0.3 / 3.0)  # eq. (3)
    # theta = +pi/2 (rig +Y) is image +y: below the centre on screen.
    x, y = cam2.project(2.9, np.pi / 2, 0.6)
    assert x == pytest.approx(64.0) and y == pytest.approx(64.0 + 37.2)
    x, y = cam2.project(2.9, 0.0, 0.6)
    assert x == pytest.approx(64.0 + 37.2) and y == pytest.approx(64.0)


@pytest.mark.parametrize("cam", ["cam1", "cam2"])
def test_rim_point_maps_to_r_m(odd_rig, cam):
    unit = getattr(odd_rig, cam)
    # The rim is at r = R, h = tip_h + R (45-degree cone): eq. (2) makes its image r_m.
    assert unit.image_radius(R_MIRROR, unit.tip_h + R_MIRROR) == pytest.approx(unit.r_m, rel=1e-12)
    assert unit.visible(R_MIRROR, unit.tip_h + R_MIRROR)


@pytest.mark.parametrize("cam", ["cam1", "cam2"])
def test_project_and_back_round_trip(odd_rig, cam):
    unit = getattr(odd_rig, cam)
    r, theta, h = _scene_points(odd_rig)
    x, y = unit.project(r, theta, h)
    h_i, th = unit.polar_of_pixel(x, y)
    # Measured max relative error: cam2 1.1e-15; cam1 5.8e-13 in r and 4.4e-13 rad in
    # theta, from points just above cam1's tip that image within 1e-3 px of the centre
    # (x_c + h_i cos(theta) keeps few digits of h_i there). Bounds 1e-10: x170.
    np.testing.assert_allclose(unit.range_of(h, h_i), r, rtol=1e-10)
    np.testing.assert_allclose(unit.height_of(r, h_i), h, rtol=1e-12)  # measured 1.1e-15
    np.testing.assert_allclose(np.angle(np.exp(1j * (th - theta))), 0.0, atol=1e-10)
    hx, hy = unit.pixel_of_polar(h_i, th)  # eq. (6), (7)
    np.testing.assert_allclose(hx, x, rtol=1e-12)
    np.testing.assert_allclose(hy, y, rtol=1e-12)


def test_pixel_centres_follow_the_conventions(odd_rig):
    x, y = odd_rig.cam1.pixel_centres()
    assert x.shape == (120, 140)
    assert x[0, 0] == 0.5 and y[0, 0] == 0.5 and x[0, 139] == 139.5 and y[119, 0] == 119.5


def test_visibility_limits(rig):
    cam2, cam1 = rig.cam2, rig.cam1
    r = 2.0
    top = (D + r) * R_MIRROR / (D + R_MIRROR)  # h_i = r_m exactly
    assert cam2.visible(r, top) and not cam2.visible(r, top * (1 + 1e-9))
    assert cam2.visible(r, 1e-9) and not cam2.visible(r, 0.0) and not cam2.visible(r, -0.1)
    assert cam1.visible(r, S + top) and not cam1.visible(r, S) and not cam1.visible(r, S - 0.01)
    # A point inside the mirror's own radius is in front of where its ray leaves the cone.
    k = 0.2  # slope of the ray: h = k (d + r) for r >= rho = d k / (1 - k) = 0.025
    assert cam2.visible(0.03, k * (D + 0.03)) and not cam2.visible(0.02, k * (D + 0.02))
    # Visible points image inside the rim.
    r_s, _, h_s = _scene_points(rig)
    assert np.all(cam2.image_radius(r_s, h_s) <= cam2.r_m * (1 + 1e-12))


def test_ray_slope_is_h_i_over_v(rig):
    cam2 = rig.cam2
    h_i = 30.0
    r1, r2 = 1.0, 4.0
    dh = cam2.height_of(r2, h_i) - cam2.height_of(r1, h_i)
    assert dh / (r2 - r1) == pytest.approx(cam2.ray_slope(h_i)) == pytest.approx(h_i / cam2.v)


# -- coaxial stereo: eq. (3), (4), (5) ---------------------------------------------


@pytest.mark.parametrize("which", ["rig", "odd_rig"])
def test_triangulate_inverts_stereo_radii(which, request):
    rig = request.getfixturevalue(which)
    r, _, h = _scene_points(rig)
    h1, h2 = rig.stereo_radii(r, h)
    assert np.all(h2 > h1 * rig.cam2.v / rig.cam1.v)  # positive disparity
    r_t, h_t = rig.triangulate(h1, h2)  # eq. (5)
    np.testing.assert_allclose(r_t, r, rtol=1e-12)  # measured 2.9e-15 relative
    np.testing.assert_allclose(h_t, h, rtol=1e-12)


def test_eq5_literal_form_for_identical_units(rig):
    r, _, h = _scene_points(rig, n=50)
    h1, h2 = rig.stereo_radii(r, h)
    v = rig.cam2.v
    np.testing.assert_allclose(v * S / (h2 - h1) - D, r, rtol=1e-11)  # eq. (5) as printed
    np.testing.assert_allclose(h2 * (D + r) / v, h, rtol=1e-12)  # eq. (4)


def test_nonpositive_disparity_gives_infinite_range(rig):
    r, h = rig.triangulate([10.0, 10.0], [10.0, 9.0])
    assert np.all(np.isinf(r)) and np.all(np.isnan(h))


def test_disparity_window_brackets_the_match(odd_rig):
    r, _, h = _scene_points(odd_rig, n=200)
    r_min, r_max = 2.0, 6.0
    h1, h2 = odd_rig.stereo_radii(r, h)
    lo, hi = odd_rig.disparity_window(h1, r_min, r_max)
    inside = (r >= r_min) & (r <= r_max)
    assert np.all((h2 >= lo - 1e-9) & (h2 <= hi + 1e-9) == inside)
    # The window's ends are the images of the range limits.
    h1_at = odd_rig.cam1.image_radius(r_min, h[0])
    lo0, hi0 = odd_rig.disparity_window(h1_at, r_min, r_max)
    assert hi0 == pytest.approx(odd_rig.cam2.image_radius(r_min, h[0]), rel=1e-12)
    h1_at = odd_rig.cam1.image_radius(r_max, h[0])
    lo0, hi0 = odd_rig.disparity_window(h1_at, r_min, r_max)
    assert lo0 == pytest.approx(odd_rig.cam2.image_radius(r_max, h[0]), rel=1e-12)


def test_common_region_starts_at_min_common_range(rig):
    r0 = rig.min_common_range  # s (d + R) / R - d = 0.8 m
    assert r0 == pytest.approx(0.8)
    eps = 1e-6
    assert rig.common_region(r0 + 0.01, S + eps)
    assert not np.any(rig.common_region(r0 - 0.01, np.linspace(0.0, 2.0, 2001)))


# -- unwarping (eq. 6, 7) ----------------------------------------------------------


def test_unwarp_maps_a_radial_line_to_a_column_and_a_circle_to_a_row(odd_rig):
    unit = odd_rig.cam2
    x, y = unit.pixel_centres()
    h_i, theta = unit.polar_of_pixel(x, y)
    theta0 = 1.0  # a radial line at theta = 1 rad
    line = np.exp(-0.5 * (np.angle(np.exp(1j * (theta - theta0))) * h_i / 1.5) ** 2)
    width, height = 360, 50
    pano = unwarp(line, unit, width=width, height=height)
    assert pano.shape == (height, width)
    expected_col = theta0 * width / (2 * np.pi) - 0.5  # theta_i = 2 pi (x + 0.5) / width
    rows = slice(0, 30)  # h_i >= 22 px: the line is several samples wide in theta below that
    cols = np.argmax(pano[rows], axis=1)
    assert np.all(np.abs(cols - expected_col) <= 1)
    # A ring at h_i = 30 px: the row with h_i = r_m (height - (y + 0.5)) / height.
    ring = np.exp(-0.5 * ((h_i - 30.0) / 1.5) ** 2)
    pano = unwarp(ring, unit, width=width, height=height)
    expected_row = height - 30.0 * height / unit.r_m - 0.5
    assert np.all(np.abs(np.argmax(pano, axis=0) - expected_row) <= 1)


def test_unwarp_keeps_channels(rig):
    img = np.ones((128, 128, 3), np.float32)
    assert unwarp(img, rig.cam1, width=64, height=16).shape == (16, 64, 3)


# -- files and dicts -----------------------------------------------------------------


def test_to_dict_round_trips_through_json_and_toml(odd_rig, tmp_path):
    data = odd_rig.to_dict()
    assert rig_from_dict(data) == odd_rig
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data))
    assert load_rig(path) == odd_rig
    toml = tmp_path / "rig.toml"
    toml.write_text(
        f"[rig]\nd = {D}\nR = {R_MIRROR}\ns = {S}\n"
        + "".join(
            f"[[cameras]]\nname = '{c.name}'\nx_c = {c.x_c}\ny_c = {c.y_c}\nr_m = {c.r_m}\n"
            f"width = {c.width}\nheight = {c.height}\n"
            for c in (odd_rig.cam1, odd_rig.cam2)
        )
    )
    assert load_rig(toml) == odd_rig


def _good() -> dict:
    """A minimal valid rig dict (no optional v / tip_h)."""
    data = Rig.symmetric(d=D, R=R_MIRROR, s=S, size=64).to_dict()
    for cam in data["cameras"]:
        del cam["v"], cam["tip_h"]
    return data


def _edit(path, value):
    data = _good()
    node = data
    for key in path[:-1]:
        node = node[key]
    if value is _DELETE:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return data


_DELETE = object()


@pytest.mark.parametrize(
    ("path", "value", "match"),
    [
        (("rig", "d"), _DELETE, r"rig\.d is missing"),
        (("rig", "R"), "big", r"rig\.R = 'big': expected a finite number"),
        (("rig", "s"), math.nan, r"rig\.s = nan"),
        (("rig", "s"), 0.12, r"rig\.s = 0\.12 too small"),
        (("rig", "d"), -0.1, r"d = -0\.1: expected > 0"),
        (("cameras", 0, "x_c"), _DELETE, r"cameras\[0\] \(cam1\)\.x_c is missing"),
        (("cameras", 1, "r_m"), True, r"cameras\[1\] \(cam2\)\.r_m = True"),
        (("cameras", 0, "name"), "left", r"name = 'left'"),
        (("cameras", 0, "focal"), 3.0, r"unknown key\(s\) \['focal'\]"),
        (("rig", "baseline"), 0.3, r"rig: unknown key\(s\) \['baseline'\]; expected \['R', 'd'"),
        (
            ("cameras", 1, "v"),
            999.0,
            r"cameras\[1\] \(cam2\)\.v = 999\.0: disagrees with eq\. \(2\)",
        ),
        (("cameras", 0, "tip_h"), 0.0, r"cameras\[0\] \(cam1\)\.tip_h = 0\.0: expected 0\.3"),
        (("cameras", 0, "name"), "cam2", r"cameras\[1\]\.name = 'cam2'"),
        (("cameras", 1, "x_c"), 500.0, r"centre \(500\.0, 32\.0\) lies outside"),
        (("cameras", 1, "width"), 4, r"width = 4: expected integer >= 8"),
        (("cameras",), [], r"exactly two cameras"),
    ],
)
def test_rig_from_dict_errors_name_the_field(path, value, match):
    with pytest.raises(RigError, match=match):
        rig_from_dict(_edit(path, value), where="rig.json")


def test_rig_entry_that_is_not_a_table_is_a_rig_error():
    with pytest.raises(RigError, match="rig"):
        rig_from_dict(_edit(("rig",), None), where="rig.json")


def test_rig_from_dict_rejects_non_tables():
    with pytest.raises(RigError, match="expected a table 'rig'"):
        rig_from_dict([1, 2])


def test_fractional_image_size_is_rejected():
    with pytest.raises(RigError, match="width"):
        rig_from_dict(_edit(("cameras", 0, "width"), 64.5))


def test_load_rig_file_errors(tmp_path):
    with pytest.raises(RigError, match="rig file not found"):
        load_rig(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[rig\nd = 1")
    with pytest.raises(RigError, match=r"bad\.toml: not valid TOML"):
        load_rig(bad)
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    with pytest.raises(RigError, match=r"bad\.json: not valid JSON"):
        load_rig(bad)


def test_rig_validate_requires_shared_mirror_and_tips(rig):
    with pytest.raises(RigError, match="share d and R"):
        dataclasses.replace(rig, cam1=dataclasses.replace(rig.cam1, d=0.2)).validate()
    with pytest.raises(RigError, match="tip_h"):
        dataclasses.replace(rig, cam1=dataclasses.replace(rig.cam1, tip_h=0.0)).validate()


# -- dtypes --------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int64])
def test_dtype_sweep(rig, dtype):
    r = np.array([1, 2, 5, 9], dtype=dtype)
    h = np.array([1, 1, 2, 3], dtype=dtype)
    theta = np.array([0, 1, 2, -3], dtype=dtype)
    as64 = [a.astype(np.float64) for a in (r, theta, h)]
    # The model computes in float64 whatever comes in: the results equal the float64
    # ones for the same input values, bit for bit.
    for got, ref in zip(rig.cam2.project(r, theta, h), rig.cam2.project(*as64), strict=True):
        assert got.dtype == np.float64
        np.testing.assert_array_equal(got, ref)
    h1, h2 = rig.stereo_radii(r, h)
    assert h1.dtype == h2.dtype == np.float64
    # Radii stored in the input dtype (e.g. a float32 image pipeline) still triangulate:
    # float32 rounding of h_1, h_2 (6e-8 relative) gives measured max 2.8e-7 relative
    # error in r and h here (5.5e-7 over the random points of the tests above: the
    # disparity amplifies it); bound 1e-5.
    r_t, h_t = rig.triangulate(h1.astype(np.float32), h2.astype(np.float32))
    np.testing.assert_allclose(r_t, r, rtol=1e-5)
    np.testing.assert_allclose(h_t, h, rtol=1e-5)


def test_polar_angle_is_in_half_open_interval():
    unit = Unit(d=D, R=R_MIRROR, x_c=32.5, y_c=32.5, r_m=30.0, width=65, height=65)
    _, theta = unit.polar_of_pixel(10.5, 32.5)
    assert -np.pi <= theta < np.pi
