"""Approximate image motion per frame for library scenes (the figures in README.md).

    python scenes/motion_stats.py scenes/*.toml

Samples 20 000 points on every object's surface, keeps those a camera sees
at frames 0 and 1 according to the mirror's field of view (occlusion is NOT
considered), projects them with eq. (1) at both frames and prints the median
and 95th percentile of the displacement in pixels at the scene's resolution.
The exact per-pixel flow is the renderer's ground truth (gt.flow.*).
"""

from __future__ import annotations

import sys

import numpy as np
import trimesh

from omnisim.scene import load_scene


def motion_stats(path: str, frame: int = 0) -> dict[str, dict[str, float]]:
    scene = load_scene(path)
    out = {}
    for cam in (scene.rig.cam1, scene.rig.cam2):
        per_object = {}
        for obj in scene.objects:
            pts = trimesh.sample.sample_surface(obj.mesh, 20000, seed=1)[0]
            pts = np.c_[pts, np.ones(len(pts))]
            cyl = []
            for k in (frame, frame + 1):
                q = pts @ np.linalg.solve(scene.robot.pose(k), obj.pose(k)).T  # rig frame
                cyl.append((np.hypot(q[:, 0], q[:, 1]), np.arctan2(q[:, 1], q[:, 0]), q[:, 2]))
            (r0, t0, h0), (r1, t1, h1) = cyl
            seen = cam.visible(r0, h0) & cam.visible(r1, h1)
            if seen.any():
                x0, y0 = cam.project(r0[seen], t0[seen], h0[seen])
                x1, y1 = cam.project(r1[seen], t1[seen], h1[seen])
                per_object[obj.name] = np.hypot(x1 - x0, y1 - y0)
        flow = np.concatenate(list(per_object.values()))
        out[cam.name] = {"median": float(np.median(flow)), "p95": float(np.percentile(flow, 95))}
        out[cam.name] |= {name: float(np.median(v)) for name, v in per_object.items()}
    return out


def main() -> None:
    for path in sys.argv[1:]:
        print(path)
        for cam, row in motion_stats(path).items():
            objs = ", ".join(f"{k} {v:.2f}" for k, v in row.items() if k not in ("median", "p95"))
            head = f"  {cam}: median {row['median']:.2f} px, p95 {row['p95']:.2f} px"
            print(f"{head}; per object: {objs}")


if __name__ == "__main__":
    main()
