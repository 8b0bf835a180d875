"""Exact per-pixel ground truth, traced through the same geometry as the render.

``ground_truth(scene, frame, cam)`` returns the contract's ``gt.*`` channels,
(H, W) float32 each, at every pixel centre (x = j + 0.5, y = i + 0.5):

``gt.valid``
    1 where the pixel centre is inside the rim and its reflected ray hits a
    scene object.
``gt.r``, ``gt.theta``, ``gt.h``
    The seen point in rig cylindrical coordinates at this frame (metres,
    radians in [-pi, pi), metres; h measured from cam2's tip, eq. 4).
``gt.X``, ``gt.Y``, ``gt.Z``
    The point in world coordinates, metres.
``gt.object``
    The object id (>= 1) as a float; 0 where nothing is hit.
``gt.flow.dx``, ``gt.flow.dy``
    Where the same material point is imaged at frame + 1 minus this pixel
    centre, pixels: the point is moved with its object's pose
    (``pose(frame + 1) @ inv(pose(frame))``), expressed in the rig frame of
    frame + 1 (``inv(robot.pose(frame + 1))``) and projected with eq. (1)
    (``omniflow.rig.Unit.project``).
``gt.flow.dh``, ``gt.flow.hdtheta``
    The same displacement as (dh_i, h_i dtheta) with dtheta wrapped to
    [-pi, pi) and h_i at this frame (``omniflow.conventions``).
``gt.flow.valid``
    1 where the point is still seen at frame + 1: on the mirror
    (``Unit.visible``: inside the rim and beyond its mirror point), inside
    the image, and not occluded: the reflected ray of the projected position
    at frame + 1, traced through the scene of frame + 1, hits the same
    object at the same point, within ``TRACE_TOL_REL * distance +
    TRACE_TOL_ABS`` along the ray.
``gt.stereo.h_other``
    h_i of the same point in the other camera at this frame, eq. (3)/(4).
``gt.stereo.valid``
    1 where the other camera sees the point: on its mirror and unoccluded,
    by the same trace test in the scene of this frame.

Where a quantity is undefined (``gt.valid`` = 0, or a projection that does
not exist) the channel holds 0; the flow and ``h_other`` are kept wherever
``gt.valid`` = 1, also where the corresponding ``valid`` is 0 (a point
occluded at frame + 1 still has a well-defined image position).

Accuracy: rays are computed in float64 (``omnisim.sensor.mirror_rays``),
traced by Mitsuba/Embree in float32, and each hit is then re-intersected in
float64 with the plane of the triangle that was hit (``prim_index`` is the
trimesh face index), so the points obey eq. (1) to float64 round-off (the
departure is measured in ``tests/test_groundtruth.py``). Shapes that are not
scene objects (area-light panels) keep Embree's float32 distance and get
``gt.object`` = 0 and ``gt.valid`` = 0: they are not material points with a
known motion.

The poses are defined for any frame number, so the flow of the last frame of
a sequence is computed from the poses at frame + 1 like any other.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from omnisim.render import CAMERAS, MitsubaFrame, _unit, get_mitsuba_scene
from omnisim.sensor import apply_affine, ensure_mitsuba, mirror_rays, transform_rays

__all__ = [
    "GT_CHANNELS",
    "TRACE_TOL_ABS",
    "TRACE_TOL_REL",
    "ground_truth",
    "ground_truth_frame",
    "trace",
]

GT_CHANNELS = (
    "gt.valid",
    "gt.r",
    "gt.theta",
    "gt.h",
    "gt.X",
    "gt.Y",
    "gt.Z",
    "gt.object",
    "gt.flow.dx",
    "gt.flow.dy",
    "gt.flow.dh",
    "gt.flow.hdtheta",
    "gt.flow.valid",
    "gt.stereo.h_other",
    "gt.stereo.valid",
)

#: Same-point test of the visibility traces: |t_hit - t_expected| <= REL * t + ABS.
TRACE_TOL_REL = 1e-4
TRACE_TOL_ABS = 1e-5  # metres


def trace(ms, fr: MitsubaFrame, origin: NDArray, direction: NDArray) -> tuple[NDArray, NDArray]:
    """Trace world rays (N, 3) float64 through the frame's scene.

    Returns ``(t, obj)``: the float64 distance to the first hit (inf where
    none; refined in float64 on the hit triangle's plane for scene objects)
    and the object id (0 for no hit or a shape that is not an object).
    """
    mi = ensure_mitsuba()
    import drjit as dr

    n = len(origin)
    if n == 0:
        return np.zeros(0), np.zeros(0, dtype=np.int32)
    o32 = np.ascontiguousarray(origin.T, dtype=np.float32)
    d32 = np.ascontiguousarray(direction.T, dtype=np.float32)
    ray = mi.Ray3f(
        mi.Point3f(mi.Float(o32[0]), mi.Float(o32[1]), mi.Float(o32[2])),
        mi.Vector3f(mi.Float(d32[0]), mi.Float(d32[1]), mi.Float(d32[2])),
    )
    pi = fr.scene.ray_intersect_preliminary(ray)
    sid = dr.reinterpret_array(mi.UInt32, pi.shape)
    valid = pi.is_valid()
    dr.eval(pi.t, pi.prim_index, sid, valid)
    t = np.array(pi.t, dtype=np.float64)
    prim = np.array(pi.prim_index, dtype=np.int64)
    sid = np.array(sid, dtype=np.int64)
    hit = np.array(valid, dtype=bool)
    t[~hit] = np.inf
    ids = fr.shape_ids
    obj = np.where(hit & (sid < len(ids)), ids[np.clip(sid, 0, len(ids) - 1)], 0)
    # float64 refinement on the plane of the hit triangle
    for oid in np.unique(obj[obj > 0]):
        sel = np.nonzero(obj == oid)[0]
        nrm, off = _planes(ms, fr, int(oid))
        f = prim[sel]
        n = nrm[f]
        den = np.einsum("ij,ij->i", n, direction[sel])
        with np.errstate(divide="ignore", invalid="ignore"):
            t64 = (off[f] - np.einsum("ij,ij->i", n, origin[sel])) / den
        good = np.isfinite(t64) & (np.abs(t64 - t[sel]) <= 1e-3 * t[sel] + 1e-4)
        t[sel[good]] = t64[good]
    return t, obj.astype(np.int32)


def _planes(ms, fr: MitsubaFrame, oid: int) -> tuple[NDArray, NDArray]:
    """World-frame planes n . x = c of object ``oid``'s triangles at the slot's frame."""
    key = (oid, fr.object_poses[oid].tobytes())
    cache = fr.__dict__.setdefault("_planes", {})
    hit = cache.get(key)
    if hit is None:
        for k in [k for k in cache if k[0] == oid]:
            del cache[k]
        part = ms.parts(oid)
        pose = fr.object_poses[oid]
        v = part.vertices @ pose[:3, :3].T + pose[:3, 3]
        tri = v[part.faces]
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        hit = cache[key] = (nrm, np.einsum("ij,ij->i", nrm, tri[:, 0]))
    return hit


def _cyl(q: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    return np.hypot(q[:, 0], q[:, 1]), np.arctan2(q[:, 1], q[:, 0]), q[:, 2]


def _wrap(a: NDArray) -> NDArray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def _inv(m: NDArray) -> NDArray:
    out = np.eye(4)
    out[:3, :3] = m[:3, :3].T
    out[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return out


def _project(unit, q_rig: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
    """(x, y, h_i, theta, seen) of rig points in ``unit``: eq. (1), (6), (7).

    ``seen``: on the mirror (``Unit.visible``), in front (h_i > 0) and inside
    the image. Occlusion is not considered here.
    """
    r, theta, h = _cyl(q_rig)
    with np.errstate(divide="ignore", invalid="ignore"):
        h_i = unit.image_radius(r, h)
        x, y = unit.pixel_of_polar(h_i, theta)
        seen = unit.visible(r, h) & (h_i > 0)
    seen &= np.isfinite(x) & np.isfinite(y)
    seen &= (x >= 0) & (x < unit.width) & (y >= 0) & (y < unit.height)
    return x, y, h_i, theta, seen


def _same_point_batch(ms, fr: MitsubaFrame, jobs) -> list[NDArray]:
    """Visibility of points by the trace test, several (unit, x, y, p_world, obj) at once.

    For each job, traces the reflected rays of the image positions (x, y)
    through frame ``fr`` and returns True where the first hit is on object
    ``obj`` at the distance of ``p_world`` (``TRACE_TOL_*``).
    """
    origins, dirs = [], []
    for unit, x, y, _, _ in jobs:
        rays = mirror_rays(unit, x, y)
        o, d = transform_rays(fr.robot_pose, rays.origin, rays.direction)
        origins.append(o)
        dirs.append(d)
    t, oid = trace(ms, fr, np.concatenate(origins), np.concatenate(dirs))
    out, start = [], 0
    for (_, _, _, p_world, obj), o in zip(jobs, origins, strict=True):
        sl = slice(start, start + len(o))
        start += len(o)
        t_exp = np.sqrt(((p_world - o) ** 2).sum(axis=1))
        out.append(
            (oid[sl] == obj) & (np.abs(t[sl] - t_exp) <= TRACE_TOL_REL * t_exp + TRACE_TOL_ABS)
        )
    return out


def ground_truth_frame(scene, frame: int, cams=CAMERAS) -> dict[str, dict[str, NDArray]]:
    """The ``gt.*`` channels of several cameras at ``frame``, traced in batches.

    Tracing both cameras together needs three Mitsuba traces per frame: the
    pixel centres at ``frame``, the flow checks at ``frame + 1`` and the
    stereo checks at ``frame``.
    """
    ms = get_mitsuba_scene(scene)
    fr = ms.frame(frame)
    inv_robot = _inv(fr.robot_pose)
    state = {}
    # -- 1. the pixel centres' rays ---------------------------------------------
    origins, dirs, sel = [], [], []
    for cam in cams:
        unit = _unit(scene, cam)
        xs, ys = unit.pixel_centres()
        rays = mirror_rays(unit, xs.ravel(), ys.ravel())
        idx = np.nonzero(rays.valid)[0]
        o, d = transform_rays(fr.robot_pose, rays.origin[idx], rays.direction[idx])
        origins.append(o)
        dirs.append(d)
        sel.append((unit, xs.ravel(), ys.ravel(), rays, idx))
    t_all, obj_all = trace(ms, fr, np.concatenate(origins), np.concatenate(dirs))
    start = 0
    for cam, (unit, xs, ys, rays, idx), o, d in zip(cams, sel, origins, dirs, strict=True):
        sl = slice(start, start + len(o))
        start += len(o)
        t, obj = t_all[sl], obj_all[sl]
        hit = obj > 0
        idx, o, d, t, obj = idx[hit], o[hit], d[hit], t[hit], obj[hit]
        p_world = o + t[:, None] * d
        state[cam] = dict(
            unit=unit,
            idx=idx,
            obj=obj,
            p=p_world,
            q=apply_affine(inv_robot, p_world),
            x0=xs[idx],
            y0=ys[idx],
            h_i0=rays.h_i[idx],
            theta0=np.arctan2(rays.dy[idx], rays.dx[idx]),
        )
    # -- 2. flow: the material points at frame + 1 --------------------------------
    fr1 = ms.frame(frame + 1)
    inv_robot1 = _inv(fr1.robot_pose)
    moves = {oid: fr1.object_poses[oid] @ _inv(fr.object_poses[oid]) for oid in fr.object_poses}
    jobs = []
    for cam in cams:
        st = state[cam]
        obj, p = st["obj"], st["p"]
        p1 = np.empty_like(p)
        for oid in np.unique(obj):
            m = obj == oid
            p1[m] = apply_affine(moves[int(oid)], p[m])
        x1, y1, h_i1, theta1, seen = _project(st["unit"], apply_affine(inv_robot1, p1))
        st.update(x1=x1, y1=y1, h_i1=h_i1, theta1=theta1, seen1=seen)
        k = np.nonzero(seen)[0]
        st["k1"] = k
        jobs.append((st["unit"], x1[k], y1[k], p1[k], obj[k]))
    ok1 = _same_point_batch(ms, fr1, jobs)
    # -- 3. stereo: the same points in the other camera at this frame --------------
    fr = ms.frame(frame)
    jobs = []
    for cam in cams:
        st = state[cam]
        other = _unit(scene, CAMERAS[1 - CAMERAS.index(cam)])
        xo, yo, h_o, _, seen = _project(other, st["q"])
        k = np.nonzero(seen)[0]
        st.update(h_o=h_o, ko=k)
        jobs.append((other, xo[k], yo[k], st["p"][k], st["obj"][k]))
    ok_o = _same_point_batch(ms, fr, jobs)
    # -- channels ----------------------------------------------------------------
    result = {}
    for cam, flow_ok, stereo_ok in zip(cams, ok1, ok_o, strict=True):
        st = state[cam]
        unit, idx = st["unit"], st["idx"]
        H, W = unit.height, unit.width
        out = {name: np.zeros(H * W, dtype=np.float32) for name in GT_CHANNELS}
        r, theta, h = _cyl(st["q"])
        out["gt.valid"][idx] = 1.0
        out["gt.r"][idx] = r
        out["gt.theta"][idx] = theta
        out["gt.h"][idx] = h
        p = st["p"]
        out["gt.X"][idx], out["gt.Y"][idx], out["gt.Z"][idx] = p[:, 0], p[:, 1], p[:, 2]
        out["gt.object"][idx] = st["obj"]
        x1, y1, h_i1 = st["x1"], st["y1"], st["h_i1"]
        fin = np.isfinite(x1) & np.isfinite(y1) & (h_i1 > 0)
        with np.errstate(invalid="ignore"):
            out["gt.flow.dx"][idx] = np.where(fin, x1 - st["x0"], 0.0)
            out["gt.flow.dy"][idx] = np.where(fin, y1 - st["y0"], 0.0)
            out["gt.flow.dh"][idx] = np.where(fin, h_i1 - st["h_i0"], 0.0)
            out["gt.flow.hdtheta"][idx] = np.where(
                fin, st["h_i0"] * _wrap(st["theta1"] - st["theta0"]), 0.0
            )
        fv = np.zeros(len(idx), dtype=bool)
        fv[st["k1"]] = flow_ok
        out["gt.flow.valid"][idx] = fv
        h_o = st["h_o"]
        out["gt.stereo.h_other"][idx] = np.where(np.isfinite(h_o), h_o, 0.0)
        sv = np.zeros(len(idx), dtype=bool)
        sv[st["ko"]] = stereo_ok
        out["gt.stereo.valid"][idx] = sv
        result[cam] = {name: arr.reshape(H, W) for name, arr in out.items()}
    return result


def ground_truth(scene, frame: int, cam: str) -> dict[str, NDArray[np.float32]]:
    """The ``gt.*`` channels of camera ``cam`` at ``frame`` (module docstring)."""
    _unit(scene, cam)
    return ground_truth_frame(scene, frame, (cam,))[cam]
