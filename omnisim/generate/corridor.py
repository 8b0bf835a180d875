"""``corridor``: 6-20 m long, 1.8-3.2 m wide, 2.2-3.2 m high; the robot near one end,
heading down it, so the far end wall is in view."""

from __future__ import annotations

from typing import Any

from omnisim.generate import common as c
from omnisim.generate.room import furnished_box

__all__ = ["build"]


def build(draw: c.Draw) -> tuple[dict[str, Any], list[str]]:
    """The scene table of one corridor and notes for the header."""
    size = [draw.uniform(6.0, 20.0), draw.uniform(1.8, 3.2), draw.uniform(2.2, 3.2)]
    sx = size[0]
    heading = draw.uniform(-0.2, 0.2)  # down the corridor (+X), within 11 degrees
    start = (-sx / 2 + 0.8, -sx / 2 + sx / 3)
    return furnished_box(draw, size, max_clutter=2, heading=heading, start=start, lights=2)
