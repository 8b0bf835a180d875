"""Speed and memory of the omni flow stereo-flow step against OpenCV's dense flow, same frames.

Times, interleaved in one run on the same image pairs of both cameras (wall
clock and CPU time, median of ``--repeats`` rounds after ``--warmup``):

- ``omniflow pair``: omniflow.pipeline.estimate end to end (DCT fits,
  gradients, matching, flow), with its per-stage split from
  ``OmniFlowResult.timings``;
- ``omniflow stream``: omniflow.stream.OmniFlowStream.push, the cost of one
  new stereo frame of a sequence (each frame fitted once);
- OpenCV DIS optical flow (presets ultrafast and medium) and Farneback, each
  on the cam1 pair and the cam2 pair (both pairs per call: the work omni
  flow does per stereo frame); DIS medium and the omniflow pair also on one
  thread (OpenCV uses every core by default, omni flow two threads:
  :mod:`omniflow.parallel`), the like-for-like figure, timed interleaved
  after the main block, so the other rows run with the default thread
  counts. The use of the second core varies from run to run on a shared
  machine (DIS: CPU / wall 1.0-2.0 measured): compare CPU times, or the
  one-thread rows.

Omni flow answers at its matched points only and DIS at every pixel, so the
points per frame and the milliseconds per 1000 points are printed beside the
time. Peak resident memory of a pair and of a stream (``--memory-sizes``,
closed-form frames, each size in a fresh process) closes the report. The
targets (issue 10): omniflow / DIS-medium <= 1 for the pair; 10 ms per
stereo frame streamed at 512 x 512.

Frames: closed-form scenes from :mod:`omnisim.synthetic` (a textured round
room, the robot turning and driving slowly), or rendered frames with
``--dataset DIR --frame K``. Run::

    python benchmarks/bench_omniflow.py                  # 512 x 512 closed-form frames
    python benchmarks/bench_omniflow.py --size 256 --repeats 10 --json bench.json
    python benchmarks/bench_omniflow.py --dataset runs/default/dataset --memory-sizes
    python benchmarks/bench_omniflow.py --set solver=pooled --set fit.gradients=first
    python benchmarks/bench_omniflow.py --dataset runs/default/dataset --profile 20
    python benchmarks/bench_omniflow.py --dataset runs/default/dataset --versus monocular_gap=24
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from omniflow.geometry.rig import Rig
from omniflow.io.imageio import atomic_write_text, to_uint8
from omniflow.io.jsonio import json_text


def synthetic_frames(size: int, count: int) -> tuple[list, list, Rig, str]:
    """Closed-form frames of both cameras: textured room, robot turning and driving."""
    from omnisim.synthetic import Motion, SyntheticScene

    rig = Rig.symmetric(d=0.10, R=0.05, s=0.30, size=size)
    scene = SyntheticScene.room(
        rig, wall_radius=3.0, ceiling=2.5, texture_seed=3,
        robot=Motion(velocity=(0.004, 0.002), yaw_rate=0.002),
    )  # fmt: skip
    f1 = [scene.render("cam1", t).astype(np.float32) for t in range(count)]
    f2 = [scene.render("cam2", t).astype(np.float32) for t in range(count)]
    return f1, f2, rig, f"omnisim.synthetic room {size}x{size}, robot 4.5 mm + 2 mrad per frame"


def dataset_frames(directory: str, k: int, count: int) -> tuple[list, list, Rig, str]:
    """Rendered frames k .. k + count - 1 of an omnisim dataset."""
    from omniflow.io.dataset import open_dataset

    ds = open_dataset(directory)
    f1 = [ds.read_grey(j, "cam1") for j in range(k, k + count)]
    f2 = [ds.read_grey(j, "cam2") for j in range(k, k + count)]
    u = ds.rig.cam1
    return f1, f2, ds.rig, f"dataset {directory} frames {k}..{k + count - 1}, {u.width}x{u.height}"


def time_interleaved(
    fns: dict[str, Callable[[], object]], repeats: int, warmup: int
) -> tuple[dict[str, list[float]], dict[str, list[float]], dict[str, object]]:
    """Wall and CPU seconds of each function, called in turn ``repeats`` times.

    The functions alternate within every repeat, so a change of load on a
    shared machine hits all of them alike; ``warmup`` rounds first, untimed.
    Returns (wall, cpu, last result) per name.
    """
    wall: dict[str, list[float]] = {k: [] for k in fns}
    cpu: dict[str, list[float]] = {k: [] for k in fns}
    out: dict[str, object] = {}
    for i in range(warmup + repeats):
        for name, fn in fns.items():
            c0, t0 = time.process_time(), time.perf_counter()
            out[name] = fn()
            t1, c1 = time.perf_counter(), time.process_time()
            if i >= warmup:
                wall[name].append(t1 - t0)
                cpu[name].append(c1 - c0)
    return wall, cpu, out


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


def parse_set(items: list[str], flag: str = "--set"):
    """The OmniFlowConfig of ``NAME=VALUE`` items (a group's knobs by dotted name,
    ``pooling.pool_k=64``; ``dense`` or ``paper`` starts from that preset), checked as
    omniflow's own ``--set`` is (omniflow.cli.common.config_from_settings); ``flag`` is the
    option named in the error."""
    from omniflow.cli.common import CLIError, config_from_settings

    try:
        return config_from_settings(list(items))
    except CLIError as exc:
        raise SystemExit(f"bench: {flag} {exc}") from None


def _rss_mb(field: str) -> float | None:
    """VmRSS (now) or VmHWM (peak) of this process, MiB; None where /proc is missing."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) / 1024.0
    except OSError:  # not Linux: ru_maxrss below
        pass
    if field == "VmHWM":
        import resource

        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0
    return None


def _reset_peak() -> bool:
    """Reset VmHWM to the current RSS (Linux >= 4.0); False where that is not possible."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:  # no /proc or not allowed: the peak then includes what came before
        return False


def memory_probe(folder: str, config_items: list[str]) -> dict:
    """Peak resident memory of one pair and of a streamed sequence on frames saved in ``folder``.

    Runs in its own process (``--memory-probe``), so the peak is the pipeline's
    alone: the frames are loaded from .npz, one estimate() warms up (imports,
    caches, the compiled kernels), the baseline is read and the peak reset, then
    estimate() runs twice; the peak is reset again and a stream takes the frames
    (forwards and backwards) three times over.
    """
    from omniflow.pipeline import estimate
    from omniflow.stream import OmniFlowStream

    data = np.load(Path(folder) / "frames.npz")
    f1, f2 = list(data["f1"]), list(data["f2"])
    rig = Rig.symmetric(d=0.10, R=0.05, s=0.30, size=f1[0].shape[0])
    config = parse_set(config_items)
    estimate(f1, f2, rig, config, t=0)  # imports, caches, compiled kernels: not the pipeline's
    base = _rss_mb("VmRSS")
    reset = _reset_peak()
    for _ in range(2):
        estimate(f1, f2, rig, config, t=0)
    pair_peak = _rss_mb("VmHWM")
    reset = _reset_peak() and reset
    stream = OmniFlowStream(rig, config)
    order = list(range(len(f1))) + list(range(len(f1) - 2, 0, -1))
    for i in range(3 * len(order)):
        stream.push(f1[order[i % len(order)]], f2[order[i % len(order)]])
    stream_peak = _rss_mb("VmHWM")
    return {"size": int(f1[0].shape[0]), "baseline_mb": base, "pair_peak_mb": pair_peak,
            "stream_peak_mb": stream_peak, "peaks_separate": reset}  # fmt: skip


def measure_memory(sizes: list[int], config_items: list[str]) -> list[dict]:
    """:func:`memory_probe` at each image size, closed-form frames, each in a fresh process."""
    import subprocess
    import tempfile

    out = []
    for size in sizes:
        f1, f2, _, _ = synthetic_frames(size, 3)
        with tempfile.TemporaryDirectory() as tmp:
            np.savez(Path(tmp) / "frames.npz", f1=np.stack(f1), f2=np.stack(f2))
            cmd = [sys.executable, __file__, "--memory-probe", tmp]
            for item in config_items:
                cmd += ["--set", item]
            proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            raise SystemExit(f"bench: memory probe at {size} px failed: {proc.stderr.strip()}")
        out.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    return out


def profile_pairs(run: Callable[[], object], n: int, top: int = 25) -> None:
    """cProfile of ``n`` calls (process time, so other load on the machine counts less)."""
    import cProfile
    import pstats

    profiler = cProfile.Profile(time.process_time)
    profiler.enable()
    for _ in range(n):
        run()
    profiler.disable()
    print(f"cProfile of {n} omniflow pair runs (CPU seconds, sorted by own time):")
    pstats.Stats(profiler, stream=sys.stdout).sort_stats("tottime").print_stats(top)


def time_paced_stream(f1, f2, rig, config, repeats: int, warmup: int, interval: float) -> dict:
    """Push latency of a stream fed one frame every ``interval`` seconds, plain and background.

    A robot's camera delivers frames at its own rate; with ``background=True``
    the matching of each frame runs while the robot waits for the next one, so
    a push costs only the fit, the sampling and the solve. Not interleaved with
    the other methods (the background thread would run during their timing).
    Returns, per mode, the median push latency (ms) and the CPU time per frame
    (ms, every thread).
    """
    from omniflow.stream import OmniFlowStream

    order = list(range(len(f1))) + list(range(len(f1) - 2, 0, -1))
    out = {"interval_ms": 1e3 * interval, "frames": repeats}
    for mode in ("plain", "background"):
        latency = []
        with OmniFlowStream(rig, config, background=mode == "background") as stream:
            c0 = None
            for i in range(warmup + 1 + repeats):
                if i == warmup + 1:
                    c0 = time.process_time()
                k = order[i % len(order)]
                s0 = time.perf_counter()
                stream.push(f1[k], f2[k])
                spent = time.perf_counter() - s0
                if c0 is not None:
                    latency.append(spent)
                time.sleep(max(0.0, interval - spent))
            stream.close()
            cpu = time.process_time() - c0
        out[mode] = {"push_median_ms": 1e3 * statistics.median(latency),
                     "cpu_ms_per_frame": 1e3 * cpu / repeats}  # fmt: skip
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="bench_omniflow",
        description="Time omni flow (pair and streaming) against OpenCV DIS and Farneback.",
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
    parser.add_argument(
        "--versus", action="append", default=[], metavar="NAME=VALUE",
        help="also time the pair with these fields changed (repeatable), interleaved with "
        "the others: a candidate default against the current one in the same run",
    )  # fmt: skip
    parser.add_argument(
        "--memory-sizes", type=int, nargs="*", default=[512, 1024], metavar="PX",
        help="closed-form image sizes for the peak-memory probe (default 512 1024; none: skip)",
    )  # fmt: skip
    parser.add_argument("--memory-probe", metavar="DIR", help=argparse.SUPPRESS)
    parser.add_argument(
        "--profile", type=int, default=0, metavar="N",
        help="also profile N pair runs with cProfile (CPU time) and print the top functions",
    )  # fmt: skip
    parser.add_argument(
        "--interval", type=float, default=100.0, metavar="MS",
        help="frame interval of the paced stream (plain vs background), ms; 0: skip (100)",
    )  # fmt: skip
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON here")
    args = parser.parse_args(argv)

    if args.memory_probe:  # the child process of measure_memory
        print(json.dumps(memory_probe(args.memory_probe, args.set)))
        return 0

    from omniflow.pipeline import estimate
    from omniflow.stream import OmniFlowStream

    config = parse_set(args.set)
    pair_frames = config.fit.temporal_frames if config.fit.temporal == "dct3d" else 2
    count = max(pair_frames, 4)
    if args.dataset:
        from omniflow.io.dataset import open_dataset

        available = open_dataset(args.dataset).frame_count - args.frame
        f1, f2, rig, source = dataset_frames(args.dataset, args.frame, min(count, available))
    else:
        f1, f2, rig, source = synthetic_frames(args.size, count)
    if len(f1) < pair_frames:
        raise SystemExit(f"bench: {source}: {pair_frames} frames needed, {len(f1)} available")

    # omni flow, pair mode: one call does both cameras (4 fits, matching, flow)
    stage_runs: list[dict] = []

    def omni_pair():
        res = estimate(f1, f2, rig, config, t=0)
        stage_runs.append(dict(res.timings))
        return res

    # streaming: one new stereo frame per call, the sequence played forwards and
    # backwards so every push is a real pair
    order = list(range(len(f1))) + list(range(len(f1) - 2, 0, -1))
    stream = OmniFlowStream(rig, config)
    position = [0]
    stream_points: list[int] = []
    stream.push(f1[0], f2[0])
    for _ in range(pair_frames - 2):  # dct3d: the window fills before the first result
        position[0] += 1
        stream.push(f1[order[position[0]]], f2[order[position[0]]])

    def omni_stream():
        position[0] += 1
        k = order[position[0] % len(order)]
        res = stream.push(f1[k], f2[k])
        stream_points.append(len(res))
        return res

    u8 = {cam: [to_uint8(f) for f in frames[:2]] for cam, frames in (("cam1", f1), ("cam2", f2))}
    fns: dict[str, Callable[[], object]] = {"omniflow pair": omni_pair,
                                            "omniflow stream": omni_stream}  # fmt: skip
    if args.versus:
        versus = parse_set([*args.set, *args.versus], "--versus")
        fns["omniflow pair versus"] = lambda: estimate(f1, f2, rig, versus, t=0)
    for name, flow in opencv_methods().items():

        def both(flow=flow):  # both camera pairs per call, as omni flow does
            return [flow(u8[c][0], u8[c][1]) for c in ("cam1", "cam2")]

        fns[name] = both
    wall, cpu, last = time_interleaved(fns, args.repeats, args.warmup)
    import cv2

    pair_stages = stage_runs[args.warmup :]  # the stage split of the default-thread runs
    from omniflow import parallel

    threads, omni_threads = cv2.getNumThreads(), parallel.THREADS
    cv2.setNumThreads(1)
    parallel.THREADS = 1
    try:
        one_fns = {"omniflow pair 1 thr": omni_pair, "DIS medium 1 thr": fns["DIS medium"]}
        one = time_interleaved(one_fns, args.repeats, args.warmup)
    finally:
        cv2.setNumThreads(threads)
        parallel.THREADS = omni_threads
    wall.update(one[0])
    cpu.update(one[1])
    fns.update(one_fns)
    last.update(one[2])

    stages = {}
    for key in pair_stages[0] if pair_stages else {}:
        vals = [s[key] for s in pair_stages if isinstance(s.get(key), int | float)]
        if vals:
            stages[key] = statistics.median(vals)
    points = {"omniflow pair": len(last["omniflow pair"]),
              "omniflow pair 1 thr": len(last["omniflow pair 1 thr"]),
              "omniflow stream": statistics.median(stream_points[args.warmup :])}  # fmt: skip
    if args.versus:
        points["omniflow pair versus"] = len(last["omniflow pair versus"])
    rows: list[dict] = []
    for name in fns:
        row = {"method": name, "median_s": statistics.median(wall[name]),
               "min_s": min(wall[name]), "cpu_median_s": statistics.median(cpu[name])}  # fmt: skip
        if name in points:
            row["points"] = points[name]
            row["ms_per_1000_points"] = (
                1e3 * row["median_s"] / (points[name] / 1e3) if points[name] else None
            )
        rows.append(row)
    rows[0]["stages_s"] = stages
    dis = next(r for r in rows if r["method"] == "DIS medium")
    for r in rows:
        r["ratio_to_dis_medium"] = r["median_s"] / dis["median_s"]
        r["cpu_ratio_to_dis_medium"] = r["cpu_median_s"] / dis["cpu_median_s"]

    if args.profile:
        profile_pairs(lambda: estimate(f1, f2, rig, config, t=0), args.profile)
    paced = (
        time_paced_stream(f1, f2, rig, config, args.repeats, args.warmup, args.interval / 1e3)
        if args.interval > 0
        else None
    )
    memory = measure_memory(args.memory_sizes, args.set) if args.memory_sizes else []

    import scipy

    env = {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "opencv": cv2.__version__,
        "opencv_threads": cv2.getNumThreads(),
        "cpus": os.cpu_count(),
        "load_average": os.getloadavg() if hasattr(os, "getloadavg") else None,
        "machine": platform.machine(),
    }
    report = {
        "frames": source,
        "image_size": list(f1[0].shape),
        "config": config.to_dict(),
        "versus": args.versus,
        "repeats": args.repeats,
        "warmup": args.warmup,
        "results": rows,
        "stream_paced": paced,
        "memory": memory,
        "environment": env,
    }

    print(f"frames: {source}")
    print(f"median of {args.repeats} interleaved runs after {args.warmup} warm-up; both camera "
          "pairs per run (stream: per new stereo frame); CPU = process time")  # fmt: skip
    print(f"{'method':<20}{'median ms':>10}{'min ms':>8}{'CPU ms':>8}{'vs DIS-m':>9}"
          f"{'CPU vs':>8}{'points':>8}{'ms/1000 pts':>12}")  # fmt: skip
    for r in rows:
        pts = f"{r['points']:>8.0f}" if "points" in r else f"{'all px':>8}"
        per = r.get("ms_per_1000_points")
        per_text = f"{per:>12.1f}" if per is not None else f"{'-':>12}"
        print(f"{r['method']:<20}{1e3 * r['median_s']:>10.1f}{1e3 * r['min_s']:>8.1f}"
              f"{1e3 * r['cpu_median_s']:>8.1f}{r['ratio_to_dis_medium']:>8.2f}x"
              f"{r['cpu_ratio_to_dis_medium']:>7.2f}x{pts}{per_text}")  # fmt: skip
    omni_row = rows[0]
    parts = {k: v for k, v in omni_row["stages_s"].items() if k != "total"}
    if parts:
        total = sum(parts.values())
        print(f"omniflow pair stages ({omni_row['points']} points; median ms, share of their sum):")
        for k, v in sorted(parts.items(), key=lambda kv: -kv[1]):
            print(f"  {k:<22}{1e3 * v:>8.1f}  {100 * v / total:>5.1f} %")
        omni_row["dominant_stage"] = max(parts, key=parts.get)
    if paced:
        pl, bg = paced["plain"], paced["background"]
        print(f"omniflow stream fed one frame every {paced['interval_ms']:.0f} ms (not "
              f"interleaved): push latency median {pl['push_median_ms']:.1f} ms plain, "
              f"{bg['push_median_ms']:.1f} ms with background matching (CPU per frame "
              f"{pl['cpu_ms_per_frame']:.1f} / {bg['cpu_ms_per_frame']:.1f} ms)")  # fmt: skip
    for m in memory:
        note = "" if m["peaks_separate"] else " (stream peak includes the pair runs)"
        print(f"peak resident memory at {m['size']} px: pair {m['pair_peak_mb']:.0f} MiB, "
              f"stream {m['stream_peak_mb']:.0f} MiB (process with frames loaded: "
              f"{m['baseline_mb']:.0f} MiB){note}")  # fmt: skip
    one = next(r for r in rows if r["method"] == "DIS medium 1 thr")
    for r in rows[:2]:
        verdict = "meets" if r["ratio_to_dis_medium"] <= 1.0 else "misses"
        ratios = (f"{r['ratio_to_dis_medium']:.2f}x wall, {r['cpu_ratio_to_dis_medium']:.2f}x CPU; "
                  f"{r['median_s'] / one['median_s']:.2f}x DIS medium on one thread")  # fmt: skip
        print(f"target ({r['method']} <= DIS medium on both pairs): {verdict} ({ratios})")
    print(f"environment: {env}")
    if args.json:
        atomic_write_text(Path(args.json), json_text(report))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
