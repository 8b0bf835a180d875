"""Is the rig possible in this scene? Collision and common-region checks of the loader.

Called by :func:`omnisim.scene.load_scene` once the scene model is built: the rig must
not touch any object at any checked frame, both cameras must see a common region, and
no object (other than a room) may enclose a camera's mirror tip. A failure raises
``SceneError`` through the loader's checker, naming the frame and the object.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import trimesh
from numpy.typing import NDArray

from omnisim.motion import StaticMotion
from omnisim.rig_parts import RIG_PART_KINDS
from omnisim.scene_checker import Checker

#: At most this many frames are checked (evenly spaced, always including the ends).
MAX_CHECKED_FRAMES = 513
#: Surface samples per object for the rig-collision and common-region checks.
SURFACE_SAMPLES = 4000


def _checked_frames(frames: int) -> NDArray[np.float64]:
    # Frames 0 .. frames: the last frame's flow needs the poses of frame + 1.
    if frames + 1 <= MAX_CHECKED_FRAMES:
        return np.arange(frames + 1, dtype=float)
    return np.unique(np.round(np.linspace(0, frames, MAX_CHECKED_FRAMES)))


def _surface_points(mesh: trimesh.Trimesh) -> NDArray[np.float64]:
    samples = trimesh.sample.sample_surface(mesh, SURFACE_SAMPLES, seed=0)[0]
    return np.concatenate([np.asarray(mesh.vertices), samples])


def _to_rig(world_from_rig: NDArray, world_from_obj: NDArray, pts: NDArray) -> NDArray:
    m = np.linalg.solve(world_from_rig, world_from_obj)
    return pts @ m[:3, :3].T + m[:3, 3]


def check_rig_in_scene(chk: Checker, scene: Any) -> None:
    """Raise SceneError if the rig collides with the scene or cannot see a common region.

    At every checked frame: the rig's body (the cylinder of radius R about the
    axis from cam2's camera centre, h = -d, to the top of cam1's mirror,
    h = s + R) must be clear of every object; a room must contain the rig with
    its walls farther from the axis than ``Rig.min_common_range`` (else the two
    cameras share no view of them); and some surface must lie in the two
    cameras' common region (occlusion not considered).
    """
    rig = scene.rig
    d, big_r, s = rig.d, rig.R, rig.s
    h_lo, h_hi = -d, s + big_r
    moving_robot = not isinstance(scene.robot.motion, StaticMotion)
    robot_key = "robot.motion" if moving_robot else "robot.position"
    frames = _checked_frames(scene.frames)
    content = [obj for obj in scene.objects if obj.kind not in RIG_PART_KINDS]
    surface = [(obj, _surface_points(obj.mesh)) for obj in content]
    others = [(obj, pts) for obj, pts in surface if obj.kind != "room"]

    axis = np.zeros((9, 4))
    axis[:, 2] = np.linspace(h_lo, h_hi, 9)
    axis[:, 3] = 1.0
    for k in frames:
        w_rig = scene.robot.pose(k)
        where_k = f"frame {k:g}"
        # Rooms: the axis inside, walls beyond the common range, floor and ceiling clear.
        for room in scene.rooms:
            idx, rname, size = room.index, room.name, room.size
            m = np.linalg.solve(scene.object_by_id(room.first_id).pose(k), w_rig)  # room from rig
            a = axis @ m.T
            wall = np.minimum(size[0] / 2 - np.abs(a[:, 0]), size[1] / 2 - np.abs(a[:, 1]))
            if wall.min() <= rig.min_common_range:
                raise chk.error(
                    robot_key,
                    f"at {where_k} the rig's axis is {max(wall.min(), 0):.3g} m from a wall of "
                    f"room {rname!r} (objects[{idx}]); expected more than the rig's "
                    f"min_common_range = {rig.min_common_range:.3g} m (s (d + R) / R - d), or the "
                    "two cameras share no view of the walls",
                )
            if a[0, 2] <= 0 or a[-1, 2] >= size[2]:
                raise chk.error(
                    robot_key,
                    f"at {where_k} the rig (h = -d .. s + R, z = {a[0, 2]:.3g} .. {a[-1, 2]:.3g} m "
                    f"in the room) does not fit between the floor and the ceiling (0 .. "
                    f"{size[2]:g} m) of room {rname!r}; expected it inside",
                )
        # Other objects: clear of the rig's body.
        for obj, pts in others:
            i = obj.index
            p = _to_rig(w_rig, obj.pose(k), pts)
            inside = (np.hypot(p[:, 0], p[:, 1]) < big_r) & (p[:, 2] >= h_lo) & (p[:, 2] <= h_hi)
            if inside.any():
                key = f"objects[{i}].motion" if obj.moving else f"objects[{i}].position"
                raise chk.error(
                    key if not moving_robot else f"{key} / {robot_key}",
                    f"object {obj.name!r} enters the rig at {where_k} (within R = {big_r:g} m of "
                    f"the axis between h = {h_lo:g} and {h_hi:g} m); expected it to stay clear",
                )
        # Something to see in stereo (a registration card is for one unit at a time).
        seen = any(obj.kind == "test_card" for obj in content)
        for obj, pts in surface:
            p = _to_rig(w_rig, obj.pose(k), pts)
            if rig.common_region(np.hypot(p[:, 0], p[:, 1]), p[:, 2]).any():
                seen = True
                break
        if not seen:
            raise chk.error(
                "objects",
                f"at {where_k} no surface lies in the region both cameras see (r > "
                f"{rig.min_common_range:.3g} m, above cam1's tip, below cam2's upper limit); "
                "expected a room or objects there",
            )


def _winding_numbers(mesh: trimesh.Trimesh, points: NDArray) -> NDArray[np.float64]:
    """Generalised winding number of a triangle mesh at each point (N, 3): the summed
    signed solid angle of its triangles over 4 pi (van Oosterom and Strackee's formula).
    About +-1 inside a closed mesh, 0 outside; between for open surfaces."""
    tri = np.asarray(mesh.triangles, dtype=np.float64)
    out = np.zeros(len(points))
    for i, p in enumerate(points):
        a, b, c = (tri[:, k] - p for k in range(3))
        la, lb, lc = (np.linalg.norm(v, axis=1) for v in (a, b, c))
        num = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = (
            la * lb * lc
            + np.einsum("ij,ij->i", a, b) * lc
            + np.einsum("ij,ij->i", b, c) * la
            + np.einsum("ij,ij->i", c, a) * lb
        )
        out[i] = 2.0 * np.arctan2(num, den).sum() / (4.0 * np.pi)
    return out


def check_not_enclosed(chk: Checker, scene: Any) -> None:
    """Raise SceneError when an object (not a room) encloses a camera's mirror tip at a
    checked frame: the cameras would see nothing but its inside (no stereo).

    Inside means a generalised winding number above 0.5 at the tip (a closed mesh:
    about 1; an open fence ring around the rig stays well below).
    """
    tips = np.array([[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, scene.rig.s, 1.0]])
    frames = _checked_frames(scene.frames)
    for obj in scene.objects:
        if obj.kind in ("room", "test_card") or obj.kind in RIG_PART_KINDS:
            continue
        lo, hi = obj.mesh.bounds
        pts, at = [], []
        for k in frames:
            m = np.linalg.solve(obj.pose(k), scene.robot.pose(k))  # object from rig
            p = (tips @ m.T)[:, :3]
            keep = np.all((p >= lo) & (p <= hi), axis=1)
            pts.extend(p[keep])
            at.extend([k] * int(keep.sum()))
        if not pts:
            continue
        w = np.abs(_winding_numbers(obj.mesh, np.asarray(pts)))
        if (w > 0.5).any():
            k = at[int(np.argmax(w > 0.5))]
            key = f"objects[{obj.index}].position"
            raise chk.error(
                key,
                f"object {obj.name!r} encloses the rig at frame {k:g} (winding number "
                f"{w.max():.2f} at a mirror tip): the cameras would see only its inside; "
                "expected the rig outside every object but a room",
            )
