"""One compact table of the figures that decide whether a method is accurate, over many runs.

``omnivalidate`` writes one report per dataset; comparing a method across the
scene library meant reading five reports, and the mover criterion (the error of
an object's mean flow vector) was computed by hand each time. This reads the
``summary.json`` of each report directory and prints, per dataset and omniflow
row, one Markdown row with:

* points per frame and their share of the valid pixels (``density``);
* radial and tangential gain per camera (the least-squares slope of estimated
  against true through the origin; 1 = unbiased; ``-`` where the component's
  true rms is below :data:`MIN_TRUE_RMS` px, too small to judge);
* mean and median EPE per camera, and each as a multiple of a baseline's at
  the same points (``--baseline``, DIS-medium by default);
* the share of stereo matches more than 1 px off;
* time to contact over every approaching point: median relative error and
  failure share (receding or infinite);
* per moving object, the points scored (all pairs together) and the error of
  its mean flow vector, ``|mean est - mean true| / |mean true|`` of the
  (radial, tangential) means, cam1 / cam2, in %.

Run::

    python -m validation.scorecard runs/*/report            # every row of each
    python -m validation.scorecard /tmp/a /tmp/b --rows default --baseline DIS-medium

Rows are labelled ``default`` or by the settings that differ from the defaults
(the dense preset's written ``dense``), with the full names listed under the table.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from omniflow.config import OmniFlowConfig

__all__ = ["MIN_TRUE_RMS", "ScorecardError", "main", "mover_error", "rows", "table"]

#: A component's gain is printed only where its true rms is at least this (px), as the
#: headline's verdicts judge it (validation.summary): below, the slope is noise.
MIN_TRUE_RMS = 0.05


class ScorecardError(ValueError):
    """A report directory or summary that cannot be read; the message names it."""


def mover_error(block: Mapping[str, Any]) -> float:
    """The error of an object's mean flow vector, ``|mean est - mean true| / |mean true|``.

    ``block`` is one object's flow block of summary.json (``radial`` and
    ``tangential`` with ``mean_est`` and ``mean_true``, px per frame). NaN where
    the object has no point or no true motion.
    """
    try:
        er, et = float(block["radial"]["mean_est"]), float(block["tangential"]["mean_est"])
        tr, tt = float(block["radial"]["mean_true"]), float(block["tangential"]["mean_true"])
    except (KeyError, TypeError, ValueError):
        return math.nan
    true = math.hypot(tr, tt)
    return math.hypot(er - tr, et - tt) / true if true > 0 else math.nan


def _num(x: Any) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def _fmt(x: float, digits: int = 3) -> str:
    return "-" if not math.isfinite(x) else f"{x:.{digits}f}"


def _gain(cam: Mapping[str, Any], component: str) -> str:
    g = cam.get("all", {}).get(component, {})
    if _num(g.get("true_rms")) < MIN_TRUE_RMS:
        return "-"
    return _fmt(_num(g.get("gain")), 2)


def _label(method: Mapping[str, Any]) -> str:
    """``default``, or the row's settings that differ from the defaults or from the dense
    preset, whichever is the shorter list (``dense,KEY=VALUE``)."""
    if method.get("default"):
        return "default"
    config = method.get("config")
    name = str(method["name"])
    if not isinstance(config, Mapping):
        inside = name[name.find("[") + 1 : name.rfind("]")] if "[" in name else name
        return inside.partition(";")[2] or name
    labels = []
    for prefix, base in (([], OmniFlowConfig()), (["dense"], OmniFlowConfig.dense())):
        ref = base.to_dict()
        changed = [f"{k}={v}" for k, v in config.items() if k in ref and not _same(v, ref[k])]
        labels.append(prefix + changed)
    return ",".join(min(labels, key=len)) or "default settings"


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, int | float) and isinstance(b, int | float):
        return math.isclose(a, b, rel_tol=1e-9, abs_tol=0.0)
    return a == b


def rows(summary: Mapping[str, Any], *, baseline: str = "DIS-medium",
         only: Sequence[str] = ()) -> list[dict[str, Any]]:  # fmt: skip
    """The scorecard's figures of each omniflow row of one summary (a dict per row).

    ``only`` keeps the rows whose label (``default`` or the settings part of the
    name) or full name is listed.
    """
    out = []
    names = summary["dataset"].get("objects", {})
    moving = [names.get(str(i), f"id{i}") for i in summary["dataset"].get("moving_objects", [])]
    for m in summary["methods"]:
        if m.get("kind") != "omniflow" or m.get("points") != "own":
            continue
        label = _label(m)
        if only and label not in only and m["name"] not in only:
            continue
        flow = m.get("flow", {})
        base = m.get("baselines_at_same_points", {}).get(baseline, {})
        row: dict[str, Any] = {"scene": summary["dataset"].get("scene"), "row": label,
                               "name": m["name"]}  # fmt: skip
        dens = flow.get("cam1", {}).get("density", {})
        row["points_per_frame"] = _num(dens.get("points_per_frame"))
        row["of_valid"] = _num(dens.get("of_valid_pixels"))
        for cam in ("cam1", "cam2"):
            c = flow.get(cam, {})
            epe = c.get("all", {}).get("epe", {})
            b = base.get(cam, {})
            row[f"{cam}_radial_gain"] = _gain(c, "radial")
            row[f"{cam}_tangential_gain"] = _gain(c, "tangential")
            for stat in ("mean", "median"):
                mine, theirs = _num(epe.get(stat)), _num(b.get(stat))
                row[f"{cam}_epe_{stat}"] = mine
                row[f"{cam}_x_{stat}"] = mine / theirs if theirs > 0 else math.nan
        row["stereo_outliers"] = _num(m.get("stereo", {}).get("all", {}).get("outliers"))
        ttc = m.get("derived", {}).get("ttc_relative_error", {})
        row["ttc_median"] = _num(ttc.get("median"))
        row["ttc_failures"] = _num(ttc.get("failure_share"))
        row["movers"] = []
        for name in moving:
            o1 = flow.get("cam1", {}).get("objects", {}).get(name, {})
            o2 = flow.get("cam2", {}).get("objects", {}).get(name, {})
            row["movers"].append((name, int(o1.get("n", 0) or 0), mover_error(o1),
                                  mover_error(o2)))  # fmt: skip
        out.append(row)
    return out


def table(all_rows: Sequence[Mapping[str, Any]], *, baseline: str = "DIS-medium") -> str:
    """The rows as a Markdown table, the full row names listed below it."""
    head = ["scene", "row", "points / frame (% valid)", "radial gain c1 / c2",
            "tangential gain c1 / c2", f"EPE mean c1 / c2 px (x {baseline})",
            f"EPE median c1 / c2 px (x {baseline})", "stereo > 1 px",
            "TTC median rel. err. / failures",
            "movers: points, mean-flow error c1 / c2 %"]  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in all_rows:
        epe = {s: f"{_fmt(r[f'cam1_epe_{s}'])} / {_fmt(r[f'cam2_epe_{s}'])} "
                  f"({_fmt(r[f'cam1_x_{s}'], 2)}x / {_fmt(r[f'cam2_x_{s}'], 2)}x)"
               for s in ("mean", "median")}  # fmt: skip
        movers = "; ".join(f"{n} {k}, {_fmt(100 * e1, 1)} / {_fmt(100 * e2, 1)}"
                           for n, k, e1, e2 in r["movers"])  # fmt: skip
        cells = [str(r["scene"]), str(r["row"]),
                 f"{_fmt(r['points_per_frame'], 0)} ({_fmt(100 * r['of_valid'], 2)} %)",
                 f"{r['cam1_radial_gain']} / {r['cam2_radial_gain']}",
                 f"{r['cam1_tangential_gain']} / {r['cam2_tangential_gain']}",
                 epe["mean"], epe["median"], f"{_fmt(100 * r['stereo_outliers'], 1)} %",
                 f"{_fmt(r['ttc_median'])} / {_fmt(100 * r['ttc_failures'], 0)} %",
                 movers or "-"]  # fmt: skip
        lines.append("| " + " | ".join(cells) + " |")
    names = {r["row"]: r["name"] for r in all_rows}
    lines += [""] + [f"- `{k}`: `{v}`" for k, v in names.items()]
    return "\n".join(lines)


def _load(directory: str) -> Mapping[str, Any]:
    path = Path(directory)
    path = path if path.suffix == ".json" else path / "summary.json"
    try:
        summary = json.loads(path.read_text())
    except OSError as exc:
        raise ScorecardError(f"{path}: cannot read ({exc.strerror}); expected an omnivalidate "
                             "report directory holding summary.json") from None  # fmt: skip
    except json.JSONDecodeError as exc:
        raise ScorecardError(f"{path}: not JSON ({exc.msg}, line {exc.lineno})") from None
    if not isinstance(summary, dict) or "methods" not in summary or "dataset" not in summary:
        raise ScorecardError(f"{path}: expected an omnivalidate summary (keys 'dataset', "
                             "'methods')")  # fmt: skip
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m validation.scorecard DIR [DIR ...]``: print the table; 2 on bad input."""
    ap = argparse.ArgumentParser(prog="python -m validation.scorecard",
                                 description=__doc__.split("\n")[0])  # fmt: skip
    ap.add_argument("reports", nargs="+", help="omnivalidate --out directories (or summary.json)")
    ap.add_argument("--baseline", default="DIS-medium", help="the baseline of the 'x' ratios")
    ap.add_argument("--rows", nargs="*", default=[],
                    help="only these rows: 'default' or a row's settings as printed")  # fmt: skip
    args = ap.parse_args(argv)
    out = []
    try:
        for d in args.reports:
            out += rows(_load(d), baseline=args.baseline, only=args.rows)
    except ScorecardError as exc:
        print(f"scorecard: {exc}", file=sys.stderr)
        return 2
    print(table(out, baseline=args.baseline))
    return 0


if __name__ == "__main__":
    sys.exit(main())
