"""The refinement's step against the first displacement at the points it refines.

For each dataset (pairs 0-2, images as omnivalidate forms them) runs omniflow with the
default configuration and the given solver and prints, at the points
:func:`omniflow.solve.refine.refine_moving` refines (for ``direct``, which it declines, those it
would refine were the solve pooled), the step's size as a share of the first
step's displacement (percentiles, the share above 0.5) and cam1's endpoint error, mean
and median, of the first and of the refined flow, overall and at the steps above 0.5.
Run::

    python benchmarks/refine_steps.py pooled|direct DATASET...
"""

from __future__ import annotations

import sys

import numpy as np


def main(solver: str, directories: list[str]) -> None:
    import omniflow.solve.at_matches as solve_mod
    import omniflow.solve.refine as refine
    from omniflow.config import OmniFlowConfig
    from omniflow.io.dataset import open_dataset
    from omniflow.pipeline import estimate
    from validation.inputs import Inputs, camera_model
    from validation.sampling import sample_truth

    seen = {}
    original = refine.refine_moving

    def capture(a, b, conf, **kw):
        # what the step does, also where refine_moving declines (the direct solver): it
        # runs as for a pooled solve, its solver built as configured
        make = kw["make_solver"]
        step_kw = dict(kw, config=kw["config"].replace(solver="pooled"),
                       make_solver=lambda rig, c, *args, **kws: make(rig, c.replace(solver=solver),
                                                                     *args, **kws))  # fmt: skip
        seen["call"] = (a, b, original(a, b, conf, **step_kw), kw)
        return original(a, b, conf, **kw)

    solve_mod.refine_moving = capture
    config = OmniFlowConfig(solver=solver)
    for directory in directories:
        ds = open_dataset(directory)
        camera = camera_model(ds.meta)
        inputs = Inputs(ds, camera, auto_exposure=camera is not None and "camera" not in ds.meta)
        ratio, first, refined = [], [], []
        for t in range(min(3, ds.frame_count - 1)):
            g1 = [inputs.grey(k, "cam1") for k in (t, t + 1)]
            g2 = [inputs.grey(k, "cam2") for k in (t, t + 1)]
            estimate(g1, g2, ds.rig, config)
            a, b, (a2, b2, _, sel), kw = seen["call"]
            h1, h2 = kw["h1"], kw["h2"]
            k = h2 / h1
            d1 = np.maximum(np.hypot(a, h1 * b), np.hypot(k * a, h2 * b))
            da, db = a2 - a, b2 - b
            step = np.maximum(np.hypot(da, h1 * db), np.hypot(k * da, h2 * db))
            truth = sample_truth(ds.read_frame(t, "cam1"), kw["x1"], kw["y1"])
            ratio.append((step / d1)[sel])
            for out, (fa, fb) in ((first, (a, b)), (refined, (a2, b2))):
                err = np.hypot(fa - truth["gt.flow.dh"], h1 * fb - truth["gt.flow.hdtheta"])
                out.append(err[sel])
        r, e0, e1 = (np.concatenate(v) for v in (ratio, first, refined))
        name = ds.meta.get("scene", {}).get("name", directory)
        if r.size == 0:
            print(f"{name} ({solver}): no refined points")
            continue
        big = r > 0.5
        q = np.percentile(r, [50, 90, 99, 100])
        line = (f"{name} ({solver}): {r.size} refined points; step / first displacement "
                f"p50 {q[0]:.3f} p90 {q[1]:.3f} p99 {q[2]:.3f} max {q[3]:.3f}, "
                f"{big.mean():.1%} above 0.5; EPE first {np.nanmean(e0):.3f}/"
                f"{np.nanmedian(e0):.3f} refined {np.nanmean(e1):.3f}/"
                f"{np.nanmedian(e1):.3f}")  # fmt: skip
        if big.any():
            line += (f"; above 0.5: first {np.nanmean(e0[big]):.3f}/{np.nanmedian(e0[big]):.3f}"
                     f" refined {np.nanmean(e1[big]):.3f}/{np.nanmedian(e1[big]):.3f}")  # fmt: skip
        print(line, flush=True)


if __name__ == "__main__":
    if len(sys.argv) < 3 or sys.argv[1] not in ("pooled", "direct"):
        sys.exit("usage: python benchmarks/refine_steps.py pooled|direct DATASET...")
    main(sys.argv[1], sys.argv[2:])
