"""Truth for derived quantities, from the poses in ``dataset.json``.

Poses are 4x4 world-from-body matrices per frame: the robot's (world from rig
frame, ``omniflow.conventions``) and each object's (world from object). Both
come from the dataset's metadata, so the truth here is the known motion, not
an estimate from images.

* :func:`robot_motion`: the rig's motion from frame t to t + 1 expressed in the
  rig frame at t: yaw rate w (rad/frame) and velocity (V_x, V_y) (m/frame).
  This is what odometry (``omniflow.applications.navigation``) estimates.
* :func:`point_motion`: where a material point seen at frame t (world X, Y, Z
  and its object id) is at t + 1 in the rig's cylindrical coordinates, hence
  its true dr/dt (m/frame) and time to contact -r / (dr/dt) (frames).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["point_motion", "robot_motion"]


def robot_motion(pose_t: ArrayLike, pose_t1: ArrayLike) -> dict[str, float]:
    """Yaw rate and planar velocity of the rig in its own frame at t.

    Parameters
    ----------
    pose_t, pose_t1 : array_like, shape (4, 4)
        World-from-rig poses at frames t and t + 1.

    Returns
    -------
    dict with ``w`` (rad/frame, counter-clockwise seen from above), ``vx``,
    ``vy``, ``vz`` (m/frame, rig axes at t) and ``speed`` (hypot(vx, vy)).
    """
    m = np.linalg.inv(np.asarray(pose_t, dtype=np.float64)) @ np.asarray(pose_t1, dtype=np.float64)
    w = float(np.arctan2(m[1, 0], m[0, 0]))
    vx, vy, vz = (float(v) for v in m[:3, 3])
    return {"w": w, "vx": vx, "vy": vy, "vz": vz, "speed": float(np.hypot(vx, vy))}


def point_motion(
    world: NDArray,
    object_id: ArrayLike,
    object_poses_t: Mapping[int, ArrayLike],
    object_poses_t1: Mapping[int, ArrayLike],
    rig_pose_t: ArrayLike,
    rig_pose_t1: ArrayLike,
) -> dict[str, NDArray]:
    """True motion of material points between frames t and t + 1.

    Parameters
    ----------
    world : ndarray, shape (N, 3)
        World coordinates of the points at frame t (``gt.X, gt.Y, gt.Z``).
    object_id : array_like of int, shape (N,)
        ``gt.object`` of each point; ids without a pose are taken as static.
    object_poses_t, object_poses_t1 : mapping of id to (4, 4)
        World-from-object poses at t and t + 1.
    rig_pose_t, rig_pose_t1 : array_like, shape (4, 4)
        World-from-rig poses at t and t + 1.

    Returns
    -------
    dict with ``r0, theta0, h0`` (rig cylindrical at t), ``r1, theta1, h1``
    (at t + 1, in the rig frame of t + 1), ``dr_dt`` = r1 - r0 (m/frame),
    ``dh_dt`` = h1 - h0 and ``ttc`` = -r0 / dr_dt (frames; inf where the point
    does not approach).
    """
    world = np.asarray(world, dtype=np.float64).reshape(-1, 3)
    ids = np.asarray(object_id).astype(np.int64).ravel()
    hom = np.concatenate([world, np.ones((world.shape[0], 1))], axis=1)
    moved = hom.copy()
    for oid in np.unique(ids):
        if int(oid) not in object_poses_t or int(oid) not in object_poses_t1:
            continue
        a = np.asarray(object_poses_t[int(oid)], dtype=np.float64)
        b = np.asarray(object_poses_t1[int(oid)], dtype=np.float64)
        sel = ids == oid
        moved[sel] = hom[sel] @ (b @ np.linalg.inv(a)).T
    rig0 = hom @ np.linalg.inv(np.asarray(rig_pose_t, dtype=np.float64)).T
    rig1 = moved @ np.linalg.inv(np.asarray(rig_pose_t1, dtype=np.float64)).T
    r0, r1 = np.hypot(rig0[:, 0], rig0[:, 1]), np.hypot(rig1[:, 0], rig1[:, 1])
    dr = r1 - r0
    with np.errstate(divide="ignore", invalid="ignore"):
        ttc = np.where(dr < 0, -r0 / dr, np.inf)
    return {
        "r0": r0,
        "theta0": np.arctan2(rig0[:, 1], rig0[:, 0]),
        "h0": rig0[:, 2],
        "r1": r1,
        "theta1": np.arctan2(rig1[:, 1], rig1[:, 0]),
        "h1": rig1[:, 2],
        "dr_dt": dr,
        "dh_dt": rig1[:, 2] - rig0[:, 2],
        "ttc": ttc,
    }
