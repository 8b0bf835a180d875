"""Derived quantities against the known motion in dataset.json: dr/dt, time to contact
(failures counted), odometry; which objects move."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .metrics import stats
from .motion import point_motion, robot_motion
from .results import Results
from .sampling import sample_truth
from .scoring_stereo import STEREO_TRUTH

__all__ = ["ODOMETRY_POINTS", "meta_poses", "moving_objects", "score_derived", "ttc_scores"]


#: At most this many matched points (a fixed random subset) go into the odometry fit.
ODOMETRY_POINTS = 2000


def meta_poses(meta: dict[str, Any]) -> tuple[list | None, dict[int, list]]:
    robot = meta.get("robot", {}).get("poses") if isinstance(meta.get("robot"), dict) else None
    objects = {}
    for obj in meta.get("objects", []) or []:
        if isinstance(obj, dict) and "poses" in obj and "id" in obj:
            objects[int(obj["id"])] = obj["poses"]
    return robot, objects


def moving_objects(meta: dict[str, Any]) -> list[int]:
    """Ids of the objects whose pose changes over the dataset's frames."""
    _, objects = meta_poses(meta)
    out = []
    for oid, poses in objects.items():
        p = np.asarray(poses, np.float64)
        if p.ndim == 3 and len(p) > 1 and np.abs(p - p[0]).max() > 1e-9:
            out.append(int(oid))
    return sorted(out)


def score_derived(
    results: Results,
    name: str,
    cols: dict,
    truth: dict[str, NDArray],
    t: int,
    robot_poses: list | None,
    object_poses: dict[int, list],
) -> dict[str, Any]:
    """dr/dt and time to contact against the objects' known motion; odometry vs the robot's."""
    if robot_poses is None or len(robot_poses) <= t + 1:
        return {}
    x = np.asarray(cols["x"], np.float64)
    y = np.asarray(cols["y"], np.float64)
    tr = sample_truth(truth, x, y, channels=STEREO_TRUTH)
    has = tr["bilinear_ok"] & np.isfinite(np.asarray(cols["dr_dt"], np.float64))
    world = np.stack([tr["gt.X"], tr["gt.Y"], tr["gt.Z"]], axis=1)[has]
    ids = np.rint(tr["gt.object"][has]).astype(np.int64)
    poses_t = {k: v[t] for k, v in object_poses.items() if len(v) > t + 1}
    poses_t1 = {k: v[t + 1] for k, v in object_poses.items() if len(v) > t + 1}
    mot = point_motion(world, ids, poses_t, poses_t1, robot_poses[t], robot_poses[t + 1])
    dr_est = np.asarray(cols["dr_dt"], np.float64)[has]
    r_est = np.asarray(cols["r"], np.float64)[has]
    # Time to contact of approaching points (true dr/dt below -0.1 % of r per frame).
    approaching = mot["dr_dt"] < -1e-3 * mot["r0"]
    ttc_est = _time_to_contact(r_est, dr_est)
    rec: dict[str, Any] = {
        "frame": t,
        "dr_err": np.abs(dr_est - mot["dr_dt"]),
        "dr_est": dr_est,
        "dr_true": mot["dr_dt"],
        "ids": ids,
        "approaching": approaching,
        "ttc_est": ttc_est,
        "ttc_true": mot["ttc"],
    }
    # Odometry: robust fit of the robot's yaw rate and velocity to all matched points.
    truth_motion = robot_motion(robot_poses[t], robot_poses[t + 1])
    rec["robot_true"] = truth_motion
    fits = _odometry(cols)
    if fits is not None:
        rec["robot_est"] = fits
        for label, fit in fits.items():
            rec[f"odo_{label}_w_err"] = abs(fit["w"] - truth_motion["w"])
            rec[f"odo_{label}_v_err"] = math.hypot(
                fit["vx"] - truth_motion["vx"], fit["vy"] - truth_motion["vy"]
            )
    results.derived[name].append(rec)
    ttc = ttc_scores(ttc_est[approaching], mot["ttc"][approaching])
    out = {
        "drdt_err_median": stats(rec["dr_err"])["median"],
        "ttc_n": ttc["n"],
        "ttc_failure_share": ttc["failure_share"],
        "ttc_relerr_median": ttc["median"],
    }
    for key in ("odo_both_w_err", "odo_both_v_err", "odo_tangential_w_err", "odo_tangential_v_err"):
        if key in rec:
            out[key] = rec[key]
    return out


def ttc_scores(est: NDArray, true: NDArray) -> dict[str, float]:
    """Time to contact of approaching points, failures counted.

    A point that truly approaches but is estimated as keeping its range or
    receding (``est`` infinite, NaN or not positive) is a **failure**; its
    relative error counts as infinite, so ``median`` is over ALL approaching
    points and cannot be improved by giving up on hard points.
    ``median_of_successes`` is the median over the finite estimates only.
    """
    est = np.asarray(est, np.float64)
    true = np.asarray(true, np.float64)
    failed = ~(np.isfinite(est) & (est > 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(failed, np.inf, np.abs(est - true) / true)
    n = int(est.size)
    return {
        "n": n,
        "failures": int(failed.sum()),
        "failure_share": float(failed.mean()) if n else math.nan,
        "median": float(np.median(rel)) if n else math.nan,
        "median_of_successes": stats(rel[~failed])["median"],
        "true_median_frames": float(np.median(true)) if n else math.nan,
        "est_median_frames": float(np.median(np.where(failed, np.inf, est))) if n else math.nan,
    }


def _time_to_contact(r: NDArray, dr_dt: NDArray) -> NDArray:
    from omniflow.applications.navigation import time_to_contact

    return np.asarray(time_to_contact(r, dr_dt), dtype=np.float64)


def _odometry(cols: dict) -> dict[str, dict[str, float]] | None:
    """omniflow.applications.navigation.odometry on all matched points: both flow components,
    and the bearing rates alone (omni flow's radial component is the noisier one)."""
    from omniflow.applications.navigation import odometry

    theta = np.asarray(cols["theta"], np.float64)
    r = np.asarray(cols["r"], np.float64)
    dr = np.asarray(cols["dr_dt"], np.float64)
    dth = np.asarray(cols["dtheta_dt"], np.float64)
    ok = np.isfinite(theta) & np.isfinite(r) & np.isfinite(dr) & np.isfinite(dth) & (r > 0)
    if ok.sum() < 10:
        return None
    if ok.sum() > ODOMETRY_POINTS:  # a fixed random subset keeps the robust fit fast
        keep = np.random.default_rng(0).choice(np.flatnonzero(ok), ODOMETRY_POINTS, replace=False)
        ok = np.zeros_like(ok)
        ok[keep] = True
    out = {}
    for label, radial in (("both", dr[ok]), ("tangential", None)):
        fit = odometry(theta[ok], r[ok], dth[ok], radial)
        out[label] = {
            "w": float(fit.w),
            "vx": float(fit.V_x),
            "vy": float(fit.V_y),
            "inliers": float(fit.inlier_fraction),
        }
    return out
