"""A/B of the compiled pooled-solver sums (omniflow.solve.pooled_kernels) against numpy's
formulation.

Runs ``omniflow.pipeline.estimate`` on the same rendered pair alternately with
``omniflow.paper.flow.pooled_sums`` as shipped (Numba) and replaced by the numpy
formulation it replaced (``tests/omniflow/test_kernels.py``), at the default
configuration and at a dense one (more matches, as the accuracy work aims for),
and prints the medians of wall time, CPU time and the solve stage, and the
largest difference of the flow columns. Run from the repository root::

    PYTHONPATH=$PWD python benchmarks/bench_kernels.py --dataset runs/default/dataset --runs 30
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numpy as np

import omniflow.paper.flow
from omniflow.io.dataset import open_dataset
from omniflow.pipeline import OmniFlowConfig, estimate
from tests.omniflow.test_kernels import numpy_pooled_sums

CONFIGS = {
    "default": OmniFlowConfig(),
    "dense (threshold_percentile=30, min_score=0.9, n_theta=720)": OmniFlowConfig(
        threshold_percentile=30, n_theta=720, matching={"min_score": 0.9}
    ),
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bench_kernels", description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", required=True, metavar="DIR")
    parser.add_argument("--frame", type=int, default=0)
    parser.add_argument("--runs", type=int, default=30, help="timed runs of each (default 30)")
    args = parser.parse_args(argv)
    ds = open_dataset(args.dataset)
    f1 = [ds.read_grey(k, "cam1") for k in (args.frame, args.frame + 1)]
    f2 = [ds.read_grey(k, "cam2") for k in (args.frame, args.frame + 1)]
    variants = {"numpy": numpy_pooled_sums, "kernel": omniflow.paper.flow.pooled_sums}
    for label, config in CONFIGS.items():
        wall, cpu, solve, cols = ({k: [] for k in variants} for _ in range(4))
        for i in range(args.runs + 2):  # 2 warm-up rounds; the order alternates
            names = list(variants) if i % 2 else list(variants)[::-1]
            for name in names:
                omniflow.paper.flow.pooled_sums = variants[name]
                c0, t0 = time.process_time(), time.perf_counter()
                result = estimate(f1, f2, ds.rig, config)
                t1, c1 = time.perf_counter(), time.process_time()
                if i >= 2:
                    wall[name].append(t1 - t0)
                    cpu[name].append(c1 - c0)
                    solve[name].append(result.timings["solve"])
                cols[name] = result.columns
        omniflow.paper.flow.pooled_sums = variants["kernel"]
        worst = max(
            float(np.max(np.abs(cols["kernel"][k] - v)) / np.max(np.abs(v)))
            for k, v in cols["numpy"].items()
            if v.size and np.max(np.abs(v)) > 0
        )
        n = len(cols["kernel"]["x"])
        print(f"{label}: {n} points; median of {args.runs} interleaved runs each, ms")
        print(f"  {'':8}{'wall':>8}{'CPU':>8}{'solve':>8}")
        for name in variants:
            med = [1e3 * statistics.median(v[name]) for v in (wall, cpu, solve)]
            print(f"  {name:8}{med[0]:8.1f}{med[1]:8.1f}{med[2]:8.1f}")
        print(f"  largest column difference, relative to the column's largest value: {worst:.1e}")
    print(f"load average {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
