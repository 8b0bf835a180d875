"""``hall``: walls 8-30 m from the centre (16-60 m across), 3-12 m high with the height
drawn so the ceiling enters the common view inside the hall, and a grid of columns."""

from __future__ import annotations

import math
from typing import Any

from omnisim.generate import common as c
from omnisim.generate.room import furnished_box

__all__ = ["build"]


def build(draw: c.Draw) -> tuple[dict[str, Any], list[str]]:
    """The scene table of one hall and notes for the header."""
    sx, sy = 2 * draw.uniform(8.0, 30.0), 2 * draw.uniform(8.0, 30.0)
    # provisional height; furnished_box draws the rig, so the ceiling is checked after
    size = [sx, sy, 12.0]
    data, notes = furnished_box(draw, size, max_clutter=3, heading=None, lights=2)
    rig, z = data["rig"], data["robot"]["position"][2]
    # cam2 sees h <= (d + r) R / (d + R) above its tip: the ceiling enters the common view
    # at r = (H - z) (d + R) / R - d; keep that within 0.8 of the far walls' distance
    far = 0.8 * math.hypot(sx, sy) / 2
    top = z + (far + rig["d"]) * rig["R"] / (rig["d"] + rig["R"])
    height = draw.uniform(3.0, max(3.0, min(12.0, top)))
    data["objects"][0]["size"] = [sx, sy, height]
    for obj in data["objects"][1:]:
        if obj["type"] == "cylinder" and obj["name"].startswith("pillar"):
            obj["height"] = height
            obj["position"][2] = height / 2
    for light in data["lights"]:
        light["position"][2] = 0.8 * height
        light["intensity"] *= (height / 12.0) ** 2  # drawn for 12 m
    lights = [li["position"] for li in data["lights"]]
    data["objects"] += _columns(draw, sx, sy, height, data["robot"]["position"], rig["R"], lights)
    notes[0] = notes[0].replace("x 12.0 m", f"x {height:.1f} m", 1)
    return data, notes


def _columns(draw: c.Draw, sx: float, sy: float, height: float, robot, R: float, lights) -> list:
    """A grid of columns every 4-8 m, leaving out those within 1.5 m of the robot and
    those within 0.3 m of a light (which they would swallow)."""
    pitch = draw.uniform(4.0, 8.0)
    radius = draw.uniform(0.2, 0.6)
    tex = c.texture_table(draw, min(sx, sy) / 4)  # half way to the nearer walls
    out = []
    nx, ny = int(sx / pitch) - 1, int(sy / pitch) - 1
    for i in range(nx):
        for j in range(ny):
            x = -sx / 2 + pitch * (i + 1)
            y = -sy / 2 + pitch * (j + 1)
            if math.hypot(x - robot[0], y - robot[1]) < 1.5 + radius + R or len(out) >= 12:
                continue
            if any(math.hypot(x - p[0], y - p[1]) < radius + 0.3 for p in lights):
                continue
            out.append(
                {
                    "name": f"column{i}_{j}",
                    "type": "cylinder",
                    "radius": radius,
                    "height": height,
                    "sections": 48,
                    "position": [x, y, height / 2],
                    "texture": tex,
                }
            )
    return out
