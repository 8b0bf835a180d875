"""The Mitsuba scene of an omnisim Scene, shared by the render and the ground truth.

``get_mitsuba_scene(scene) -> MitsubaScene`` is the cached Mitsuba state of a
Scene (BSDFs, meshes, lights, integrators, sensors) and
``MitsubaScene.frame(frame) -> MitsubaFrame`` the Mitsuba scene posed for one
frame: :mod:`omnisim.render` renders it, :mod:`omnisim.groundtruth` traces
the same geometry for the exact ground truth. This module imports neither.

Scene content -> Mitsuba: each object's trimesh mesh becomes an ``mi.Mesh``
built from arrays (vertices, faces, per-vertex UVs, in the object's original
face order so a hit's ``prim_index`` is the trimesh face index; shading
normals are trimesh's vertex normals: smooth on curved parts, flat where
the scene's meshes split vertices at creases), placed in the world by
``object.pose(frame)``; its texture becomes a ``bitmap`` texture (linear
float32, bilinear, repeat; the texel convention of ``omnisim.textures``:
row 0 at v = 0, which is Mitsuba's for UVs given as
arrays); its material a BSDF (``diffuse``, ``plastic``/``roughplastic``,
``conductor``, ``roughconductor``; ``twosided`` unless the material says
otherwise). Lights: ``area`` (a one-sided emitting rectangle placed by
``AreaLight.to_world()``), ``point``, ``environment`` (constant, or a
latitude-longitude image with row 0 at the zenith), ``directional``.
The cone mirrors are not shapes: the sensor (``omnisim.sensor``) traces them
analytically, as perfect conductors (reflectance 1).

Moving objects: every Scene keeps ``FRAME_SLOTS`` (2) Mitsuba scenes; a
frame not in a slot re-poses the least recently used one in place (the
moving meshes' ``vertex_positions`` through ``mi.traverse``, then
``params.update()`` rebuilds the BVH), so the ground truth of frame t (which
also traces frame t + 1) and the render of frame t + 1 share them. Measured
(benchmarks/bench_render.py --updates, scenes/crossing.toml): the in-place
update takes about 1 ms against 2.5 ms for loading a new scene, and the
shapes keep their identity, so the compiled kernels are re-used; a rebuilt
scene whose shapes get new registry ids forces a JIT recompilation of the
render kernel (about 0.35 s measured with rebuilt scenes kept in a cache).
``MitsubaScene.update = "rebuild"`` selects the rebuild for comparison.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from omnisim.denoise import guide_integrator_dict
from omnisim.sensor import ensure_mitsuba, make_sensor

__all__ = [
    "CAMERAS",
    "FRAME_SLOTS",
    "MAX_SCENES",
    "MitsubaFrame",
    "MitsubaScene",
    "camera_unit",
    "clear_cache",
    "get_mitsuba_scene",
    "render_setting",
]

CAMERAS = ("cam1", "cam2")
#: Mitsuba scenes kept per Scene, each re-posed in place for the frame asked for.
FRAME_SLOTS = 2


def camera_unit(scene, cam: str):
    """The ``omniflow.geometry.rig.Unit`` of camera ``cam`` (``"cam1"`` or ``"cam2"``) of
    ``scene``."""
    if cam not in CAMERAS:
        raise ValueError(f"camera {cam!r}: expected 'cam1' or 'cam2'")
    return getattr(scene.rig, cam)


def render_setting(scene, key: str, default: Any = None) -> Any:
    """``scene.render.<key>`` (attribute or mapping item), ``default`` when absent."""
    return _get(scene.render, key, default)


def _get(obj: Any, key: str, default: Any = None) -> Any:
    """Attribute or mapping item ``key`` of ``obj``."""
    if isinstance(obj, dict):
        return obj.get(key, default)
    return getattr(obj, key, default)


# ----------------------------------------------------------------------------
# Scene conversion
# ----------------------------------------------------------------------------
@dataclass
class MitsubaFrame:
    """The Mitsuba scene of one frame and what the ground truth needs of it."""

    frame: int
    scene: Any  # mi.Scene
    robot_pose: NDArray  # (4, 4) world from rig
    object_poses: dict[int, NDArray]  # id -> (4, 4) world from object
    shape_ids: NDArray  # Mitsuba shape registry id -> object id (0: not an object)
    params: Any = None  # mi.SceneParameters of the moving meshes' vertex positions
    cache: dict = field(default_factory=dict)  # per-frame data of the ground truth


@dataclass
class _ObjectParts:
    id: int
    name: str
    vertices: NDArray  # (V, 3) float64, object frame
    faces: NDArray  # (F, 3) int64
    uv: NDArray  # (V, 2) float32
    normals: NDArray | None  # (V, 3) float64, object frame; None: flat shading
    bsdf: Any
    static: bool
    static_mesh: Any = None
    static_pose: NDArray | None = None


@dataclass
class MitsubaScene:
    """Per-Scene Mitsuba state: cached BSDFs, meshes, lights, sensors and frames."""

    scene: Any
    objects: list[_ObjectParts] = field(default_factory=list)
    lights: dict[str, Any] = field(default_factory=dict)
    slots: list[MitsubaFrame] = field(default_factory=list)
    sensors: dict[str, Any] = field(default_factory=dict)
    integrator: Any = None
    #: Mitsuba ``aov`` integrator of the denoiser's guides (None: no denoiser).
    guides: Any = None
    #: "traverse": re-pose the moving meshes of a kept scene in place (the default:
    #: no JIT recompilation); "rebuild": load a new Mitsuba scene for every new frame.
    update: str = "traverse"

    def __post_init__(self) -> None:
        mi = ensure_mitsuba(_get(self.scene.render, "variant", None))
        scene = self.scene
        r = scene.render
        for obj in scene.objects:
            self.objects.append(_object_parts(mi, obj, scene.frames))
        self.lights = _light_dicts(mi, scene.lights)
        all_diffuse = all(_material_type(o) == "diffuse" for o in scene.objects) and not any(
            _get(light, "type", None) == "environment" for light in scene.lights or ()
        )
        self.integrator = mi.load_dict(
            _integrator_dict(_get(r, "integrator", "path"), _get(r, "max_depth", 3), all_diffuse)
        )
        if _get(r, "denoise", "none") != "none":
            self.guides = mi.load_dict(guide_integrator_dict())

    # -- frames -------------------------------------------------------------
    def frame(self, frame: int) -> MitsubaFrame:
        """The Mitsuba scene posed for ``frame`` (one of ``FRAME_SLOTS`` kept in place).

        A fractional frame (a sub-frame of a motion-blurred exposure) is posed exactly.
        """
        frame = float(frame)
        for slot in self.slots:
            if slot.frame == frame:
                self.slots.remove(slot)
                self.slots.append(slot)  # most recently used last
                return slot
        if len(self.slots) < FRAME_SLOTS:
            slot = self._build(frame)
        elif self.update == "rebuild":
            self.slots.pop(0)
            slot = self._build(frame)
        else:
            slot = self.slots.pop(0)
            self._update(slot, frame)
        self.slots.append(slot)
        return slot

    def _poses(self, frame: int) -> dict[int, NDArray]:
        return {
            part.id: (
                part.static_pose if part.static else _pose(self.scene_object(part.id).pose(frame))
            )
            for part in self.objects
        }

    def _build(self, frame: int) -> MitsubaFrame:
        mi = ensure_mitsuba()
        import drjit as dr

        desc: dict[str, Any] = {"type": "scene"}
        poses = self._poses(frame)
        shape_of: list[tuple[Any, int]] = []
        for part in self.objects:
            mesh = part.static_mesh if part.static else _make_mesh(mi, part, poses[part.id])
            desc[f"obj{part.id}"] = mesh
            shape_of.append((mesh, part.id))
        desc.update(self.lights)
        mscene = mi.load_dict(desc)
        reg = [int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(m))[0]) for m, _ in shape_of]
        every = [int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(m))[0]) for m in mscene.shapes()]
        ids = np.zeros(max(reg + every, default=0) + 1, dtype=np.int32)
        for (_, oid), rid in zip(shape_of, reg, strict=True):
            ids[rid] = oid
        params = mi.traverse(mscene)
        params.keep(
            [f"obj{p.id}.vertex_positions" for p in self.objects if not p.static]
            + [
                f"obj{p.id}.vertex_normals"
                for p in self.objects
                if not p.static and p.normals is not None
            ]
        )
        robot = _pose(self.scene.robot.pose(frame))
        return MitsubaFrame(
            frame=frame,
            scene=mscene,
            robot_pose=robot,
            object_poses=poses,
            shape_ids=ids,
            params=params,
        )

    def _update(self, slot: MitsubaFrame, frame: int) -> None:
        """Re-pose the moving meshes of ``slot`` for ``frame`` through ``mi.traverse``."""
        mi = ensure_mitsuba()
        poses = self._poses(frame)
        for part in self.objects:
            if not part.static:
                v = part.vertices @ poses[part.id][:3, :3].T + poses[part.id][:3, 3]
                slot.params[f"obj{part.id}.vertex_positions"] = mi.Float(
                    np.ascontiguousarray(v, dtype=np.float32).ravel()
                )
                if part.normals is not None:
                    n = part.normals @ poses[part.id][:3, :3].T
                    slot.params[f"obj{part.id}.vertex_normals"] = mi.Float(
                        np.ascontiguousarray(n, dtype=np.float32).ravel()
                    )
        slot.params.update()
        slot.frame = frame
        slot.object_poses = poses
        slot.robot_pose = _pose(self.scene.robot.pose(frame))

    def scene_object(self, oid: int):
        for obj in self.scene.objects:
            if int(obj.id) == oid:
                return obj
        raise KeyError(oid)

    def parts(self, oid: int) -> _ObjectParts:
        for part in self.objects:
            if part.id == oid:
                return part
        raise KeyError(oid)

    # -- sensors ------------------------------------------------------------
    def sensor(self, cam: str, pose: NDArray):
        sensor = self.sensors.get(cam)
        if sensor is None:
            spp = int(_get(self.scene.render, "spp", 16))
            sensor = make_sensor(
                camera_unit(self.scene, cam),
                pose,
                spp=spp,
                sampler=_get(self.scene.render, "sampler", None),
                optics=getattr(self.scene, "optics", None),
            )
            self.sensors[cam] = sensor
        else:
            sensor.set_pose(pose)
        return sensor


def _pose(m) -> NDArray:
    m = np.asarray(m, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"pose has shape {m.shape}: expected (4, 4)")
    return m


def _is_static(obj, frames: int) -> bool:
    """True when the object's pose is the same at every frame we may need."""
    moving = _get(obj, "moving", None)
    if isinstance(moving, bool):
        return not moving
    p0 = _pose(obj.pose(0))
    return all(np.array_equal(p0, _pose(obj.pose(f))) for f in (1, max(1, frames // 2), frames))


def _object_parts(mi, obj, frames: int) -> _ObjectParts:
    mesh = obj.mesh
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    uv = _get(_get(mesh, "visual"), "uv")
    if uv is None or len(uv) != len(vertices):
        uv = np.zeros((len(vertices), 2))
    uv = np.asarray(uv, dtype=np.float64)
    uv_mi = uv.astype(np.float32)  # omnisim.textures: row 0 at v = 0, as Mitsuba's bitmap
    bsdf = mi.load_dict(_bsdf_dict(mi, _get(obj, "material", "diffuse"), _get(obj, "texture")))
    part = _ObjectParts(
        id=int(obj.id),
        name=str(_get(obj, "name", f"obj{obj.id}")),
        vertices=vertices,
        faces=faces,
        uv=uv_mi,
        normals=_smooth_normals(mesh),
        bsdf=bsdf,
        static=_is_static(obj, frames),
    )
    if part.static:
        part.static_pose = _pose(obj.pose(0))
        part.static_mesh = _make_mesh(mi, part, part.static_pose)
    return part


def _smooth_normals(mesh) -> NDArray | None:
    """trimesh's vertex normals where they differ from the face normals, else None.

    Flat meshes (walls, boxes: vertices split at the creases) are given no
    vertex normals: Mitsuba's shading with vertex normals costs about 60 %
    more render time on the default scene, for nothing on a flat face.
    """
    normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
    faces = np.asarray(mesh.faces)
    if len(faces) == 0:
        return None
    cos = np.einsum("fij,fj->fi", normals[faces], np.asarray(mesh.face_normals, dtype=np.float64))
    return None if cos.min() > 1.0 - 1e-9 else normals


def _make_mesh(mi, part: _ObjectParts, pose: NDArray):
    v = part.vertices @ pose[:3, :3].T + pose[:3, 3]
    props = mi.Properties()
    props["bsdf"] = part.bsdf
    mesh = mi.Mesh(
        part.name,
        len(v),
        len(part.faces),
        props=props,
        has_vertex_normals=part.normals is not None,
        has_vertex_texcoords=True,
    )
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(v, dtype=np.float32).ravel())
    if part.normals is not None:
        n = part.normals @ pose[:3, :3].T
        params["vertex_normals"] = mi.Float(np.ascontiguousarray(n, dtype=np.float32).ravel())
    params["faces"] = mi.UInt32(np.ascontiguousarray(part.faces, dtype=np.uint32).ravel())
    params["vertex_texcoords"] = mi.Float(part.uv.ravel())
    params.update()
    return mesh


def _texture_dict(mi, texture) -> dict | float:
    """Bitmap texture of a float32 (H, W, 3) linear texture (omnisim.textures convention).

    Texel [i, j] covers u in [j / W, (j + 1) / W), v in [i / H, (i + 1) / H)
    (row 0 at v = 0), which is exactly Mitsuba's bitmap lookup of the UVs
    given to an ``mi.Mesh`` built from arrays (no flip; only Mitsuba's OBJ
    loader flips v). Bilinear, repeating, raw (no colour conversion).
    """
    if texture is None:
        return 0.5
    arr = np.asarray(texture, dtype=np.float32)
    if arr.ndim == 2:
        arr = np.repeat(arr[..., None], 3, axis=-1)
    return {
        "type": "bitmap",
        "bitmap": mi.Bitmap(np.ascontiguousarray(arr)),
        "raw": True,
        "filter_type": "bilinear",
        "wrap_mode": "repeat",
    }


def _bsdf_dict(mi, material, texture) -> dict:
    """BSDF of an ``omnisim.scene.Material`` (or a material name) with its texture.

    ``diffuse``: texture = albedo. ``plastic``: texture = diffuse albedo under
    a dielectric coat (``int_ior``; ``roughplastic`` with GGX alpha =
    ``roughness`` when > 0). ``conductor``: perfect specular, texture =
    specular reflectance. ``roughconductor``: GGX alpha = ``roughness``.
    Wrapped in ``twosided`` when ``material.two_sided`` (the default).
    """
    if material is None or isinstance(material, str):
        kind, rough, ior, two = material or "diffuse", 0.0, 1.5, True
    else:
        kind = str(_get(material, "type", "diffuse"))
        rough = float(_get(material, "roughness", 0.0) or 0.0)
        ior = float(_get(material, "int_ior", 1.5))
        two = bool(_get(material, "two_sided", True))
    tex = _texture_dict(mi, texture)
    if kind == "diffuse":
        inner = {"type": "diffuse", "reflectance": tex}
    elif kind == "plastic" and rough > 0:
        inner = {"type": "roughplastic", "diffuse_reflectance": tex, "int_ior": ior, "alpha": rough}
    elif kind == "plastic":
        inner = {"type": "plastic", "diffuse_reflectance": tex, "int_ior": ior}
    elif kind == "conductor":
        inner = {"type": "conductor", "material": "none", "specular_reflectance": tex}
    elif kind == "roughconductor":
        inner = {
            "type": "roughconductor",
            "material": "none",
            "specular_reflectance": tex,
            "alpha": max(rough, 1e-3),
        }
    else:
        raise ValueError(
            f"material {kind!r}: expected diffuse, plastic, conductor or roughconductor"
        )
    return {"type": "twosided", "bsdf": inner} if two else inner


def _material_type(obj) -> str:
    mat = _get(obj, "material", "diffuse")
    return str(mat if isinstance(mat, str) or mat is None else _get(mat, "type", "diffuse"))


def _integrator_dict(kind: str, max_depth: int, all_diffuse: bool = False) -> dict:
    """The Mitsuba integrator of a scene's ``render.integrator`` and ``max_depth``.

    ``path``: Mitsuba's path tracer (emitter sampling with MIS) to
    ``max_depth`` (2 = direct light only; the analytic mirror is not a
    bounce, so 3 adds one indirect bounce). ``direct``: direct illumination;
    when every material is diffuse and there is no environment light it
    samples the emitters only (no BSDF samples): on the default scene this
    has the same noise as MIS at about 0.4x the time
    (benchmarks/bench_render.py); otherwise it keeps Mitsuba's MIS defaults.
    Any other name is passed to Mitsuba with ``max_depth``.
    """
    kind = str(kind or "path")
    if kind == "direct":
        if all_diffuse:
            return {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0}
        return {"type": "direct"}
    if kind == "path":
        return {"type": "path", "max_depth": int(max_depth), "hide_emitters": False}
    return {"type": kind, "max_depth": int(max_depth)}


def _rgb(value, default=1.0):
    if value is None:
        value = default
    arr = np.broadcast_to(np.asarray(value, dtype=np.float64), (3,))
    return {"type": "rgb", "value": [float(a) for a in arr]}


def _vec(value) -> list[float]:
    return [float(a) for a in np.asarray(value, dtype=np.float64).reshape(3)]


def _light_dicts(mi, lights) -> dict[str, Any]:
    """Mitsuba emitters (and emitting shapes) for ``omnisim.scene`` lights.

    ``point`` -> point emitter; ``area`` -> a one-sided ``rectangle`` with an
    area emitter, placed by ``AreaLight.to_world()`` (black, non-reflecting
    BSDF: it is a light panel, not a scene object, and has no object id);
    ``environment`` -> ``constant`` or, with an image, ``envmap``;
    ``directional`` -> ``directional``.
    """
    out: dict[str, Any] = {}
    for i, light in enumerate(lights or ()):
        kind = _get(light, "type", None) or _get(light, "kind", None)
        if kind == "point":
            out[f"light{i}"] = {
                "type": "point",
                "position": _vec(_get(light, "position")),
                "intensity": _rgb(_get(light, "intensity")),
            }
        elif kind == "area":
            if hasattr(light, "to_world"):
                m = np.asarray(light.to_world(), dtype=np.float64)
            else:
                size = np.broadcast_to(np.asarray(_get(light, "size", 1.0), float), (2,))
                m = np.eye(4)
                m[:3, :3] = np.diag([size[0] / 2, size[1] / 2, -1.0])
                m[:3, 3] = _vec(_get(light, "position"))
            out[f"light{i}"] = {
                "type": "rectangle",
                "to_world": mi.ScalarTransform4f(m.tolist()),
                "emitter": {"type": "area", "radiance": _rgb(_get(light, "radiance"))},
                "bsdf": {"type": "diffuse", "reflectance": 0.0},
            }
        elif kind == "environment":
            image = _get(light, "image", None)
            scale = float(_get(light, "scale", 1.0))
            if image is not None:
                # latitude-longitude image, row 0 at the zenith: Mitsuba's envmap has
                # +Y up, the world has +Z up
                out[f"light{i}"] = {
                    "type": "envmap",
                    "scale": scale,
                    "bitmap": mi.Bitmap(np.asarray(image, dtype=np.float32)),
                    "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], 90),
                }
            else:
                rad = np.asarray(_get(light, "radiance", 1.0), float) * scale
                out[f"light{i}"] = {"type": "constant", "radiance": _rgb(rad)}
        elif kind == "directional":
            out[f"light{i}"] = {
                "type": "directional",
                "direction": _vec(_get(light, "direction")),
                "irradiance": _rgb(_get(light, "irradiance")),
            }
        else:
            raise ValueError(
                f"light {i}: unknown type {kind!r}: expected point, area, "
                "environment or directional"
            )
    return out


# ----------------------------------------------------------------------------
# Cache of Mitsuba scenes per Scene object
# ----------------------------------------------------------------------------
#: Mitsuba states of the most recently used Scenes (each holds its Scene alive).
_CACHE: list[MitsubaScene] = []
#: How many Scenes keep their Mitsuba state (JIT memory is freed with the rest).
MAX_SCENES = 2


def get_mitsuba_scene(scene) -> MitsubaScene:
    """The cached Mitsuba state of ``scene`` (the ``MAX_SCENES`` last Scenes are kept)."""
    for i, ms in enumerate(_CACHE):
        if ms.scene is scene:  # by identity: Scenes hold arrays, so == is ambiguous
            _CACHE.append(_CACHE.pop(i))
            return ms
    ms = MitsubaScene(scene)
    _CACHE.append(ms)
    del _CACHE[:-MAX_SCENES]
    return ms


def clear_cache() -> None:
    """Forget every cached Mitsuba scene (tests; frees JIT memory)."""
    _CACHE.clear()


# ----------------------------------------------------------------------------
