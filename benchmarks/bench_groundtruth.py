"""Seconds per ground_truth_frame (both cameras, 256 px, scenes/default.toml, frames 2..7).

Run from a checkout: ``PYTHONPATH=$PWD nice python3 benchmarks/bench_groundtruth.py LABEL``;
compare two checkouts by running it in each, interleaved
(docs/decisions/ground_truth.md).
"""

import statistics
import sys
import time

from omnisim import groundtruth, scene

OVERRIDES = {"render.width": 256, "render.height": 256, "frames": 8}


def main() -> None:
    sc = scene.load_scene("scenes/default.toml", overrides=OVERRIDES)
    for f in (0, 1):  # compile the kernels
        groundtruth.ground_truth_frame(sc, f)
    times = []
    for f in range(2, 8):
        t = time.perf_counter()
        groundtruth.ground_truth_frame(sc, f)
        times.append(time.perf_counter() - t)
    label = sys.argv[1] if len(sys.argv) > 1 else ""
    print(label, f"median {statistics.median(times):.3f} s", [f"{t:.3f}" for t in times])


if __name__ == "__main__":
    main()
