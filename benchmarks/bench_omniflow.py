"""Speed of the omni flow stereo-flow step against OpenCV's dense flow, same frames.

Times, in one run on the same image pairs of both cameras:

- omniflow.pipeline.estimate end to end (DCT fits, gradients, matching, flow),
  with its per-stage split from ``OmniFlowResult.timings``;
- OpenCV DIS optical flow (presets ultrafast and medium) and Farneback, each on
  the cam1 pair and the cam2 pair (the time reported is both pairs together,
  the same work omni flow does in one call).

Each figure is the median of ``--repeats`` runs after ``--warmup`` runs. The
target (the issue's): the omni flow step in no more time than DIS medium takes
for the two camera pairs together, i.e. ratio omniflow / DIS-medium <= 1.

Frames: closed-form scenes from :mod:`omniflow.synthetic` (a textured round
room, the robot turning and driving slowly), or rendered frames with
``--dataset DIR --frame K``. Run::

    python benchmarks/bench_omniflow.py                  # 512 x 512 closed-form frames
    python benchmarks/bench_omniflow.py --size 256 --repeats 10 --json bench.json
    python benchmarks/bench_omniflow.py --dataset renders/room --frame 0
    python benchmarks/bench_omniflow.py --set solver=pooled --set gradients=first
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from omniflow.imageio import atomic_write_text, to_uint8
from omniflow.jsonio import json_text
from omniflow.rig import Rig


def synthetic_frames(size: int, count: int) -> tuple[list, list, Rig, str]:
    """Closed-form frames of both cameras: textured room, robot turning and driving."""
    from omniflow.synthetic import Motion, SyntheticScene

    rig = Rig.symmetric(d=0.10, R=0.05, s=0.30, size=size)
    scene = SyntheticScene.room(
        rig, wall_radius=3.0, ceiling=2.5, texture_seed=3,
        robot=Motion(velocity=(0.004, 0.002), yaw_rate=0.002),
    )  # fmt: skip
    f1 = [scene.render("cam1", t).astype(np.float32) for t in range(count)]
    f2 = [scene.render("cam2", t).astype(np.float32) for t in range(count)]
    return f1, f2, rig, f"omniflow.synthetic room {size}x{size}, robot 4.5 mm + 2 mrad per frame"


def dataset_frames(directory: str, k: int, count: int) -> tuple[list, list, Rig, str]:
    """Rendered frames k .. k + count - 1 of an omnisim dataset."""
    from omniflow.dataset import open_dataset

    ds = open_dataset(directory)
    f1 = [ds.read_grey(j, "cam1") for j in range(k, k + count)]
    f2 = [ds.read_grey(j, "cam2") for j in range(k, k + count)]
    u = ds.rig.cam1
    return f1, f2, ds.rig, f"dataset {directory} frames {k}..{k + count - 1}, {u.width}x{u.height}"


def time_it(fn: Callable[[], object], repeats: int, warmup: int) -> tuple[list[float], object]:
    """Wall-clock seconds of ``repeats`` calls after ``warmup`` calls; and the last result."""
    out = None
    for _ in range(warmup):
        out = fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return times, out


def opencv_methods() -> dict[str, Callable]:
    """name -> flow(prev_u8, next_u8) for the OpenCV baselines."""
    import cv2

    dis_fast = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST)
    dis_medium = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)

    def farneback(a, b):
        return cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 3, 15, 3, 5, 1.2, 0)

    return {
        "DIS ultrafast": lambda a, b: dis_fast.calc(a, b, None),
        "DIS medium": lambda a, b: dis_medium.calc(a, b, None),
        "Farneback": farneback,
    }


def parse_set(items: list[str], cls) -> dict:
    """``--set name=value`` pairs for OmniFlowConfig, converted by each field's default type."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    out = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or name not in fields:
            raise SystemExit(
                f"bench: --set {item!r}: expected NAME=VALUE, NAME one of {list(fields)}"
            )
        default = fields[name].default
        if isinstance(default, bool):
            value = text.lower() in ("1", "true", "yes", "on")
        elif isinstance(default, int | float) and default is not None:
            value = type(default)(text)
        elif text.lower() == "none":
            value = None
        else:
            try:
                value = json.loads(text)
            except json.JSONDecodeError:
                value = text
        out[name] = value
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="bench_omniflow",
        description="Time omni flow against OpenCV DIS and Farneback on the same frames.",
    )
    parser.add_argument(
        "--size", type=int, default=512, help="closed-form image size (default 512)"
    )
    parser.add_argument("--dataset", metavar="DIR", help="use rendered frames from this dataset")
    parser.add_argument("--frame", type=int, default=0, help="--dataset: first frame (default 0)")
    parser.add_argument("--repeats", type=int, default=20, help="timed runs (default 20)")
    parser.add_argument("--warmup", type=int, default=3, help="untimed runs first (default 3)")
    parser.add_argument(
        "--set", action="append", default=[], metavar="NAME=VALUE",
        help="OmniFlowConfig field to change (repeatable), e.g. --set solver=pooled",
    )  # fmt: skip
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON here")
    args = parser.parse_args(argv)

    from omniflow.pipeline import OmniFlowConfig, estimate

    config = OmniFlowConfig(**parse_set(args.set, OmniFlowConfig))
    count = 3 if getattr(config, "temporal", "") == "dct3d" else 2
    if args.dataset:
        f1, f2, rig, source = dataset_frames(args.dataset, args.frame, count)
    else:
        f1, f2, rig, source = synthetic_frames(args.size, count)

    rows: list[dict] = []

    # omni flow: one call does both cameras (4 fits, matching, flow).
    stage_runs: list[dict] = []

    def omni():
        res = estimate(f1, f2, rig, config, t=0)
        stage_runs.append(dict(getattr(res, "timings", {})))
        return res

    times, result = time_it(omni, args.repeats, args.warmup)
    stage_runs = stage_runs[args.warmup :]
    stages = {}
    for key in stage_runs[0] if stage_runs else {}:
        vals = [s[key] for s in stage_runs if isinstance(s.get(key), int | float)]
        if vals:
            stages[key] = statistics.median(vals)
    npts = len(next(iter(result.columns.values()))) if result.columns else 0
    rows.append({"method": "omniflow", "median_s": statistics.median(times),
                 "min_s": min(times), "points": npts, "stages_s": stages})  # fmt: skip

    # OpenCV baselines on the same frames, 8-bit, both camera pairs per call.
    u8 = {cam: [to_uint8(f) for f in frames[:2]] for cam, frames in (("cam1", f1), ("cam2", f2))}
    for name, flow in opencv_methods().items():

        def both(flow=flow):
            return [flow(u8[c][0], u8[c][1]) for c in ("cam1", "cam2")]

        times, _ = time_it(both, args.repeats, args.warmup)
        rows.append({"method": name, "median_s": statistics.median(times), "min_s": min(times)})

    dis = next(r for r in rows if r["method"] == "DIS medium")["median_s"]
    for r in rows:
        r["ratio_to_dis_medium"] = r["median_s"] / dis

    import cv2
    import scipy

    env = {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "opencv": cv2.__version__,
        "opencv_threads": cv2.getNumThreads(),
        "cpus": os.cpu_count(),
        "machine": platform.machine(),
    }
    report = {
        "frames": source,
        "image_size": list(f1[0].shape),
        "config": {k: v for k, v in dataclasses.asdict(config).items()},
        "repeats": args.repeats,
        "warmup": args.warmup,
        "results": rows,
        "environment": env,
    }

    print(f"frames: {source}")
    print(f"median of {args.repeats} runs after {args.warmup} warm-up; both camera pairs per run")
    print(f"{'method':<16}{'median ms':>11}{'min ms':>9}{'vs DIS medium':>15}")
    for r in rows:
        print(f"{r['method']:<16}{1e3 * r['median_s']:>11.1f}{1e3 * r['min_s']:>9.1f}"
              f"{r['ratio_to_dis_medium']:>14.2f}x")  # fmt: skip
    omni_row = rows[0]
    parts = {k: v for k, v in omni_row["stages_s"].items() if k != "total"}
    if parts:
        total = sum(parts.values())
        print(f"omniflow stages ({omni_row['points']} points; median ms, share of their sum):")
        for k, v in sorted(parts.items(), key=lambda kv: -kv[1]):
            print(f"  {k:<22}{1e3 * v:>8.1f}  {100 * v / total:>5.1f} %")
        omni_row["dominant_stage"] = max(parts, key=parts.get)
    verdict = "meets" if omni_row["ratio_to_dis_medium"] <= 1.0 else "misses"
    print(f"target (omniflow <= DIS medium on both pairs): {verdict} "
          f"({omni_row['ratio_to_dis_medium']:.2f}x)")  # fmt: skip
    print(f"environment: {env}")
    if args.json:
        atomic_write_text(Path(args.json), json_text(report))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
