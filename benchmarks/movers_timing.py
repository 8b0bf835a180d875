"""Seconds of estimate() on one rendered pair with and without the movers' knobs.

    python benchmarks/movers_timing.py [DATASET] [REPEATS]

DATASET defaults to /work/data/default (frame pair 0, grey = Rec. 709 luma of R, G, B);
prints the median total and the median time of omniflow.solve.decoupled.decouple per
configuration (docs/measurements.md, "Movers: decoupled radial flow").
"""

from __future__ import annotations

import sys
import time

import numpy as np

import omniflow.solve.at_matches as solve
import omniflow.solve.decoupled as decoupled
from omniflow.config import OmniFlowConfig
from omniflow.io.dataset import open_dataset
from omniflow.pipeline import estimate


def main(argv: list[str]) -> int:
    path = argv[0] if argv else "/work/data/default"
    repeats = int(argv[1]) if len(argv) > 1 else 5
    ds = open_dataset(path)

    def grey(k: int, cam: str) -> np.ndarray:
        f = ds.read_frame(k, cam)
        return (0.2126 * f["R"] + 0.7152 * f["G"] + 0.0722 * f["B"]).astype(np.float32)

    frames = {cam: [grey(0, cam), grey(1, cam)] for cam in ("cam1", "cam2")}
    spent: list[float] = []
    original = decoupled.decouple

    def timed(*args, **kwargs):
        t0 = time.perf_counter()
        out = original(*args, **kwargs)
        spent.append(time.perf_counter() - t0)
        return out

    solve.decouple = timed
    for knobs in ({"decouple_tol": None}, {}, {"flow_shading": 8.0},
                  {"flow_shading": 8.0, "flow_shading_where": "moving"}):  # fmt: skip
        spent.clear()
        totals = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            res = estimate(frames["cam1"], frames["cam2"], ds.rig, OmniFlowConfig(**knobs))
            totals.append(time.perf_counter() - t0)
        print(f"{knobs or 'default'}: total {np.median(totals):.3f} s, decouple "
              f"{np.median(spent) if spent else 0.0:.4f} s, {len(res)} points")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
