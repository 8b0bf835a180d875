"""The suite's leaderboard: every method on every scene, and aggregated, ranked by ``1px``.

Read from the per-scene summaries (``summary.json``, :mod:`validation.summary`). Each
method's row on a scene holds its **dense** score (the protocol's ``1px``, ``epe``,
``fl``, ``wauc`` at every valid pixel of both cameras: a dense method's own field, a
sparse method's flow interpolated by :mod:`validation.densify`) and, for a sparse
method, its **sparse** score at its own points and its density (points per valid
pixel), beside stereo outliers, the radial and tangential gains (cam1) and the
median time per frame pair.

The aggregate of a method is the mean over the scenes, each scene weighing the
same. A scene where the method gave no dense value at all counts as every pixel
wrong (``1px`` = ``fl`` = 1, ``wauc`` = 0) and leaves its mean ``epe`` undefined,
so a failure is never averaged away; ``missing`` counts those scenes. Methods are
ranked by the aggregated ``1px`` (lower is better), then ``epe``.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from omniflow.io.imageio import atomic_write_text

from .metrics import PROTOCOL_METRICS
from .report_doc import Doc, fmt, pct

__all__ = ["FORMAT", "OUTPUTS", "leaderboard", "scene_rows", "write_leaderboard"]

FORMAT = "omnivalidate-leaderboard/1"
OUTPUTS = ("leaderboard.md", "leaderboard.html", "leaderboard.csv", "leaderboard.json")
#: Columns of every row, in the CSV's order.
COLUMNS = ("rank", "method", "scene", "split", "kind", "1px", "epe", "fl", "wauc", "coverage",
           "sparse_1px", "sparse_epe", "density", "stereo_outliers", "radial_gain",
           "tangential_gain", "within2_flow", "within2_range", "flagged", "unflagged_epe",
           "flagged_epe", "flag_precision", "flag_recall", "time_s", "scenes",
           "missing")  # fmt: skip
#: Columns aggregated as the plain mean over the scenes that have them.
_MEANS = ("coverage", "sparse_1px", "sparse_epe", "density", "stereo_outliers", "radial_gain",
          "tangential_gain", "within2_flow", "within2_range", "flagged", "unflagged_epe",
          "flagged_epe", "flag_precision", "flag_recall", "time_s")  # fmt: skip
#: What a scene with no dense value counts as (every pixel wrong).
_FAILED = {"1px": 1.0, "fl": 1.0, "wauc": 0.0, "epe": math.nan}


def _num(v: Any) -> float:
    return math.nan if v is None else float(v)


def _get(d: Any, *path: str) -> Any:
    for k in path:
        if not isinstance(d, Mapping) or k not in d:
            return None
        d = d[k]
    return d


def scene_rows(scene: str, split: str, summary: Mapping[str, Any]) -> list[dict[str, Any]]:
    """One row per method of a scene's summary (a baseline's dense field, not its
    samples at omniflow's points)."""
    rows = []
    for m in summary.get("methods", []):
        own = m.get("points") == "own"
        if not own and m.get("points") != "dense":
            continue
        dense = m.get("protocol_interpolated") if own else m.get("protocol")
        sparse = m.get("protocol") if own else None
        d_all = _get(dense, "all") or {}
        row: dict[str, Any] = {"method": m["name"], "scene": scene, "split": split,
                               "kind": m.get("kind")}  # fmt: skip
        for k in PROTOCOL_METRICS:
            row[k] = _num(d_all.get(k))
        row["coverage"] = _num(_get(dense, "density"))
        row["sparse_1px"] = _num(_get(sparse, "all", "1px"))
        row["sparse_epe"] = _num(_get(sparse, "all", "epe"))
        row["density"] = _num(_get(sparse, "density")) if own else row["coverage"]
        row["stereo_outliers"] = _num(_get(m, "stereo", "all", "outliers"))
        row["radial_gain"] = _num(_get(m, "flow", "cam1", "all", "radial", "gain"))
        row["tangential_gain"] = _num(_get(m, "flow", "cam1", "all", "tangential", "gain"))
        row["within2_flow"], row["within2_range"] = _within2(m.get("calibration"))
        # the eq. (14) flag (validation.scoring_flags): share flagged, each part's sparse EPE
        row["flagged"] = _num(_get(m, "flags", "share_flagged"))
        for label in ("unflagged", "flagged"):
            row[f"{label}_epe"] = _num(_get(m, "flags", "protocol", label, "all", "epe"))
        row["flag_precision"] = _num(_get(m, "flags", "precision"))
        row["flag_recall"] = _num(_get(m, "flags", "recall"))
        row["time_s"] = _num(_get(m, "time_per_frame", "median_s"))
        row["missing"] = int(not d_all.get("n"))
        rows.append(row)
    return rows


def _within2(cal: Mapping[str, Any] | None) -> tuple[float, float]:
    """The shares of points within 2 predicted sigma: flow (cam1 and cam2 pooled) and
    range; NaN for a method that predicts no sigma (validation.calibration_sigma)."""
    if not cal:
        return math.nan, math.nan
    flow = [cal[c] for c in ("cam1", "cam2") if c in cal and cal[c].get("n")]
    n = sum(b["n"] for b in flow)
    w_flow = sum(b["n"] * _num(b["within2"]) for b in flow) / n if n else math.nan
    rng = cal.get("range") or {}
    return w_flow, _num(rng.get("within2")) if rng.get("n") else math.nan


def _mean(values: Sequence[float]) -> float:
    v = [x for x in values if not math.isnan(x)]
    return sum(v) / len(v) if v else math.nan


def _ranked(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    def key(r: dict[str, Any]) -> tuple[float, float, str]:
        a, b = r["1px"], r["epe"]
        return (math.inf if math.isnan(a) else a, math.inf if math.isnan(b) else b, r["method"])

    out = sorted(rows, key=key)
    for i, r in enumerate(out, 1):
        r["rank"] = i
    return out


def leaderboard(
    scenes: Sequence[tuple[str, str, Mapping[str, Any]]], *, suite: Mapping[str, Any]
) -> dict[str, Any]:
    """The leaderboard of ``(scene, split, summary)`` triples as a JSON-able dict:
    ``methods`` (aggregated over every scene, ranked), ``splits`` (the same per split,
    when the scenes come from both) and ``scenes`` (each scene's rows, ranked)."""
    per_scene = {name: _ranked(scene_rows(name, split, s)) for name, split, s in scenes}
    splits = sorted({split for _, split, _ in scenes})
    split_of = {name: split for name, split, _ in scenes}
    by_split = {
        sp: _aggregate([rows for n, rows in per_scene.items() if split_of[n] == sp], sp)
        for sp in splits
    }
    return {
        "format": FORMAT,
        "suite": dict(suite),
        "primary": "1px",
        "metrics": {
            "1px": "fraction of valid pixels with EPE > 1 px (lower is better)",
            "epe": "mean endpoint error, px",
            "fl": "fraction with EPE > 3 px and > 5 % of the true flow (KITTI)",
            "wauc": "weighted area under the accuracy curve, 0.05-5 px (VIPER), higher better",
        },
        "methods": _aggregate(list(per_scene.values()), ""),
        "splits": by_split if len(splits) > 1 else {},
        "scenes": per_scene,
    }


def _aggregate(scene_lists: Sequence[list[dict[str, Any]]], split: str) -> list[dict[str, Any]]:
    """Each method's mean over the scenes (module docstring), ranked."""
    by_method: dict[str, list[dict[str, Any]]] = {}
    for rows in scene_lists:
        for r in rows:
            by_method.setdefault(r["method"], []).append(r)
    agg = []
    for method, rows in by_method.items():
        a: dict[str, Any] = {"method": method, "scene": "all", "split": split,
                             "kind": rows[0]["kind"]}  # fmt: skip
        for k in PROTOCOL_METRICS:
            vals = [_FAILED[k] if r["missing"] else r[k] for r in rows]
            a[k] = math.nan if any(math.isnan(v) for v in vals) else _mean(vals)
        for k in _MEANS:
            a[k] = _mean([r[k] for r in rows])
        a["scenes"] = len(rows)
        a["missing"] = sum(r["missing"] for r in rows)
        agg.append(a)
    return _ranked(agg)


def _table(doc: Doc, rows: Sequence[Mapping[str, Any]], aggregated: bool) -> None:
    header = ["rank", "method", "1px", "epe", "fl", "wauc", "coverage", "sparse 1px",
              "sparse epe", "density", "stereo out", "radial gain", "tang. gain",
              "2σ flow", "2σ range", "flagged", "unflagged epe", "flagged epe", "flag prec.",
              "flag recall", "time s"]  # fmt: skip
    if aggregated:
        header += ["scenes", "missing"]
    body = []
    for r in rows:
        line = [str(r["rank"]), f"`{r['method']}`", pct(r["1px"]), fmt(r["epe"]), pct(r["fl"]),
                fmt(r["wauc"]), pct(r["coverage"]), pct(r["sparse_1px"]), fmt(r["sparse_epe"]),
                pct(r["density"]), pct(r["stereo_outliers"]), fmt(r["radial_gain"]),
                fmt(r["tangential_gain"]), pct(r["within2_flow"]), pct(r["within2_range"]),
                pct(r["flagged"]), fmt(r["unflagged_epe"]), fmt(r["flagged_epe"]),
                fmt(r["flag_precision"]), fmt(r["flag_recall"]),
                fmt(r["time_s"])]  # fmt: skip
        if aggregated:
            line += [str(r["scenes"]), str(r["missing"])]
        body.append(line)
    doc.table(header, body)


def _document(board: Mapping[str, Any], command: str | None) -> Doc:
    s = board["suite"]
    doc = Doc()
    doc.h(1, f"Leaderboard: suite {s.get('name')} ({s.get('split')} split)")
    doc.p(
        f"Suite `{s.get('path')}`: {len(board['scenes'])} scenes, {s.get('frames')} frames "
        f"each at {s.get('resolution')} px. Ranked by `1px` (the fraction of valid pixels "
        "with endpoint error above 1 px, both cameras; lower is better). `2σ flow` and "
        "`2σ range`: the share of a method's points whose flow error (both cameras) or "
        "range error is within 2 predicted sigma, for methods that predict sigmas "
        "(target 90-97 %). The first four "
        "figures are dense (every valid pixel; a sparse method's flow interpolated "
        "edge-aware); `sparse` figures are at the method's own points, `density` their "
        "share of the valid pixels. A scene with no dense value counts as every pixel "
        "wrong (`missing`). docs/suite.md defines every column."
    )
    if command:
        doc.code(command)
    doc.h(2, "All scenes (mean over scenes)")
    _table(doc, board["methods"], aggregated=True)
    for split, rows in board.get("splits", {}).items():
        doc.h(2, f"Split {split} (mean over its scenes)")
        _table(doc, rows, aggregated=True)
    for name, rows in board["scenes"].items():
        split = rows[0]["split"] if rows else ""
        doc.h(2, f"Scene {name} ({split})")
        _table(doc, rows, aggregated=False)
    return doc


def _csv(board: Mapping[str, Any]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(COLUMNS), extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    splits = [r for rows in board.get("splits", {}).values() for r in rows]
    scenes = [r for rows in board["scenes"].values() for r in rows]
    for r in [*board["methods"], *splits, *scenes]:
        w.writerow({k: ("" if isinstance(v, float) and math.isnan(v) else v)
                    for k, v in r.items()})  # fmt: skip
    return buf.getvalue()


def write_leaderboard(
    board: Mapping[str, Any], out_dir: str | Path, *, command: str | None = None
) -> list[Path]:
    """Write the four leaderboard files into ``out_dir``, each to a temporary name then
    renamed; returns their paths."""
    from omniflow.io.jsonio import jsonable

    out = Path(out_dir)
    doc = _document(board, command)
    title = f"Leaderboard: {board['suite'].get('name')}"
    texts = {
        "leaderboard.md": doc.markdown(),
        "leaderboard.html": doc.html(title),
        "leaderboard.csv": _csv(board),
        "leaderboard.json": json.dumps(jsonable(board), indent=1, allow_nan=False) + "\n",
    }
    return [atomic_write_text(out / name, text) for name, text in texts.items()]
