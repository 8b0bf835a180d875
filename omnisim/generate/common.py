"""Parts every family shares: the seeded draws, rig, camera, textures, materials, robot
motion and moving objects, each drawn from the ranges documented in ``docs/generator.md``.

Every draw goes through :class:`Draw`, which uses only ``Generator.random`` and
``Generator.integers`` of a ``numpy.random.Generator(PCG64(...))`` and does the rest of
the arithmetic in Python floats, so a (family, seed) gives the same scene on any machine
(the golden hashes in ``tests/omnisim/test_generate.py`` would show a difference).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "Draw",
    "Layout",
    "camera_table",
    "draw_rig",
    "light_factor",
    "material_table",
    "movers",
    "render_table",
    "robot_table",
    "texture_table",
]

#: Library-scene reference levels that ``light_factor`` scales (``scenes/default.toml``,
#: ``scenes/open_field.toml``): ceiling area lights, the sky and the sun.
AREA_RADIANCE = 12.0
SKY_RADIANCE = (0.35, 0.40, 0.50)
SUN_IRRADIANCE = (2.5, 2.4, 2.2)
#: Image sizes a scene is drawn at (width = height, px).
IMAGE_SIZES = (256, 384, 512, 640, 768, 1024)
FRAMES = 8
FRAME_INTERVAL = 0.05
#: Robot motions and mover motions.
ROBOT_MOTIONS = ("static", "straight", "yaw", "arc", "stop_and_go")
MOVER_MOTIONS = ("translating", "approaching", "passing", "spinning", "rolling")
#: Image motion drawn for a moving robot or mover, px/frame (log-uniform).
PX_PER_FRAME = (0.1, 8.0)


class Draw:
    """Seeded draws over a ``numpy.random.Generator``, in Python floats (portable)."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng

    def uniform(self, lo: float, hi: float) -> float:
        return lo + (hi - lo) * float(self.rng.random())

    def log_uniform(self, lo: float, hi: float) -> float:
        return math.exp(self.uniform(math.log(lo), math.log(hi)))

    def integer(self, lo: int, hi: int) -> int:
        """An integer in [lo, hi], both included."""
        return int(self.rng.integers(lo, hi + 1))

    def choice(self, items: Sequence[Any], weights: Sequence[float] | None = None) -> Any:
        if weights is None:
            return items[self.integer(0, len(items) - 1)]
        u = self.uniform(0.0, sum(weights))
        for item, w in zip(items, weights, strict=True):
            if u < w:
                return item
            u -= w
        return items[-1]

    def chance(self, p: float) -> bool:
        return float(self.rng.random()) < p

    def seed(self) -> int:
        """A seed for a texture or the renderer, 0 ... 2**31 - 1."""
        return self.integer(0, 2**31 - 1)

    def unit_vector(self) -> list[float]:
        z = self.uniform(-1.0, 1.0)
        phi = self.uniform(0.0, 2 * math.pi)
        s = math.sqrt(max(0.0, 1 - z * z))
        return [s * math.cos(phi), s * math.sin(phi), z]


@dataclass(frozen=True)
class Layout:
    """What the motion and mover draws need to know about a drawn scene."""

    width: int  # image size, px
    rig: dict[str, float]  # d, R, s
    distance: float  # typical distance from the axis to the surfaces seen, m
    floor: float = 0.0  # floor height, m

    @property
    def px_per_rad(self) -> float:
        """Nominal image motion per radian of bearing change: a quarter of the width."""
        return self.width / 4.0

    @property
    def min_common_range(self) -> float:
        r = self.rig
        return r["s"] * (r["d"] + r["R"]) / r["R"] - r["d"]


def light_factor(draw: Draw) -> float:
    """Light level relative to the library's, log-uniform in [1/16, 4]."""
    return draw.log_uniform(1 / 16, 4.0)


def draw_rig(draw: Draw, max_common_range: float) -> dict[str, float]:
    """d, R, s with d/R in [1.5, 3], s/(d + R) in [1.3, 2.5], R in [0.03, 0.08] m.

    Redrawn (up to 200 times) until ``min_common_range`` <= ``max_common_range``; the
    last draw is shrunk to R = 0.03 m if none fits (the scene loader then decides).
    """
    rig = {}
    for _ in range(200):
        R = draw.uniform(0.03, 0.08)
        d = R * draw.uniform(1.5, 3.0)
        s = (d + R) * draw.uniform(1.3, 2.5)
        rig = {"d": round(d, 4), "R": round(R, 4), "s": round(s, 4)}
        if s * (d + R) / R - d <= max_common_range:
            return rig
    k = 0.03 / rig["R"]
    return {key: round(v * k, 4) for key, v in rig.items()}


def render_table(draw: Draw, width: int) -> dict[str, Any]:
    return {
        "width": width,
        "height": width,
        "spp": 16,
        "max_depth": 3,
        "seed": draw.seed(),
        "integrator": "direct",
        "denoise": "oidn",
    }


def camera_table(draw: Draw, factor: float) -> dict[str, Any]:
    """The camera for a light level: above the library's (factor > 1) a deeper well.

    With ``factor`` > 1 the full well grows by ``factor`` and the exposure shrinks by it,
    so the image fills the same share of the well with ``factor`` times the electrons
    (shot noise down by sqrt(factor)); below 1 the library's camera gets fewer electrons.
    """
    k = max(1.0, factor)
    return {
        "exposure": 2.0 / k,
        "full_well": float(round(20000.0 * k)),
        "read_noise": draw.uniform(2.0, 10.0),
        "bits": draw.choice((8, 8, 12)),
        "seed": draw.seed(),
    }


def _colors(draw: Draw) -> tuple[list[float], list[float]]:
    tint = [draw.uniform(0.6, 1.0) for _ in range(3)]
    top = max(tint)
    tint = [t / top for t in tint]
    lo = draw.uniform(0.02, 0.15)
    hi = draw.uniform(0.55, 0.9)
    return [lo * t for t in tint], [hi * t for t in tint]


def texture_table(draw: Draw, scale: float, *, allow_solid: bool = False) -> dict[str, Any]:
    """One texture for a surface about ``scale`` metres away: sizes are ``scale`` times
    the ranges below, so the finest features stay about 2.5 px wide at 128 px (10 px at
    512 px; the library's walls are 0.08-0.8 m at 2.5 m, 2.4 times finer).

    Types: noise in one of three wavelength bands, grating, checker, the shipped image
    ``library:assets/poster.png`` and (``allow_solid``) a plain colour. ``contrast`` is
    drawn log-uniform in [0.1, 1]; a checker, which has no contrast key, has its two
    colours pulled together by it.
    """
    kinds = ["noise", "grating", "checker", "image"] + (["solid"] if allow_solid else [])
    weights = [0.45, 0.17, 0.17, 0.11] + ([0.1] if allow_solid else [])
    kind = draw.choice(kinds, weights)
    contrast = draw.log_uniform(0.1, 1.0)
    lo, hi = _colors(draw)
    if kind == "noise":
        band = draw.choice(((0.08, 0.8), (0.15, 1.5), (0.3, 3.0)))
        wl = [band[0] * scale, band[1] * scale]
        return {
            "type": "noise",
            "tile": wl[1] * draw.uniform(1.0, 2.0),
            "resolution": 256,
            "wavelength": wl,
            "exponent": draw.uniform(0.5, 1.5),
            "contrast": contrast,
            "colors": [lo, hi],
            "seed": draw.seed(),
        }
    if kind == "grating":
        wl = draw.log_uniform(0.1, 0.6) * scale
        return {
            "type": "grating",
            "tile": wl * draw.integer(4, 10),
            "resolution": 256,
            "wavelength": wl,
            "angle": draw.uniform(0.0, 180.0),
            "phase": draw.uniform(0.0, 360.0),
            "contrast": contrast,
            "colors": [lo, hi],
        }
    if kind == "checker":
        size = draw.log_uniform(0.1, 0.5) * scale
        mid = [(a + b) / 2 for a, b in zip(lo, hi, strict=True)]
        pulled = [
            [m + contrast * (c - m) for m, c in zip(mid, col, strict=True)] for col in (lo, hi)
        ]
        return {
            "type": "checker",
            "tile": 2 * size * draw.integer(1, 4),
            "resolution": 256,
            "size": size,
            "colors": pulled,
        }
    if kind == "image":
        return {
            "type": "image",
            "tile": draw.log_uniform(0.5, 2.0) * scale,
            "path": "library:assets/poster.png",
        }
    return {"type": "solid", "color": [(a + b) / 2 for a, b in zip(lo, hi, strict=True)]}


def material_table(draw: Draw, glossy_share: float = 0.4) -> dict[str, Any]:
    """Diffuse, or (with probability ``glossy_share``) rough plastic or rough metal."""
    if not draw.chance(glossy_share):
        return {"type": "diffuse"}
    if draw.chance(0.6):
        return {"type": "plastic", "roughness": draw.uniform(0.02, 0.4), "int_ior": 1.5}
    return {"type": "roughconductor", "roughness": draw.uniform(0.05, 0.5)}


def _px_to_angle(draw: Draw, layout: Layout) -> tuple[float, float]:
    """A target image motion (px/frame) and the bearing change giving it (rad/frame)."""
    px = draw.log_uniform(*PX_PER_FRAME)
    return px, px / layout.px_per_rad


def robot_table(
    draw: Draw, layout: Layout, position: list[float], heading: float, kind: str
) -> tuple[dict[str, Any], float, float]:
    """The ``[robot]`` table for motion ``kind``; also its nominal px/frame and its path
    length over the frames (m), which the family keeps clear of the walls.

    A translation of delta per frame moves a surface at the layout's distance D by about
    px_per_rad * delta / D px; a yaw of w rad per frame moves it by px_per_rad * w px.
    """
    rot = [0.0, 0.0, math.degrees(heading)]
    table: dict[str, Any] = {"position": position, "rotation": rot}
    if kind == "static":
        return table, 0.0, 0.0
    px, angle = _px_to_angle(draw, layout)
    dt = FRAME_INTERVAL
    if kind == "yaw":
        sign = draw.choice((-1.0, 1.0))
        w = [0.0, 0.0, sign * math.degrees(angle) / dt]
        table["motion"] = {"type": "constant", "angular_velocity": w}
        return table, px, 0.0
    step = angle * layout.distance  # m per frame
    direction = heading + draw.uniform(-0.5, 0.5)
    ux, uy = math.cos(direction), math.sin(direction)
    if kind == "straight":
        table["motion"] = {"type": "constant", "velocity": [ux * step / dt, uy * step / dt, 0.0]}
        return table, px, step * FRAMES
    if kind == "stop_and_go":
        # moving for 2 frames, stopped for 2, moving again to the last frame
        frames_at = (0, 2, 4, FRAMES)
        travelled = (0.0, 2.0, 2.0, 2.0 + FRAMES - 4)
        keys = [
            {
                "frame": f,
                "position": [position[0] + ux * step * t, position[1] + uy * step * t, position[2]],
            }
            for f, t in zip(frames_at, travelled, strict=True)
        ]
        table["motion"] = {"type": "keyframes", "interpolation": "linear", "keys": keys}
        return table, px, step * travelled[-1]
    # arc: a key at every frame on a circle of radius rho, the heading along the tangent
    rho = draw.uniform(1.0, 5.0)
    sign = draw.choice((-1.0, 1.0))
    cx = position[0] - sign * rho * math.sin(direction)
    cy = position[1] + sign * rho * math.cos(direction)
    keys = []
    for f in range(FRAMES + 1):
        a = direction + sign * f * step / rho
        keys.append(
            {
                "frame": f,
                "position": [
                    cx + sign * rho * math.sin(a),
                    cy - sign * rho * math.cos(a),
                    position[2],
                ],
                "rotation": [0.0, 0.0, math.degrees(heading + a - direction)],
            }
        )
    table["motion"] = {"type": "keyframes", "interpolation": "linear", "keys": keys}
    return table, px, step * FRAMES


def _shape(draw: Draw, size: float, motion: str) -> dict[str, Any]:
    if motion == "rolling":
        return {"type": "sphere", "radius": size / 2, "sections": 48}
    kind = draw.choice(("box", "sphere", "cylinder", "torus"))
    if kind == "box":
        return {"type": "box", "size": [size * draw.uniform(0.4, 1.0) for _ in range(3)]}
    if kind == "sphere":
        return {"type": "sphere", "radius": size / 2, "sections": 48}
    if kind == "cylinder":
        return {
            "type": "cylinder",
            "radius": size * draw.uniform(0.15, 0.5),
            "height": size,
            "sections": 48,
        }
    # the shipped torus (0.66 m across): scaled to the size
    return {"type": "mesh", "path": "library:assets/torus.obj", "scale": size / 0.66}


def _half_height(shape: dict[str, Any]) -> float:
    if shape["type"] == "box":
        return shape["size"][2] / 2
    if shape["type"] == "sphere":
        return shape["radius"]
    if shape["type"] == "cylinder":
        return shape["height"] / 2
    return 0.08 * shape["scale"]  # torus: minor radius 0.08 m


def movers(
    draw: Draw,
    layout: Layout,
    robot_xy: tuple[float, float],
    max_distance: float,
    count: int,
) -> tuple[list[dict[str, Any]], list[str]]:
    """``count`` moving objects (sizes 0.1-2 m) around the robot, and a summary line each.

    Each is placed at a bearing drawn at random and a distance from the axis in
    [R + size + 0.4, max_distance]; its speed is drawn for 0.1-8 px/frame at that distance.
    """
    objs, notes = [], []
    R = layout.rig["R"]
    for i in range(count):
        motion = draw.choice(MOVER_MOTIONS)
        size = draw.log_uniform(0.1, 2.0)
        near = R + size + 0.4
        if near >= max_distance:
            size = max(0.1, (max_distance - R - 0.4) / 2)
            near = R + size + 0.4
        dist = draw.uniform(near, max(near, max_distance))
        bearing = draw.uniform(0.0, 2 * math.pi)
        bx, by = math.cos(bearing), math.sin(bearing)
        shape = _shape(draw, size, motion)
        z = layout.floor + _half_height(shape)
        if motion in ("translating", "spinning") and draw.chance(0.5):
            z += draw.uniform(0.0, 1.5)  # floating
        pos = [robot_xy[0] + bx * dist, robot_xy[1] + by * dist, z]
        px, angle = _px_to_angle(draw, layout)
        speed = angle * dist / FRAME_INTERVAL  # m/s
        motion_tbl: dict[str, Any]
        if motion == "spinning":
            w = math.degrees(angle * dist / max(size / 2, 0.05)) / FRAME_INTERVAL
            motion_tbl = {
                "type": "constant",
                "angular_velocity": [w * c for c in draw.unit_vector()],
            }
        elif motion == "approaching":
            # towards the axis, never closer than `near` by the last frame
            speed = min(speed, (dist - near) / (FRAMES * FRAME_INTERVAL))
            motion_tbl = {"type": "constant", "velocity": [-bx * speed, -by * speed, 0.0]}
        elif motion == "passing":
            sign = draw.choice((-1.0, 1.0))
            motion_tbl = {
                "type": "constant",
                "velocity": [-by * sign * speed, bx * sign * speed, 0.0],
            }
        elif motion == "rolling":
            a = draw.uniform(0.0, 2 * math.pi)
            v = [math.cos(a) * speed, math.sin(a) * speed, 0.0]
            r = shape["radius"]
            # rolling without slipping: w = z x v / r
            w = [math.degrees(-v[1] / r), math.degrees(v[0] / r), 0.0]
            motion_tbl = {"type": "constant", "velocity": v, "angular_velocity": w}
        else:  # translating: any direction, mostly horizontal
            u = draw.unit_vector()
            u[2] *= 0.3
            n = math.sqrt(sum(c * c for c in u))
            motion_tbl = {"type": "constant", "velocity": [speed * c / n for c in u]}
        obj = {
            "name": f"mover{i}_{motion}",
            **shape,
            "position": pos,
            "rotation": [draw.uniform(0.0, 360.0) for _ in range(3)],
        }
        obj["texture"] = texture_table(draw, 0.7 * dist)
        obj["material"] = material_table(draw, 0.3)
        obj["motion"] = motion_tbl
        objs.append(obj)
        notes.append(
            f"{obj['name']}: {shape['type']} {size:.2f} m at {dist:.1f} m, "
            f"{px:.2f} px/frame nominal"
        )
    return objs, notes


def shift_robot(table: dict[str, Any], box: tuple[float, float, float, float], draw: Draw) -> None:
    """Move the robot (drawn at x = y = 0) so its whole path lies in ``box``.

    ``box`` = (x_min, x_max, y_min, y_max) is where the axis may go; the offset is drawn
    uniformly among those that keep the path's extent inside (the centre when none does).
    """
    pts = [table["position"][:2]]
    motion = table.get("motion", {})
    if motion.get("type") == "constant":
        v = motion.get("velocity", [0.0, 0.0, 0.0])
        t = FRAMES * FRAME_INTERVAL
        pts.append([v[0] * t, v[1] * t])
    for key in motion.get("keys", []):
        pts.append(key["position"][:2])
    offset = []
    for axis in (0, 1):
        lo = box[2 * axis] - min(p[axis] for p in pts)
        hi = box[2 * axis + 1] - max(p[axis] for p in pts)
        offset.append(draw.uniform(lo, hi) if hi > lo else (lo + hi) / 2)
    table["position"] = [
        table["position"][0] + offset[0],
        table["position"][1] + offset[1],
        table["position"][2],
    ]
    for key in motion.get("keys", []):
        p = key["position"]
        key["position"] = [p[0] + offset[0], p[1] + offset[1], p[2]]


def clutter(
    draw: Draw,
    count: int,
    box: tuple[float, float, float, float],
    keep_out: Sequence[tuple[float, float, float]],
    floor: float,
    height: float,
    texture_scale: float,
) -> list[dict[str, Any]]:
    """Up to ``count`` static crates, pillars and boulders standing in ``box``, each outside
    every disc (x, y, radius) of ``keep_out`` (20 tries each, else left out)."""
    out = []
    for i in range(count):
        kind = draw.choice(("crate", "pillar", "boulder"))
        size = draw.uniform(0.3, 1.5)
        for _ in range(20):
            x = draw.uniform(box[0] + size, box[1] - size)
            y = draw.uniform(box[2] + size, box[3] - size)
            if all(math.hypot(x - kx, y - ky) > kr + size for kx, ky, kr in keep_out):
                break
        else:
            continue
        if kind == "crate":
            dims = [size, size * draw.uniform(0.5, 1.0), size * draw.uniform(0.5, 1.5)]
            obj = {
                "type": "box",
                "size": dims,
                "position": [x, y, floor + dims[2] / 2],
                "rotation": [0.0, 0.0, draw.uniform(0.0, 90.0)],
            }
        elif kind == "pillar":
            obj = {
                "type": "cylinder",
                "radius": size * 0.25,
                "height": height,
                "sections": 64,
                "position": [x, y, floor + height / 2],
            }
        else:
            obj = {
                "type": "sphere",
                "radius": size / 2,
                "sections": 48,
                "position": [x, y, floor + size / 2 * draw.uniform(0.6, 1.0)],
            }
        out.append(
            {
                "name": f"{kind}{i}",
                **obj,
                "texture": texture_table(draw, texture_scale, allow_solid=True),
                "material": material_table(draw, 0.3),
            }
        )
    return out


def ceiling_lights(
    draw: Draw, size: Sequence[float], factor: float, count: int
) -> list[dict[str, Any]]:
    """``count`` point lights below a ceiling at ``size[2]`` (at 0.8 of the height).

    Point lights, not the library's area lights: no camera ray can hit them, so no
    light's edge (which has no object id for the checks to mask) moves across the image.
    Intensity is the library's area light (radiance 12 over 1.44 m^2: 17.28 W/sr) times
    ``factor``, times (height / 3 m)^2 and the floor area per light over the library's
    15 m^2 (at most 4: more saturated the floor near the lights of a hall), so the floor
    gets about the library's irradiance times ``factor`` (less far from the lights).
    """
    sx, sy, sz = size
    share = min(4.0, max(1.0, sx * sy / count / 15.0))
    out = []
    for _ in range(count):
        out.append(
            {
                "type": "point",
                "position": [
                    draw.uniform(-0.3 * sx, 0.3 * sx),
                    draw.uniform(-0.3 * sy, 0.3 * sy),
                    0.8 * sz,
                ],
                "intensity": AREA_RADIANCE * 1.44 * factor * (sz / 3.0) ** 2 * share,
            }
        )
    return out
