"""Probe: the refinement's error at the points it refines, against the truth.

For each dataset and frame pair, runs omniflow with ``iterations=1,
iterate_min_px=1.0`` (or the dense preset, ``--dense``), keeps the first-order
flow that :func:`omniflow.solve.refine.refine_moving` receives and scores, at the
points it refines (the fast ones), three answers against the truth: the first
step, the refinement as an increment pooled over neighbours that each moved by
their own first estimate (omniflow's form before stop 18, re-coded here for the
comparison) and omniflow's refinement. Prints cam1 / cam2 endpoint error mean /
median and the radial and tangential error's mean and spread in cam1, px per
frame. Run::

    python benchmarks/probe_refine.py /work/data/crossing /work/data/approach [--dense]
"""

from __future__ import annotations

import argparse

import numpy as np


def increment_form(a, b, conf, *, cam1, cam2, rig, x1, y1, x2, y2, theta, h1, h2, r, config,
                   make_solver, noise, pools=None):  # fmt: skip
    """The refinement of commit 0099986: fast points only, pooled increments."""
    from scipy.spatial import cKDTree

    from omniflow.solve import refine

    sel = refine.moving_far(a, b, h1, h2, config.iterate_min_px)
    radius = rig.cam1.r_m / 8.0 if config.pool_radius is None else config.pool_radius
    xy = np.column_stack([x1[sel], y1[sel]])
    near = cKDTree(xy).query_ball_point(xy, radius, return_length=True) - 1
    sel[np.flatnonzero(sel)[near < refine.MIN_NEIGHBOURS]] = False
    i = np.flatnonzero(sel)
    th, g1, g2 = theta[i], h1[i], h2[i]
    solve = make_solver(rig, config, x1[i], y1[i], th, g1, g2, r[i], noise)
    k = g2 / g1
    rows1 = refine._unit_rows(cam1, x1[i], y1[i], g1, a[i], th, b[i], config)
    rows2 = refine._unit_rows(cam2, x2[i], y2[i], g2, k * a[i], th, b[i], config)
    da, db, _ = solve(*rows1, *rows2)
    step = np.isfinite(da) & np.isfinite(db)
    a, b = a.copy(), b.copy()
    a[i] = np.where(step, a[i] + da, a[i])
    b[i] = np.where(step, b[i] + db, b[i])
    return a, b


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="+")
    parser.add_argument("--frames", default="0,1,2", help="first frames of the pairs")
    parser.add_argument("--dense", action="store_true", help="the dense preset")
    args = parser.parse_args()

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
        seen["call"] = (a, b, conf, kw)
        return original(a, b, conf, **kw)

    solve_mod.refine_moving = capture
    refined = OmniFlowConfig(iterations=1, iterate_min_px=1.0)
    config = OmniFlowConfig.dense() if args.dense else refined
    print(f"{'dense preset' if args.dense else 'iterations=1, iterate_min_px=1.0'}; "
          "EPE mean/median px; cam1 radial and tangential error mean (sd)")  # fmt: skip
    for directory in args.datasets:
        ds = open_dataset(directory)
        camera = camera_model(ds.meta)
        inputs = Inputs(ds, camera, auto_exposure=camera is not None and "camera" not in ds.meta)
        acc: dict[str, list] = {}
        for t in (int(v) for v in args.frames.split(",")):
            g1 = [inputs.grey(k, "cam1") for k in (t, t + 1)]
            g2 = [inputs.grey(k, "cam2") for k in (t, t + 1)]
            estimate(g1, g2, ds.rig, config)
            a, b, conf, kw = seen["call"]
            new_a, new_b, _, fast = original(a, b, conf, **kw)
            old_a, old_b = increment_form(a, b, conf, **kw)
            x1, y1, x2, y2, h1, h2 = (kw[c] for c in ("x1", "y1", "x2", "y2", "h1", "h2"))
            tr1 = sample_truth(ds.read_frame(t, "cam1"), x1, y1)
            tr2 = sample_truth(ds.read_frame(t, "cam2"), x2, y2)
            k = h2 / h1
            for name, (fa, fb) in (("first order", (a, b)), ("increment form", (old_a, old_b)),
                                   ("refined", (new_a, new_b))):  # fmt: skip
                er1 = fa - tr1["gt.flow.dh"]
                et1 = h1 * fb - tr1["gt.flow.hdtheta"]
                e2 = np.hypot(k * fa - tr2["gt.flow.dh"], h2 * fb - tr2["gt.flow.hdtheta"])
                ok = fast & (tr1["gt.flow.valid"] > 0.5) & (tr2["gt.flow.valid"] > 0.5)
                ok &= np.isfinite(er1 + et1 + e2)
                acc.setdefault(name, []).append((er1[ok], et1[ok], e2[ok]))
        name0 = ds.meta.get("scene", {}).get("name", directory)
        for name, parts in acc.items():
            er, et, e2 = (np.concatenate([p[j] for p in parts]) for j in range(3))
            if er.size == 0:
                print(f"{name0:20s} {name:15s} no refined points")
                continue
            e1 = np.hypot(er, et)
            print(f"{name0:20s} {name:15s} {er.size:5d} points: cam1 {e1.mean():.4f}/"
                  f"{np.median(e1):.4f} cam2 {e2.mean():.4f}/{np.median(e2):.4f} | radial "
                  f"{er.mean():+.4f} ({er.std():.4f}) tangential {et.mean():+.4f} "
                  f"({et.std():.4f})")  # fmt: skip


if __name__ == "__main__":
    main()
