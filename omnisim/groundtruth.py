"""Exact per-pixel ground truth, traced through the same geometry as the render.

``ground_truth(scene, frame, cam)`` returns the contract's ``gt.*`` channels,
(H, W) float32 each, at every pixel centre (x = j + 0.5, y = i + 0.5):

``gt.valid``
    1 where the pixel centre is inside the rim and its reflected ray hits a
    scene object; 0 where it hits a strut or mount flange of the rig
    (``omnisim.rig_parts``: not scene content), whose id ``gt.object`` still holds.
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
    (``omniflow.geometry.rig.Unit.project``).
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
``gt.flow.occluded``, ``gt.flow.outside`` (format version 2)
    Where ``gt.flow.valid`` is 0 but the position at frame + 1 is defined
    (h_i > 0): ``occluded`` when that position is on the mirror and in the
    image but the trace hits something else first, ``outside`` when it is
    off the mirror or the image. The three masks are disjoint; where none is
    1 on a ``gt.valid`` pixel the next position does not exist (flow 0).
``gt.bflow.*`` (format version 2)
    The same seven channels from this frame to frame - 1 (backward flow),
    traced in the scene of frame - 1; all 0 on frame 0.
``gt.stereo.h_other``
    h_i of the same point in the other camera at this frame, eq. (3)/(4).
``gt.stereo.valid``
    1 where the other camera sees the point: on its mirror and unoccluded,
    by the same trace test in the scene of this frame.

Where a quantity is undefined (``gt.valid`` = 0, or a projection that does
not exist) the channel holds 0; the flow and ``h_other`` are kept wherever
``gt.valid`` = 1, also where the corresponding ``valid`` is 0 (a point
occluded at frame + 1 still has a well-defined image position).

Accuracy: rays are computed in float64 (the same formulas as
``omnisim.sensor.mirror_rays``), traced by Mitsuba/Embree in float32, and
each hit is then re-intersected in float64 with the plane of the triangle
that was hit (``prim_index`` is the trimesh face index), so the points obey
eq. (1) to float64 round-off before the float32 storage (max departure
measured in ``tests/omnisim/test_groundtruth.py``: ~1e-5 px, from storing r and h
as float32). Shapes that are not scene objects (area-light panels) get
``gt.object`` = 0 and ``gt.valid`` = 0: they are not material points with a
known motion; they do occlude.

Speed: :func:`ground_truth_frame` runs every per-pixel step as fused float64
Dr.Jit kernels (about 0.1 s per 512 x 512 stereo frame on 2 cores, a few
percent of the render); :func:`ground_truth_reference` is the same
computation step by step in numpy, kept as the tests' reference.

The poses are defined for any frame number, so the flow of the last frame of
a sequence is computed from the poses at frame + 1 like any other.

Rig errors (``Unit.errors``, ``[rig.errors.camN]``): every ray is the traced model's
(``omniflow.geometry.rig_errors.traced_rays``, through ``mirror_rays``) and every
projection above that says eq. (1) is its numerical inverse (``traced_project``,
Gauss-Newton to under 1e-4 px); h_i and theta of the flow and of ``h_other`` are then
the traced pixel's polar coordinates about (x_c, y_c). :func:`ground_truth_frame` runs
the numpy path (:func:`ground_truth_reference`) for such a rig: about 21 s per 512 px
stereo frame against 0.8 s (``docs/decisions/rig_errors.md``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from omniflow.geometry.rig_errors import traced_project
from omniflow.io.dataset import GT_CHANNELS
from omnisim.mitsuba_scene import CAMERAS, MitsubaFrame, camera_unit, get_mitsuba_scene
from omnisim.rig_parts import RIG_PART_KINDS
from omnisim.sensor import apply_affine, ensure_mitsuba, mirror_rays, transform_rays

__all__ = [
    "GT_CHANNELS",
    "TRACE_TOL_ABS",
    "TRACE_TOL_REL",
    "ground_truth",
    "ground_truth_frame",
    "trace",
]

# The contract's channel names live in omniflow.io.dataset, the one place that defines them.

#: Same-point test of the visibility traces: |t_hit - t_expected| <= REL * t + ABS.
TRACE_TOL_REL = 1e-4
TRACE_TOL_ABS = 1e-5  # metres


def trace(ms, fr: MitsubaFrame, origin: NDArray, direction: NDArray) -> tuple[NDArray, NDArray]:
    """Trace world rays (N, 3) float64 through the frame's scene.

    Returns ``(t, obj)``: the float64 distance to the first hit (inf where
    none) and the object id (0 for no hit or a shape that is not an object).
    Embree intersects in float32; for scene objects the distance is then
    recomputed in float64 on the plane of the triangle that was hit
    (``prim_index`` is the trimesh face index), in one fused Dr.Jit kernel.
    """
    mi = ensure_mitsuba()
    import drjit as dr

    n = len(origin)
    if n == 0:
        return np.zeros(0), np.zeros(0, dtype=np.int32)
    tables = _tables(ms, fr)
    f64 = mi.Float64
    o = [f64(np.ascontiguousarray(origin[:, k])) for k in range(3)]
    d = [f64(np.ascontiguousarray(direction[:, k])) for k in range(3)]
    t32, prim, sid, hit = _first_hit(mi, dr, fr, o, d, dr.full(mi.Bool, True, n))
    obj = dr.gather(mi.UInt32, tables["obj"], sid)
    is_obj = hit & (obj > 0)
    face = dr.gather(mi.UInt32, tables["base"], sid) + prim
    nx, ny, nz, c = (dr.gather(f64, tables[k], face, is_obj) for k in ("nx", "ny", "nz", "c"))
    den = nx * d[0] + ny * d[1] + nz * d[2]
    t64 = (c - (nx * o[0] + ny * o[1] + nz * o[2])) / den
    close = dr.abs(t64 - t32) <= 1e-3 * t32 + 1e-4  # False for NaN / inf
    t = dr.select(hit, dr.select(is_obj & close, t64, t32), dr.inf)
    dr.eval(t, obj)
    return np.array(t.numpy(), dtype=np.float64), np.array(obj.numpy(), dtype=np.int32)


#: Relative size of the two nudges of a ray's direction tried when it misses everything
#: (radians): a ray through the shared edge of two triangles can slip between them in
#: Embree's float32 test; the nudged ray finds one of the two triangles, and the hit is
#: then re-intersected in float64 with the EXACT ray on that triangle's plane, which
#: contains the edge, so the point is exact. 1e-5 rad is about 100 float32 ulps of a
#: direction, far above the slip (measured: every hole of the open_field fence closed at
#: 1e-6 and 1e-5, tests/omnisim/test_groundtruth.py::test_no_holes_in_any_scene).
EDGE_NUDGE = 1e-5
# A fixed direction that no axis-aligned or diagonal mesh edge of the scenes follows.
_NUDGE_AXIS = (0.2672612419124244, 0.5345224838248488, 0.8017837257372732)


def _first_hit(mi, dr, fr: MitsubaFrame, o, d, active):
    """Embree's first hit of the float64 rays (o, d) where ``active``.

    Returns ``(t, prim_index, shape id, hit)`` (t float64, inf where no hit). A ray that
    misses is traced again with its direction nudged by :data:`EDGE_NUDGE` towards two
    directions perpendicular to it (see there): a genuine miss (sky) stays a miss, a ray
    that slipped through a mesh edge finds the triangle it grazes.
    """
    f64 = mi.Float64

    def shoot(dirs, mask):
        ray = mi.Ray3f(
            mi.Point3f(*(mi.Float(c) for c in o)), mi.Vector3f(*(mi.Float(c) for c in dirs))
        )
        pi = fr.scene.ray_intersect_preliminary(ray, active=mask)
        ok = mask & pi.is_valid()
        return (
            f64(pi.t),
            pi.prim_index,
            dr.select(ok, dr.reinterpret_array(mi.UInt32, pi.shape), 0),
            ok,
        )

    t, prim, sid, hit = shoot(d, active)
    # Two unit vectors perpendicular to d: e1 = d x a / |d x a|, e2 = d x e1.
    a = _NUDGE_AXIS
    e1 = [d[1] * a[2] - d[2] * a[1], d[2] * a[0] - d[0] * a[2], d[0] * a[1] - d[1] * a[0]]
    n1 = dr.sqrt(e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2])
    e1 = [dr.select(n1 > 1e-9, c / n1, 1.0 if i == 0 else 0.0) for i, c in enumerate(e1)]
    e2 = [d[1] * e1[2] - d[2] * e1[1], d[2] * e1[0] - d[0] * e1[2], d[0] * e1[1] - d[1] * e1[0]]
    for e in (e1, e2):
        miss = active & ~hit
        t2, prim2, sid2, hit2 = shoot([d[k] + EDGE_NUDGE * e[k] for k in range(3)], miss)
        t = dr.select(hit2, t2, t)
        prim = dr.select(hit2, prim2, prim)
        sid = dr.select(hit2, sid2, sid)
        hit |= hit2
    return t, prim, sid, hit


def _tables(ms, fr: MitsubaFrame) -> dict:
    """Dr.Jit lookup tables of the slot's frame: shape id -> object id and first face,
    and every object's triangle planes n . x = c in world coordinates (float64)."""
    mi = ensure_mitsuba()
    key = tuple((oid, fr.object_poses[oid].tobytes()) for oid in sorted(fr.object_poses))
    cached = fr.cache.get("tables")
    if cached is not None and cached[0] == key:
        return cached[1]
    n_all, c_all, base = [], [], np.zeros(len(fr.shape_ids), dtype=np.uint32)
    start = 0
    for rid, oid in enumerate(fr.shape_ids):
        if oid <= 0:
            continue
        part = ms.parts(int(oid))
        pose = fr.object_poses[int(oid)]
        v = part.vertices @ pose[:3, :3].T + pose[:3, 3]
        tri = v[part.faces]
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n_all.append(nrm)
        c_all.append(np.einsum("ij,ij->i", nrm, tri[:, 0]))
        base[rid] = start
        start += len(nrm)
    nrm = np.concatenate(n_all) if n_all else np.zeros((1, 3))
    off = np.concatenate(c_all) if c_all else np.zeros(1)
    tables = {
        "obj": mi.UInt32(fr.shape_ids.astype(np.uint32)),
        "base": mi.UInt32(base),
        "nx": mi.Float64(np.ascontiguousarray(nrm[:, 0])),
        "ny": mi.Float64(np.ascontiguousarray(nrm[:, 1])),
        "nz": mi.Float64(np.ascontiguousarray(nrm[:, 2])),
        "c": mi.Float64(off),
    }
    fr.cache["tables"] = (key, tables)
    return tables


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
    the image. Occlusion is not considered here. A unit with rig errors is projected
    through its traced model (``omniflow.geometry.rig_errors.traced_project``); theta
    is then the image angle about (x_c, y_c), which eq. (1) makes the point's azimuth.
    """
    if getattr(unit, "errors", None) is not None:
        x, y, seen = traced_project(unit, q_rig)
        h_i, theta = np.hypot(x - unit.x_c, y - unit.y_c), np.arctan2(y - unit.y_c, x - unit.x_c)
        seen &= (x >= 0) & (x < unit.width) & (y >= 0) & (y < unit.height)
        return x, y, h_i, theta, seen
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


def ground_truth_reference(scene, frame: int, cams=CAMERAS) -> dict[str, dict[str, NDArray]]:
    """:func:`ground_truth_frame` computed step by step in numpy (slower; the tests'
    reference for the fused Dr.Jit path). Four batched traces per frame (three on
    frame 0): this frame, frame + 1, frame - 1, the other unit."""
    ms = get_mitsuba_scene(scene)
    fr = ms.frame(frame)
    inv_robot = _inv(fr.robot_pose)
    state = {}
    # -- 1. the pixel centres' rays ---------------------------------------------
    origins, dirs, sel = [], [], []
    for cam in cams:
        unit = camera_unit(scene, cam)
        xs, ys = unit.pixel_centres()
        rays = mirror_rays(unit, xs.ravel(), ys.ravel())
        idx = np.nonzero(rays.valid)[0]
        o, d = transform_rays(fr.robot_pose, rays.origin[idx], rays.direction[idx])
        origins.append(o)
        dirs.append(d)
        sel.append((unit, xs.ravel(), ys.ravel(), rays, idx))
    t_all, obj_all = trace(ms, fr, np.concatenate(origins), np.concatenate(dirs))
    first_part, parts_seen = first_rig_part_id(scene), {}
    start = 0
    for cam, (unit, xs, ys, rays, idx), o, d in zip(cams, sel, origins, dirs, strict=True):
        sl = slice(start, start + len(o))
        start += len(o)
        t, obj = t_all[sl], obj_all[sl]
        part = obj >= first_part
        hit = (obj > 0) & ~part
        parts_seen[cam] = (idx[part], obj[part])
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
    # -- 2. flow: the material points at frame + 1 (gt.flow) and frame - 1 (gt.bflow) ----
    poses0 = dict(fr.object_poses)
    for key, step in (("gt.flow", 1), ("gt.bflow", -1)):
        if frame + step < 0:
            continue  # frame 0 has no backward flow: its channels stay 0
        frn = ms.frame(frame + step)
        inv_robot_n = _inv(frn.robot_pose)
        moves = {oid: frn.object_poses[oid] @ _inv(pose) for oid, pose in poses0.items()}
        jobs = []
        for cam in cams:
            st = state[cam]
            obj, p = st["obj"], st["p"]
            p1 = np.empty_like(p)
            for oid in np.unique(obj):
                m = obj == oid
                p1[m] = apply_affine(moves[int(oid)], p[m])
            x1, y1, h_i1, theta1, seen = _project(st["unit"], apply_affine(inv_robot_n, p1))
            k = np.nonzero(seen)[0]
            st[key] = dict(x1=x1, y1=y1, h_i1=h_i1, theta1=theta1, seen1=seen, k1=k)
            jobs.append((st["unit"], x1[k], y1[k], p1[k], obj[k]))
        for cam, ok in zip(cams, _same_point_batch(ms, frn, jobs), strict=True):
            state[cam][key]["ok"] = ok
    # -- 3. stereo: the same points in the other camera at this frame --------------
    fr = ms.frame(frame)
    jobs = []
    for cam in cams:
        st = state[cam]
        other = camera_unit(scene, CAMERAS[1 - CAMERAS.index(cam)])
        xo, yo, h_o, _, seen = _project(other, st["q"])
        k = np.nonzero(seen)[0]
        st.update(h_o=h_o, ko=k)
        jobs.append((other, xo[k], yo[k], st["p"][k], st["obj"][k]))
    ok_o = _same_point_batch(ms, fr, jobs)
    # -- channels ----------------------------------------------------------------
    result = {}
    for cam, stereo_ok in zip(cams, ok_o, strict=True):
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
        out["gt.object"][parts_seen[cam][0]] = parts_seen[cam][1]
        for key in ("gt.flow", "gt.bflow"):
            if key in st:
                for name, values in _reference_flow(st, st[key]).items():
                    out[f"{key}.{name}"][idx] = values
        h_o = st["h_o"]
        out["gt.stereo.h_other"][idx] = np.where(np.isfinite(h_o), h_o, 0.0)
        sv = np.zeros(len(idx), dtype=bool)
        sv[st["ko"]] = stereo_ok
        out["gt.stereo.valid"][idx] = sv
        result[cam] = {name: arr.reshape(H, W) for name, arr in out.items()}
    return result


def _reference_flow(st: dict, fl: dict) -> dict[str, NDArray]:
    """The flow channels (without the ``gt.flow.`` prefix) of the hit pixels, from the
    pixel state ``st`` and one direction's projection and trace ``fl`` (numpy path)."""
    x1, y1, h_i1 = fl["x1"], fl["y1"], fl["h_i1"]
    fin = np.isfinite(x1) & np.isfinite(y1) & (h_i1 > 0)
    seen = np.zeros(len(x1), dtype=bool)
    seen[fl["k1"]] = True
    ok = np.zeros(len(x1), dtype=bool)
    ok[fl["k1"]] = fl["ok"]
    with np.errstate(invalid="ignore"):
        return {
            "dx": np.where(fin, x1 - st["x0"], 0.0),
            "dy": np.where(fin, y1 - st["y0"], 0.0),
            "dh": np.where(fin, h_i1 - st["h_i0"], 0.0),
            "hdtheta": np.where(fin, st["h_i0"] * _wrap(fl["theta1"] - st["theta0"]), 0.0),
            "valid": ok,
            "occluded": seen & ~ok,
            "outside": fin & ~seen,
        }


# ----------------------------------------------------------------------------
# The fused Dr.Jit path (float64, multi-threaded; used by render_frame)
# ----------------------------------------------------------------------------
class _Consts:
    """A unit's parameters as opaque float64 JIT scalars (no recompilation per scene)."""

    def __init__(self, mi, unit):
        import drjit as dr

        def op(x):
            return dr.opaque(mi.Float64, float(x))

        self.x_c, self.y_c, self.r_m, self.v = op(unit.x_c), op(unit.y_c), op(unit.r_m), op(unit.v)
        self.d, self.tip = op(unit.d), op(unit.tip_h)
        self.slope = op(unit.R / (unit.d + unit.R))  # visible: h - tip <= (d + r) R / (d + R)
        self.w, self.h = op(unit.width), op(unit.height)


def _mat(mi, m: NDArray):
    import drjit as dr

    return [[dr.opaque(mi.Float64, float(m[i, j])) for j in range(4)] for i in range(3)]


def _xf(m, p, translate=True):
    return [
        m[i][0] * p[0] + m[i][1] * p[1] + m[i][2] * p[2] + (m[i][3] if translate else 0.0)
        for i in range(3)
    ]


def _dr_rays(dr, u: _Consts, x, y, pose):
    """World reflected rays of image points (x, y): ``mirror_rays`` in Dr.Jit."""
    dx, dy = x - u.x_c, y - u.y_c
    h_i = dr.sqrt(dx * dx + dy * dy)
    pos = h_i > 0
    c = dr.select(pos, dx / h_i, 1.0)
    s = dr.select(pos, dy / h_i, 0.0)
    k = dr.minimum(h_i, u.r_m) / u.v
    rho = u.d * k / (1.0 - k)
    inv_n = 1.0 / dr.sqrt(u.v * u.v + h_i * h_i)
    o = _xf(pose, [rho * c, rho * s, u.tip + rho])
    w = _xf(pose, [u.v * c * inv_n, u.v * s * inv_n, h_i * inv_n], translate=False)
    return o, w, h_i


def first_rig_part_id(scene) -> int:
    """The smallest object id of the rig's struts and flanges (``omnisim.rig_parts``: they
    come after every scene object); 2^31 when there are none."""
    ids = [o.id for o in scene.objects if getattr(o, "kind", "") in RIG_PART_KINDS]
    return int(min(ids, default=2**31))


def _dr_trace(mi, dr, fr: MitsubaFrame, tables: dict, o, d, active):
    """First hit (float64 distance refined on the hit triangle's plane, object id)."""
    f64 = mi.Float64
    t32, prim, sid, hit = _first_hit(mi, dr, fr, o, d, active)
    obj = dr.gather(mi.UInt32, tables["obj"], sid)
    is_obj = hit & (obj > 0)
    face = dr.gather(mi.UInt32, tables["base"], sid) + prim
    nx, ny, nz, c = (dr.gather(f64, tables[k], face, is_obj) for k in ("nx", "ny", "nz", "c"))
    t64 = (c - (nx * o[0] + ny * o[1] + nz * o[2])) / (nx * d[0] + ny * d[1] + nz * d[2])
    close = dr.abs(t64 - t32) <= 1e-3 * t32 + 1e-4  # False for NaN / inf
    t = dr.select(is_obj & close, t64, t32)
    return t, dr.select(is_obj, obj, 0), is_obj


def _dr_project(dr, u: _Consts, q):
    """Eq. (1), (6), (7) of rig points q: (x, y, h_i, seen on the mirror and in the image)."""
    r = dr.sqrt(q[0] * q[0] + q[1] * q[1])
    rel = q[2] - u.tip
    h_i = u.v * rel / (u.d + r)
    x = u.x_c + h_i * q[0] / r
    y = u.y_c + h_i * q[1] / r
    k = rel / (u.d + r)
    rho = u.d * k / (1.0 - k)
    seen = (rel > 0) & (rel <= (u.d + r) * u.slope) & (r >= rho) & (r > 0)
    seen &= (x >= 0) & (x < u.w) & (y >= 0) & (y < u.h)
    return x, y, h_i, seen


def _move_table(mi, fr0: MitsubaFrame, fr1: MitsubaFrame):
    """12 float64 arrays indexed by object id: pose(t + 1) inv(pose(t))."""
    n = max(fr0.object_poses, default=0) + 1
    tab = np.zeros((12, n))
    for oid, p0 in fr0.object_poses.items():
        tab[:, oid] = (fr1.object_poses[oid] @ _inv(p0))[:3].ravel()
    return [mi.Float64(np.ascontiguousarray(row)) for row in tab]


def _dr_primary(mi, dr, ms, unit, fr):
    """Step 1 of every camera: the pixel centres' reflected rays at frame ``fr`` and the
    points they hit. Returns (u, x, y, h_i, p world, q rig, obj, valid)."""
    u = _Consts(mi, unit)
    f64 = mi.Float64
    idx = dr.arange(mi.UInt32, unit.width * unit.height)
    x = f64(idx % unit.width) + 0.5
    y = f64(idx // unit.width) + 0.5
    o, d, h_i = _dr_rays(dr, u, x, y, _mat(mi, fr.robot_pose))
    t, obj, valid = _dr_trace(mi, dr, fr, _tables(ms, fr), o, d, h_i <= u.r_m)
    valid &= obj < first_rig_part_id(ms.scene)  # a strut or flange: not scene content
    p = [o[k] + t * d[k] for k in range(3)]
    q = _xf(_mat(mi, _inv(fr.robot_pose)), p)
    return u, x, y, h_i, p, q, obj, valid


def _dr_flow(mi, dr, ms, u: _Consts, x, y, h_i, p, obj, valid, fr, frn, key: str) -> dict:
    """Flow of the material points p (seen at frame ``fr``) to frame ``frn`` (t + 1 for
    ``key`` "gt.flow", t - 1 for "gt.bflow"): the point moved with its object, seen from
    the rig at ``frn``, projected with eq. (1) and traced there for visibility.

    The three masks split the pixels where the new position is defined (``gt.valid``
    and h_i > 0 at ``frn``): ``valid`` seen there, ``occluded`` on the mirror but
    another surface (or another point of the same one) is hit first, ``outside`` off
    the mirror or the image. The flow is kept wherever the position is defined.
    """
    f64 = mi.Float64
    mv = [dr.gather(f64, row, obj, valid) for row in _move_table(mi, fr, frn)]
    mvm = [mv[0:4], mv[4:8], mv[8:12]]
    p1 = _xf(mvm, p)
    q1 = _xf(_mat(mi, _inv(frn.robot_pose)), p1)
    x1, y1, h_i1, seen1 = _dr_project(dr, u, q1)
    o1, d1, _ = _dr_rays(dr, u, x1, y1, _mat(mi, frn.robot_pose))
    t1, obj1, _ = _dr_trace(mi, dr, frn, _tables(ms, frn), o1, d1, valid & seen1)
    t1_exp = dr.norm(mi.Vector3d(*(p1[k] - o1[k] for k in range(3))))
    flow_ok = valid & seen1 & (obj1 == obj)
    flow_ok &= dr.abs(t1 - t1_exp) <= TRACE_TOL_REL * t1_exp + TRACE_TOL_ABS
    fin1 = valid & (h_i1 > 0) & dr.isfinite(x1) & dr.isfinite(y1)
    # dtheta = angle from the pixel's azimuth (dx, dy) to q1's, wrapped to [-pi, pi)
    dxp, dyp = x - u.x_c, y - u.y_c
    dtheta = dr.atan2(dxp * q1[1] - dyp * q1[0], dxp * q1[0] + dyp * q1[1])
    f32 = mi.Float

    def ch(value, mask=fin1):
        return f32(dr.select(mask, value, 0.0))

    return {
        f"{key}.dx": ch(x1 - x),
        f"{key}.dy": ch(y1 - y),
        f"{key}.dh": ch(h_i1 - h_i),
        f"{key}.hdtheta": ch(h_i * dtheta),
        f"{key}.valid": ch(1.0, flow_ok & fin1),
        f"{key}.occluded": ch(1.0, valid & seen1 & ~flow_ok),
        f"{key}.outside": ch(1.0, fin1 & ~seen1),
    }


def _dr_backward(mi, dr, ms, scene, fr, frp, cam: str) -> dict[str, NDArray]:
    """The ``gt.bflow.*`` channels of ``cam``: flow from frame ``fr`` to ``frp`` (t - 1)."""
    unit = camera_unit(scene, cam)
    u, x, y, h_i, p, _, obj, valid = _dr_primary(mi, dr, ms, unit, fr)
    out = _dr_flow(mi, dr, ms, u, x, y, h_i, p, obj, valid, fr, frp, "gt.bflow")
    dr.eval(*out.values())
    shape = (unit.height, unit.width)
    return {name: np.array(a.numpy(), dtype=np.float32).reshape(shape) for name, a in out.items()}


def _dr_camera(mi, dr, ms, scene, fr, fr1, cam: str) -> dict[str, NDArray]:
    unit = camera_unit(scene, cam)
    other = camera_unit(scene, CAMERAS[1 - CAMERAS.index(cam)])
    uo = _Consts(mi, other)
    tab0 = _tables(ms, fr)
    pose0 = _mat(mi, fr.robot_pose)
    # 1. the pixel centre's reflected ray at this frame
    u, x, y, h_i, p, q, obj, valid = _dr_primary(mi, dr, ms, unit, fr)
    # 2. flow: the material point at frame + 1, its image, and the visibility trace
    flow = _dr_flow(mi, dr, ms, u, x, y, h_i, p, obj, valid, fr, fr1, "gt.flow")
    # 3. stereo: the same point in the other unit at this frame
    xo, yo, h_o, seen_o = _dr_project(dr, uo, q)
    oo, do, _ = _dr_rays(dr, uo, xo, yo, pose0)
    to, objo, _ = _dr_trace(mi, dr, fr, tab0, oo, do, valid & seen_o)
    to_exp = dr.norm(mi.Vector3d(*(p[k] - oo[k] for k in range(3))))
    stereo_ok = valid & seen_o & (objo == obj)
    stereo_ok &= dr.abs(to - to_exp) <= TRACE_TOL_REL * to_exp + TRACE_TOL_ABS

    f32 = mi.Float

    def ch(value, mask=valid):
        return f32(dr.select(mask, value, 0.0))

    r = dr.sqrt(q[0] * q[0] + q[1] * q[1])
    out = {
        "gt.valid": f32(dr.select(valid, 1.0, 0.0)),
        "gt.r": ch(r),
        "gt.theta": ch(dr.atan2(q[1], q[0])),
        "gt.h": ch(q[2]),
        "gt.X": ch(p[0]),
        "gt.Y": ch(p[1]),
        "gt.Z": ch(p[2]),
        "gt.object": f32(obj),
        **flow,
        "gt.stereo.h_other": ch(h_o, valid & dr.isfinite(h_o)),
        "gt.stereo.valid": f32(dr.select(stereo_ok, 1.0, 0.0)),
    }
    dr.eval(*out.values())
    shape = (unit.height, unit.width)
    return {
        name: np.array(arr.numpy(), dtype=np.float32).reshape(shape) for name, arr in out.items()
    }


def ground_truth_frame(scene, frame: int, cams=CAMERAS) -> dict[str, dict[str, NDArray]]:
    """The ``gt.*`` channels of several cameras at ``frame`` (module docstring).

    Everything per pixel (rays, the traces per camera: this frame, the flow
    check at frame + 1, the stereo check, and for the backward flow this frame
    again and the check at frame - 1; the projections) runs
    as float64 Dr.Jit kernels; every per-frame number is an opaque JIT
    scalar or an array, so the kernels compile once per process.
    """
    mi = ensure_mitsuba()
    import drjit as dr

    if any(getattr(camera_unit(scene, cam), "errors", None) is not None for cam in CAMERAS):
        # rig errors: every ray and projection through the traced model, in numpy
        return ground_truth_reference(scene, frame, cams)
    ms = get_mitsuba_scene(scene)
    back = {cam: _no_backward(camera_unit(scene, cam)) for cam in cams}
    if frame > 0:
        # Frame t - 1 first: the render of frame t leaves t - 1 and t in the two slots,
        # so only the forward pass below re-poses one (t - 1 -> t + 1), as before.
        fr = ms.frame(frame)
        frp = ms.frame(frame - 1)
        back = {cam: _dr_backward(mi, dr, ms, scene, fr, frp, cam) for cam in cams}
    fr = ms.frame(frame)
    fr1 = ms.frame(frame + 1)
    out = {cam: {**_dr_camera(mi, dr, ms, scene, fr, fr1, cam), **back[cam]} for cam in cams}
    return {cam: {name: out[cam][name] for name in GT_CHANNELS} for cam in cams}


def _no_backward(unit) -> dict[str, NDArray]:
    """The ``gt.bflow.*`` channels of frame 0: no frame t - 1, all zero (masks 0)."""
    return {
        name: np.zeros((unit.height, unit.width), np.float32)
        for name in GT_CHANNELS
        if name.startswith("gt.bflow.")
    }


def ground_truth(scene, frame: int, cam: str) -> dict[str, NDArray[np.float32]]:
    """The ``gt.*`` channels of camera ``cam`` at ``frame`` (module docstring)."""
    camera_unit(scene, cam)
    return ground_truth_frame(scene, frame, (cam,))[cam]
