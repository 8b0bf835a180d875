"""Scene files: read, check and build the scene model (no renderer here).

A scene is a TOML file (``scenes/*.toml``, documented key by key in
``docs/scene_format.md``). :func:`load_scene` parses it, applies command-line
overrides, checks every key and value, builds the rig
(:class:`omniflow.geometry.rig.Rig`), the robot's motion, the objects' meshes
(trimesh, with UVs) and textures, and the lights, and checks that the rig is
possible in that scene at every frame. Any problem raises :class:`SceneError`
naming the file, the key and what was expected, before anything is rendered.

For the renderer (a backend; this module imports no renderer):

* ``Scene.robot.pose(frame)`` is world-from-rig, (4, 4). The rig frame is
  :mod:`omniflow.conventions`'s: origin at cam2's cone tip, Z up the axis.
* ``SceneObject.mesh`` is in the object's own frame with per-vertex UVs
  (``mesh.visual.uv``, in texture tiles, wrap-around: use a repeating bitmap);
  ``SceneObject.pose(frame)`` is world-from-object, (4, 4). Poses exist for
  any real frame number (frame + 1 after the last rendered frame too).
* ``SceneObject.texture``: float32 (H, W, 3) linear RGB, texel convention in
  :mod:`omnisim.textures` (row 0 at v = 0).
* Orientation: closed meshes face outward; the room's floor, ceiling and
  walls face INTO the room. ``Material.two_sided`` (default True) asks the
  renderer to shade both sides as well, so either choice renders.
* ``SceneObject.material``: ``diffuse`` (texture = albedo), ``plastic``
  (texture = diffuse albedo under a dielectric coat of ``int_ior``; rough when
  ``roughness`` > 0), ``conductor`` (perfect specular, texture = specular
  reflectance), ``roughconductor`` (GGX ``roughness`` alpha, texture =
  specular reflectance).
* Lights: :class:`PointLight`, :class:`AreaLight` (a rectangle, its
  ``to_world()`` maps the square [-1, 1]^2 in z = 0 with normal +Z onto it),
  :class:`EnvironmentLight`, :class:`DirectionalLight`. Area lights are
  shapes a camera ray can hit; they are not objects and have no object id.
* Object ids are integers >= 1, unique; id 0 is left for "nothing hit".
"""

from __future__ import annotations

import copy
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from omniflow.geometry.rig import Rig, RigError, rig_from_dict
from omniflow.geometry.test_card import card_from_table
from omniflow.input_files import InputFileError, parse_text, read_input
from omnisim import geometry, rig_parts, scene_placement
from omnisim.camera import CameraError, CameraModel
from omnisim.motion import (
    ConstantMotion,
    KeyframeMotion,
    Motion,
    StaticMotion,
    euler_deg,
)
from omnisim.optics import Optics, optics_from_table
from omnisim.rig_errors import rig_with_errors
from omnisim.scene_checker import REQUIRED, Checker, SceneError
from omnisim.scene_lights import (
    AreaLight,
    DirectionalLight,
    EnvironmentLight,
    Light,
    PointLight,
    lights_from_tables,
)
from omnisim.scene_textures import (
    texture_from_table,
    tile_of,
)

__all__ = [
    "AreaLight",
    "DirectionalLight",
    "EnvironmentLight",
    "Light",
    "Material",
    "PointLight",
    "RenderSettings",
    "Robot",
    "RoomInfo",
    "Scene",
    "SceneError",
    "SceneObject",
    "apply_overrides",
    "load_scene",
    "parse_override",
]


# ---------------------------------------------------------------------------
# The scene model
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class RenderSettings:
    """How to render: image size (pixels), samples per pixel, path depth, seed, integrator."""

    width: int = 512
    height: int = 512
    spp: int = 64
    max_depth: int = 4
    seed: int = 0
    integrator: str = "direct"
    variant: str = "llvm_ad_rgb"
    denoise: str = "oidn"
    time_samples: int = 8  # sub-frames of an open shutter (camera.shutter > 0)


@dataclass(frozen=True)
class Material:
    """Surface scattering; the object's texture feeds its main reflectance (see module doc)."""

    type: str = "diffuse"
    roughness: float = 0.0
    int_ior: float = 1.5
    two_sided: bool = True


@dataclass(frozen=True)
class Robot:
    """The rig as a rigid body: ``pose(frame)`` is world from rig, (4, 4)."""

    motion: Motion
    frame_interval: float

    def pose(self, frame: float) -> NDArray[np.float64]:
        return self.motion.pose_at(float(frame) * self.frame_interval)


@dataclass(frozen=True)
class SceneObject:
    """One textured rigid object; ``pose(frame)`` is world from object, (4, 4)."""

    id: int
    name: str
    kind: str
    mesh: trimesh.Trimesh = field(repr=False)
    texture: NDArray[np.float32] = field(repr=False)
    material: Material
    motion: Motion
    frame_interval: float
    index: int = -1  # position in the file's objects list (for messages)

    def pose(self, frame: float) -> NDArray[np.float64]:
        return self.motion.pose_at(float(frame) * self.frame_interval)

    @property
    def moving(self) -> bool:
        return not isinstance(self.motion, StaticMotion)


@dataclass(frozen=True)
class RoomInfo:
    """A room of the scene file (``objects[index]``), built as six objects from ``first_id``."""

    index: int
    name: str
    size: NDArray[np.float64]
    first_id: int


@dataclass(frozen=True)
class Scene:
    """A loaded, checked scene. ``data`` is the parsed file with overrides applied."""

    name: str
    description: str
    path: Path
    data: dict[str, Any] = field(repr=False)
    source: str = field(repr=False)
    rig: Rig = field(repr=False)
    frames: int
    frame_interval: float
    render: RenderSettings
    robot: Robot
    objects: tuple[SceneObject, ...] = field(repr=False)
    lights: tuple[Light, ...] = field(repr=False)
    rooms: tuple[RoomInfo, ...] = ()
    overrides: dict[str, Any] = field(default_factory=dict)
    camera: CameraModel = field(default_factory=CameraModel)
    optics: Optics = field(default_factory=Optics)

    def object_by_id(self, object_id: int) -> SceneObject:
        for obj in self.objects:
            if obj.id == object_id:
                return obj
        raise KeyError(object_id)

    @property
    def object_names(self) -> dict[int, str]:
        """Object id -> name (the meaning of the ``gt.object`` channel)."""
        return {obj.id: obj.name for obj in self.objects}

    def poses(self, frame: float) -> dict[str, Any]:
        """Robot and object poses at a frame as nested lists (for dataset.json)."""
        return {
            "robot": self.robot.pose(frame).tolist(),
            "objects": {str(o.id): o.pose(frame).tolist() for o in self.objects},
        }


# ---------------------------------------------------------------------------
# Overrides
# ---------------------------------------------------------------------------


def parse_override(text: str) -> tuple[str, Any]:
    """Split a command-line ``key=value`` into (dotted key, value).

    The value is read as a TOML value (``4``, ``0.5``, ``true``, ``[1, 2, 3]``,
    ``"text"``); anything TOML cannot read is kept as a string.
    """
    if "=" not in text:
        raise SceneError(f"override {text!r}: expected KEY=VALUE, e.g. render.spp=4")
    key, raw = text.split("=", 1)
    key, raw = key.strip(), raw.strip()
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    return key, value


def apply_overrides(data: dict, overrides: Mapping[str, Any] | None, where: str) -> dict:
    """Return a deep copy of ``data`` with dotted-key overrides set.

    ``{"render.width": 128, "frames": 3}``; a numeric part indexes a list
    (``"objects.1.motion.velocity"``). Missing tables are created; values are
    type-checked later with the rest of the file.
    """
    out = copy.deepcopy(data)
    for key, value in (overrides or {}).items():
        parts = str(key).split(".")
        if not all(parts):
            raise SceneError(f"{where}: override {key!r}: expected a dotted key like render.spp")
        node: Any = out
        for depth, part in enumerate(parts[:-1]):
            here = ".".join(parts[: depth + 1])
            if isinstance(node, list):
                if not part.isdigit() or int(part) >= len(node):
                    raise SceneError(
                        f"{where}: override {key!r}: {here}: expected an index below {len(node)}"
                    )
                node = node[int(part)]
            elif isinstance(node, dict):
                node = node.setdefault(part, {})
            else:
                raise SceneError(f"{where}: override {key!r}: {here} is not a table")
        last = parts[-1]
        if isinstance(node, list) and last.isdigit() and int(last) < len(node):
            node[int(last)] = value
        elif isinstance(node, dict):
            node[last] = value
        else:
            raise SceneError(f"{where}: override {key!r}: {'.'.join(parts[:-1])} is not a table")
    return out


# ---------------------------------------------------------------------------
# Schema (the allowed keys of each table)
# ---------------------------------------------------------------------------

TOP_KEYS = frozenset(
    "name description frames frame_interval render rig robot objects lights camera optics".split()
)
RENDER_KEYS = frozenset(
    {"width", "height", "spp", "max_depth", "seed", "integrator", "variant", "denoise"}
    | {"time_samples"}
)
RIG_KEYS = frozenset(
    {"d", "R", "s", "x_c", "y_c", "r_m", "margin", "struts", "mount_radius", "errors"}
)
ROBOT_KEYS = frozenset({"position", "rotation", "motion"})
MOTION_KEYS = frozenset({"type", "velocity", "angular_velocity", "interpolation", "keys"})
KEY_KEYS = frozenset({"time", "frame", "position", "rotation"})
OBJECT_TYPES = ("room", "box", "cylinder", "sphere", "plane", "mesh", "test_card")
_OBJ_COMMON = {"name", "type", "id", "position", "rotation", "motion", "texture", "material"}
OBJECT_KEYS = {
    "room": frozenset(_OBJ_COMMON | {"size", "floor_texture", "ceiling_texture", "wall_texture"}),
    "box": frozenset(_OBJ_COMMON | {"size"}),
    "cylinder": frozenset(_OBJ_COMMON | {"radius", "height", "sections", "caps"}),
    "sphere": frozenset(_OBJ_COMMON | {"radius", "sections"}),
    "plane": frozenset(_OBJ_COMMON | {"size"}),
    "mesh": frozenset(_OBJ_COMMON | {"path", "scale", "uv", "center"}),
    "test_card": frozenset(
        (_OBJ_COMMON - {"texture"}) | {"radius", "height", "sectors", "ring_spacing", "colors"}
    ),
}
#: A test card's dark and light albedo (``colors``), linear RGB.
CARD_COLORS = ((0.08, 0.08, 0.08), (0.80, 0.80, 0.80))
MATERIAL_TYPES = ("diffuse", "plastic", "conductor", "roughconductor")
MATERIAL_KEYS = frozenset({"type", "roughness", "int_ior", "two_sided"})
INTEGRATORS = ("path", "direct")
#: ``render.denoise``: none, or Intel Open Image Denoise (``omnisim.denoise``).
DENOISERS = ("none", "oidn")
#: Most frames a scene may have (dataset.json holds a pose per frame and object; 100000
#: frames of a scene with 8 objects are about 360 MB of it).
MAX_FRAMES = 100_000


# ---------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------


def load_scene(path: str | Path, overrides: Mapping[str, Any] | None = None) -> Scene:
    """Read, check and build a scene file.

    Parameters
    ----------
    path : str or Path
        The TOML scene file; mesh and texture paths in it are relative to it.
    overrides : mapping, optional
        Dotted keys set before checking, e.g. ``{"render.width": 128,
        "render.spp": 4, "frames": 3, "render.seed": 7}``.

    Raises
    ------
    SceneError
        On any unknown key, wrong type, impossible value or rig, or missing
        mesh/texture file; the message names the file and the key.
    """
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: scene file not found")
    source = _read_text(path)
    try:
        raw = parse_text(source, path, "toml")
    except InputFileError as exc:
        raise SceneError(str(exc)) from None
    overrides = dict(overrides or {})
    data = apply_overrides(raw, overrides, str(path))
    # Error keys write list items as objects[1]; overrides as objects.1.
    chk = Checker(path, {re.sub(r"\.(\d+)(?=\.|$)", r"[\1]", str(k)) for k in overrides})
    return _build(chk, path, source, data, overrides)


def _read_text(path: Path) -> str:
    """The scene file's text; SceneError for a binary or unreadable file."""
    try:
        return read_input(path, "TOML scene")
    except InputFileError as exc:  # binary, too large
        raise SceneError(str(exc)) from None
    except OSError as exc:
        raise SceneError(f"{path}: cannot read: {exc.strerror or exc}") from None


def _build(chk: Checker, path: Path, source: str, data: dict, overrides: dict) -> Scene:
    chk.table(data, "", TOP_KEYS)
    name = chk.string(data, "name", "", path.stem)
    description = chk.string(data, "description", "", "")
    frames = chk.integer(data, "frames", "", 8, lo=1)
    if frames > MAX_FRAMES:
        raise chk.bad("frames", frames, f"at most {MAX_FRAMES} (render a longer run in parts)")
    dt = chk.number(data, "frame_interval", "", 0.1, lo=0.0, lo_open=True)

    render = _render_settings(chk, data.get("render", {}))
    rig = _rig(chk, data.get("rig", REQUIRED), render, path)
    robot = _robot(chk, data.get("robot", {}), dt)
    objects, rooms = _objects(chk, data.get("objects", []), dt, path.parent)
    objects += _rig_parts(chk, data["rig"], rig, robot, objects)
    lights = lights_from_tables(chk, data.get("lights", REQUIRED), path.parent)
    camera = _camera(chk, data.get("camera", {}))
    optics = optics_from_table(chk, data.get("optics", {}), rig.cam1.v)

    scene = Scene(
        name=name,
        description=description,
        path=path,
        data=data,
        source=source,
        rig=rig,
        frames=frames,
        frame_interval=dt,
        render=render,
        robot=robot,
        objects=tuple(objects),
        lights=tuple(lights),
        rooms=tuple(rooms),
        overrides=overrides,
        camera=camera,
        optics=optics,
    )
    scene_placement.check_rig_in_scene(chk, scene)
    scene_placement.check_not_enclosed(chk, scene)
    return scene


def _render_settings(chk: Checker, tbl: Any) -> RenderSettings:
    chk.table(tbl, "render", RENDER_KEYS)
    w = "render"
    d = RenderSettings()
    variant = chk.string(tbl, "variant", w, d.variant)
    if not variant.endswith("_rgb") or variant.split("_")[0] not in ("scalar", "llvm", "cuda"):
        raise chk.bad(f"{w}.variant", variant, "an RGB variant such as 'llvm_ad_rgb'")
    return RenderSettings(
        width=chk.integer(tbl, "width", w, d.width, lo=8, hi=16384),
        height=chk.integer(tbl, "height", w, d.height, lo=8, hi=16384),
        spp=chk.integer(tbl, "spp", w, d.spp, lo=1),
        max_depth=chk.integer(tbl, "max_depth", w, d.max_depth, lo=1),
        seed=chk.integer(tbl, "seed", w, d.seed, lo=0, hi=2**31 - 1),
        integrator=chk.string(tbl, "integrator", w, d.integrator, choices=INTEGRATORS),
        variant=variant,
        denoise=chk.string(tbl, "denoise", w, d.denoise, choices=DENOISERS),
        time_samples=chk.integer(tbl, "time_samples", w, d.time_samples, lo=1, hi=1024),
    )


def _camera(chk: Checker, tbl: Any) -> CameraModel:
    """The ``[camera]`` table (:class:`omnisim.camera.CameraModel`; defaults for missing keys)."""
    if not isinstance(tbl, dict):
        raise chk.bad("camera", tbl, "a table of camera parameters ([camera])")
    try:
        return CameraModel.from_mapping(tbl, where=str(chk.scene_file))
    except CameraError as exc:
        if f"camera.{exc.key}" in chk.overridden:
            raise SceneError(
                f"{exc.where}: camera.{exc.key} (set by an override) = {exc.value!r}: "
                f"expected {exc.expected}"
            ) from exc
        raise SceneError(str(exc)) from exc


def _rig(chk: Checker, tbl: Any, render: RenderSettings, path: Path) -> Rig:
    if tbl is REQUIRED:
        raise chk.error("rig", "missing; expected a table with d, R, s (metres)")
    chk.table(tbl, "rig", RIG_KEYS)
    d = chk.number(tbl, "d", "rig", lo=0, lo_open=True)
    big_r = chk.number(tbl, "R", "rig", lo=0, lo_open=True)
    s = chk.number(tbl, "s", "rig", lo=0, lo_open=True)
    w, h = render.width, render.height
    margin = chk.number(tbl, "margin", "rig", 2.0, lo=0.0)
    x_c = chk.number(tbl, "x_c", "rig", w / 2.0)
    y_c = chk.number(tbl, "y_c", "rig", h / 2.0)
    r_m = chk.number(tbl, "r_m", "rig", min(w, h) / 2.0 - margin, lo=0, lo_open=True)
    for key, val, size in (("x_c", x_c, w), ("y_c", y_c, h)):
        if not 0 <= val <= size:
            raise chk.bad(f"rig.{key}", val, f"a centre inside the image, in [0, {size}] px")
    if x_c - r_m < 0 or y_c - r_m < 0 or x_c + r_m > w or y_c + r_m > h:
        given = [k for k in ("r_m", "x_c", "y_c") if k in tbl]
        key = "rig." + (given[0] if given else "margin")
        raise chk.error(
            key,
            f"the rim circle (centre ({x_c:g}, {y_c:g}), radius {r_m:g} px) leaves the "
            f"{w}x{h} image; expected it inside the image",
        )
    cam = {"x_c": x_c, "y_c": y_c, "r_m": r_m, "width": w, "height": h}
    try:
        cams = [dict(cam, name="cam1"), dict(cam, name="cam2")]
        rig = rig_from_dict({"rig": {"d": d, "R": big_r, "s": s}, "cameras": cams}, str(path))
    except RigError as exc:
        raise SceneError(str(exc)) from exc
    return rig_with_errors(chk, tbl, rig)  # [rig.errors.camN] (omnisim.rig_errors)


def _rig_parts(chk: Checker, tbl: dict, rig: Rig, robot: Robot, objects: list) -> list:
    """Struts and flanges (:mod:`omnisim.rig_parts`): objects moving with the robot."""
    first = max((o.id for o in objects), default=0) + 1
    tex = np.full((2, 2, 3), rig_parts.PART_ALBEDO, dtype=np.float32)
    return [
        SceneObject(
            p["id"],
            p["name"],
            p["kind"],
            p["mesh"],
            tex,
            Material(),
            robot.motion,
            robot.frame_interval,
        )
        for p in rig_parts.rig_parts(chk, tbl, rig, first)
    ]


def _motion(
    chk: Checker, tbl: Any, where: str, position: NDArray, rotation: Rotation, dt: float
) -> Motion:
    if tbl is None:
        return StaticMotion(position, rotation)
    chk.table(tbl, where, MOTION_KEYS)
    kind = chk.string(tbl, "type", where, "static", choices=("static", "constant", "keyframes"))
    allowed = {
        "static": {"type"},
        "constant": {"type", "velocity", "angular_velocity"},
        "keyframes": {"type", "interpolation", "keys"},
    }[kind]
    extra = sorted(set(tbl) - allowed)
    if extra:
        raise chk.error(
            f"{where}.{extra[0]}",
            f"not used by motion type {kind!r}; expected one of: {', '.join(sorted(allowed))}",
        )
    if kind == "static":
        return StaticMotion(position, rotation)
    if kind == "constant":
        v = chk.vector(tbl, "velocity", where, [0.0, 0.0, 0.0])
        w = chk.vector(tbl, "angular_velocity", where, [0.0, 0.0, 0.0])
        return ConstantMotion(position, rotation, v, np.radians(w))
    interp = chk.string(tbl, "interpolation", where, "linear", choices=("linear", "cubic"))
    keys = tbl.get("keys", REQUIRED)
    if keys is REQUIRED or not isinstance(keys, list) or not keys:
        raise chk.bad(
            f"{where}.keys",
            keys if keys is not REQUIRED else None,
            "a non-empty list of tables with time (s) or frame, position, rotation",
        )
    times, positions, rotations = [], [], []
    for i, key in enumerate(keys):
        kw = f"{where}.keys[{i}]"
        chk.table(key, kw, KEY_KEYS)
        if ("time" in key) == ("frame" in key):
            raise chk.error(kw, "expected exactly one of 'time' (seconds) or 'frame'")
        if "time" in key:
            t = chk.number(key, "time", kw)
        else:
            t = chk.number(key, "frame", kw) * dt
        if times and t <= times[-1]:
            tkey = "time" if "time" in key else "frame"
            raise chk.bad(f"{kw}.{tkey}", key[tkey], "keys in strictly increasing time")
        times.append(t)
        positions.append(chk.vector(key, "position", kw, position))
        rotations.append(chk.vector(key, "rotation", kw, rotation.as_euler("xyz", degrees=True)))
    return KeyframeMotion(
        np.asarray(times), np.asarray(positions), euler_deg(np.asarray(rotations)), interp
    )


def _pose_and_motion(chk: Checker, tbl: dict, where: str, default_pos, dt: float) -> Motion:
    pos = chk.vector(tbl, "position", where, default_pos)
    rot = euler_deg(chk.vector(tbl, "rotation", where, [0.0, 0.0, 0.0]))
    return _motion(chk, tbl.get("motion"), f"{where}.motion", pos, rot, dt)


def _robot(chk: Checker, tbl: Any, dt: float) -> Robot:
    chk.table(tbl, "robot", ROBOT_KEYS)
    return Robot(_pose_and_motion(chk, tbl, "robot", [0.0, 0.0, 0.5], dt), dt)


def _material(chk: Checker, tbl: Any, where: str) -> Material:
    tbl = {} if tbl is None else tbl
    chk.table(tbl, where, MATERIAL_KEYS)
    kind = chk.string(tbl, "type", where, "diffuse", choices=MATERIAL_TYPES)
    default_rough = 0.1 if kind == "roughconductor" else 0.0
    rough = chk.number(tbl, "roughness", where, default_rough, lo=0.0, hi=1.0)
    if kind == "roughconductor" and rough <= 0:
        raise chk.bad(f"{where}.roughness", rough, "> 0 for a roughconductor")
    return Material(
        type=kind,
        roughness=rough,
        int_ior=chk.number(tbl, "int_ior", where, 1.5, lo=1.0, hi=4.0),
        two_sided=chk.boolean(tbl, "two_sided", where, True),
    )


def _objects(
    chk: Checker, items: Any, dt: float, base: Path
) -> tuple[list[SceneObject], list[RoomInfo]]:
    if not isinstance(items, list):
        raise chk.bad("objects", items, "a list of tables ([[objects]])")
    # First pass: types and explicit ids, so automatic ids avoid explicit ones.
    kinds, explicit, used = [], {}, set()
    for i, tbl in enumerate(items):
        where = f"objects[{i}]"
        if not isinstance(tbl, dict):
            raise chk.bad(where, tbl, "a table")
        kinds.append(chk.string(tbl, "type", where, choices=OBJECT_TYPES))
        chk.table(tbl, where, OBJECT_KEYS[kinds[-1]])
        if "id" in tbl:
            first = chk.integer(tbl, "id", where, lo=1)
            span = range(first, first + (len(geometry.ROOM_PARTS) if kinds[-1] == "room" else 1))
            if used.intersection(span):
                raise chk.bad(
                    f"{where}.id", first, "an id not used by another object (a room uses six)"
                )
            explicit[i] = first
            used.update(span)
    next_id = 1
    objects: list[SceneObject] = []
    rooms: list[RoomInfo] = []
    names: set[str] = set()
    for i, tbl in enumerate(items):
        where, kind = f"objects[{i}]", kinds[i]
        span = len(geometry.ROOM_PARTS) if kind == "room" else 1
        if i in explicit:
            first = explicit[i]
        else:
            while any(k in used for k in range(next_id, next_id + span)):
                next_id += 1
            first = next_id
            used.update(range(first, first + span))
        name = chk.string(tbl, "name", where, f"{kind}{i}")
        if name in names:
            raise chk.bad(f"{where}.name", name, "a name not used by another object")
        names.add(name)
        motion = _pose_and_motion(chk, tbl, where, [0.0, 0.0, 0.0], dt)
        material = _material(chk, tbl.get("material"), f"{where}.material")
        if kind == "room":
            size = chk.vector(tbl, "size", where, lo=0, lo_open=True)
            rooms.append(RoomInfo(i, name, size, first))
            objects.extend(_room(chk, tbl, i, name, first, size, motion, material, dt, base))
            continue
        if kind == "test_card":
            mesh, texture = _test_card(chk, tbl, where)
            objects.append(SceneObject(first, name, kind, mesh, texture, material, motion, dt, i))
            continue
        tex_tbl = tbl.get("texture")
        texture = texture_from_table(chk, tex_tbl, f"{where}.texture", first, base)
        tile = tile_of(tex_tbl)
        mesh = _mesh(chk, tbl, kind, where, tile, base)
        objects.append(SceneObject(first, name, kind, mesh, texture, material, motion, dt, i))
    return objects, rooms


def _mesh(chk: Checker, tbl: dict, kind: str, where: str, tile: float, base: Path):
    if kind == "box":
        return geometry.box(chk.vector(tbl, "size", where, lo=0, lo_open=True), tile=tile)
    if kind == "plane":
        size = chk.vector(tbl, "size", where, n=2, lo=0, lo_open=True)
        return geometry.plane(size, tile=tile)
    if kind in ("cylinder", "sphere"):
        radius = chk.number(tbl, "radius", where, lo=0, lo_open=True)
        sections = chk.integer(tbl, "sections", where, 96, lo=8, hi=4096)
        if kind == "sphere":
            return geometry.sphere(radius, tile=tile, sections=sections)
        height = chk.number(tbl, "height", where, lo=0, lo_open=True)
        caps = chk.boolean(tbl, "caps", where, True)
        return geometry.cylinder(radius, height, tile=tile, sections=sections, caps=caps)
    # kind == "mesh"
    mesh_path = chk.file(tbl, "path", where, base, geometry.MESH_SUFFIXES)
    scale = tbl.get("scale", 1.0)
    if isinstance(scale, list):
        scale = chk.vector(tbl, "scale", where, lo=0, lo_open=True)
    else:
        scale = chk.number(tbl, "scale", where, 1.0, lo=0, lo_open=True)
    uv = chk.string(tbl, "uv", where, "auto", choices=("auto", "file", "box"))
    center = chk.boolean(tbl, "center", where, False)
    try:
        return geometry.load_mesh_file(mesh_path, scale=scale, uv=uv, tile=tile, center=center)
    except ValueError as exc:
        raise chk.error(f"{where}.path", f"{exc}; expected a mesh with triangles") from exc


def _test_card(chk: Checker, tbl: dict, where: str):
    """The mesh and texture of a ``test_card`` (``omniflow.geometry.test_card``)."""
    card = card_from_table(tbl, lambda key, v, expected: chk.bad(f"{where}.{key}", v, expected))
    colors = tbl.get("colors", CARD_COLORS)
    if not isinstance(colors, list | tuple) or len(colors) != 2:
        raise chk.bad(f"{where}.colors", colors, "two [r, g, b] colours (dark, light) in [0, 1]")
    dark, light = (chk.vector({"c": c}, "c", f"{where}.colors", n=3, lo=0, hi=1) for c in colors)
    t = card.texture()[..., None]
    texture = (dark * (1 - t) + light * t).astype(np.float32)
    return geometry.test_card(card), texture


def _room(chk, tbl, index, name, first, size, motion, material, dt, base) -> list[SceneObject]:
    where = f"objects[{index}]"
    out = []
    for k, part in enumerate(geometry.ROOM_PARTS):
        specific = {"floor": "floor_texture", "ceiling": "ceiling_texture"}.get(
            part, "wall_texture"
        )
        key = specific if specific in tbl else "texture"
        tex_tbl = tbl.get(key)
        tex_where = f"{where}.{key}"
        # Each part gets its own pattern: the seed (given or the id) plus the part number.
        if isinstance(tex_tbl, dict) and "seed" in tex_tbl:
            seed = chk.integer(tex_tbl, "seed", tex_where, lo=0)
            tex_tbl = dict(tex_tbl, seed=seed + k)
        texture = texture_from_table(chk, tex_tbl, tex_where, first + k, base)
        mesh = geometry.room(size, tile=tile_of(tex_tbl))[part]
        out.append(
            SceneObject(
                first + k, f"{name}.{part}", "room", mesh, texture, material, motion, dt, index
            )
        )
    return out
