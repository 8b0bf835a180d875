"""Stereo matching on rendered datasets: matches per frame, outliers, points per mover, time.

For each dataset and frame pair, runs the stereo-flow step
(:func:`omniflow.pipeline.estimate`) on the images every method sees in
``omnivalidate`` (the dataset's camera model applied to its radiance,
:mod:`validation.inputs`) and scores its points against the truth:

- points per frame and their share of the valid pixels (``gt.valid``);
- stereo outliers: |h2 - gt.stereo.h_other| > 1 px, over the points whose
  truth is defined (as ``omnivalidate``'s "stereo >1px");
- points on each moving object (``gt.object``), summed over the frame pairs
  (as the per-object ``n`` of ``omnivalidate``'s summary);
- the median time of the matching stage (``timings["match"]``) and of the
  whole step, in ms (one run per frame pair: noisy on a loaded machine).

The scored points are the flow step's columns, so the figures agree with
``omnivalidate --variants default`` for the default configuration. Run::

    python benchmarks/bench_matching.py runs/default/dataset runs/crossing/dataset
    python benchmarks/bench_matching.py runs/default/dataset --set dense_percentile=none
    python benchmarks/bench_matching.py runs/default/dataset --table "edges only" \\
        --set dense_percentile=none --json out.json

``--table NAME`` prints one markdown row (all datasets) instead of a block
per dataset.
"""

from __future__ import annotations

import argparse
import statistics

import numpy as np

from benchmarks.bench_omniflow import parse_set
from omniflow.io.imageio import atomic_write_text
from omniflow.io.jsonio import json_text

TRUTH = ("gt.valid", "gt.object", "gt.stereo.valid", "gt.stereo.h_other")


def score_dataset(directory: str, config) -> dict:
    """Matching figures of ``config`` on every complete frame pair of one dataset."""
    from omniflow.io.dataset import open_dataset
    from omniflow.pipeline import estimate
    from validation.inputs import Inputs, camera_model
    from validation.sampling import sample_truth
    from validation.scoring_derived import moving_objects

    ds = open_dataset(directory)
    camera = camera_model(ds.meta)
    inputs = Inputs(ds, camera, auto_exposure=camera is not None and "camera" not in ds.meta)
    frames = ds.frames_done()
    g1 = [inputs.grey(k, "cam1") for k in frames]
    g2 = [inputs.grey(k, "cam2") for k in frames]
    names = ds.objects
    movers = {names.get(i, str(i)): 0 for i in moving_objects(ds.meta)}
    ids = {names.get(i, str(i)): i for i in moving_objects(ds.meta)}
    n = n_out = n_truth = valid = 0
    match_ms, total_ms = [], []
    for t in range(len(frames) - 1):
        res = estimate(g1, g2, ds.rig, config, t=t)
        c = res.columns
        truth = {k: v for k, v in ds.read_frame(frames[t], "cam1").items() if k in TRUTH}
        tr = sample_truth(truth, c["x"], c["y"], channels=TRUTH)
        has = tr["bilinear_ok"] & (tr["gt.stereo.valid"] > 0.5)
        n += len(c["x"])
        n_truth += int(has.sum())
        n_out += int(np.sum(np.abs(np.asarray(c["h2"])[has] - tr["gt.stereo.h_other"][has]) > 1.0))
        valid += int(np.count_nonzero(truth["gt.valid"] > 0.5))
        obj = np.rint(tr["gt.object"]).astype(int)
        for name, i in ids.items():
            movers[name] += int(np.sum(obj == i))
        match_ms.append(1e3 * res.timings.get("match", np.nan))
        total_ms.append(1e3 * res.timings.get("total", np.nan))
    pairs = max(len(frames) - 1, 1)
    return {
        "dataset": str(directory),
        "pairs": len(frames) - 1,
        "points_per_frame": n / pairs,
        "of_valid_pixels": n / valid if valid else float("nan"),
        "outliers": n_out / n_truth if n_truth else float("nan"),
        "movers": movers,
        "match_ms": statistics.median(match_ms) if match_ms else float("nan"),
        "total_ms": statistics.median(total_ms) if total_ms else float("nan"),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bench_matching", description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="+", help="omnisim dataset directories")
    parser.add_argument(
        "--set", action="append", default=[], metavar="NAME=VALUE",
        help="OmniFlowConfig field to change (repeatable), e.g. --set dense_percentile=none",
    )  # fmt: skip
    parser.add_argument("--table", metavar="NAME", help="print one markdown row named NAME")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON here")
    args = parser.parse_args(argv)

    config = parse_set(args.set)
    rows = [score_dataset(d, config) for d in args.datasets]
    if args.table:
        cell = {k: " / ".join(f(r) for r in rows) for k, f in (
            ("pts", lambda r: f"{r['points_per_frame']:.0f}"),
            ("share", lambda r: f"{100 * r['of_valid_pixels']:.2f}"),
            ("out", lambda r: f"{100 * r['outliers']:.2f}"),
            ("ms", lambda r: f"{r['match_ms']:.0f} ({r['total_ms']:.0f})"),
        )}  # fmt: skip
        few = ", ".join(f"{k} {v}" for r in rows for k, v in r["movers"].items() if v < 20)
        print(f"| {args.table} | {cell['pts']} | {cell['share']} | {cell['out']} | "
              f"{cell['ms']} | {few or 'none'} |")  # fmt: skip
    else:
        for r in rows:
            movers = ", ".join(f"{k} {v}" for k, v in r["movers"].items()) or "none"
            print(f"{r['dataset']}: {r['points_per_frame']:.0f} points per frame "
                  f"({100 * r['of_valid_pixels']:.2f} % of valid pixels), stereo outliers "
                  f"{100 * r['outliers']:.2f} %, points on movers ({r['pairs']} pairs): {movers}; "
                  f"match {r['match_ms']:.0f} ms, step {r['total_ms']:.0f} ms")  # fmt: skip
    if args.json:
        atomic_write_text(args.json, json_text({"config": args.set, "rows": rows}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
