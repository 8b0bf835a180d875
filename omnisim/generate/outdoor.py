"""``outdoor``: open ground under a sky (environment light) and a sun (directional light);
far surfaces 8-30 m away (a ring wall or a ring of buildings), near boulders and posts."""

from __future__ import annotations

import math
from typing import Any

from omnisim.generate import common as c

__all__ = ["build"]


def build(draw: c.Draw) -> tuple[dict[str, Any], list[str]]:
    """The scene table of one outdoor scene and notes for the header."""
    far = draw.uniform(8.0, 30.0)
    width = draw.choice(c.IMAGE_SIZES)
    rig = c.draw_rig(draw, max_common_range=far / 2)
    factor = c.light_factor(draw)
    layout = c.Layout(width=width, rig=rig, distance=far / 2)
    z = draw.uniform(rig["d"] + 0.2, 1.2)
    kind = draw.choice(c.ROBOT_MOTIONS)
    robot, px, travel = c.robot_table(
        draw, layout, [0.0, 0.0, z], draw.uniform(-3.14159, 3.14159), kind
    )
    c.shift_robot(robot, (-1.0, 1.0, -1.0, 1.0), draw)
    rx, ry = robot["position"][:2]
    ground = {
        "name": "ground",
        "type": "plane",
        "size": [2 * far + 20, 2 * far + 20],
        "texture": c.texture_table(draw, 1.0),
        "material": {"type": "diffuse"},
    }
    objects = [ground, *_far_ring(draw, far)]
    near = 0.6 * far
    keep = [(rx, ry, rig["R"] + travel + 0.4)]
    box = (rx - near, rx + near, ry - near, ry + near)
    height = draw.uniform(1.5, 4.0)
    objects += c.clutter(draw, draw.integer(1, 6), box, keep, 0.0, height, 0.3 * far)
    moving, mover_notes = c.movers(draw, layout, (rx, ry), near, draw.integer(0, 6))
    objects += moving
    elevation = math.radians(draw.uniform(15.0, 75.0))
    azimuth = draw.uniform(0.0, 2 * math.pi)
    sun = [
        -math.cos(elevation) * math.cos(azimuth),
        -math.cos(elevation) * math.sin(azimuth),
        -math.sin(elevation),
    ]
    sky_k = factor * draw.uniform(0.7, 1.3)
    sun_k = factor * draw.uniform(0.5, 1.5)
    data = {
        "render": c.render_table(draw, width),
        "rig": rig,
        "camera": c.camera_table(draw, factor),
        "robot": robot,
        "objects": objects,
        "lights": [
            {"type": "environment", "radiance": [v * sky_k for v in c.SKY_RADIANCE]},
            {
                "type": "directional",
                "direction": sun,
                "irradiance": [v * sun_k for v in c.SUN_IRRADIANCE],
            },
        ],
    }
    notes = [
        f"outdoor, far surfaces at {far:.1f} m; rig d = {rig['d']}, R = {rig['R']}, "
        f"s = {rig['s']} m (min common range {layout.min_common_range:.2f} m); {width} px",
        f"light x{factor:.3f} of the library's (sun {math.degrees(elevation):.0f} deg up); "
        f"robot {kind}, {px:.2f} px/frame nominal",
        *mover_notes,
    ]
    return data, notes


def _far_ring(draw: c.Draw, far: float) -> list[dict[str, Any]]:
    """An open cylinder wall of radius ``far`` (2-8 m high), or 6-12 buildings on that ring."""
    scale = far
    height = draw.uniform(2.0, 8.0)
    if draw.chance(0.5):
        return [
            {
                "name": "ring_wall",
                "type": "cylinder",
                "radius": far,
                "height": height,
                "caps": False,
                "sections": 256,
                "position": [0.0, 0.0, height / 2],
                "texture": c.texture_table(draw, scale),
            }
        ]
    out = []
    n = draw.integer(6, 12)
    for i in range(n):
        a = 2 * math.pi * (i + draw.uniform(-0.2, 0.2)) / n
        w = draw.uniform(3.0, 2 * math.pi * far / n)
        h = draw.uniform(2.0, 10.0)
        out.append(
            {
                "name": f"building{i}",
                "type": "box",
                "size": [w, draw.uniform(3.0, 8.0), h],
                "position": [far * math.cos(a), far * math.sin(a), h / 2],
                "rotation": [0.0, 0.0, math.degrees(a) + 90.0],
                "texture": c.texture_table(draw, scale),
                "material": c.material_table(draw, 0.3),
            }
        )
    return out
