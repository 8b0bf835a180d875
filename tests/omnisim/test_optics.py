"""The thin lens in front of the cone (omnisim.optics): parsing, rays, and the blur."""

from __future__ import annotations

import gc
import math
from pathlib import Path

import numpy as np
import pytest

from omniflow.geometry.rig import Rig
from omnisim.optics import (
    NUMPY_OPS,
    Optics,
    cone_blur_sigma,
    image_distance,
    thin_lens_cone_ray,
)
from omnisim.sensor import mirror_rays

RIG = Rig.symmetric(d=0.10, R=0.05, s=0.30, size=256)  # r_m = 126 px, v = 378 px
WALL = 2.7  # metres from the axis, the issue's wall


def test_chief_ray_is_the_pinhole_ray():
    """Through the lens centre the ray is the pinhole's (mirror_rays), at any focus."""
    u = RIG.cam2
    rng = np.random.default_rng(3)
    x, y = rng.uniform(0, 256, 2000), rng.uniform(0, 256, 2000)
    ref = mirror_rays(u, x, y)
    for focus in (0.1, 0.7, 5.0):
        q, w, ok = thin_lens_cone_ray(
            NUMPY_OPS, x - u.x_c, y - u.y_c, 0.0, 0.0, v=u.v, d=u.d, focus=focus
        )
        keep = ref.valid & (ref.h_i > 1e-6)
        assert ok[keep].all()
        origin = np.stack([q[0], q[1], q[2] + u.tip_h], axis=-1)
        np.testing.assert_allclose(origin[keep], ref.origin[keep], atol=1e-14)
        np.testing.assert_allclose(np.stack(w, -1)[keep], ref.direction[keep], atol=1e-12)


def test_lens_rays_reflect_off_the_cone_and_meet_at_the_focus():
    """Every lens ray lies on the cone, obeys the mirror law, and passes the focus point."""
    u = RIG.cam2
    rng = np.random.default_rng(4)
    n = 3000
    px, py = rng.uniform(-90, 90, n), rng.uniform(-90, 90, n)
    lx, ly = rng.uniform(-2e-3, 2e-3, n), rng.uniform(-2e-3, 2e-3, n)
    focus = 0.25
    q, w, ok = thin_lens_cone_ray(NUMPY_OPS, px, py, lx, ly, v=u.v, d=u.d, focus=focus)
    q, w = np.stack(q, -1), np.stack(w, -1)
    assert ok.all()
    np.testing.assert_allclose(np.hypot(q[:, 0], q[:, 1]), q[:, 2], atol=1e-12)
    # incoming direction: from the lens point to the mirror point; it passes the focus F
    inc = q - np.stack([lx, ly, np.full(n, -u.d)], -1)
    inc /= np.linalg.norm(inc, axis=1, keepdims=True)
    f_pt = np.stack([px, py, np.full(n, u.v)], -1) * (focus / u.v) - [0, 0, u.d]
    to_f = f_pt - np.stack([lx, ly, np.full(n, -u.d)], -1)
    np.testing.assert_allclose(np.cross(inc, to_f), 0.0, atol=1e-15)
    # mirror law: w = inc - 2 (inc . n) n with the cone's outward normal (x, y, -z)/|.|
    nrm = q * [1, 1, -1] / np.linalg.norm(q, axis=1, keepdims=True)
    refl = inc - 2 * np.sum(inc * nrm, axis=1, keepdims=True) * nrm
    np.testing.assert_allclose(w, refl, atol=1e-12)


def test_closed_form_reproduces_the_issues_table():
    """The issue's sigmas (512 px, f/2.8, f = 5.6 mm, wall at 2.7 m), focus 0.10 and 0.20 m.

    The table's figures come from an independent ray-traced check; agreement to 0.02 px
    (its two decimals and the issue's rounding) shows the closed form is the same model.
    """
    v = (0.10 / 0.05 + 1) * 254  # 512 px, margin 2: r_m = 254
    h_i = np.array([20.0, 80.0, 160.0, 240.0])
    table = {
        0.10: ([3.68] * 4, [0.20, 0.76, 1.43, 2.01]),
        0.20: ([1.76, 1.77, 1.77, 1.77], [1.71, 1.15, 0.48, 0.10]),
    }
    for focus, (rad, tan) in table.items():
        r, t = cone_blur_sigma(v=v, d=0.10, optics=Optics(2.8, 5.6e-3, focus), h_i=h_i, r=WALL)
        np.testing.assert_allclose(r, rad, atol=0.02)
        np.testing.assert_allclose(t, tan, atol=0.02)


# ---------------------------------------------------------------------------
# the render
# ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def mi():
    pytest.importorskip("mitsuba")
    from omnisim.sensor import ensure_mitsuba

    mod = ensure_mitsuba()
    yield mod
    gc.collect()


def _spot_variance(mi, optics, h_i, theta=0.7, half=20, spp=1024):
    """Radial and tangential variance (px^2) of a small emitting sphere's rendered image.

    The sphere (radius 4 mm) sits on the 2.7 m wall where eq. (1) images it at (h_i,
    theta); only a 40 x 40 crop around it is rendered, on a black background.
    """
    from omnisim.sensor import sensor_dict

    u = RIG.cam2
    centre = [WALL * np.cos(theta), WALL * np.sin(theta), h_i * (u.d + WALL) / u.v]
    ox = int(u.x_c + h_i * np.cos(theta)) - half
    oy = int(u.y_c + h_i * np.sin(theta)) - half
    sd = sensor_dict(u, spp, "independent", optics)
    sd["film"].update(crop_offset_x=ox, crop_offset_y=oy, crop_width=2 * half, crop_height=2 * half)
    emitter = {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "direct"},
            "sensor": sd,
            "src": {"type": "sphere", "center": centre, "radius": 0.004, "emitter": emitter},
        }
    )
    img = np.array(mi.render(scene, spp=spp, seed=1), dtype=np.float64)[..., 0]
    jj, ii = np.meshgrid(np.arange(2 * half) + ox + 0.5, np.arange(2 * half) + oy + 0.5)
    dx, dy = jj - u.x_c, ii - u.y_c
    w = img / img.sum()
    out = []
    for a in (np.hypot(dx, dy), h_i * np.arctan2(dy, dx)):
        m = np.sum(w * a)
        out.append(np.sum(w * (a - m) ** 2))
    return out


@pytest.mark.render
@pytest.mark.parametrize("focus", [0.10, 0.20])
def test_rendered_point_blur_matches_thin_lens_geometry(mi, focus):
    """Radial and tangential blur of a point through the cone, against the closed form.

    f/1.4, f = 5.6 mm at 256 px (the issue's f/2.8 at 512 px scaled). The lens blur's
    variance is the rendered spot's minus the pinhole spot's (the sphere's own size and
    the pixel box; variances add under convolution). Measured: within 6 % of
    :func:`cone_blur_sigma` wherever it is 0.5 px or more (5.2 % worst, tangential at
    focus 0.20 m, h_i = 60 px); the test allows the issue's 10 %. Below 0.5 px the
    difference from the pinhole is not resolved by 4 mm source and 1024 spp, so there
    the spot must only stay under 0.5 px.
    """
    optics = Optics(1.4, 5.6e-3, focus)
    u = RIG.cam2
    for h_i in (30.0, 60.0, 110.0):
        lens = _spot_variance(mi, optics, h_i)
        pin = _spot_variance(mi, Optics(), h_i)
        measured = np.sqrt(np.maximum(np.subtract(lens, pin), 0.0))
        expected = cone_blur_sigma(v=u.v, d=u.d, optics=optics, h_i=h_i, r=WALL)
        for got, want, name in zip(measured, expected, ("radial", "tangential"), strict=True):
            where = f"focus {focus} m, h_i {h_i} px, {name}"
            if want >= 0.5:
                assert got == pytest.approx(float(want), rel=0.10), where
            else:
                assert got < 0.5, where


def test_image_distance_is_the_thin_lens_equation():
    # 1/f = 1/D + 1/v_img: f = 5.6 mm, D = 0.2 m -> v_img = 5.6 * 200 / 194.4 mm
    assert image_distance(5.6e-3, 0.2) == pytest.approx(5.6e-3 * 0.2 / 0.1944, rel=1e-12)
    assert Optics().pinhole and Optics().aperture_radius == 0.0
    assert Optics(2.0, 4e-3, 1.0).aperture_radius == pytest.approx(1e-3)
    assert math.isinf(Optics().f_number)


# ---------------------------------------------------------------------------
# the [optics] table
# ---------------------------------------------------------------------------
DEFAULT_SCENE = Path(__file__).resolve().parents[2] / "scenes" / "default.toml"
LENS = {"optics.f_number": 2.8, "optics.focal_length": 5.6e-3, "optics.focus_distance": 0.2}


def test_optics_table_defaults_to_a_pinhole_and_derives_the_pitch():
    from omnisim.scene import load_scene

    assert load_scene(DEFAULT_SCENE, {"render.width": 64, "render.height": 64}).optics.pinhole
    sc = load_scene(DEFAULT_SCENE, LENS)
    # 512 px, margin 2: v = 3 * 254 = 762 px; pitch = f D / (D - f) / v
    assert sc.optics.pixel_pitch == pytest.approx(5.6e-3 * 0.2 / (0.2 - 5.6e-3) / 762, rel=1e-12)
    assert sc.optics.aperture_radius == pytest.approx(1e-3)
    ok = load_scene(DEFAULT_SCENE, {**LENS, "optics.pixel_pitch": 7.4e-6})  # 3.2 % off
    assert ok.optics.pixel_pitch == 7.4e-6


@pytest.mark.parametrize(
    ("extra", "fragment"),
    [
        ({"optics.pixel_pitch": 7.0e-6}, "optics.pixel_pitch (set by an override): got 7e-06 m"),
        ({"optics.f_number": 0}, "optics.f_number (set by an override): got 0, expected a number"),
        ({"optics.focus_distance": 0.005}, "expected more than focal_length (0.0056 m)"),
        ({"optics.aperture": 2}, "optics.aperture (set by an override): unknown key"),
    ],
)
def test_optics_table_errors_name_the_key(extra, fragment):
    from omnisim.scene import SceneError, load_scene

    with pytest.raises(SceneError) as err:
        load_scene(DEFAULT_SCENE, {**LENS, **extra})
    assert fragment in str(err.value)


def test_a_lens_needs_its_focal_length():
    from omnisim.scene import SceneError, load_scene

    with pytest.raises(SceneError) as err:
        load_scene(DEFAULT_SCENE, {"optics.f_number": 2.8, "optics.focus_distance": 0.2})
    assert "optics.focal_length: missing" in str(err.value)
