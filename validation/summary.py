"""Pool per-frame errors into the summary (JSON) and the flat tables of the report.

Statistics are pooled over all points of all scored frame pairs (not means
of per-frame medians), so a frame with many points weighs more.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .metrics import flow_summary, stats, stereo_summary
from .runner import Results

__all__ = ["FORMAT", "flat_table", "jsonable", "summarize"]

FORMAT = "omnivalidate-summary/1"


def _concat(frames: Iterable[Mapping[str, NDArray]], keys: Iterable[str]) -> dict[str, NDArray]:
    frames = list(frames)
    return {
        k: np.concatenate([np.asarray(f[k]).ravel() for f in frames]) if frames else np.zeros(0)
        for k in keys
    }


_FLOW_KEYS = ("epe", "err_dh", "err_hdtheta", "ae", "speed", "noc", "range", "object")
_STEREO_KEYS = ("err_h2", "rel_r", "err_h", "range")


def pooled_flow(results: Results, method: str, points: str, cam: str) -> dict[str, NDArray] | None:
    frames = results.flow.get((method, points, cam))
    if not frames:
        return None
    out = _concat(frames, _FLOW_KEYS)
    out["noc"] = out["noc"].astype(bool)
    out["n_points"] = int(sum(int(f["n_points"]) for f in frames))
    return out


def _flow_block(results: Results, method: str, points: str) -> dict[str, Any]:
    out = {}
    names = results.dataset.get("objects", {})
    for cam in ("cam1", "cam2"):
        err = pooled_flow(results, method, points, cam)
        if err is None:
            continue
        s = flow_summary(err, err["noc"])
        s["n_points"] = err["n_points"]
        # Per object (gt.object, named as in dataset.json), e.g. a mover vs the static room.
        s["objects"] = {}
        ids = np.rint(err["object"]).astype(np.int64)
        every = {int(k) for k in names} | {int(i) for i in np.unique(ids)}
        for oid in sorted(every):
            sel = ids == oid
            sub = {k: v[sel] for k, v in err.items() if isinstance(v, np.ndarray)}
            block = flow_summary(sub, sub["noc"])
            del block["speed"]
            s["objects"][names.get(str(int(oid)), f"id{int(oid)}")] = block["all"]
        out[cam] = s
    return out


def _time_block(seconds: list[float]) -> dict[str, Any]:
    s = stats(seconds)
    return {"frames": s["n"], "median_s": s["median"], "mean_s": s["mean"]}


def _derived_block(records: list[dict[str, Any]]) -> dict[str, Any]:
    if not records:
        return {}
    dr_err = np.concatenate([r["dr_err"] for r in records])
    dr_true = np.concatenate([r["dr_true"] for r in records])
    ttc = np.concatenate([r["ttc_relerr"] for r in records])
    out: dict[str, Any] = {
        "dr_dt_abs_error_m_per_frame": stats(dr_err),
        "dr_dt_true_abs_m_per_frame": stats(np.abs(dr_true)),
        "ttc_relative_error": stats(ttc),
        "ttc_objects": [],
        "odometry": [],
    }
    for r in records:
        for oid, (true, est, n) in r.get("ttc_objects", {}).items():
            out["ttc_objects"].append(
                {
                    "frame": r["frame"],
                    "object": oid,
                    "n": n,
                    "ttc_true_frames": true,
                    "ttc_est_frames": est,
                }
            )
        if "robot_est" in r:
            out["odometry"].append(
                {"frame": r["frame"], "true": r["robot_true"], "est": r["robot_est"]}
            )
    for label in ("both", "tangential"):
        w = [r[f"odo_{label}_w_err"] for r in records if f"odo_{label}_w_err" in r]
        v = [r[f"odo_{label}_v_err"] for r in records if f"odo_{label}_v_err" in r]
        out[f"odometry_{label}"] = {
            "yaw_rate_abs_error_rad_per_frame": stats(w),
            "velocity_abs_error_m_per_frame": stats(v),
        }
    speeds = [r["robot_true"]["speed"] for r in records]
    yaws = [abs(r["robot_true"]["w"]) for r in records]
    out["robot_true"] = {
        "speed_m_per_frame": stats(speeds),
        "abs_yaw_rate_rad_per_frame": stats(yaws),
    }
    return out


def summarize(results: Results) -> dict[str, Any]:
    """The summary as a JSON-able dict (NaN written as null by :func:`jsonable`)."""
    methods = []
    default = next((m.name for m in results.methods if m.kind == "omniflow"), None)
    for m in results.methods:
        if m.kind == "omniflow":
            frames = results.stereo.get(m.name, [])
            counts = results.stereo_counts.get(m.name, {})
            err = _concat(frames, _STEREO_KEYS)
            stereo = (
                stereo_summary(
                    err,
                    n_matched=counts.get("matched", 0),
                    n_significant_valid=(
                        None
                        if counts.get("significant_unknown")
                        else counts.get("significant_valid", 0)
                    ),
                    n_valid_pixels=counts.get("valid_pixels", 0),
                )
                if frames
                else {}
            )
            same = {}
            for (meth, pts, cam), _ in results.flow.items():
                if pts == f"@{m.name}":
                    e = pooled_flow(results, meth, pts, cam)
                    same.setdefault(meth, {})[cam] = flow_summary(e, e["noc"])["all"]["epe"]
            methods.append(
                {
                    "name": m.name,
                    "kind": "omniflow",
                    "default": m.default,
                    "paper": m.paper,
                    "config": m.config,
                    "points": "own",
                    "time_per_frame": _time_block(results.times.get(m.name, [])),
                    "stage_seconds_total": dict(results.stages.get(m.name, {})),
                    "flow": _flow_block(results, m.name, "own"),
                    "stereo": stereo,
                    "derived": _derived_block(results.derived.get(m.name, [])),
                    "baselines_at_same_points": same,
                }
            )
        else:
            for pts in ("omniflow points", "dense"):
                flow = _flow_block(results, m.name, pts)
                if not flow:
                    continue
                methods.append(
                    {
                        "name": m.name,
                        "kind": "baseline",
                        "points": pts,
                        "points_of": default if pts == "omniflow points" else None,
                        "time_per_frame": _time_block(results.times.get(m.name, [])),
                        "flow": flow,
                    }
                )
    return {
        "format": FORMAT,
        "dataset": results.dataset,
        "units": {
            "flow": "pixels per frame interval; omniflow's velocities (per frame) are compared "
            "with the true displacement of each material point from frame t to t + 1",
            "angular_error": "degrees (Barron et al.: angle between (dx, dy, 1) vectors)",
            "stereo": "err_h2 px; rel_r = |r - r_gt| / r_gt; err_h metres",
            "derived": "dr/dt m per frame; time to contact in frames; odometry rad and m per frame",
            "time": "seconds per frame pair, both cameras, wall clock, same run",
        },
        "methods": methods,
        "notes": list(results.notes),
    }


def find_method(summary: Mapping[str, Any], name: str, points: str | None = None) -> dict:
    """The summary entry of a method (``points`` to pick a baseline's point set)."""
    for m in summary["methods"]:
        if m["name"] == name and (points is None or m["points"] == points):
            return m
    raise KeyError(f"no method {name!r}" + (f" at points {points!r}" if points else ""))


def get_path(entry: Mapping[str, Any], path: str) -> Any:
    """Value at a dotted path, e.g. ``flow.cam1.noc.epe.median`` (KeyError names it)."""
    cur: Any = entry
    for part in path.split("."):
        if isinstance(cur, Mapping) and part in cur:
            cur = cur[part]
        else:
            raise KeyError(f"{path!r}: no key {part!r}")
    return cur


def _num(v: Any) -> float:
    return math.nan if v is None else float(v)


def flat_table(summary: Mapping[str, Any]) -> list[dict[str, Any]]:
    """One flat row per method and point set: the side-by-side table of the report."""
    rows = []
    for m in summary["methods"]:
        row: dict[str, Any] = {
            "method": m["name"],
            "points": m["points"] if m["kind"] == "baseline" else "own",
        }
        for cam in ("cam1", "cam2"):
            f = m["flow"].get(cam)
            if f is None:
                continue
            row[f"{cam}_n"] = f["all"]["n"]
            row[f"{cam}_epe_median"] = f["all"]["epe"]["median"]
            row[f"{cam}_epe_mean"] = f["all"]["epe"]["mean"]
            row[f"{cam}_noc_epe_median"] = f["noc"]["epe"]["median"]
            row[f"{cam}_occ_epe_median"] = f["occ"]["epe"]["median"]
            row[f"{cam}_dh_median"] = f["all"]["dh"]["median"]
            row[f"{cam}_hdtheta_median"] = f["all"]["hdtheta"]["median"]
            row[f"{cam}_ae_median"] = f["all"]["ae"]["median"]
            row[f"{cam}_out1"] = f["all"]["out1"]
            row[f"{cam}_out3"] = f["all"]["out3"]
        st = m.get("stereo") or {}
        if st:
            row["stereo_outliers"] = st["all"]["outliers"]
            row["rel_r_median"] = st["all"]["rel_r"]["median"]
            row["err_h_median"] = st["all"]["err_h"]["median"]
            row["match_rate"] = st["match_rate"]
            row["density"] = st["density"]
        same = m.get("baselines_at_same_points") or {}
        if "DIS-medium" in same and "cam1" in same["DIS-medium"]:
            row["dis_same_points_cam1_epe_median"] = same["DIS-medium"]["cam1"]["median"]
        row["time_ms"] = 1000 * _num(m["time_per_frame"]["median_s"])
        rows.append(row)
    return rows


def jsonable(obj: Any) -> Any:
    """Replace NaN/inf by None and numpy scalars by Python numbers, recursively."""
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj
