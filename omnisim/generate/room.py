"""``room``: a box room 3-15 m across and 2.2-4 m high, clutter, movers, ceiling lights."""

from __future__ import annotations

from typing import Any

from omnisim.generate import common as c

__all__ = ["build"]


def build(draw: c.Draw) -> tuple[dict[str, Any], list[str]]:
    """The scene table of one room (before the loader's check) and notes for the header."""
    size = [draw.uniform(3.0, 15.0), draw.uniform(3.0, 15.0), draw.uniform(2.2, 4.0)]
    return furnished_box(draw, size, max_clutter=4, heading=None)


def furnished_box(
    draw: c.Draw,
    size: list[float],
    *,
    max_clutter: int,
    heading: float | None,
    start: tuple[float, float] | None = None,
    lights: int | None = None,
) -> tuple[dict[str, Any], list[str]]:
    """A room of ``size`` with the rig, motion, clutter, movers and lights drawn in it.

    Shared by ``room``, ``corridor`` and ``hall``. ``heading`` fixes the robot's heading
    (radians, else drawn); ``start`` = (x_min, x_max) limits where its path may lie along X.
    """
    sx, sy, sz = size
    width = draw.choice(c.IMAGE_SIZES)
    half = min(sx, sy) / 2
    rig = c.draw_rig(draw, max_common_range=half - 0.6)
    factor = c.light_factor(draw)
    layout = c.Layout(width=width, rig=rig, distance=half)  # the nearer walls
    mcr = layout.min_common_range
    z_hi = min(1.2, sz - rig["s"] - rig["R"] - 0.15)
    z = draw.uniform(rig["d"] + 0.2, max(rig["d"] + 0.2, z_hi))
    kind = draw.choice(c.ROBOT_MOTIONS)
    if heading is None:
        heading = draw.uniform(-3.14159, 3.14159)
    robot, px, travel = c.robot_table(draw, layout, [0.0, 0.0, z], heading, kind)
    inset = mcr + 0.3
    x_lo, x_hi = (-sx / 2 + inset, sx / 2 - inset) if start is None else start
    c.shift_robot(robot, (x_lo, x_hi, -sy / 2 + inset, sy / 2 - inset), draw)
    rx, ry = robot["position"][:2]
    room_box = (-sx / 2, sx / 2, -sy / 2, sy / 2)
    scale = half  # the nearer walls' distance
    room: dict[str, Any] = {
        "name": "room",
        "type": "room",
        "size": size,
        "texture": c.texture_table(draw, scale),
    }
    for part in ("floor_texture", "ceiling_texture", "wall_texture"):
        if draw.chance(0.6):
            room[part] = c.texture_table(draw, scale)
    room["material"] = c.material_table(draw, 0.25)
    n_lights = lights if lights is not None else max(1, min(2, round(sx * sy / 15.0)))
    light_tables = c.ceiling_lights(draw, size, factor, n_lights)
    # clutter stays off the robot's path and off the lights (a pillar could swallow one)
    keep = [(rx, ry, rig["R"] + travel + 0.4)]
    keep += [(li["position"][0], li["position"][1], 0.3) for li in light_tables]
    objects = [
        room,
        *c.clutter(draw, draw.integer(0, max_clutter), room_box, keep, 0.0, sz, 0.5 * scale),
    ]
    reach = max(0.5, min(rx - room_box[0], room_box[1] - rx, ry - room_box[2], room_box[3] - ry))
    moving, mover_notes = c.movers(draw, layout, (rx, ry), reach - 0.2, draw.integer(0, 6))
    objects += moving
    data = {
        "render": c.render_table(draw, width),
        "rig": rig,
        "camera": c.camera_table(draw, factor),
        "robot": robot,
        "objects": objects,
        "lights": light_tables,
    }
    notes = [
        f"room {sx:.1f} x {sy:.1f} x {sz:.1f} m; rig d = {rig['d']}, R = {rig['R']}, "
        f"s = {rig['s']} m (min common range {mcr:.2f} m); {width} px",
        f"light x{factor:.3f} of the library's; robot {kind}, {px:.2f} px/frame nominal",
        *mover_notes,
    ]
    return data, notes
