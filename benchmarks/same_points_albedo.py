"""Omniflow's flow at the same stereo matches on the lit images and on their albedo copy.

The matches omniflow finds on the lit dataset (frame pairs 0-2, ``BASE`` configuration:
``default`` or ``dense``) are given to ``estimate(..., matches=...)`` on the shading-free
copy made by benchmarks/albedo_dataset.py (same geometry, same truth), so the two
flows differ only by the lighting. Per camera and moving object: points, mean radial
(dh) and tangential (h dtheta) flow, lit / albedo / truth (px per frame), and the
relative error of the mean flow vector on each. Usage::

    python benchmarks/same_points_albedo.py LIT_DATASET ALBEDO_DATASET [BASE]
"""

from __future__ import annotations

import math
import sys
from collections import defaultdict

import numpy as np


def main(lit_dir: str, albedo_dir: str, base: str = "default") -> None:
    from omniflow.config import OmniFlowConfig
    from omniflow.io.dataset import open_dataset
    from omniflow.matching import Matches
    from omniflow.pipeline import estimate
    from validation.inputs import Inputs, camera_model
    from validation.sampling import sample_truth
    from validation.scoring_derived import moving_objects
    from validation.scoring_flow import omniflow_points

    lit, alb = open_dataset(lit_dir), open_dataset(albedo_dir)
    cfg = OmniFlowConfig.dense() if base == "dense" else OmniFlowConfig()
    ins = {name: Inputs(ds, camera_model(ds.meta)) for name, ds in (("lit", lit), ("alb", alb))}
    movers = moving_objects(lit.meta)
    acc: dict = defaultdict(list)
    for t in (0, 1, 2):

        def grey(name, cam, t=t):
            return [ins[name].grey(k, cam) for k in (t, t + 1)]

        a = estimate(grey("lit", "cam1"), grey("lit", "cam2"), lit.rig, cfg).columns
        m = Matches.from_polar(lit.rig, a["theta"], a["h1"], a["h2"])
        b = estimate(grey("alb", "cam1"), grey("alb", "cam2"), lit.rig, cfg, matches=m).columns
        for cam in ("cam1", "cam2"):
            xa, ya, ea = omniflow_points(a, cam)
            xb, yb, eb = omniflow_points(b, cam)
            kb = {xy: i for i, xy in enumerate(zip(xb.tolist(), yb.tolist(), strict=True))}
            ia = [i for i, xy in enumerate(zip(xa.tolist(), ya.tolist(), strict=True)) if xy in kb]
            ib = [kb[(xa[i], ya[i])] for i in ia]
            ia, ib = np.array(ia, dtype=int), np.array(ib, dtype=int)
            tr = sample_truth(lit.read_frame(t, cam), xa[ia], ya[ia])
            ok = tr["bilinear_ok"] & (tr["gt.valid"] > 0.5)
            obj = np.rint(tr["gt.object"]).astype(int)
            for oid in movers:
                s = ok & (obj == oid)
                acc[(cam, lit.objects.get(oid, str(oid)))].append(np.stack([
                    ea["dh"][ia][s], ea["hdtheta"][ia][s], eb["dh"][ib][s], eb["hdtheta"][ib][s],
                    tr["gt.flow.dh"][s], tr["gt.flow.hdtheta"][s]]))  # fmt: skip
    print(f"{base}: mean dh, h dtheta (px/frame) lit / albedo / truth at the lit run's matches")
    for (cam, name), parts in sorted(acc.items()):
        v = np.concatenate(parts, axis=1)
        if v.shape[1] == 0:
            continue
        mu = v.mean(axis=1)
        true = math.hypot(mu[4], mu[5])
        e_lit = math.hypot(mu[0] - mu[4], mu[1] - mu[5]) / true
        e_alb = math.hypot(mu[2] - mu[4], mu[3] - mu[5]) / true
        print(f"{cam} {name:8s} n {v.shape[1]:4d}  dh {mu[0]:+.3f} / {mu[2]:+.3f} / {mu[4]:+.3f}"
              f"  h dtheta {mu[1]:+.3f} / {mu[3]:+.3f} / {mu[5]:+.3f}"
              f"  vector error lit {100 * e_lit:5.1f} %  albedo {100 * e_alb:5.1f} %")  # fmt: skip


if __name__ == "__main__":
    main(*sys.argv[1:])
