"""Where one stereo pair's time goes: per component of estimate(), or a two-thread timeline.

``--mode cpu`` (default): ``omniflow.parallel.THREADS`` 1, each component's thread CPU time
(``time.thread_time``, inclusive, summed over its calls in the pair), median over
``--repeats`` pairs; ``--mode timeline``: the default threads, each call's thread, start and
end (wall, ms from the call's start) for the median pair. The components are the module
functions below, wrapped where estimate() looks them up (so a checkout that lacks one
just leaves it out). ``--set`` as omniflow's (the dense preset: ``--set
dense_percentile=60 --set matching.dense_smooth=0.95 --set pooling.pool_grid=0.125
--set decouple_tol=60``)::

    PYTHONPATH=<checkout> python benchmarks/solve_profile.py runs/approach/dataset [--set ...]
"""

from __future__ import annotations

import argparse
import functools
import importlib
import os
import statistics
import sys
import threading
import time

#: (module, attribute, label): the components, as estimate() looks them up
COMPONENTS = (
    ("omniflow.pipeline", "_unit_series", "fit: unit series"),
    ("omniflow.pipeline", "matching_grid", "grids: matching grid"),
    ("omniflow.pipeline", "flow_grids", "grids: flow grids"),
    ("omniflow.pipeline", "stereo_matches", "match: all"),
    ("omniflow.matching.radial", "densify", "match: densification"),
    ("omniflow.pipeline", "flow_at_matches", "sample + solve: flow_at_matches"),
    (
        "omniflow.solve.at_matches",
        "pooled_solution",
        "solve: plain pooled solves (first, refinement)",
    ),
    ("omniflow.solve.at_matches", "gain_solution", "solve: gain fits (first, refinement)"),
    ("omniflow.solve.at_matches", "_refine", "solve: refinement (its solves included)"),
    ("omniflow.solve.refine", "_unit_rows", "solve: refinement's exact evaluations"),
    ("omniflow.solve.gridpool.GridPools", "decouple_sums", "pool fits: two-model sums"),
    ("omniflow.solve.decoupled", "fits_from_sums", "pool fits: two-model fits"),
    ("omniflow.solve.gridpool.GridPools", "linear_gain_sums", "pool fits: linear-gain grid sums"),
    ("omniflow.solve.decoupled", "screen", "pool fits: screen"),
    ("omniflow.solve.decoupled", "neighbourhoods", "pool fits: tree search"),
    ("omniflow.solve.decoupled", "decoupled_linear_gain", "pool fits: tree linear-gain test"),
    ("omniflow.solve.at_matches", "decouple", "decouple"),
)


def _resolve(path: str):
    """A module, or a class (a last part in capitals) of one."""
    mod, _, attr = path.rpartition(".")
    if attr[:1].isupper():
        return getattr(importlib.import_module(mod), attr)
    return importlib.import_module(path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="solve_profile", description=__doc__.split("\n")[0])
    parser.add_argument("dataset")
    parser.add_argument("--mode", choices=("cpu", "timeline"), default="cpu")
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--frame", type=int, default=0)
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    args = parser.parse_args(argv)

    from omniflow import parallel
    from omniflow.cli.common import config_from_settings
    from omniflow.io.dataset import open_dataset
    from omniflow.pipeline import OmniFlowConfig, estimate

    if args.mode == "cpu":
        parallel.THREADS = 1
    clock = time.thread_time if args.mode == "cpu" else time.perf_counter
    calls: list[tuple[str, str, float, float]] = []
    for path, name, label in COMPONENTS:
        owner = _resolve(path)
        fn = getattr(owner, name, None)
        if fn is None:
            continue

        def wrapped(*a, _fn=fn, _label=label, **k):
            t0 = clock()
            try:
                return _fn(*a, **k)
            finally:
                thread = threading.current_thread().name
                calls.append((_label, "pool" if thread.startswith("omniflow") else "main",
                              t0, clock()))  # fmt: skip

        setattr(owner, name, functools.wraps(fn)(wrapped))
    ds = open_dataset(args.dataset)
    t = args.frame
    f1 = [ds.read_grey(j, "cam1") for j in (t, t + 1)]
    f2 = [ds.read_grey(j, "cam2") for j in (t, t + 1)]
    config = config_from_settings(",".join(args.set)) if args.set else OmniFlowConfig()
    for _ in range(2):
        estimate(f1, f2, ds.rig, config)
    pairs = []
    for _ in range(args.repeats):
        calls.clear()
        t0 = clock()
        out = estimate(f1, f2, ds.rig, config)
        pairs.append((clock() - t0, t0, list(calls), dict(out.timings)))
    n = len(out.columns["h1"])
    head = f"# {args.dataset} pair {t}, {n} points, load {os.getloadavg()[0]:.1f}"
    if args.mode == "cpu":
        print(f"{head}; thread CPU ms (one thread), medians of {args.repeats}")
        per: dict[str, list[float]] = {}
        for total, _, seen, timings in pairs:
            sums: dict[str, float] = {}
            for label, _, a, b in seen:
                sums[label] = sums.get(label, 0.0) + b - a
            sums["total"] = total
            sums.update({f"timings.{k}": v for k, v in timings.items()})
            for k, v in sums.items():
                per.setdefault(k, []).append(1e3 * v)
        for k, v in per.items():
            print(f"{k:50s} {statistics.median(v):7.1f}")
    else:
        order = sorted(range(len(pairs)), key=lambda i: pairs[i][0])
        total, t0, seen, _ = pairs[order[len(order) // 2]]
        print(f"{head}; wall ms, threads {parallel.THREADS}, the median of {args.repeats} "
              f"pairs: {1e3 * total:.1f}")  # fmt: skip
        for label, thread, a, b in sorted(seen, key=lambda c: c[2]):
            print(f"{label:50s} {thread:5s} {1e3 * (a - t0):7.1f} {1e3 * (b - t0):7.1f} "
                  f"{1e3 * (b - a):6.1f}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
