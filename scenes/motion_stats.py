"""Image motion per frame in the library scenes (the figures in README.md).

    python scenes/motion_stats.py scenes/*.toml

For each scene at its own resolution, computes the exact ground truth of
frame 0 with ``omnisim.groundtruth.ground_truth`` (ray tracing only, no
rendering; needs Mitsuba) and prints, per camera, the median and 95th
percentile of |gt.flow| in pixels over the pixels whose flow is valid, and
the median per object (by gt.object).
"""

from __future__ import annotations

import sys

import numpy as np

from omnisim.groundtruth import ground_truth
from omnisim.scene import load_scene


def motion_stats(path: str, frame: int = 0) -> dict[str, dict[str, float]]:
    scene = load_scene(path)
    out = {}
    for cam in ("cam1", "cam2"):
        gt = ground_truth(scene, frame, cam)
        valid = gt["gt.flow.valid"] > 0
        mag = np.hypot(gt["gt.flow.dx"], gt["gt.flow.dy"])
        row = {"median": float(np.median(mag[valid])), "p95": float(np.percentile(mag[valid], 95))}
        for obj in scene.objects:
            sel = valid & (gt["gt.object"] == obj.id)
            if sel.sum() >= 50:
                row[obj.name] = float(np.median(mag[sel]))
        out[cam] = row
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
