"""Points below a confidence floor of the pooled solver, and their flow, per dataset.

Runs ``estimate`` with the defaults (but no conditioning floor) on the validation inputs
(the dataset's camera model applied, as ``omnivalidate`` feeds omniflow) of the first
``--pairs`` frame pairs, and prints, per floor, how many points fall below it, the
largest flow among them and the largest flow among the rest (cam1 px per frame).

    python benchmarks/pool_conditioning.py DATASET [DATASET ...] [--pairs 3]
"""

import argparse

import numpy as np

from omniflow.io.dataset import open_dataset
from omniflow.pipeline import OmniFlowConfig, estimate
from validation.inputs import Inputs, camera_model

FLOORS = (1e-4, 1e-3, 1e-2, 3e-2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", nargs="+")
    ap.add_argument("--pairs", type=int, default=3)
    args = ap.parse_args()
    config = OmniFlowConfig(pool_min_conditioning=0.0)
    for path in args.datasets:
        ds = open_dataset(path)
        inputs = Inputs(ds, camera_model(ds.meta, []))
        conf, flow = [], []
        for t in range(args.pairs):
            f1 = [inputs.grey(k, "cam1") for k in (t, t + 1)]
            f2 = [inputs.grey(k, "cam2") for k in (t, t + 1)]
            r = estimate(f1, f2, ds.rig, config)
            conf.append(r["confidence"])
            flow.append(np.hypot(r["dx"], r["dy"]))
        c, f = np.concatenate(conf), np.concatenate(flow)
        for floor in FLOORS:
            low = c < floor
            below = f"{f[low].max():.2f}" if low.any() else "-"
            print(f"{path}: floor {floor:g}: {low.sum()} of {c.size} below (max flow {below} px), "
                  f"max flow of the rest {f[~low].max():.2f} px")  # fmt: skip


if __name__ == "__main__":
    main()
