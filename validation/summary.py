"""Pool per-frame errors into the summary (JSON) and the flat tables of the report.

Statistics are pooled over all points of all scored frame pairs (not means
of per-frame medians), so a frame with many points weighs more.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from omniflow.io.jsonio import jsonable

from .calibration_sigma import calibration
from .metrics import flow_summary, protocol_splits, stats, stereo_summary
from .results import Results
from .scoring_flags import FLAG_SETS, flag_counts

__all__ = ["FORMAT", "flat_table", "headline", "summarize", "sweep_rows"]

FORMAT = "omnivalidate-summary/1"


def _concat(frames: Iterable[Mapping[str, NDArray]], keys: Iterable[str]) -> dict[str, NDArray]:
    frames = list(frames)
    return {
        k: np.concatenate([np.asarray(f[k]).ravel() for f in frames]) if frames else np.zeros(0)
        for k in keys
    }


_FLOW_KEYS = ("epe", "err_dh", "err_hdtheta", "ae", "speed", "noc", "range", "object",
              "gt_dh", "gt_hdtheta", "est_dh", "est_hdtheta")  # fmt: skip
_STEREO_KEYS = ("err_h2", "rel_r", "err_h", "range")


def pooled_flow(results: Results, method: str, points: str, cam: str) -> dict[str, NDArray] | None:
    frames = results.flow.get((method, points, cam))
    if not frames:
        return None
    out = _concat(frames, _FLOW_KEYS)
    out["noc"] = out["noc"].astype(bool)
    out["outside"] = np.concatenate(
        [np.asarray(f.get("outside", np.zeros(np.size(f["epe"]), bool))).ravel() for f in frames]
    ).astype(bool)
    for key in ("n_points", "n_valid_pixels", "n_stereo_pixels"):
        out[key] = int(sum(int(f.get(key, 0)) for f in frames))
    out["n_frames"] = len(frames)
    pix: dict[int, int] = defaultdict(int)
    for f in frames:
        for oid, c in f.get("object_pixels", {}).items():
            pix[int(oid)] += int(c)
    out["object_pixels"] = dict(pix)
    return out


def _share(n: float, d: float) -> float:
    return n / d if d else math.nan


def _flow_block(results: Results, method: str, points: str) -> dict[str, Any]:
    out = {}
    names = results.dataset.get("objects", {})
    for cam in ("cam1", "cam2"):
        err = pooled_flow(results, method, points, cam)
        if err is None:
            continue
        s = flow_summary(err, err["noc"])
        s["n_points"] = err["n_points"]
        n = s["all"]["n"]
        s["density"] = {
            "points_per_frame": _share(n, err["n_frames"]),
            "of_valid_pixels": _share(n, err["n_valid_pixels"]),
            "of_stereo_pixels": _share(n, err["n_stereo_pixels"]),
            "valid_pixels_per_frame": _share(err["n_valid_pixels"], err["n_frames"]),
            "stereo_pixels_per_frame": _share(err["n_stereo_pixels"], err["n_frames"]),
        }
        # Per object (gt.object, named as in dataset.json), e.g. a mover vs the static room;
        # every object of the dataset is listed, with n = 0 where the method scored none.
        s["objects"] = {}
        ids = np.rint(err["object"]).astype(np.int64)
        every = {int(k) for k in names} | {int(i) for i in np.unique(ids)}
        for oid in sorted(every):
            sel = ids == oid
            sub = {k: v[sel] for k, v in err.items() if isinstance(v, np.ndarray)}
            block = flow_summary(sub, sub["noc"])["all"]
            pixels = err["object_pixels"].get(oid, 0)
            block["id"] = oid
            block["valid_pixels"] = pixels
            block["density"] = _share(block["n"], pixels)
            s["objects"][names.get(str(int(oid)), f"id{int(oid)}")] = block
        out[cam] = s
    return out


def protocol_block(results: Results, method: str, points: str) -> dict[str, Any]:
    """The benchmark protocol (:func:`validation.metrics.protocol_splits`) over both
    cameras' points pooled, with ``density``: the points scored per valid pixel."""
    errs = [e for cam in ("cam1", "cam2") if (e := pooled_flow(results, method, points, cam))]
    if not errs:
        return {}
    keys = ("epe", "speed", "noc", "outside", "range", "object")
    both = {k: np.concatenate([e[k] for e in errs]) for k in keys}
    out = protocol_splits(both, moving=results.dataset.get("moving_objects", []))
    out["density"] = _share(out["all"]["n"], sum(e["n_valid_pixels"] for e in errs))
    return out


def _same_points(results: Results, points: str) -> dict[str, dict[str, Any]]:
    """EPE of each baseline scored at one row's points (``points`` key), per camera."""
    same: dict[str, dict[str, Any]] = {}
    for meth, pts, cam in results.flow:
        if pts == points:
            e = pooled_flow(results, meth, pts, cam)
            same.setdefault(meth, {})[cam] = flow_summary(e, e["noc"])["all"]["epe"]
    return same


def _flags_block(results: Results, method: str) -> dict[str, Any]:
    """A row's eq. (14) flag (:mod:`validation.scoring_flags`): the counts, the flag's
    precision and recall against the truth, and the flow and protocol of the flagged
    and the unflagged points apart."""
    out: dict[str, Any] = flag_counts(results.flags[method])
    out["flow"] = {label: _flow_block(results, method, label) for label in FLAG_SETS}
    out["protocol"] = {label: protocol_block(results, method, label) for label in FLAG_SETS}
    return out


def _time_block(seconds: list[float]) -> dict[str, Any]:
    s = stats(seconds)
    return {"frames": s["n"], "median_s": s["median"], "mean_s": s["mean"]}


def _derived_block(
    records: list[dict[str, Any]], names: Mapping[str, str], moving: Iterable[int]
) -> dict[str, Any]:
    if not records:
        return {}
    from .scoring_derived import ttc_scores

    cat = _concat(records, ("dr_err", "dr_est", "dr_true", "ids", "approaching", "ttc_est",
                            "ttc_true"))  # fmt: skip
    appr = cat["approaching"].astype(bool)
    ids = cat["ids"].astype(np.int64)
    out: dict[str, Any] = {
        "dr_dt_abs_error_m_per_frame": stats(cat["dr_err"]),
        "dr_dt_true_abs_m_per_frame": stats(np.abs(cat["dr_true"])),
        "ttc_relative_error": ttc_scores(cat["ttc_est"][appr], cat["ttc_true"][appr]),
        "objects": {},
        "odometry": [],
    }
    # Each moving object's own motion, recovered: mean dr/dt and time to contact of its
    # points (every moving object listed, n = 0 where the method scored none of it).
    for oid in sorted(set(int(i) for i in moving)):
        sel = ids == oid
        sa = sel & appr
        out["objects"][names.get(str(oid), f"id{oid}")] = {
            "id": oid,
            "n": int(sel.sum()),
            "dr_dt_est_mean_m_per_frame": stats(cat["dr_est"][sel])["mean"],
            "dr_dt_true_mean_m_per_frame": stats(cat["dr_true"][sel])["mean"],
            "dr_dt_abs_error_m_per_frame": stats(cat["dr_err"][sel]),
            "ttc": ttc_scores(cat["ttc_est"][sa], cat["ttc_true"][sa]),
        }
    for r in records:
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
    """The summary as a JSON-able dict (NaN written as null by
    :func:`omniflow.io.jsonio.jsonable`)."""
    methods = []
    default = next((m.name for m in results.methods if m.kind == "omniflow"), None)
    for m in results.methods:
        if m.kind in ("omniflow", "external"):
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
            same = _same_points(results, f"@{m.name}")
            methods.append(
                {
                    "name": m.name,
                    "kind": m.kind,
                    "default": m.default,
                    "paper": m.paper,
                    "config": m.config,
                    "points": "own",
                    "time_per_frame": _time_block(results.times.get(m.name, [])),
                    "stage_seconds_total": dict(results.stages.get(m.name, {})),
                    "flow": _flow_block(results, m.name, "own"),
                    "protocol": protocol_block(results, m.name, "own"),
                    "protocol_interpolated": protocol_block(results, m.name, "interpolated"),
                    "stereo": stereo,
                    "derived": _derived_block(
                        results.derived.get(m.name, []),
                        results.dataset.get("objects", {}),
                        results.dataset.get("moving_objects", []),
                    ),
                    "baselines_at_same_points": same,
                }
            )
            if results.sigma.get(m.name):  # the method predicts its sigmas
                methods[-1]["calibration"] = calibration(results.sigma[m.name])
            if results.flags.get(m.name):  # eq. (14) flagged and unflagged points apart
                methods[-1]["flags"] = _flags_block(results, m.name)
            mono = _flow_block(results, m.name, "monocular")
            if mono:  # cam1's flow alone where no stereo match is near (monocular_gap)
                same_mono = _same_points(results, f"@{m.name}:monocular")
                methods[-1]["monocular"] = {"flow": mono, "baselines_at_same_points": same_mono}
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
                        "protocol": protocol_block(results, m.name, pts),
                    }
                )
    out = {
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
    out["headline"] = headline(jsonable(out))
    return out


#: A method's EPE (mean or median) must be below this share of zero flow's at the same
#: points to count as "clearly below" it.
ZERO_FLOW_MARGIN = 0.8
#: Radial or tangential gain outside [1 - GAIN_BAND, 1 + GAIN_BAND] is called biased: the
#: band issue 9 sets as omniflow's target (0.95-1.05), so a method that loses a tenth of
#: the radial motion is named biased in the headline, not passed as accurate.
GAIN_BAND = 0.05
#: A gain is judged only where the truth's rms of that component is at least this (px):
#: over points that barely move (a static scene) the gain is noise over nothing.
GAIN_MIN_SIGNAL = 0.05
#: Two EPEs within this ratio of each other are "comparable", not better or worse.
TIE = 0.1


def _g(d: Any, path: str) -> float:
    try:
        return _num(get_path(d, path))
    except KeyError:
        return math.nan


def _v(x: float | None, digits: int = 3) -> str:
    x = _num(x)
    if math.isnan(x):
        return "n/a"
    return ("-" if x < 0 else "") + "inf" if math.isinf(x) else f"{x:.{digits}f}"


def _epe_pair(f: Mapping[str, Any]) -> tuple[float, float]:
    return _g(f, "all.epe.mean"), _g(f, "all.epe.median")


def _biased(f: Mapping[str, Any], block: str = "all") -> str:
    """'biased (radial gain 0.60)' where a gain with enough true motion under it lies
    outside 1 +- GAIN_BAND; 'unbiased' where every judged gain is inside; 'bias not
    judged' where no component moves enough (truth rms below GAIN_MIN_SIGNAL)."""
    if _g(f, f"{block}.n") == 0:
        return "no points scored"
    bad, judged = [], 0
    for comp in ("radial", "tangential"):
        g = _g(f, f"{block}.{comp}.gain")
        if not (math.isfinite(g) and _g(f, f"{block}.{comp}.true_rms") >= GAIN_MIN_SIGNAL):
            continue
        judged += 1
        if abs(g - 1) > GAIN_BAND:
            bad.append(f"{comp} gain {g:.2f}")
    if bad:
        return "biased (" + ", ".join(bad) + ")"
    return "unbiased" if judged else f"bias not judged (truth rms < {GAIN_MIN_SIGNAL:g} px)"


def _gains(f: Mapping[str, Any], block: str = "all") -> str:
    def one(comp: str) -> str:
        se = _g(f, f"{block}.{comp}.gain_se")
        pm = f" +- {se:.2f}" if math.isfinite(se) else ""
        return (f"{comp} gain {_v(_g(f, f'{block}.{comp}.gain'), 2)}{pm} (truth rms "
                f"{_v(_g(f, f'{block}.{comp}.true_rms'), 2)} px)")  # fmt: skip

    return f"{one('radial')}, {one('tangential')}"


def _verdict(mine: tuple[float, float], other: tuple[float, float]) -> str:
    if not all(math.isfinite(v) for v in (*mine, *other)):
        return "not comparable"
    if mine[0] < (1 - TIE) * other[0] and mine[1] < (1 - TIE) * other[1]:
        return "better"
    if mine[0] > (1 + TIE) * other[0] and mine[1] > (1 + TIE) * other[1]:
        return "worse"
    return "comparable"


def headline(summary: Mapping[str, Any]) -> list[str]:
    """The answer in words and numbers: one line per comparison, verdict first.

    Per camera: the default omniflow variant's own figures (points, density, mean /
    median EPE, gains, biased or not), then one line per baseline at the same points
    (better / worse / comparable, and whether omniflow is clearly below zero flow);
    then stereo, time to contact (per moving object, failures counted), time per frame,
    and one line per row whose mean or median EPE is not clearly below zero flow's at
    the same points (below ``ZERO_FLOW_MARGIN`` x).
    """
    lines: list[str] = []
    methods = summary["methods"]
    omni = next((m for m in methods if m["kind"] == "omniflow" and m.get("default")), None)
    if omni is None:
        omni = next((m for m in methods if m["kind"] in ("omniflow", "external")), None)
    at_pts = {m["name"]: m for m in methods if m["kind"] == "baseline"
              and m["points"] == "omniflow points"}  # fmt: skip
    if omni is not None:
        me = omni["name"]
        for cam in ("cam1", "cam2"):
            f = omni["flow"].get(cam)
            if not f:
                continue
            mine = _epe_pair(f)
            bias = _biased(f)
            lines.append(
                f"{cam}, {me}: {bias} -- {_g(f, 'all.n'):.0f} points "
                f"({_v(_g(f, 'density.points_per_frame'), 0)} per frame = "
                f"{_v(100 * _g(f, 'density.of_valid_pixels'), 2)} % of valid pixels, "
                f"{_v(100 * _g(f, 'density.of_stereo_pixels'), 2)} % of those both cameras "
                f"see); EPE mean {_v(mine[0])} px, median {_v(mine[1])} px; {_gains(f)}"
            )
            lines += _mover_lines(summary, f"{cam}, {me}", f)
            for name, b in at_pts.items():
                fb = b["flow"].get(cam)
                if not fb:
                    continue
                other = _epe_pair(fb)
                if name == "zero-flow" and all(math.isfinite(v) for v in (*mine, *other)):
                    clear = all(a < ZERO_FLOW_MARGIN * b for a, b in zip(mine, other, strict=True))
                    verdict = (
                        "clearly below zero flow"
                        if clear
                        else f"NOT clearly below zero flow (needs < {ZERO_FLOW_MARGIN:g} x)"
                    )
                else:
                    verdict = _verdict(mine, other)
                lines.append(
                    f"{cam}, omniflow vs {name} at the same points: {verdict} -- EPE mean "
                    f"{_v(mine[0])} vs {_v(other[0])} px, median {_v(mine[1])} vs "
                    f"{_v(other[1])} px; radial gain {_v(_g(f, 'all.radial.gain'), 2)} vs "
                    f"{_v(_g(fb, 'all.radial.gain'), 2)}"
                )
        lines += _flag_lines(omni)
        for m in methods:  # every row with cam1-only flow (monocular_gap)
            lines += _monocular_lines(summary, m)
        st = omni.get("stereo") or {}
        if st:
            lines.append(
                f"stereo, {me}: {_v(100 * _g(st, 'all.outliers'), 1)} % of "
                f"{_g(st, 'all.n'):.0f} matches more than 1 px off; range error median "
                f"{_v(100 * _g(st, 'all.rel_r.median'), 1)} %, mean "
                f"{_v(100 * _g(st, 'all.rel_r.mean'), 1)} % of r"
            )
        d = omni.get("derived") or {}
        for name, o in (d.get("objects") or {}).items():
            t = o["ttc"]
            if not t["n"]:
                lines.append(
                    f"time to contact, mover {name}: no approaching point scored "
                    f"({o['n']} points with a dr/dt on it)"
                )
                continue
            lines.append(
                f"time to contact, mover {name}: {_v(100 * _num(t['failure_share']), 0)} % "
                f"failures -- {t['n']} approaching points of {o['n']}; true median "
                f"{_v(t['true_median_frames'], 0)} frames, estimated "
                f"{_v(t['est_median_frames'], 0)}; median relative error {_v(t['median'], 2)} "
                f"over all approaching points (failures = estimated receding or infinite, "
                f"counted as infinite); dr/dt mean "
                f"{_v(1000 * _num(o['dr_dt_est_mean_m_per_frame']), 1)} vs true "
                f"{_v(1000 * _num(o['dr_dt_true_mean_m_per_frame']), 1)} mm/frame"
            )
        t = d.get("ttc_relative_error")
        if t and t["n"]:
            lines.append(
                f"time to contact, all approaching points: {_v(100 * _num(t['failure_share']), 0)}"
                f" % failures of {t['n']}; median relative error {_v(t['median'], 2)} counting "
                f"failures, {_v(t['median_of_successes'], 2)} without"
            )
        dense = [m for m in methods if m["kind"] == "baseline" and m["points"] == "dense"
                 and m["name"] != "zero-flow"]  # fmt: skip
        times = [f"{me} {_v(1000 * _g(omni, 'time_per_frame.median_s'), 1)}"]
        times += [f"{b['name']} {_v(1000 * _g(b, 'time_per_frame.median_s'), 1)}"
                  for b in dense]  # fmt: skip
        lines.append("ms per frame pair (both cameras, median): " + ", ".join(times))
    lines += _zero_flow_flags(summary)
    return lines


def _mover_lines(summary: Mapping[str, Any], who: str, f: Mapping[str, Any]) -> list[str]:
    """One headline line per moving object of one flow block (``who``: camera and row)."""
    lines = []
    moving = {str(i) for i in summary["dataset"].get("moving_objects", [])}
    names = summary["dataset"].get("objects", {})
    for oid in sorted(moving, key=int):
        name = names.get(oid, f"id{oid}")
        o = f.get("objects", {}).get(name)
        if o is None:
            continue
        if not o["n"]:
            lines.append(f"{who} on mover {name}: 0 points scored")
            continue
        ob = {"all": o}
        lines.append(
            f"{who} on mover {name}: {_biased(ob)} -- {o['n']} "
            f"points ({_v(100 * _num(o['density']), 2)} % of its pixels); EPE mean "
            f"{_v(_g(ob, 'all.epe.mean'))} px, median {_v(_g(ob, 'all.epe.median'))} px; "
            f"{_gains(ob)}; mean flow dh {_v(_g(ob, 'all.radial.mean_est'))} vs true "
            f"{_v(_g(ob, 'all.radial.mean_true'))} px, h dtheta "
            f"{_v(_g(ob, 'all.tangential.mean_est'))} vs true "
            f"{_v(_g(ob, 'all.tangential.mean_true'))} px"
        )
    return lines


def _flag_lines(omni: Mapping[str, Any]) -> list[str]:
    """The row's eq. (14) flag (``coupled`` = 0): its share, its precision and recall
    against the truth, and each camera's EPE at the unflagged and the flagged points."""
    fl = omni.get("flags")
    if not fl:
        return []
    line = (
        f"eq. (14) flag, {omni['name']}: {_v(100 * _num(fl['share_flagged']), 1)} % of "
        f"{fl['n_points']} points flagged (not confident answers)"
    )
    if fl.get("n_breaks") is not None:
        line += (
            f"; precision {_v(fl['precision'], 2)}, recall {_v(fl['recall'], 2)} against the "
            f"{fl['n_breaks']} points whose true axial motion breaks eq. (14) by >= "
            f"{fl['break_px']:g} px/frame"
        )
    lines = [line]
    for cam in ("cam1", "cam2"):
        parts = []
        for label in ("unflagged", "flagged"):
            f = (fl["flow"].get(label) or {}).get(cam)
            if f:
                mean, median = _epe_pair(f)
                parts.append(f"{label} {_g(f, 'all.n'):.0f} points, EPE mean {_v(mean)} px, "
                             f"median {_v(median)} px, {_biased(f)}")  # fmt: skip
        if parts:
            lines.append(f"{cam}, {omni['name']}: " + "; ".join(parts))
    return lines


def _monocular_lines(summary: Mapping[str, Any], omni: Mapping[str, Any]) -> list[str]:
    """One row's cam1-only flow (``monocular_gap``), if it has one."""
    mono = omni.get("monocular") or {}
    f = (mono.get("flow") or {}).get("cam1")
    if not f:
        return []
    who = f"cam1 alone (monocular_gap), {omni['name']}"
    mine = _epe_pair(f)
    line = (
        f"{who}: {_biased(f)} -- {_g(f, 'all.n'):.0f} points "
        f"({_v(_g(f, 'density.points_per_frame'), 0)} per frame) where no stereo match is near; "
        f"EPE mean {_v(mine[0])} px, median {_v(mine[1])} px; {_gains(f)}"
    )
    dis = (mono.get("baselines_at_same_points") or {}).get("DIS-medium", {}).get("cam1")
    if dis:
        line += f"; DIS-medium there: EPE mean {_v(dis['mean'])}, median {_v(dis['median'])} px"
    return [line, *_mover_lines(summary, who, f)]


def sweep_rows(summary: Mapping[str, Any], key: str, value: Any) -> list[dict[str, Any]]:
    """Rows of the camera sweep table for one level: every method at its main point set
    (omniflow rows at their own points, baselines at the default variant's points)."""
    rows = []
    for m in summary["methods"]:
        if m["kind"] == "baseline" and m["points"] != "omniflow points":
            continue
        for cam, f in m["flow"].items():
            rows.append({
                "parameter": key, "value": value, "method": m["name"], "points": m["points"],
                "camera": cam, "n": f["all"]["n"], "epe_mean": f["all"]["epe"]["mean"],
                "epe_median": f["all"]["epe"]["median"],
                "radial_gain": f["all"]["radial"]["gain"],
                "tangential_gain": f["all"]["tangential"]["gain"],
            })  # fmt: skip
    return rows


def _zero_flow_flags(summary: Mapping[str, Any]) -> list[str]:
    """One line per row (omniflow rows at their points, baselines at the default's points)
    whose mean or median EPE is not clearly below zero flow's at the same points."""
    out = []
    zero_at = {cam: f["all"]["epe"] for m in summary["methods"]
               if m["name"] == "zero-flow" and m["points"] == "omniflow points"
               for cam, f in m["flow"].items()}  # fmt: skip
    for m in summary["methods"]:
        if m["name"] == "zero-flow" or m["points"] == "dense":
            continue
        bad = []
        for cam, f in m["flow"].items():
            if m["kind"] in ("omniflow", "external"):
                z = (m.get("baselines_at_same_points") or {}).get("zero-flow", {}).get(cam)
            else:
                z = zero_at.get(cam)
            if not z:
                continue
            mine = _epe_pair(f)
            zero = (_num(z.get("mean")), _num(z.get("median")))
            if not all(math.isfinite(v) for v in (*mine, *zero)):
                continue
            if mine[0] >= ZERO_FLOW_MARGIN * zero[0] or mine[1] >= ZERO_FLOW_MARGIN * zero[1]:
                bad.append(f"{cam} {mine[0]:.3f} / {mine[1]:.3f} vs {zero[0]:.3f} / {zero[1]:.3f}")
        if bad:
            pts = "" if m["kind"] in ("omniflow", "external") else f" ({m['points']})"
            out.append(
                f"WARNING {m['name']}{pts} is not clearly below zero flow (mean / median EPE, "
                f"px, vs zero flow's at the same points; needs < {ZERO_FLOW_MARGIN:g} x): "
                + "; ".join(bad)
            )
    return out


def find_method(summary: Mapping[str, Any], name: str, points: str | None = None) -> dict:
    """The summary entry of a method (``points`` to pick a baseline's point set)."""
    for m in summary["methods"]:
        if m["name"] == name and (points is None or m["points"] == points):
            return m
    raise KeyError(f"no method {name!r}" + (f" at points {points!r}" if points else ""))


def get_path(entry: Mapping[str, Any], path: str) -> Any:
    """Value at a dotted path, e.g. ``flow.cam1.noc.epe.median`` (KeyError names it).

    A key that itself holds dots (an object named ``room.floor``) is matched whole:
    at each level the longest run of parts that is a key wins.
    """
    cur: Any = entry
    parts = path.split(".")
    i = 0
    while i < len(parts):
        if not isinstance(cur, Mapping):
            raise KeyError(f"{path!r}: no key {parts[i]!r}")
        for j in range(len(parts), i, -1):
            key = ".".join(parts[i:j])
            if key in cur:
                cur, i = cur[key], j
                break
        else:
            raise KeyError(f"{path!r}: no key {parts[i]!r}")
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
        if m.get("flags"):
            row["flagged_share"] = m["flags"]["share_flagged"]
        row["time_ms"] = 1000 * _num(m["time_per_frame"]["median_s"])
        rows.append(row)
    return rows
