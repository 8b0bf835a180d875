"""The analytic cone-mirror sensor: exact geometry (eq. 1) and the Mitsuba plugin."""

from __future__ import annotations

import gc

import numpy as np
import pytest

from omniflow.geometry.rig import Rig
from omnisim.sensor import apply_affine, mirror_rays, pixel_rays_world, transform_rays

RIG = Rig.symmetric(d=0.10, R=0.05, s=0.30, size=128)


def _pose(yaw=0.4, t=(0.3, -0.2, 0.6), tilt=0.1):
    cz, sz = np.cos(yaw), np.sin(yaw)
    cx, sx = np.cos(tilt), np.sin(tilt)
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    m = np.eye(4)
    m[:3, :3] = rz @ rx
    m[:3, 3] = t
    return m


# ---------------------------------------------------------------------------
# numpy geometry (no Mitsuba)
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("cam", ["cam1", "cam2"])
def test_mirror_rays_match_explicit_vector_reflection(cam):
    """rho = d k / (1 - k) and slope h_i / v agree with reflecting off the cone's normal."""
    unit = getattr(RIG, cam)
    rng = np.random.default_rng(1)
    x = rng.uniform(0, unit.width, 5000)
    y = rng.uniform(0, unit.height, 5000)
    rays = mirror_rays(unit, x, y)
    keep = rays.valid & (rays.h_i > 1e-3)
    x, y = x[keep], y[keep]
    # camera ray from the camera centre through the image point
    c = np.array([0.0, 0.0, unit.tip_h - unit.d])
    w = np.stack([x - unit.x_c, y - unit.y_c, np.full_like(x, unit.v)], axis=-1)
    w /= np.linalg.norm(w, axis=-1, keepdims=True)
    # intersect the cone Z - tip_h = sqrt(X^2 + Y^2): solve along the ray numerically
    # (bisection on f(t) = Z - tip_h - rho, monotone in t on the ray's way up)
    lo, hi = np.zeros(len(x)), np.full(len(x), 10.0)
    for _ in range(200):
        mid = (lo + hi) / 2
        p = c + mid[:, None] * w
        f = p[:, 2] - unit.tip_h - np.hypot(p[:, 0], p[:, 1])
        lo, hi = np.where(f < 0, mid, lo), np.where(f < 0, hi, mid)
    p = c + lo[:, None] * w
    # the cone's unit normal: gradient of Z - tip_h - rho
    rho = np.hypot(p[:, 0], p[:, 1])
    n = np.stack([-p[:, 0] / rho, -p[:, 1] / rho, np.ones_like(rho)], axis=-1) / np.sqrt(2)
    refl = w - 2 * np.sum(w * n, axis=-1, keepdims=True) * n
    np.testing.assert_allclose(rays.origin[keep], p, atol=1e-12)
    np.testing.assert_allclose(rays.direction[keep], refl, atol=1e-12)
    # the reflected ray goes outward along (cos theta, sin theta) with dZ/dr = h_i / v
    d = rays.direction[keep]
    np.testing.assert_allclose(
        d[:, 2] / np.hypot(d[:, 0], d[:, 1]), rays.h_i[keep] / unit.v, rtol=1e-12
    )
    np.testing.assert_allclose(np.arctan2(d[:, 1], d[:, 0]), rays.theta[keep], atol=1e-12)


@pytest.mark.parametrize("cam", ["cam1", "cam2"])
def test_points_on_reflected_rays_obey_eq1(cam):
    unit = getattr(RIG, cam)
    x, y = unit.pixel_centres()
    rays = mirror_rays(unit, x.ravel(), y.ravel())
    v = rays.valid
    for dist in (0.05, 1.0, 7.3):
        p = rays.origin[v] + dist * rays.direction[v]
        r, h = np.hypot(p[:, 0], p[:, 1]), p[:, 2]
        np.testing.assert_allclose(unit.image_radius(r, h), rays.h_i[v], atol=1e-9)
        assert unit.visible(r, h).all()
    # the rim: rho = R exactly at h_i = r_m, and outside the rim nothing is valid
    rim = mirror_rays(unit, [unit.x_c + unit.r_m], [unit.y_c])
    np.testing.assert_allclose(rim.rho, unit.R, rtol=1e-12)
    assert rim.valid.all()
    assert not mirror_rays(unit, [unit.x_c + unit.r_m + 1e-6], [unit.y_c]).valid.any()


def test_other_units_mirror_cannot_be_hit():
    """cam2's fan passes below cam1's camera; cam1's fan stays above cam2's mirror."""
    x, y = RIG.cam2.pixel_centres()
    rays = mirror_rays(RIG.cam2, x.ravel(), y.ravel())
    v = rays.valid
    # height of cam2's rays where they reach r = R (cam1's mirror radius)
    k = rays.h_i[v] / RIG.cam2.v
    z_at_R = rays.origin[v, 2] + (RIG.R - rays.rho[v]) * k
    assert z_at_R.max() <= RIG.R < RIG.s - RIG.d
    rays1 = mirror_rays(RIG.cam1, x.ravel(), y.ravel())
    assert rays1.origin[rays1.valid, 2].min() >= RIG.s > RIG.R
    assert (rays1.direction[rays1.valid, 2] >= 0).all()


def test_transform_rays_is_the_pose():
    m = _pose()
    rng = np.random.default_rng(2)
    p = rng.normal(size=(100, 3))
    d = rng.normal(size=(100, 3))
    o2, d2 = transform_rays(m, p, d)
    np.testing.assert_allclose(o2, p @ m[:3, :3].T + m[:3, 3], atol=1e-14)
    np.testing.assert_allclose(d2, d @ m[:3, :3].T, atol=1e-14)
    np.testing.assert_allclose(apply_affine(np.linalg.inv(m), o2), p, atol=1e-12)


# ---------------------------------------------------------------------------
# Mitsuba
# ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def mi():
    pytest.importorskip("mitsuba")
    from omnisim.sensor import ensure_mitsuba

    mod = ensure_mitsuba()
    yield mod
    gc.collect()


def _sensor_rays(mi, sensor, unit, x, y):
    ray, weight = sensor.sample_ray(
        mi.Float(0.0),
        mi.Float(0.5),
        mi.Point2f(mi.Float(x / unit.width), mi.Float(y / unit.height)),
        mi.Point2f(0.5, 0.5),
    )
    o = np.stack([np.array(c, dtype=np.float64) for c in ray.o], axis=-1)
    d = np.stack([np.array(c, dtype=np.float64) for c in ray.d], axis=-1)
    w = np.array(weight[0], dtype=np.float64)
    return o, d, w


@pytest.mark.render
@pytest.mark.parametrize("cam", ["cam1", "cam2"])
def test_sensor_rays_equal_numpy_rays(mi, cam):
    from omnisim.sensor import make_sensor

    unit = getattr(RIG, cam)
    pose = _pose()
    sensor = make_sensor(unit, pose, spp=1)
    x, y = unit.pixel_centres()
    x, y = x.ravel(), y.ravel()
    o, d, w = _sensor_rays(mi, sensor, unit, x, y)
    o64, d64, rays = pixel_rays_world(unit, pose, x, y)
    v = rays.valid
    assert np.abs(o - o64)[v].max() < 1e-6  # float32 on coordinates of ~1 m
    assert np.abs(d - d64)[v].max() < 1e-6
    assert (w[v] == 1.0).all()  # perfect conductor
    assert (w[~v] == 0.0).all()  # black outside the rim
    # a new pose re-uses the sensor
    sensor.set_pose(np.eye(4))
    o, d, _ = _sensor_rays(mi, sensor, unit, x, y)
    np.testing.assert_allclose(o[v], rays.origin[v], atol=1e-6)


def _open_cylinder(mi, radius, z0, z1, **extra):
    return {
        "type": "cylinder",
        "radius": radius,
        "p0": [0, 0, z0],
        "p1": [0, 0, z1],
        "flip_normals": True,
        **extra,
    }


@pytest.mark.render
@pytest.mark.parametrize("size", [128, 512])
def test_rendered_geometry_departs_from_eq1_by_float32_only(mi, size):
    """Trace each pixel centre's float32 sensor ray through Mitsuba: eq. (1) holds to < 0.02 px."""
    from omnisim.sensor import make_sensor

    rig = Rig.symmetric(d=0.10, R=0.05, s=0.30, size=size)
    scene = mi.load_dict({"type": "scene", "wall": _open_cylinder(mi, 2.5, -3.0, 6.0)})
    worst = 0.0
    for unit in (rig.cam1, rig.cam2):
        sensor = make_sensor(unit, np.eye(4), spp=1)
        x, y = unit.pixel_centres()
        x, y = x.ravel(), y.ravel()
        ray, _ = sensor.sample_ray(
            mi.Float(0.0),
            mi.Float(0.5),
            mi.Point2f(mi.Float(x / unit.width), mi.Float(y / unit.height)),
            mi.Point2f(0.5, 0.5),
        )
        si = scene.ray_intersect(ray)
        p = np.stack([np.array(c, dtype=np.float64) for c in si.p], axis=-1)
        hit = np.array(si.is_valid())
        h_i = np.hypot(x - unit.x_c, y - unit.y_c)
        inside = h_i <= unit.r_m
        assert hit[inside].all()
        r, h = np.hypot(p[:, 0], p[:, 1]), p[:, 2]
        err = np.abs(unit.image_radius(r, h) - h_i)[inside]
        worst = max(worst, float(err.max()))
        # azimuth: the scene's theta is the image's theta (conventions.py)
        th_err = np.abs(
            np.angle(
                np.exp(1j * (np.arctan2(p[:, 1], p[:, 0]) - np.arctan2(y - unit.y_c, x - unit.x_c)))
            )
        )
        assert (th_err[inside & (h_i > 1)] * h_i[inside & (h_i > 1)]).max() < 0.02
    print(f"\n{size}x{size}: max departure of the rendered geometry from eq. (1): {worst:.2e} px")
    assert worst < 0.02


def _rim_coverage(unit, n=32):
    """Fraction of each pixel's area inside the rim circle (n x n supersampling)."""
    off = (np.arange(n) + 0.5) / n
    x, y = unit.pixel_centres()
    inside = np.zeros(x.shape)
    for ox in off:
        for oy in off:
            inside += np.hypot(x - 0.5 + ox - unit.x_c, y - 0.5 + oy - unit.y_c) <= unit.r_m
    return inside / n**2


@pytest.mark.render
def test_constant_sky_gives_reflectance_one_and_the_rim_at_pixel_edges(mi):
    """Under a uniform sky of radiance 1, a pixel's value is the fraction of it inside the rim.

    Checks the perfect-conductor weight (exactly 1), black outside the rim and
    the pixel convention (pixel (i, j) covers [j, j+1) x [i, i+1)).
    """
    from omnisim.sensor import make_sensor

    rig = Rig.symmetric(d=0.10, R=0.05, s=0.30, size=64, r_m=27.3)
    unit = rig.cam2
    scene = mi.load_dict({"type": "scene", "sky": {"type": "constant", "radiance": 1.0}})
    sensor = make_sensor(unit, np.eye(4), spp=256)
    img = np.array(
        mi.render(scene, sensor=sensor, integrator=mi.load_dict({"type": "direct"}), seed=3)
    )[..., 0]
    cov = _rim_coverage(unit)
    assert (img[cov == 1.0] == 1.0).all()
    assert (img[cov == 0.0] == 0.0).all()
    edge = (cov > 0) & (cov < 1)
    assert edge.sum() > 50
    # 256 stratified samples per pixel: the coverage estimate is within a few percent
    assert np.abs(img - cov)[edge].max() < 0.08
    assert np.abs(img - cov)[edge].mean() < 0.02


@pytest.mark.render
def test_emissive_textured_wall_renders_its_closed_form_image(mi):
    """An emitting textured cylinder round the axis: each pixel shows the texture at (theta, h).

    The expected image is closed form: h = tip_h + h_i (d + r) / v (eq. 1),
    u = theta / 2 pi, v = (h - z0) / (z1 - z0) (Mitsuba's cylinder UVs).
    """
    from omnisim.sensor import make_sensor
    from omnisim.textures import sample_texture

    size = 128
    rig = Rig.symmetric(d=0.10, R=0.05, s=0.30, size=size)
    n = 256
    uu, vv = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n)
    tex = 0.5 + 0.3 * np.sin(2 * np.pi * 3 * uu) * np.cos(2 * np.pi * 2 * vv)
    tex = np.repeat(tex[..., None], 3, axis=-1).astype(np.float32)
    radius, z0, z1 = 2.0, -1.0, 3.0
    scene = mi.load_dict(
        {
            "type": "scene",
            "wall": _open_cylinder(
                mi,
                radius,
                z0,
                z1,
                emitter={
                    "type": "area",
                    "radiance": {
                        "type": "bitmap",
                        "bitmap": mi.Bitmap(tex),
                        "raw": True,
                        "filter_type": "bilinear",
                        "wrap_mode": "repeat",
                    },
                },
            ),
        }
    )
    for unit in (rig.cam1, rig.cam2):
        sensor = make_sensor(unit, np.eye(4), spp=64)
        img = np.array(
            mi.render(scene, sensor=sensor, integrator=mi.load_dict({"type": "direct"}), seed=1)
        )[..., 0]
        x, y = unit.pixel_centres()
        h_i, theta = unit.polar_of_pixel(x, y)
        h = unit.height_of(radius, h_i)
        u = np.mod(theta, 2 * np.pi) / (2 * np.pi)
        expected = sample_texture(tex, u, (h - z0) / (z1 - z0))[..., 0]
        keep = (h_i > 12) & (h_i < unit.r_m - 1.5)
        diff = (img - expected)[keep]
        assert np.abs(diff).mean() < 0.01, np.abs(diff).mean()
        assert np.corrcoef(img[keep], expected[keep])[0, 1] > 0.99
