"""Time of the brightness-gain fit (omniflow.solve.gain.gain_solution) on a dataset's pools.

Runs the flow step on one pair with the defaults and with the dense preset, captures
every call of the gain fit (first solve, refinement) and times each again, the median of
``--repeats``, with the number of pools and how many passed the gate. The fit runs on the
other thread of omniflow.parallel beside the plain solve; this is its own time.

    PYTHONPATH=$PWD python benchmarks/gain_fit_time.py /work/data/approach [--frame 0]
"""

from __future__ import annotations

import argparse
import statistics
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("--frame", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args()

    import omniflow.solve.at_matches as solve_mod
    from omniflow.config import OmniFlowConfig
    from omniflow.io.dataset import open_dataset
    from omniflow.pipeline import estimate
    from omniflow.solve.gain import gated
    from validation.inputs import Inputs, camera_model

    calls = []
    real = solve_mod.gain_solution

    def capture(*a, **k):
        calls.append((a, k))
        return real(*a, **k)

    solve_mod.gain_solution = capture
    ds = open_dataset(args.dataset)
    camera = camera_model(ds.meta)
    inputs = Inputs(ds, camera, auto_exposure=camera is not None and "camera" not in ds.meta)
    t = args.frame
    g1 = [inputs.grey(k, "cam1") for k in (t, t + 1)]
    g2 = [inputs.grey(k, "cam2") for k in (t, t + 1)]
    for name, config in (("defaults", OmniFlowConfig()), ("dense preset", OmniFlowConfig.dense())):
        calls.clear()
        estimate(g1, g2, ds.rig, config)
        for step, (a, k) in zip(("first solve", "refinement"), calls, strict=False):
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                out = real(*a, **k)
                times.append(time.perf_counter() - t0)
            pools = "grid windows" if k.get("grid") is not None else "k-d tree pools"
            taken = int(gated(out[3], k["gate"], out[0], out[1]).sum())
            print(f"{name:12s} {step:11s} {a[2].size:6d} points ({pools}), gain taken at "
                  f"{taken}: {1e3 * statistics.median(times):6.1f} ms")  # fmt: skip


if __name__ == "__main__":
    main()
