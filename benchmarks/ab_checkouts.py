"""Interleaved A/B timing of omniflow.pipeline.estimate from several checkouts, with DIS.

One worker process per variant (a checkout on PYTHONPATH, optionally with
``omniflow.parallel.THREADS`` set, or OpenCV DIS medium on one or all
threads), driven in rounds so a change of load on a shared machine hits
every variant alike; prints the median wall and CPU (process) time per call,
both camera pairs of the first two frames per call. Run::

    git worktree add --detach ../ref main
    python benchmarks/ab_checkouts.py --dataset runs/default/dataset \\
        ref=../ref new=. new1=.:threads=1 dis=dis dis1=dis:threads=1

``--set NAME=VALUE`` (repeatable) gives every omniflow variant that
OmniFlowConfig field (parsed as the CLI's ``--set``), e.g. the densified
configuration: ``--set dense_percentile=60 --set pooling.pool_grid=0.125 --set decouple_tol=60``.
A variant's own ``:set=ITEMS`` (omniflow.cli.common.config_from_settings' comma-separated
items, presets included) is added after those, so one run can time several
configurations of one checkout against DIS in the same rounds::

    python benchmarks/ab_checkouts.py --dataset DATASET \
        default=. dense=.:set=dense dense75=.:set=dense,dense_percentile=75 dis=dis
``--stage solve`` (repeatable) adds the median wall time of that stage of estimate().
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time


def worker(dataset: str, dis: bool, threads: int | None, settings: str = "") -> None:
    """Answer each line N on stdin with the wall and CPU seconds of N calls (JSON)."""
    import cv2

    from omniflow.io.dataset import open_dataset
    from omniflow.io.imageio import to_uint8

    ds = open_dataset(dataset)
    f1 = [ds.read_grey(j, "cam1") for j in range(2)]
    f2 = [ds.read_grey(j, "cam2") for j in range(2)]
    if dis:
        if threads is not None:
            cv2.setNumThreads(threads)
        flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        u8 = [(to_uint8(a[0]), to_uint8(a[1])) for a in (f1, f2)]

        def fn():
            return [flow.calc(a, b, None) for a, b in u8]
    else:
        from omniflow.pipeline import OmniFlowConfig, estimate

        config = OmniFlowConfig()
        if settings:
            try:
                from omniflow.cli.common import config_from_settings
            except ImportError:  # a checkout before the presets: OmniFlowConfig.dense() etc.
                config = getattr(OmniFlowConfig, settings)()
            else:
                config = config_from_settings(settings)

        if threads is not None:
            try:
                from omniflow import parallel
            except ImportError:  # a checkout before omniflow.parallel: one thread anyway
                pass
            else:
                parallel.THREADS = threads

        def fn():
            return estimate(f1, f2, ds.rig, config)

    for _ in range(3):
        fn()
    print("ready", flush=True)
    for line in sys.stdin:
        wall, cpu, stages = [], [], []
        for _ in range(int(line)):
            t0, c0 = time.perf_counter(), time.process_time()
            out = fn()
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            stages.append(getattr(out, "timings", {}))  # omniflow's per-stage seconds
        print(json.dumps([wall, cpu, stages]), flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="ab_checkouts", description=__doc__.split("\n")[0])
    parser.add_argument(
        "variants", nargs="+", metavar="NAME=CHECKOUT[:threads=N][:set=ITEMS]",
        help="a checkout folder (put on PYTHONPATH), or 'dis' for DIS medium",
    )  # fmt: skip
    parser.add_argument(
        "--dataset", default="runs/default/dataset", help="the demo's dataset by default"
    )
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--per-round", type=int, default=3)
    parser.add_argument(
        "--set", action="append", default=[], metavar="NAME=VALUE",
        help="an OmniFlowConfig field for every omniflow variant (repeatable)",
    )  # fmt: skip
    parser.add_argument(
        "--stage", action="append", default=[], metavar="NAME",
        help="also the median of this stage's wall time (estimate()'s timings: match, "
        "solve, ...; repeatable)",
    )  # fmt: skip
    parser.add_argument("--worker", nargs=4, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        dataset, kind, threads, settings = args.worker
        worker(dataset, kind == "dis", None if threads == "-" else int(threads), settings)
        return 0
    procs = {}
    for spec in args.variants:
        name, _, rest = spec.partition("=")
        where, *opts = rest.split(":")
        threads, settings = "-", list(args.set)
        for opt in opts:
            key, _, value = opt.partition("=")
            if key == "threads":
                threads = value
            elif key == "set":
                settings.append(value)
            else:
                raise SystemExit(f"ab_checkouts: {spec}: expected :threads=N or :set=ITEMS")
        kind = "dis" if where == "dis" else "omniflow"
        path = os.path.abspath(os.path.dirname(__file__) + "/.." if kind == "dis" else where)
        env = dict(os.environ, PYTHONPATH=path)
        cmd = [sys.executable, os.path.abspath(__file__), "x", "--worker", args.dataset, kind,
               threads, ",".join(settings)]  # fmt: skip
        p = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                             env=env, cwd="/")  # fmt: skip
        if p.stdout.readline().strip() != "ready":
            raise SystemExit(f"ab_checkouts: {name}: the worker did not start")
        procs[name] = p
    times = {k: ([], [], []) for k in procs}
    for _ in range(args.rounds):
        for name, p in procs.items():
            p.stdin.write(f"{args.per_round}\n")
            p.stdin.flush()
            wall, cpu, stages = json.loads(p.stdout.readline())
            times[name][0].extend(wall)
            times[name][1].extend(cpu)
            times[name][2].extend(stages)
    print(f"load average {os.getloadavg()}; medians of {args.rounds} x {args.per_round} calls")
    for name, (wall, cpu, stages) in times.items():
        split = ""
        for stage in args.stage:
            got = [t[stage] for t in stages if stage in t]
            split += f"  {stage} {1e3 * statistics.median(got):5.1f} ms" if got else ""
        print(f"{name:12s} wall {1e3 * statistics.median(wall):6.1f} ms (min "
              f"{1e3 * min(wall):5.1f})  CPU {1e3 * statistics.median(cpu):6.1f} ms"
              + split)  # fmt: skip
    for p in procs.values():
        p.stdin.close()
        p.wait()
    return 0


if __name__ == "__main__":
    sys.exit(main())
