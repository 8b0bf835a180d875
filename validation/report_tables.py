"""The report's tables: (header, rows) of formatted cells, from the summary."""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from typing import Any

from .metrics import RANGE_BINS, SPEED_BINS, bin_label
from .report_doc import fmt, num, pct
from .summary import flat_table

__all__ = [
    "bias_speed_table",
    "bias_table",
    "derived_table",
    "flags_table",
    "headline_table",
    "method_table",
    "movers_table",
    "objects_table",
    "polar_table",
    "range_table",
    "speed_table",
]


def method_table(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    header = ["method", "points", "n cam1", "cam1 EPE median (px)", "cam1 EPE mean (px)",
              "cam1 EPE p90 (px)", "noc EPE median (px)", "occ EPE median (px)", ">1px", ">3px",
              "cam2 EPE median (px)", "DIS same pts EPE median (px)", "stereo >1px",
              "r rel err median", "match rate", "ms / frame pair"]  # fmt: skip
    rows = []
    for m, r in zip(summary["methods"], flat_table(summary), strict=True):
        f = m["flow"].get("cam1", {})
        rows.append([
            r["method"], r["points"], fmt(r.get("cam1_n")), fmt(r.get("cam1_epe_median")),
            fmt(r.get("cam1_epe_mean")), fmt(f.get("all", {}).get("epe", {}).get("p90")),
            fmt(r.get("cam1_noc_epe_median")), fmt(r.get("cam1_occ_epe_median")),
            pct(r.get("cam1_out1")), pct(r.get("cam1_out3")), fmt(r.get("cam2_epe_median")),
            fmt(r.get("dis_same_points_cam1_epe_median")), pct(r.get("stereo_outliers")),
            fmt(r.get("rel_r_median")), pct(r.get("match_rate")), fmt(r.get("time_ms"), 1),
        ])  # fmt: skip
    return header, rows


def polar_table(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    header = ["method", "points"]
    for cam in ("cam1", "cam2"):
        header += [f"{cam} |dh| med", f"{cam} |h dθ| med", f"{cam} AE med (°)"]
    rows = []
    for r in flat_table(summary):
        cells = [r["method"], r["points"]]
        for cam in ("cam1", "cam2"):
            cells += [
                fmt(r.get(f"{cam}_dh_median")),
                fmt(r.get(f"{cam}_hdtheta_median")),
                fmt(r.get(f"{cam}_ae_median"), 2),
            ]
        rows.append(cells)
    return header, rows


def headline_table(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    """The default omniflow variant, the paper's configuration, the default flow step on
    true matches, and the baselines at the default variant's points: median EPE of both
    cameras, stereo range error, time."""
    header = [
        "method",
        "cam1 EPE mean (px)",
        "cam1 EPE median (px)",
        "cam1 radial gain",
        "cam2 EPE mean (px)",
        "cam2 EPE median (px)",
        "cam2 radial gain",
        "points / frame",
        ">1px cam1",
        "r rel err median",
        "stereo >1px",
        "ms / frame pair",
    ]
    rows = []
    omni = [m for m in summary["methods"] if m["kind"] == "omniflow"]
    picked = omni[:1] + [m for m in omni[1:] if _is_paper(m)][:1]
    picked += [m for m in omni if m.get("config", {}).get("match_method") == "truth"
               and m not in picked][:1]  # fmt: skip
    picked += [
        m
        for m in summary["methods"]
        if m["kind"] == "baseline" and m["points"] == "omniflow points"
    ]
    for m in picked:
        f1, f2 = m["flow"].get("cam1", {}), m["flow"].get("cam2", {})
        st = m.get("stereo") or {}
        label = m["name"] + (" (default)" if m.get("default") else "")
        label += " (paper)" if m["kind"] == "omniflow" and _is_paper(m) else ""
        label += " at the default's points" if m["kind"] == "baseline" else ""
        a1, a2, sa = f1.get("all", {}), f2.get("all", {}), st.get("all", {})
        rows.append(
            [
                label,
                fmt(a1.get("epe", {}).get("mean")),
                fmt(a1.get("epe", {}).get("median")),
                fmt(a1.get("radial", {}).get("gain"), 2),
                fmt(a2.get("epe", {}).get("mean")),
                fmt(a2.get("epe", {}).get("median")),
                fmt(a2.get("radial", {}).get("gain"), 2),
                fmt(f1.get("density", {}).get("points_per_frame"), 0),
                pct(a1.get("out1")),
                fmt(sa.get("rel_r", {}).get("median")),
                pct(sa.get("outliers")),
                fmt(1000 * num(m["time_per_frame"]["median_s"]), 1),
            ]
        )
    return header, rows


def _is_paper(m: Mapping[str, Any]) -> bool:
    return bool(m.get("paper"))


def speed_table(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    labels = [bin_label(lo, hi, "px") for lo, hi in itertools.pairwise(SPEED_BINS)]
    header = ["method", "points"] + [f"EPE {lab} (n)" for lab in labels]
    rows = []
    for m in summary["methods"]:
        f = m["flow"].get("cam1")
        if f is None:
            continue
        cells = []
        for lab in labels:
            b = f["speed"].get(lab, {})
            cells.append(f"{fmt(b.get('epe', {}).get('median'))} ({b.get('n', 0)})")
        rows.append([m["name"], m["points"], *cells])
    return header, rows


def range_table(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    labels = [bin_label(lo, hi, "m") for lo, hi in itertools.pairwise(RANGE_BINS)]
    header = ["method"] + [f"r rel err {lab} (n, >1px)" for lab in labels] + ["|h| err med (m)"]
    rows = []
    for m in summary["methods"]:
        st = m.get("stereo")
        if not st:
            continue
        cells = []
        for lab in labels:
            b = st["range"][lab]
            cells.append(f"{fmt(b['rel_r']['median'])} ({b['n']}, {pct(b['outliers'])})")
        rows.append([m["name"], *cells, fmt(st["all"]["err_h"]["median"])])
    return header, rows


def derived_table(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    header = [
        "method",
        "|dr/dt err| med (mm/frame)",
        "true |dr/dt| med (mm/frame)",
        "TTC rel err med, failures as inf (n, failed)",
        "odometry |w err| (mrad/frame)",
        "|V err| (mm/frame)",
        "tangential only: |w err|",
        "|V err|",
    ]
    rows = []
    for m in summary["methods"]:
        d = m.get("derived")
        if not d:
            continue
        ob, ot = d.get("odometry_both", {}), d.get("odometry_tangential", {})

        def milli(block: Mapping[str, Any], key: str) -> str:
            v = block.get(key, {}).get("median")
            return fmt(None if v is None else 1000 * v)

        rows.append(
            [
                m["name"],
                fmt(1000 * num(d["dr_dt_abs_error_m_per_frame"]["median"])),
                fmt(1000 * num(d["dr_dt_true_abs_m_per_frame"]["median"])),
                f"{fmt(d['ttc_relative_error']['median'])} ({d['ttc_relative_error']['n']}, "
                f"{pct(d['ttc_relative_error']['failure_share'])} failed)",
                milli(ob, "yaw_rate_abs_error_rad_per_frame"),
                milli(ob, "velocity_abs_error_m_per_frame"),
                milli(ot, "yaw_rate_abs_error_rad_per_frame"),
                milli(ot, "velocity_abs_error_m_per_frame"),
            ]
        )
    return header, rows


def bias_table(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    header = ["method", "points", "camera", "n", "radial gain", "radial slope",
              "radial mean signed (px)", "tangential gain", "tangential slope",
              "tangential mean signed (px)"]  # fmt: skip
    rows = []
    for m in summary["methods"]:
        for cam in ("cam1", "cam2"):
            a = m["flow"].get(cam, {}).get("all")
            if not a:
                continue
            rad, tan = a["radial"], a["tangential"]
            rows.append([m["name"], m["points"], cam, fmt(a["n"]), fmt(rad["gain"], 2),
                         fmt(rad["slope"], 2), fmt(rad["mean_signed"]), fmt(tan["gain"], 2),
                         fmt(tan["slope"], 2), fmt(tan["mean_signed"])])  # fmt: skip
    return header, rows


def bias_speed_table(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    labels = [bin_label(lo, hi, "px") for lo, hi in itertools.pairwise(SPEED_BINS)]
    header = ["method", "points"] + [f"radial gain {lab} (mean signed px)" for lab in labels]
    rows = []
    for m in summary["methods"]:
        f = m["flow"].get("cam1")
        if f is None:
            continue
        cells = []
        for lab in labels:
            r = f["speed"].get(lab, {}).get("radial", {})
            cells.append(f"{fmt(r.get('gain'), 2)} ({fmt(r.get('mean_signed'))})")
        rows.append([m["name"], m["points"], *cells])
    return header, rows


def flags_table(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    """The eq. (14) flag of every omniflow row (validation.scoring_flags): its share,
    precision and recall, and each camera's flagged and unflagged points apart."""
    header = ["method", "flagged", "precision", "recall", "camera", "points", "n",
              "EPE mean (px)", "EPE median (px)", ">1px", "radial gain",
              "tangential gain"]  # fmt: skip
    rows = []
    for m in summary["methods"]:
        fl = m.get("flags")
        if not fl:
            continue
        head = [m["name"], pct(fl["share_flagged"]), fmt(fl["precision"], 2),
                fmt(fl["recall"], 2)]  # fmt: skip
        for cam in ("cam1", "cam2"):
            for label in ("unflagged", "flagged"):
                a = (fl["flow"].get(label) or {}).get(cam, {}).get("all")
                if not a:
                    continue
                rows.append([*head, cam, label, fmt(a["n"]), fmt(a["epe"]["mean"]),
                             fmt(a["epe"]["median"]), pct(a["out1"]),
                             fmt(a["radial"]["gain"], 2),
                             fmt(a["tangential"]["gain"], 2)])  # fmt: skip
    return header, rows


def objects_table(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    """Points, density and EPE per object (cam1), every object of the dataset, 0 shown.

    A row with cam1-only flow (``monocular_gap``) gets a second line, its points
    ``cam1 only``."""
    blocks = []  # (method, points, its flow block)
    for m in summary["methods"]:
        blocks.append((m, m["points"], m["flow"]))
        if m.get("monocular"):
            blocks.append((m, "cam1 only", m["monocular"]["flow"]))
    names: list[str] = []
    for _, _, flow in blocks:
        for name in flow.get("cam1", {}).get("objects", {}):
            if name not in names:
                names.append(name)
    moving = {str(i) for i in summary["dataset"].get("moving_objects", [])}
    objs = summary["dataset"].get("objects", {})
    header = ["method", "points"] + [
        name + (" (moving)" if any(objs.get(i) == name for i in moving) else "") for name in names
    ]
    rows = []
    for m, points, flow in blocks:
        if points == "dense" and m["name"] != "zero-flow":
            continue
        o = flow.get("cam1", {}).get("objects", {})
        cells = []
        for name in names:
            b = o.get(name, {"n": 0})
            epe = b.get("epe", {})
            if b["n"]:
                cells.append(f"{b['n']} ({pct(b.get('density'))}), EPE {fmt(epe.get('mean'))} / "
                             f"{fmt(epe.get('median'))}")  # fmt: skip
            else:
                cells.append("0" if b.get("valid_pixels", 1) else "0 (not in view)")
        rows.append([m["name"], points, *cells])
    return header, rows


def movers_table(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    header = ["method", "object", "points", "approaching", "TTC true med (frames)",
              "TTC est med (frames)", "failures", "TTC rel err med (all)",
              "rel err med (successes)", "dr/dt est mean (mm/frame)",
              "dr/dt true mean (mm/frame)"]  # fmt: skip
    rows = []
    for m in summary["methods"]:
        for name, o in ((m.get("derived") or {}).get("objects") or {}).items():
            t = o["ttc"]
            rows.append([m["name"], name, fmt(o["n"]), fmt(t["n"]), fmt(t["true_median_frames"], 1),
                         fmt(t["est_median_frames"], 1), pct(t["failure_share"]),
                         fmt(t["median"]), fmt(t["median_of_successes"]),
                         fmt(1000 * num(o["dr_dt_est_mean_m_per_frame"])),
                         fmt(1000 * num(o["dr_dt_true_mean_m_per_frame"]))])  # fmt: skip
    return header, rows


def calibration_table(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    """Per method that predicts sigmas and per quantity: points, points excluded for an
    infinite sigma, shares within 1 and 2 predicted sigma, median sigma
    (validation.calibration_sigma)."""
    header = ["method", "quantity", "n", "excluded (sigma inf)", "within 1 sigma",
              "within 2 sigma", "median sigma"]  # fmt: skip
    rows = []
    for m in summary["methods"]:
        for q, b in (m.get("calibration") or {}).items():
            rows.append([m["name"], q, str(b["n"]), str(b.get("excluded", 0)),
                         pct(b["within1"]), pct(b["within2"]),
                         f"{fmt(b['sigma_median'], 4)} {b['unit']}"])  # fmt: skip
    return header, rows
