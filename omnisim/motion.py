"""Rigid-body motions of the robot (the rig) and of scene objects.

A motion maps a time t in seconds to a (4, 4) homogeneous matrix, world from
body: ``x_world = M[:3, :3] @ x_body + M[:3, 3]``. The scene turns frame
numbers into times with its frame interval (t = frame * frame_interval), so
poses exist for any real frame number, including frame + 1 after the last
rendered frame (the ground-truth flow of the last frame needs it).

Rotations are written in scene files as extrinsic x-y-z Euler angles in
degrees (scipy's ``"xyz"``): ``[rx, ry, rz]`` rotates about world X, then
world Y, then world Z; a yaw alone is ``[0, 0, yaw]``.

Three kinds of motion:

``StaticMotion``
    The pose never changes.
``ConstantMotion``
    Constant linear velocity v (m/s, world axes) and constant angular velocity
    w (rad/s here, deg/s in scene files; world axes, about the body's origin):
    ``R(t) = exp([w t]_x) R0`` and ``p(t) = p0 + v t``. A rig turning in place
    has v = 0 and w = (0, 0, yaw rate).
``KeyframeMotion``
    Poses at key times; rotation by spherical linear interpolation
    (``scipy.spatial.transform.Slerp``), translation linear (``numpy.interp``)
    or cubic (``scipy.interpolate.CubicSpline``, not-a-knot). Before the first
    key and after the last one the pose is held.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, Slerp

__all__ = [
    "ConstantMotion",
    "KeyframeMotion",
    "Motion",
    "StaticMotion",
    "euler_deg",
    "pose_matrix",
]


def euler_deg(angles: ArrayLike) -> Rotation:
    """Rotation from extrinsic x-y-z Euler angles in degrees (the scene-file form)."""
    return Rotation.from_euler("xyz", np.asarray(angles, dtype=float), degrees=True)


def pose_matrix(rotation: Rotation, position: ArrayLike) -> NDArray[np.float64]:
    """(4, 4) homogeneous matrix from a rotation and a translation."""
    m = np.eye(4)
    m[:3, :3] = rotation.as_matrix()
    m[:3, 3] = np.asarray(position, dtype=float)
    return m


class Motion:
    """Base class: ``pose_at(t)`` gives the (4, 4) world-from-body matrix at t seconds."""

    kind = "motion"

    def pose_at(self, t: float) -> NDArray[np.float64]:
        raise NotImplementedError

    def to_dict(self) -> dict:
        raise NotImplementedError


@dataclass(frozen=True)
class StaticMotion(Motion):
    """A body that does not move."""

    position: NDArray[np.float64]
    rotation: Rotation
    kind = "static"

    def pose_at(self, t: float) -> NDArray[np.float64]:
        return pose_matrix(self.rotation, self.position)

    def to_dict(self) -> dict:
        return {"type": self.kind}


@dataclass(frozen=True)
class ConstantMotion(Motion):
    """Constant linear velocity (m/s) and angular velocity (rad/s), world axes.

    The rotation turns about the body's own origin: ``R(t) = exp([w t]_x) R0``,
    ``p(t) = p0 + v t``.
    """

    position: NDArray[np.float64]
    rotation: Rotation
    velocity: NDArray[np.float64]
    angular_velocity: NDArray[np.float64]
    kind = "constant"

    def pose_at(self, t: float) -> NDArray[np.float64]:
        t = float(t)
        rot = Rotation.from_rotvec(self.angular_velocity * t) * self.rotation
        return pose_matrix(rot, self.position + self.velocity * t)

    def to_dict(self) -> dict:
        return {
            "type": self.kind,
            "velocity": self.velocity.tolist(),
            "angular_velocity_deg": np.degrees(self.angular_velocity).tolist(),
        }


@dataclass(frozen=True)
class KeyframeMotion(Motion):
    """Poses at key times (s), interpolated: Slerp for rotation, linear/cubic for position."""

    times: NDArray[np.float64]
    positions: NDArray[np.float64]
    rotations: Rotation
    interpolation: str = "linear"
    kind = "keyframes"
    _slerp: Slerp | None = field(default=None, repr=False, compare=False)
    _spline: CubicSpline | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        times = np.asarray(self.times, dtype=float)
        if times.ndim != 1 or len(times) < 1 or np.any(np.diff(times) <= 0):
            raise ValueError("keyframe times must be a non-empty strictly increasing list")
        if self.interpolation not in ("linear", "cubic"):
            raise ValueError(f"interpolation {self.interpolation!r}: expected 'linear' or 'cubic'")
        if len(times) >= 2:
            object.__setattr__(self, "_slerp", Slerp(times, self.rotations))
            if self.interpolation == "cubic":
                object.__setattr__(self, "_spline", CubicSpline(times, self.positions, axis=0))

    def pose_at(self, t: float) -> NDArray[np.float64]:
        times = self.times
        tc = float(np.clip(float(t), times[0], times[-1]))  # hold outside the keys
        if len(times) == 1:
            return pose_matrix(self.rotations[0], self.positions[0])
        # Exactly at a key, return the key itself (no round-off from the interpolants).
        hit = np.flatnonzero(times == tc)
        if hit.size:
            k = int(hit[0])
            return pose_matrix(self.rotations[k], self.positions[k])
        rot = self._slerp([tc])[0]
        if self._spline is not None:
            pos = self._spline(tc)
        else:
            pos = np.array([np.interp(tc, times, self.positions[:, i]) for i in range(3)])
        return pose_matrix(rot, pos)

    def to_dict(self) -> dict:
        return {
            "type": self.kind,
            "interpolation": self.interpolation,
            "times": self.times.tolist(),
            "positions": self.positions.tolist(),
            "rotations_euler_xyz_deg": self.rotations.as_euler("xyz", degrees=True).tolist(),
        }
