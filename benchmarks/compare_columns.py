"""Every numeric column of ``estimate()`` on rendered pairs: write them, or compare with
a file written by another checkout (same matched samples? largest relative difference?).

For each dataset, the pairs (t, t + 1) for t = 0 .. --pairs - 1. Run once with the
reference checkout on PYTHONPATH and ``--write``, then with this one and ``--compare``::

    git worktree add --detach ../ref main
    PYTHONPATH=../ref python benchmarks/compare_columns.py --write ref.npz
    PYTHONPATH=$PWD python benchmarks/compare_columns.py --compare ref.npz
    PYTHONPATH=$PWD python benchmarks/compare_columns.py --compare ref.npz --threads 1
    # the densified option: the same --set for both runs
    ... --set dense_percentile=60 --set pooling.pool_grid=0.125 --set decouple_tol=60

Prints the number of points, whether every pair has the same (theta, h1) samples, and
the largest |new - reference| over a column relative to the column's largest |value|.
Exit 1 when the samples differ.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from benchmarks.bench_omniflow import parse_set


def columns(datasets: list[str], pairs: int, config) -> dict[str, np.ndarray]:
    from omniflow.io.dataset import open_dataset
    from omniflow.pipeline import estimate

    out = {}
    for path in datasets:
        ds = open_dataset(path)
        for t in range(pairs):
            f1 = [ds.read_grey(j, "cam1") for j in (t, t + 1)]
            f2 = [ds.read_grey(j, "cam2") for j in (t, t + 1)]
            res = estimate(f1, f2, ds.rig, config)
            for name, v in res.columns.items():
                v = np.asarray(v)
                if v.dtype.kind in "fiub":
                    out[f"{Path(path).name}/{t}/{name}"] = v
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="compare_columns", description=__doc__.split("\n")[0])
    parser.add_argument("datasets", nargs="*", default=[f"runs/{s}/dataset" for s in
                        ("default", "approach", "crossing")])  # fmt: skip
    parser.add_argument("--pairs", type=int, default=3)
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    parser.add_argument("--threads", type=int, help="omniflow.parallel.THREADS")
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--write", metavar="NPZ")
    group.add_argument("--compare", metavar="NPZ")
    args = parser.parse_args(argv)
    from omniflow import parallel

    if args.threads is not None:
        parallel.THREADS = args.threads
    config = parse_set(args.set)
    out = columns(args.datasets, args.pairs, config)
    if args.write:
        np.savez(args.write, **out)
        print(f"wrote {len(out)} columns to {args.write}")
        return 0
    ref = np.load(args.compare)
    same, worst, where, points = True, 0.0, "", 0
    for key in ref.files:
        a, b = ref[key], out.get(key)
        if b is None or a.shape != b.shape:
            print(f"{key}: shape {a.shape} against {None if b is None else b.shape}")
            same = False
            continue
        if key.endswith(("/theta", "/h1")) and not np.array_equal(a, b):
            print(f"{key}: the matched samples differ")
            same = False
        points += a.size if key.endswith("/theta") else 0
        fa, fb = a.astype(float), b.astype(float)
        if not np.array_equal(np.isnan(fa), np.isnan(fb)):
            print(f"{key}: NaN where the reference has none (or the other way)")
            same = False
        fa, fb = np.nan_to_num(fa), np.nan_to_num(fb)
        scale = float(np.max(np.abs(fa))) if fa.size else 0.0
        d = float(np.max(np.abs(fa - fb))) / scale if scale > 0 else 0.0
        if d > worst:
            worst, where = d, key
    print(f"points {points}, same samples {same}, largest relative difference {worst:.3g}"
          + (f" ({where})" if where else ""))  # fmt: skip
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
