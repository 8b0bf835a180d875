"""Probe: omniflow.solve.monocular's choices on a dataset, against the truth, per object.

The crossing pillar gets no stereo match because cam2 sees 3 % of it, at its
rim (docs/measurements.md, "The crossing pillar"). This runs
:func:`omniflow.solve.monocular.monocular_flow` (cam1's eq. (9) alone, pooled) with
its block size (``--step``), gradient percentile (``--percentile``) and gap
(``--gap``) set, optionally followed by ``--iterations`` Gauss-Newton steps
(as ``iterations`` does for the stereo solve; not in omniflow). Prints, per
frame pair and per object, the points and the mean radial and tangential
flow against the truth. Run::

    python benchmarks/probe_monocular.py /work/data/crossing --frames 0,1,2 --iterations 1
"""

from __future__ import annotations

import argparse

import numpy as np


def probe(directory: str, t: int, args: argparse.Namespace) -> None:
    from omniflow.config import OmniFlowConfig
    from omniflow.fit.sampling import sample_fine, sample_polar_grad
    from omniflow.fit.series import choose_flow_band, unit_frames
    from omniflow.io.dataset import open_dataset
    from omniflow.pipeline import _unit_series, estimate
    from omniflow.solve import monocular as mono
    from omniflow.solve.pooled import neighbourhoods, pooled_solution
    from validation.inputs import Inputs, camera_model
    from validation.sampling import sample_truth

    ds = open_dataset(directory)
    rig, unit = ds.rig, ds.rig.cam1
    camera = camera_model(ds.meta)
    inputs = Inputs(ds, camera, auto_exposure=camera is not None and "camera" not in ds.meta)
    g1 = [inputs.grey(k, "cam1") for k in (t, t + 1)]
    g2 = [inputs.grey(k, "cam2") for k in (t, t + 1)]
    cfg = OmniFlowConfig()
    stereo = estimate(g1, g2, rig, cfg).columns
    (s1, f1), (s2, f2) = (
        _unit_series(g, 0, u, cfg, "probe") for g, u in ((g1, rig.cam1), (g2, rig.cam2))
    )
    cam = unit_frames(f1, unit, cfg, choose_flow_band((f1, f2), (s1, s2), cfg))

    mono.BLOCK, mono.PERCENTILE = args.step, args.percentile
    cfg = OmniFlowConfig(monocular_gap=args.gap)
    m = mono.monocular_flow(cam, unit, cfg, stereo["x"], stereo["y"])
    x, y, h1, theta, a, b = (m[k] for k in ("x", "y", "h1", "theta", "dh1_dt", "dtheta_dt"))
    radius = unit.r_m / 8.0
    idx, w = neighbourhoods(x, y, k=cfg.pool_k, radius=radius, r=None, range_tol=None)
    zero = np.zeros_like(x)
    for _ in range(args.iterations):  # as solve.py's iterations, cam1 alone, same pools
        xd, yd = unit.pixel_of_polar(h1 + a, theta + b)
        g_h, g_th = sample_polar_grad(cam["b"], xd, yd, cfg.sampling)
        a_h, a_th = sample_polar_grad(cam["af"], x, y, cfg.sampling)
        res = sample_fine(cam["b"], xd, yd, cfg.sampling)
        res = res - sample_fine(cam["af"], x, y, cfg.sampling)
        da, db, _ = pooled_solution(
            0.5 * (g_h + a_h), 0.5 * (g_th + a_th), res, zero, zero, zero, h1, h1, idx, w,
            theta=theta, model=cfg.pool_model, scale=radius, min_conditioning=1e-3,
        )  # fmt: skip
        a, b = a + np.nan_to_num(da), b + np.nan_to_num(db)

    truth = sample_truth(ds.read_frame(t, "cam1"), x, y)
    ok = truth["bilinear_ok"] & (truth["gt.valid"] > 0.5) & np.isfinite(a) & np.isfinite(b)
    obj = np.rint(truth["gt.object"]).astype(int)
    print(f"{ds.meta.get('scene', {}).get('name', directory)} pair {t}: {len(stereo['x'])} stereo "
          f"matches, {x.size} cam1-only points, iterations {args.iterations}")  # fmt: skip
    print(f"  {'object':16s} {'n':>5s} {'dh est':>8s} {'dh true':>8s} {'h dtheta est':>12s} "
          f"{'true':>8s}  (px/frame, means)")  # fmt: skip
    for i in np.unique(obj[ok]):
        m = ok & (obj == i)
        print(f"  {ds.objects.get(int(i), str(i)):16s} {m.sum():5d} {a[m].mean():+8.3f} "
              f"{truth['gt.flow.dh'][m].mean():+8.3f} {(h1 * b)[m].mean():+12.3f} "
              f"{truth['gt.flow.hdtheta'][m].mean():+8.3f}")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("--frames", default="0", help="first frames t, comma-separated")
    parser.add_argument("--percentile", type=float, default=70.0)
    parser.add_argument("--gap", type=float, default=24.0, help="px from any stereo match")
    parser.add_argument("--step", type=int, default=4, help="block size, px")
    parser.add_argument("--iterations", type=int, default=0)
    args = parser.parse_args()
    for t in (int(v) for v in args.frames.split(",")):
        probe(args.dataset, t, args)


if __name__ == "__main__":
    main()
