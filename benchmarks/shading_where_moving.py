"""Probe: flow_shading only at the points odometry calls independently moving (not in omniflow).

Why: on a static scene lit by static lights the shading is attached to the surface
(Lambertian), so brightness constancy holds and flattening the shading
(``flow_shading``) only removes signal; on an object that turns under those lights the
shading stays put while the texture moves, and flattening is what brings the rolling
ball's radial flow to the truth (docs/measurements.md, "Movers: decoupled radial
flow"). Odometry's outliers (omniflow.applications.navigation.odometry on the default run's flow,
the points whose motion the robot's own does not explain) are a trigger that sees
every independent mover, turning or not, and few static points.

Runs estimate() on frame pairs of a dataset with ``BASE`` (``default`` or ``dense``) and
with ``flow_shading=SIGMA`` added (same matches: the matcher reads the frames as
given), takes the flattened run's flow where the base run's odometry rejects a point
and the base run's elsewhere ("mixed"), and prints, per camera, the EPE of the three
and each object's mean radial (dh) and tangential (h dtheta) flow against the truth.
Run::

    python benchmarks/shading_where_moving.py DATASET [SIGMA] [BASE] [PAIRS] [TRIGGER]
    python benchmarks/shading_where_moving.py /work/data/independent_movers 8 default 0-2

TRIGGER ``outliers`` (default): every point odometry rejects; ``groups[:N]``: only the
points of the groups the command's ``--auto-regions`` would find (residual > 4 x the
inlier threshold, own speed > 1e-4 m/frame, linked within r_m / 10 px, own velocities
within 0.5 x, groups of at least N points, default 20); ``clusters[:N]``: odometry's
outliers linked within r_m / 10 px into groups of at least N points (no residual,
speed or coherence test).
"""

from __future__ import annotations

import sys
from collections import defaultdict

import numpy as np

FLOW = ("dh1_dt", "dtheta_dt", "dh2_dt", "dx", "dy", "dx2", "dy2")


def mixed_columns(plain: dict, shaded: dict, moving: np.ndarray) -> dict:
    """The shaded run's flow at ``moving`` points, the plain run's elsewhere."""
    out = dict(plain)
    for k in FLOW:
        out[k] = np.where(moving, shaded[k], plain[k])
    return out


def common_points(a: dict, b: dict) -> tuple[dict, dict]:
    """Both runs' columns at the points both have (the matches can differ in a few)."""
    ka = {(x, y): i for i, (x, y) in enumerate(zip(a["x"], a["y"], strict=True))}
    kb = {(x, y): i for i, (x, y) in enumerate(zip(b["x"], b["y"], strict=True))}
    both = [k for k in ka if k in kb]
    ia = np.array([ka[k] for k in both], dtype=int)
    ib = np.array([kb[k] for k in both], dtype=int)
    return {k: v[ia] for k, v in a.items()}, {k: v[ib] for k, v in b.items()}


def main(directory: str, sigma: float, base: str, pairs: list[int], trigger: str) -> None:
    from omniflow.applications.navigation import odometry
    from omniflow.applications.regions import auto_groups
    from omniflow.config import OmniFlowConfig
    from omniflow.io.dataset import open_dataset
    from omniflow.pipeline import estimate
    from validation.inputs import Inputs, camera_model
    from validation.sampling import sample_truth
    from validation.scoring_flow import omniflow_points

    ds = open_dataset(directory)
    camera = camera_model(ds.meta)
    inputs = Inputs(ds, camera, auto_exposure=camera is not None and "camera" not in ds.meta)
    cfg = OmniFlowConfig.dense() if base == "dense" else OmniFlowConfig()
    cfg_s = (
        OmniFlowConfig.dense(flow_shading=sigma)
        if base == "dense"
        else OmniFlowConfig(flow_shading=sigma)
    )
    epe: dict[tuple, list] = defaultdict(list)
    per_object: dict[tuple, list] = defaultdict(list)
    for t in pairs:
        g1 = [inputs.grey(k, "cam1") for k in (t, t + 1)]
        g2 = [inputs.grey(k, "cam2") for k in (t, t + 1)]
        plain = estimate(g1, g2, ds.rig, cfg).columns
        shaded = estimate(g1, g2, ds.rig, cfg_s).columns
        plain, shaded = common_points(plain, shaded)
        fit = odometry(plain["theta"], plain["r"], plain["dtheta_dt"], plain["dr_dt"])
        moving = ~fit.inliers
        if trigger.startswith("groups"):  # the command's --auto-regions rule and defaults
            own = fit.own_velocity(plain["theta"], plain["r"], plain["dr_dt"], plain["dtheta_dt"])
            with np.errstate(invalid="ignore"):
                moving &= fit.residuals > 4.0 * fit.threshold
                moving &= np.hypot(own[:, 0], own[:, 1]) > 1e-4
            moving = auto_groups(plain["x"], plain["y"], moving, link=ds.rig.cam1.r_m / 10,
                                 min_points=int(trigger.partition(":")[2] or 20), velocity=own,
                                 coherence=0.5) > 0  # fmt: skip
        elif trigger.startswith("clusters"):  # odometry's outliers in groups, nothing more
            moving = auto_groups(plain["x"], plain["y"], moving, link=ds.rig.cam1.r_m / 10,
                                 min_points=int(trigger.partition(":")[2] or 20)) > 0  # fmt: skip
        runs = {"plain": plain, "mixed": mixed_columns(plain, shaded, moving), "shaded": shaded}
        for cam in ("cam1", "cam2"):
            x, y, _ = omniflow_points(plain, cam)
            truth = sample_truth(ds.read_frame(t, cam), x, y)
            ok = truth["bilinear_ok"] & (truth["gt.valid"] > 0.5)
            obj = np.rint(truth["gt.object"]).astype(int)
            t_dh, t_ht = truth["gt.flow.dh"], truth["gt.flow.hdtheta"]
            for name, c in runs.items():
                _, _, est = omniflow_points(c, cam)
                e = np.hypot(est["dh"] - t_dh, est["hdtheta"] - t_ht)
                epe[(cam, name)].append(e[ok & np.isfinite(e)])
                for i in np.unique(obj[ok]):
                    m = ok & (obj == i) & np.isfinite(e)
                    row = (est["dh"][m], t_dh[m], est["hdtheta"][m], t_ht[m], moving[m])
                    per_object[(cam, ds.objects.get(int(i), str(i)), name)].append(row)
        print(f"pair {t}: {moving.sum()} of {moving.size} points flattened", flush=True)
    for (cam, name), parts in sorted(epe.items()):
        e = np.concatenate(parts)
        print(f"{cam} {name:7s} EPE mean / median {e.mean():.4f} / {np.median(e):.4f} px")
    print("cam  object        run     points moving  dh est / true   h dtheta est / true  (px)")
    for (cam, obj_name, name), rows in sorted(per_object.items()):
        est, tru, tan, ttan, mov = (np.concatenate(col) for col in zip(*rows, strict=True))
        print(f"{cam} {obj_name:13s} {name:7s} {est.size:6d} {mov.sum():6d}  {est.mean():+.3f} / "
              f"{tru.mean():+.3f}   {tan.mean():+.3f} / {ttan.mean():+.3f}")  # fmt: skip


if __name__ == "__main__":
    a = sys.argv[1:]
    lo, _, hi = (a[3] if len(a) > 3 else "0-2").partition("-")
    main(a[0], float(a[1]) if len(a) > 1 else 8.0, a[2] if len(a) > 2 else "default",
         list(range(int(lo), int(hi or lo) + 1)), a[4] if len(a) > 4 else "outliers")  # fmt: skip
