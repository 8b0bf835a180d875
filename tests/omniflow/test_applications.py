"""omniflow.applications.navigation against exact values from known motions and poses.

Tolerances are measured (the values quoted beside each bound, with the seeds
used) and given a margin; exact-data cases are checked to float precision.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from omniflow.applications.navigation import (
    odometry,
    position_fix,
    region_flow,
    steering_heading,
    time_to_contact,
)
from omniflow.geometry.rig import Rig
from omniflow.paper.flow import radial_velocity
from omnisim.synthetic import Cylinder, Motion, SyntheticScene, Texture


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def static_flow(theta, r, w, vx, vy):
    """dr/dt and dtheta/dt of static points seen from a robot moving with (w, V_x, V_y)."""
    dr = -(vx * np.cos(theta) + vy * np.sin(theta))
    dth = -w + (vx * np.sin(theta) - vy * np.cos(theta)) / r
    return dr, dth


def observe(landmarks, x, y, yaw):
    """Exact (r, theta) of world landmarks from a robot at (x, y, yaw)."""
    rel = np.asarray(landmarks, float) - (x, y)
    c, s = math.cos(yaw), math.sin(yaw)
    rx = c * rel[:, 0] + s * rel[:, 1]
    ry = -s * rel[:, 0] + c * rel[:, 1]
    return np.hypot(rx, ry), np.arctan2(ry, rx)


@pytest.fixture(scope="module")
def rig():
    return Rig.symmetric(d=0.10, R=0.05, s=0.30, size=128)


# -- radial velocity and time to contact --------------------------------------------


def test_radial_velocity_is_exact_for_the_instantaneous_flow(rig):
    # Static points, robot velocity V: h_1 = v (h - s) / (d + r) (eq. 3) so
    # dh_1/dt = -h_1 (dr/dt) / (d + r); radial_velocity must invert it exactly.
    rng = np.random.default_rng(1)
    r = rng.uniform(0.5, 5.0, 200)
    h = rig.s + rng.uniform(0.05, 0.5, 200)
    dr_true = rng.uniform(-0.05, 0.05, 200)
    h1 = rig.cam1.image_radius(r, h)
    dh1 = -h1 * dr_true / (rig.d + r)
    np.testing.assert_allclose(radial_velocity(r, h1, dh1, d=rig.d), dr_true, rtol=1e-12)


def test_radial_velocity_from_closed_form_flow_of_a_driving_robot(rig):
    # Exact per-pixel truth (omnisim.synthetic): the robot drives 11 mm per frame
    # in a textured round room; the wall is static, so dr of each wall point is
    # known from the world positions. gt.flow.dh is a one-frame displacement, so
    # the first-order formula has a second-order error: measured max 4.0e-5 m
    # (0.4 % of the motion) at 192 px and 128 px with this scene; bound 1e-4 m.
    scene = SyntheticScene.room(rig, wall_radius=3.0, ceiling=None,
                                robot=Motion(velocity=(0.01, -0.005)))  # fmt: skip
    tr = scene.truth("cam1", 0)
    x, y = rig.cam1.pixel_centres()
    h_i, _ = rig.cam1.polar_of_pixel(x, y)
    ok = (tr["gt.valid"] > 0) & (tr["gt.flow.valid"] > 0)
    assert ok.sum() > 5000
    r = tr["gt.r"][ok]
    dr = radial_velocity(r, h_i[ok], tr["gt.flow.dh"][ok], d=rig.d)
    r1, _, _ = scene.world_to_rig(1, tr["gt.X"][ok], tr["gt.Y"][ok], tr["gt.h"][ok])
    true_dr = r1 - r
    assert np.abs(true_dr).max() > 0.009  # the motion is really there
    assert np.abs(dr - true_dr).max() < 1e-4


def test_time_to_contact_head_on_and_receding():
    # A point 2 m ahead approached at 0.05 m/frame is hit in 40 frames.
    assert time_to_contact(2.0, -0.05) == pytest.approx(40.0, rel=1e-15)
    ttc = time_to_contact([2.0, 3.0, 1.0], [-0.1, 0.0, 0.2])
    np.testing.assert_array_equal(ttc, [20.0, np.inf, np.inf])


def test_time_to_contact_from_omni_flow_quantities(rig):
    # Robot driving straight at a static point: dr/dt = -|V|; TTC = r / |V|.
    r, h = np.array([1.5, 2.5]), np.array([0.6, 0.9])
    speed = 0.02
    h1 = rig.cam1.image_radius(r, h)
    dh1 = -h1 * (-speed) / (rig.d + r)
    ttc = time_to_contact(r, radial_velocity(r, h1, dh1, d=rig.d))
    np.testing.assert_allclose(ttc, r / speed, rtol=1e-12)


# -- region flow and steering ----------------------------------------------------------


def _rigid_region(rng, centre, velocity, n=50, size=0.3):
    """Points of an object translating with ``velocity`` relative to the rig."""
    pts = np.asarray(centre) + rng.uniform(-size, size, (n, 2))
    r = np.hypot(pts[:, 0], pts[:, 1])
    theta = np.arctan2(pts[:, 1], pts[:, 0])
    vx, vy = velocity
    dr = vx * np.cos(theta) + vy * np.sin(theta)
    dth = (-vx * np.sin(theta) + vy * np.cos(theta)) / r
    return theta, r, dr, dth, pts


def test_region_flow_recovers_the_relative_motion_exactly():
    rng = np.random.default_rng(2)
    # Object moving (0.03, 0.01) m/frame in the rig frame; robot moving (0.02, -0.01):
    # relative velocity (0.01, 0.02).
    rel = (0.03 - 0.02, 0.01 - -0.01)
    theta, r, dr, dth, pts = _rigid_region(rng, (2.0, 1.0), rel)
    reg = region_flow(theta, r, dr, dth)
    assert reg.count == 50
    np.testing.assert_allclose(reg.velocity, rel, atol=1e-15)
    np.testing.assert_allclose(reg.position, pts.mean(axis=0), atol=1e-14)
    c = pts.mean(axis=0)
    rc = np.hypot(*c)
    assert reg.r == pytest.approx(rc, rel=1e-14)
    assert reg.theta == pytest.approx(math.atan2(c[1], c[0]), abs=1e-14)
    assert reg.dr_dt == pytest.approx(np.dot(c, rel) / rc, rel=1e-12)
    assert reg.dtheta_dt == pytest.approx((c[0] * rel[1] - c[1] * rel[0]) / rc**2, rel=1e-12)
    assert math.isinf(reg.time_to_contact)  # moving away (dr/dt > 0)
    assert all(math.isnan(v) for v in reg.image_flow)


def test_region_flow_time_to_contact_and_image_flow():
    rng = np.random.default_rng(3)
    theta, r, dr, dth, pts = _rigid_region(rng, (3.0, 0.0), (-0.05, 0.0), size=0.1)
    dx = rng.normal(size=theta.size)
    reg = region_flow(theta, r, dr, dth, dx=dx, dy=2 * dx)
    c = pts.mean(axis=0)  # centroid; dr/dt = c . v / |c|, so TTC = |c|^2 / (0.05 c_X)
    assert reg.time_to_contact == pytest.approx(c @ c / (0.05 * c[0]), rel=1e-12)
    assert reg.image_flow == pytest.approx((dx.mean(), 2 * dx.mean()), rel=1e-12)


def test_region_flow_mask_and_non_finite_points():
    rng = np.random.default_rng(4)
    theta, r, dr, dth, _ = _rigid_region(rng, (1.0, 2.0), (0.01, 0.0))
    other = _rigid_region(rng, (-2.0, -1.0), (0.0, 0.05))
    cat = [np.concatenate([a, b]) for a, b in zip((theta, r, dr, dth), other[:4], strict=True)]
    mask = np.arange(100) < 50
    cat[1][0] = np.nan  # dropped, not propagated
    reg = region_flow(*cat, mask=mask)
    assert reg.count == 49
    np.testing.assert_allclose(reg.velocity, (0.01, 0.0), atol=1e-15)
    with pytest.raises(ValueError, match="no point"):
        region_flow(*cat, mask=np.zeros(100, bool))


def test_steering_heading_home_in_and_avoid():
    rng = np.random.default_rng(5)
    theta, r, dr, dth, pts = _rigid_region(rng, (2.0, 0.0), (0.0, 0.1), size=0.05)
    reg = region_flow(theta, r, dr, dth)
    c = pts.mean(axis=0)
    # lead 0: straight at (or away from) the object.
    assert steering_heading(reg, lead=0) == pytest.approx(math.atan2(c[1], c[0]), abs=1e-14)
    # lead 5 frames: aim where it will be, i.e. turned the way its flow goes (+theta here).
    home = steering_heading(reg, mode="home_in", lead=5)
    assert home == pytest.approx(math.atan2(c[1] + 0.5, c[0]), abs=1e-12)
    assert home > reg.theta and reg.dtheta_dt > 0
    avoid = steering_heading(reg, mode="avoid", lead=5)
    assert _wrap(avoid - home - math.pi) == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError, match="mode"):
        steering_heading(reg, mode="follow")
    with pytest.raises(ValueError, match="lead"):
        steering_heading(reg, lead=-1)


# -- position fix ------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(12))
def test_position_fix_exact(seed):
    # Measured over 200 seeded poses (2, 3 and 6 landmarks): max error 2.5e-14.
    rng = np.random.default_rng(seed)
    n = (2, 3, 6)[seed % 3]
    lm = rng.uniform(-5, 5, (n, 2))
    x, y = rng.uniform(-3, 3, 2)
    yaw = rng.uniform(-np.pi, np.pi)
    r, th = observe(lm, x, y, yaw)
    fix = position_fix(lm, r, th)
    assert fix.x == pytest.approx(x, abs=1e-9)
    assert fix.y == pytest.approx(y, abs=1e-9)
    assert _wrap(fix.yaw - yaw) == pytest.approx(0.0, abs=1e-9)
    assert -np.pi <= fix.yaw < np.pi
    assert fix.rms_position < 1e-9
    assert fix.residuals.shape == (n, 2)


def test_position_fix_with_noise():
    # 6 landmarks, range noise 1 cm, bearing noise 2 mrad; over 67 seeds the
    # position error was at most 14.5 mm (median 4.9 mm) and yaw 2.7 mrad.
    worst_pos, worst_yaw = 0.0, 0.0
    for seed in range(20):
        rng = np.random.default_rng(100 + seed)
        lm = rng.uniform(-5, 5, (6, 2))
        x, y = rng.uniform(-3, 3, 2)
        yaw = rng.uniform(-np.pi, np.pi)
        r, th = observe(lm, x, y, yaw)
        fix = position_fix(lm, r + rng.normal(0, 0.01, 6), th + rng.normal(0, 0.002, 6))
        worst_pos = max(worst_pos, math.hypot(fix.x - x, fix.y - y))
        worst_yaw = max(worst_yaw, abs(_wrap(fix.yaw - yaw)))
    assert worst_pos < 0.025
    assert worst_yaw < 0.005


def test_position_fix_robust_loss_survives_a_misidentified_landmark():
    # One of 6 landmarks 1 m off in range (plus 1 cm noise on all): plain least
    # squares was up to 0.41 m off (50 seeds, median 0.19 m); soft_l1 with the
    # expected errors as scales at most 12 mm (median 4.5 mm).
    errs_plain, errs_robust = [], []
    for seed in range(10):
        rng = np.random.default_rng(200 + seed)
        lm = rng.uniform(-5, 5, (6, 2))
        x, y = rng.uniform(-3, 3, 2)
        yaw = rng.uniform(-np.pi, np.pi)
        r, th = observe(lm, x, y, yaw)
        r = r + rng.normal(0, 0.01, 6)
        r[0] += 1.0
        a = position_fix(lm, r, th)
        b = position_fix(lm, r, th, loss="soft_l1", sigma_r=0.01, sigma_theta=0.01)
        errs_plain.append(math.hypot(a.x - x, a.y - y))
        errs_robust.append(math.hypot(b.x - x, b.y - y))
    assert max(errs_robust) < 0.025
    assert np.median(errs_plain) > 5 * np.median(errs_robust)


def test_position_fix_under_determined_is_a_clear_error():
    with pytest.raises(ValueError, match="under-determined: 1 usable landmark"):
        position_fix([[1.0, 2.0]], [1.0], [0.3])
    with pytest.raises(ValueError, match="under-determined: 1 usable landmark"):
        position_fix([[1.0, 2.0], [3.0, 4.0]], [1.0, np.nan], [0.3, 0.2])
    with pytest.raises(ValueError, match="same world position"):
        position_fix([[1.0, 2.0], [1.0, 2.0]], [1.0, 1.0], [0.3, 0.3])
    with pytest.raises(ValueError, match="shape"):
        position_fix([1.0, 2.0], [1.0], [0.3])
    with pytest.raises(ValueError, match="2 landmarks but 3 ranges"):
        position_fix([[1.0, 2.0], [3.0, 4.0]], [1.0, 2.0, 3.0], [0.3, 0.2, 0.1])
    with pytest.raises(ValueError, match="r must be > 0"):
        position_fix([[1.0, 2.0], [3.0, 4.0]], [1.0, -2.0], [0.3, 0.2])


# -- odometry ------------------------------------------------------------------------------


def _odometry_case(seed, n=300, outlier_fraction=0.3):
    """Static points plus independently moving ones (own speed 1-5 cm/frame)."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(-np.pi, np.pi, n)
    r = rng.uniform(0.5, 4.0, n)
    w = rng.uniform(-0.02, 0.02)
    vx, vy = rng.uniform(-0.03, 0.03, 2)
    dr, dth = static_flow(theta, r, w, vx, vy)
    moving = np.zeros(n, bool)
    moving[rng.choice(n, int(outlier_fraction * n), replace=False)] = True
    speed = rng.uniform(0.01, 0.05, moving.sum())
    ang = rng.uniform(-np.pi, np.pi, moving.sum())
    ox, oy = speed * np.cos(ang), speed * np.sin(ang)
    c, s = np.cos(theta[moving]), np.sin(theta[moving])
    dr[moving] += ox * c + oy * s
    dth[moving] += (-ox * s + oy * c) / r[moving]
    return rng, theta, r, dr, dth, (w, vx, vy), moving


@pytest.mark.parametrize("seed", range(5))
def test_odometry_exact_with_30_percent_moving_points(seed):
    # Exact flow: the fit recovers (w, V) to float precision (measured <= 3.5e-18
    # over 30 seeds) and flags exactly the independently moving points.
    _, theta, r, dr, dth, truth, moving = _odometry_case(seed)
    fit = odometry(theta, r, dth, dr)
    np.testing.assert_allclose((fit.w, fit.V_x, fit.V_y), truth, atol=1e-12)
    np.testing.assert_array_equal(fit.inliers, ~moving)
    assert fit.inlier_fraction == pytest.approx(0.7)


@pytest.mark.parametrize("seed", range(3))
def test_odometry_with_noise_matches_the_oracle_fit(seed):
    # Noise 0.5 mm/frame on each point's dr/dt and r dtheta/dt: over 30 seeds the
    # parameter error was at most 9.2e-5 (median 2.7e-5), and the outliers were
    # separated exactly. The robust fit must agree with plain least squares on
    # the truly static points (the oracle) to well under that noise level.
    rng, theta, r, dr, dth, truth, moving = _odometry_case(seed)
    dr = dr + rng.normal(0, 5e-4, r.size)
    dth = dth + rng.normal(0, 5e-4, r.size) / r
    fit = odometry(theta, r, dth, dr)
    np.testing.assert_array_equal(fit.inliers, ~moving)
    st = ~moving
    c, s = np.cos(theta[st]), np.sin(theta[st])
    A = np.concatenate(
        [np.column_stack([-r[st], s, -c]), np.column_stack([np.zeros(st.sum()), -c, -s])]
    )
    b = np.concatenate([r[st] * dth[st], dr[st]])
    oracle = np.linalg.lstsq(A, b, rcond=None)[0]
    np.testing.assert_allclose((fit.w, fit.V_x, fit.V_y), oracle, atol=1e-5)
    np.testing.assert_allclose((fit.w, fit.V_x, fit.V_y), truth, atol=1.5e-4)


@pytest.mark.parametrize("seed", range(3))
def test_own_velocity_is_each_mover_s_velocity(seed):
    # Exact flow: the points' velocity the robot's motion does not explain is each moving
    # point's own velocity (rig frame) and zero on static points, to float precision.
    rng = np.random.default_rng(seed)
    theta = rng.uniform(-np.pi, np.pi, 200)
    r = rng.uniform(0.5, 4.0, 200)
    w, vx, vy = 0.01, 0.02, -0.01
    dr, dth = static_flow(theta, r, w, vx, vy)
    own = np.zeros((200, 2))
    own[:50] = rng.uniform(-0.05, 0.05, (50, 2))
    c, s = np.cos(theta[:50]), np.sin(theta[:50])
    dr[:50] += own[:50, 0] * c + own[:50, 1] * s
    dth[:50] += (-own[:50, 0] * s + own[:50, 1] * c) / r[:50]
    fit = odometry(theta, r, dth, dr)
    np.testing.assert_allclose(fit.own_velocity(theta, r, dr, dth), own, atol=1e-12)


def test_odometry_on_bearing_rates_only():
    # Without dr/dt (omni flow's noisier component) the bearing rates of points
    # spread around the axis still fix all three unknowns.
    _, theta, r, _, dth, truth, moving = _odometry_case(7)
    fit = odometry(theta, r, dth)
    np.testing.assert_allclose((fit.w, fit.V_x, fit.V_y), truth, atol=1e-12)
    np.testing.assert_array_equal(fit.inliers, ~moving)


def test_odometry_on_a_closed_form_scene_with_moving_pillars(rig):
    # omnisim.synthetic: robot driving (1 cm, -0.5 cm)/frame and turning 4 mrad/frame
    # in a textured room with two pillars moving on their own (about 30 % of the
    # points). Per-pixel truth flow (one-frame displacements) goes through the same
    # formulas omni flow's output would: dtheta = hdtheta / h_i, dr from radial_velocity.
    # Measured: |w error| 2.3e-6 rad/frame, |V error| <= 8.3e-6 m/frame (second-order
    # effect of finite motion); every pillar point rejected, no wall point rejected.
    tex = Texture.random(5, period_u=2 * np.pi * 0.7)
    pillars = [
        Cylinder(centre=(1.1, 0.3), radius=0.7, id=3, texture=tex,
                 motion=Motion(velocity=(-0.02, 0.03), yaw_rate=0.05)),
        Cylinder(centre=(-1.2, -0.8), radius=0.5, id=4, texture=tex,
                 motion=Motion(velocity=(0.03, 0.01))),
    ]  # fmt: skip
    robot = Motion(velocity=(0.01, -0.005), yaw_rate=0.004)
    scene = SyntheticScene.room(rig, wall_radius=3.0, ceiling=None, robot=robot, bodies=pillars)
    tr = scene.truth("cam1", 0)
    x, y = rig.cam1.pixel_centres()
    h_i, _ = rig.cam1.polar_of_pixel(x, y)
    ok = (tr["gt.valid"] > 0) & (tr["gt.flow.valid"] > 0)
    r, theta, hi = tr["gt.r"][ok], tr["gt.theta"][ok], h_i[ok]
    moving = tr["gt.object"][ok] >= 3
    assert 0.25 < moving.mean() < 0.4
    dth = tr["gt.flow.hdtheta"][ok] / hi
    dr = radial_velocity(r, hi, tr["gt.flow.dh"][ok], d=rig.d)
    fit = odometry(theta, r, dth, dr)
    # The rig starts with yaw 0, so its world velocity is its rig-frame velocity.
    assert fit.w == pytest.approx(0.004, abs=1e-5)
    assert fit.V_x == pytest.approx(0.01, abs=2e-5)
    assert fit.V_y == pytest.approx(-0.005, abs=2e-5)
    np.testing.assert_array_equal(fit.inliers, ~moving)


def test_odometry_bad_input():
    with pytest.raises(ValueError, match="point"):
        odometry([0.1, 0.2], [1.0, 1.0], [0.0, 0.0], [0.0, 0.0])
    with pytest.raises(ValueError, match="one bearing"):
        odometry(np.zeros(10), np.ones(10), np.zeros(10))
    with pytest.raises(ValueError, match="equal lengths"):
        odometry(np.zeros(10), np.ones(9), np.zeros(10))
