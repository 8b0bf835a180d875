"""Count ground-truth holes per scene (docs/measurements.md, issue 11 item 9).

A hole is a pixel inside the rim (centre at least 1 px inside r_m) whose rendered
radiance is > 0 but whose ``gt.valid`` is 0. Frame 0, 1 spp.

Usage: ``PYTHONPATH=. python3 benchmarks/gt_holes.py [SIZE] [SCENE ...]``
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from omnisim.render import render_frame
from omnisim.scene import load_scene

SCENES = Path(__file__).resolve().parents[1] / "scenes"


def holes(name: str, size: int) -> dict[str, tuple[int, list[tuple[int, float]]]]:
    """Per camera: the hole count and the first holes' (theta in degrees, h_i in px)."""
    ov = {"render.width": size, "render.height": size, "render.spp": 1, "frames": 1}
    sc = load_scene(SCENES / f"{name}.toml", ov)
    out = {}
    for cam, ch in render_frame(sc, 0).items():
        u = getattr(sc.rig, cam)
        yy, xx = np.mgrid[0:size, 0:size] + 0.5
        dx, dy = xx - u.x_c, yy - u.y_c
        inside = np.hypot(dx, dy) <= u.r_m - 1
        hole = inside & (ch["gt.valid"] == 0) & ((ch["R"] + ch["G"] + ch["B"]) > 0)
        where = np.column_stack(
            [np.degrees(np.arctan2(dy[hole], dx[hole])), np.hypot(dx[hole], dy[hole])]
        )
        out[cam] = (int(hole.sum()), [(round(t), round(h, 1)) for t, h in where[:8]])
    return out


def main() -> None:
    size = int(sys.argv[1]) if len(sys.argv) > 1 else 128
    names = sys.argv[2:] or sorted(p.stem for p in SCENES.glob("*.toml"))
    for name in names:
        for cam, (n, first) in holes(name, size).items():
            print(f"{name:20s} {cam}: {n:3d} holes {first}", flush=True)


if __name__ == "__main__":
    main()
