"""Rigid motions: constant velocity and keyframes (omnisim.motion)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from omnisim.motion import ConstantMotion, KeyframeMotion, StaticMotion, euler_deg, pose_matrix


def _rz(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def test_euler_is_extrinsic_xyz_degrees():
    r = euler_deg([0, 0, 90]).as_matrix()
    np.testing.assert_allclose(r @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    # Extrinsic x then z: a vector along Y goes to Z by x = 90, then stays on Z under z = 90.
    r = euler_deg([90, 0, 90]).as_matrix()
    np.testing.assert_allclose(r @ [0, 1, 0], [0, 0, 1], atol=1e-12)


def test_static_motion_is_constant():
    m = StaticMotion(np.array([1.0, 2.0, 3.0]), euler_deg([0, 0, 30]))
    np.testing.assert_array_equal(m.pose_at(0.0), m.pose_at(123.4))
    np.testing.assert_allclose(m.pose_at(0)[:3, :3], _rz(30), atol=1e-12)
    np.testing.assert_array_equal(m.pose_at(0)[:3, 3], [1, 2, 3])
    np.testing.assert_array_equal(m.pose_at(0)[3], [0, 0, 0, 1])


@pytest.mark.parametrize("t", [0.0, 0.05, 1.0, 2.5, -0.3])
def test_constant_velocity_closed_form(t):
    p0 = np.array([0.5, -1.0, 0.6])
    v = np.array([0.2, -0.1, 0.05])
    yaw0, rate = 10.0, 40.0  # degrees, degrees per second
    m = ConstantMotion(p0, euler_deg([0, 0, yaw0]), v, np.radians([0, 0, rate]))
    pose = m.pose_at(t)
    np.testing.assert_allclose(pose[:3, 3], p0 + v * t, atol=1e-12)
    np.testing.assert_allclose(pose[:3, :3], _rz(yaw0 + rate * t), atol=1e-12)


def test_constant_angular_velocity_about_tilted_axis_composes():
    w = np.radians([10.0, -20.0, 30.0])
    m = ConstantMotion(np.zeros(3), Rotation.identity(), np.zeros(3), w)
    # Constant angular velocity: R(t1 + t2) = R(t2) R(t1) (rotations about one fixed axis).
    r1, r2, r12 = (m.pose_at(t)[:3, :3] for t in (0.3, 0.7, 1.0))
    np.testing.assert_allclose(r2 @ r1, r12, atol=1e-12)
    axis = w / np.linalg.norm(w)
    np.testing.assert_allclose(r12 @ axis, axis, atol=1e-12)  # the axis is fixed
    np.testing.assert_allclose(np.linalg.det(r12), 1.0, atol=1e-12)


def _keys(interpolation: str) -> KeyframeMotion:
    times = np.array([0.0, 1.0, 3.0])
    positions = np.array([[0.0, 0.0, 0.5], [1.0, 0.0, 0.5], [1.0, 2.0, 0.7]])
    rotations = euler_deg([[0, 0, 0], [0, 0, 90], [0, 0, 90]])
    return KeyframeMotion(times, positions, rotations, interpolation)


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_keyframes_exact_at_keys(interpolation):
    m = _keys(interpolation)
    for k, t in enumerate(m.times):
        expected = pose_matrix(m.rotations[k], m.positions[k])
        np.testing.assert_array_equal(m.pose_at(t), expected)


def test_keyframes_linear_between_keys():
    m = _keys("linear")
    pose = m.pose_at(0.5)
    np.testing.assert_allclose(pose[:3, 3], [0.5, 0.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(pose[:3, :3], _rz(45.0), atol=1e-12)  # slerp: half the angle
    pose = m.pose_at(2.0)
    np.testing.assert_allclose(pose[:3, 3], [1.0, 1.0, 0.6], atol=1e-12)
    np.testing.assert_allclose(pose[:3, :3], _rz(90.0), atol=1e-12)
    # Slerp turns at a constant rate between keys.
    yaw = [np.degrees(np.arctan2(m.pose_at(t)[1, 0], m.pose_at(t)[0, 0])) for t in (0.1, 0.25)]
    np.testing.assert_allclose(yaw, [9.0, 22.5], atol=1e-9)


def test_keyframes_hold_outside_the_keys():
    m = _keys("linear")
    np.testing.assert_array_equal(m.pose_at(-5.0), m.pose_at(0.0))
    np.testing.assert_array_equal(m.pose_at(10.0), m.pose_at(3.0))


def test_keyframes_cubic_reproduces_a_parabola():
    # Not-a-knot cubic splines are exact for polynomials up to degree 3.
    times = np.array([0.0, 1.0, 2.0, 4.0])
    pos = np.stack([times**2, 2 * times - 0.5 * times**3, np.full(4, 0.4)], axis=1)
    m = KeyframeMotion(times, pos, Rotation.identity(4), "cubic")
    for t in (0.3, 1.5, 3.2):
        np.testing.assert_allclose(m.pose_at(t)[:3, 3], [t**2, 2 * t - 0.5 * t**3, 0.4], atol=1e-9)


def test_keyframes_single_key_and_bad_input():
    m = KeyframeMotion(np.array([1.0]), np.array([[1.0, 2.0, 3.0]]), euler_deg([[0, 0, 5]]))
    np.testing.assert_allclose(m.pose_at(7.0)[:3, 3], [1, 2, 3])
    with pytest.raises(ValueError, match="increasing"):
        KeyframeMotion(np.array([0.0, 0.0]), np.zeros((2, 3)), Rotation.identity(2))
    with pytest.raises(ValueError, match="interpolation"):
        KeyframeMotion(np.array([0.0, 1.0]), np.zeros((2, 3)), Rotation.identity(2), "spline")
