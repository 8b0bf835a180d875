"""Interleaved A/B timing of the matching stage alone, from several checkouts.

Like ``ab_checkouts.py`` (one worker process per variant: a checkout on
PYTHONPATH, optionally with ``omniflow.parallel.THREADS`` set; driven in rounds
so a change of load hits every variant alike), but each call is
:func:`omniflow.pipeline.stereo_matches` alone on the matching grids of the
first stereo frame (both passes, the vote, the densification where
configured): the ``match`` stage without the fit, the flow grids and the
solve. Prints the median wall and CPU (process) time per call. Run::

    git worktree add --detach /tmp/ref main
    python benchmarks/ab_matching.py --dataset /work/data/default \\
        ref=/tmp/ref new=. ref1=/tmp/ref:threads=1 new1=.:threads=1
    python benchmarks/ab_matching.py ref=/tmp/ref new=. --set dense_percentile=60
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time


def worker(dataset: str, threads: int | None, sets: list[str]) -> None:
    """Answer each line N on stdin with the wall and CPU seconds of N calls (JSON)."""
    from omniflow import parallel
    from omniflow import pipeline as P
    from omniflow.io.dataset import open_dataset

    if threads is not None:
        parallel.THREADS = threads
    fields = {}
    for s in sets:
        name, _, value = s.partition("=")
        fields[name] = int(value) if value.lstrip("-").isdigit() else float(value)
    config = P.OmniFlowConfig(**fields)
    ds = open_dataset(dataset)
    f1 = [ds.read_grey(j, "cam1") for j in range(2)]
    f2 = [ds.read_grey(j, "cam2") for j in range(2)]
    seen = {}
    stereo_matches = P.stereo_matches

    def grab(grids, rig, cfg):  # the grids estimate() hands the matcher
        seen["args"] = (grids, rig, cfg)
        return stereo_matches(grids, rig, cfg)

    P.stereo_matches = grab
    P.estimate(f1, f2, ds.rig, config)
    P.stereo_matches = stereo_matches
    args = seen["args"]
    for _ in range(3):
        stereo_matches(*args)
    print("ready", flush=True)
    for line in sys.stdin:
        wall, cpu = [], []
        for _ in range(int(line)):
            t0, c0 = time.perf_counter(), time.process_time()
            stereo_matches(*args)
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        print(json.dumps([wall, cpu]), flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="ab_matching", description=__doc__.split("\n")[0])
    parser.add_argument("variants", nargs="+", metavar="NAME=CHECKOUT[:threads=N]")
    parser.add_argument("--dataset", default="/work/data/default")
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--per-round", type=int, default=5)
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="OmniFlowConfig field for every variant (repeatable)")  # fmt: skip
    parser.add_argument("--worker", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        dataset, threads = args.worker
        worker(dataset, None if threads == "-" else int(threads), args.set)
        return 0
    procs = {}
    for spec in args.variants:
        name, _, rest = spec.partition("=")
        where, _, opt = rest.partition(":")
        threads = opt.removeprefix("threads=") if opt else "-"
        env = dict(os.environ, PYTHONPATH=os.path.abspath(where))
        cmd = [sys.executable, os.path.abspath(__file__), "x", "--worker", args.dataset, threads]
        cmd += [f"--set={s}" for s in args.set]
        p = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                             env=env, cwd="/")  # fmt: skip
        if p.stdout.readline().strip() != "ready":
            raise SystemExit(f"ab_matching: {name}: the worker did not start")
        procs[name] = p
    times = {k: ([], []) for k in procs}
    for _ in range(args.rounds):
        for name, p in procs.items():
            p.stdin.write(f"{args.per_round}\n")
            p.stdin.flush()
            wall, cpu = json.loads(p.stdout.readline())
            times[name][0].extend(wall)
            times[name][1].extend(cpu)
    print(f"load average {os.getloadavg()}; medians of {args.rounds} x {args.per_round} calls")
    for name, (wall, cpu) in times.items():
        print(f"{name:12s} match wall {1e3 * statistics.median(wall):6.1f} ms (min "
              f"{1e3 * min(wall):5.1f})  CPU {1e3 * statistics.median(cpu):6.1f} ms")  # fmt: skip
    for p in procs.values():
        p.stdin.close()
        p.wait()
    return 0


if __name__ == "__main__":
    sys.exit(main())
