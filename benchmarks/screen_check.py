"""What :func:`omniflow.solve.decoupled.screen` keeps, what it loses, and what it saves.

For each dataset and pair (t, t + 1), t in ``--frames``: :func:`omniflow.pipeline.estimate`
with the dense preset, then its :func:`omniflow.solve.decoupled.pool_fits` made again twice on
the same columns, with the screen and with every point kept (the k-d tree's test at every
point, as before the screen). Prints the points, the share the screen keeps, the points
the unscreened test switches (:func:`omniflow.solve.decoupled.chained`), those the screened one
loses or adds, whether the switched points' answers are the same bit for bit, and each
pool_fits' median time over ``--repeats`` calls (one thread)::

    PYTHONPATH=$PWD python benchmarks/screen_check.py /work/data/approach \\
        /work/data/independent_movers --frames 0,1,2 [--ratio 1.1]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import omniflow.solve.at_matches as solve_mod
import omniflow.solve.decoupled as decoupled_mod
from omniflow import parallel
from omniflow.config import OmniFlowConfig
from omniflow.io.dataset import open_dataset
from omniflow.pipeline import estimate


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="screen_check", description=__doc__.split("\n")[0])
    parser.add_argument("datasets", nargs="+")
    parser.add_argument("--frames", default="0,1,2")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--ratio", type=float, help="omniflow.solve.decoupled.SCREEN_RATIO")
    parser.add_argument("--share", type=float, help="omniflow.solve.decoupled.SCREEN_F")
    args = parser.parse_args(argv)
    if args.ratio is not None:
        decoupled_mod.SCREEN_RATIO = args.ratio
    if args.share is not None:
        decoupled_mod.SCREEN_F = args.share
    parallel.THREADS = 1
    pool_fits, screen = decoupled_mod.pool_fits, decoupled_mod.screen
    start = decoupled_mod.start_pool_fits
    seen = []  # the arguments of the solver's own call

    def capture(cols, rig, config, pools=None, brightness=None):
        seen.append((cols, rig, config, brightness))
        return start(cols, rig, config, pools, brightness)

    solve_mod.start_pool_fits = capture
    keep_share = []

    def screened(sums, *a):
        keep = screen(sums, *a)
        keep_share.append(float(keep.mean()))
        return keep

    def every(sums, *a):
        return np.ones(sums[0].shape[0], dtype=bool)

    def timed(kind):
        decoupled_mod.screen = kind
        times, fit = [], None
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            fit = pool_fits(cols, rig, config, brightness=brightness)
            times.append(time.perf_counter() - t0)
        return fit, 1e3 * float(np.median(times))

    config = OmniFlowConfig.dense()
    total = {"switched": 0, "lost": 0, "added": 0}
    print("dataset pair | points | kept | switched | lost | added | same | ms screened / all")
    for path in args.datasets:
        ds = open_dataset(path)
        for t in (int(v) for v in args.frames.split(",")):
            seen.clear()
            f1 = [ds.read_grey(j, "cam1") for j in (t, t + 1)]
            f2 = [ds.read_grey(j, "cam2") for j in (t, t + 1)]
            estimate(f1, f2, ds.rig, config)
            cols, rig, cfg, brightness = seen[-1]
            config = cfg
            new, ms_new = timed(screened)
            old, ms_old = timed(every)
            tol = config.decouple_gain_tol
            cn, co = decoupled_mod.chained(new, tol), decoupled_mod.chained(old, tol)
            keys = ("gain_a1", "gain_a2", "gain_b", "gain_F")
            same = all(np.array_equal(new[k][cn & co], old[k][cn & co]) for k in keys)
            lost, added = int((co & ~cn).sum()), int((cn & ~co).sum())
            total["switched"] += int(co.sum())
            total["lost"] += lost
            total["added"] += added
            name = path.rstrip("/").split("/")[-1]
            print(f"{name} {t} | {co.size} | {100 * keep_share[-1]:.0f} % | {int(co.sum())} "
                  f"| {lost} | {added} | {same} | {ms_new:.1f} / {ms_old:.1f}")  # fmt: skip
    print(f"total: switched {total['switched']}, lost {total['lost']}, added {total['added']}")
    decoupled_mod.screen = screen
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
