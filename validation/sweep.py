"""``omnivalidate sweep``: render one scene at each value of one scene key and score it.

The question a rig builder asks (which lens, which alignment tolerance, which exposure
keeps my accuracy?) is answered by rendering the same scene, seed and motion at a list
of values of one key (``optics.f_number``, ``optics.focus_distance``, ``camera.exposure``,
a rig error, ...), scoring every method on each render with the suite's protocol
(``validation.leaderboard.scene_rows``) and drawing each metric against the value.
Unlike ``omnivalidate DATASET --camera-sweep`` (the camera model re-applied to one
render), every point here is a render, so optics and geometry can be swept.

Layout of ``--out DIR``::

    DIR/points/NN/render/       the render at the NN-th value (omnisim's render job)
    DIR/points/NN/report/       its omnivalidate report
    DIR/points/NN/state.json    the value and the methods it was scored with (resume key)
    DIR/sweep.json, sweep.csv, sweep.md, sweep.png

Resumable like the suite: renders continue at the first missing frame, and a point
already scored with the same value and methods is not scored again.
"""

from __future__ import annotations

import csv
import io
import json
import math
import time
import tomllib
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from omniflow.io.imageio import atomic_write_text

from .inputs import InputError
from .suite_run import SuiteMethods, claim_run_folder, score_dataset
from .sweep_figure import METRICS, sweep_plot

__all__ = ["METRICS", "parse_values", "run_sweep", "value_label"]

#: The top-level names ``omnivalidate sweep`` writes into its --out.
SWEEP_NAMES = ("sweep.json", "sweep.csv", "sweep.md", "sweep.png", "points")


def parse_values(text: str) -> list[Any]:
    """``2.8,4,8,inf`` or a TOML array ``[[0, 0], [0.1, 0]]``: each value a TOML value."""
    text = text.strip()
    src = text if text.startswith("[") else f"[{text}]"
    try:
        values = tomllib.loads(f"v = {src}")["v"]
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"--values {text!r}: expected V1,V2,... or a TOML array ({exc})") from exc
    if len(values) < 2:
        raise InputError(f"--values {text!r}: expected at least two values")
    return values


def value_label(v: Any) -> str:
    """A value as the docs write it (``inf``, ``2.8``, ``[0.1, 0]``)."""
    if isinstance(v, float) and math.isinf(v):
        return "inf" if v > 0 else "-inf"
    if isinstance(v, list):
        return "[" + ", ".join(value_label(x) for x in v) + "]"
    return f"{v:g}" if isinstance(v, float) else str(v)


def run_sweep(
    scene: Path,
    key: str,
    values: Sequence[Any],
    out: Path,
    *,
    methods: SuiteMethods,
    frames: int,
    resolution: int,
    settings: Mapping[str, Any] | None = None,
    progress: bool = True,
    log: Callable[[str], None] = print,
    command: str | None = None,
) -> dict[str, Any]:
    """Render and score ``scene`` at each value of ``key``; returns the sweep dict.

    ``settings`` are further scene overrides applied at every point. Raises the render
    job's one-line errors (SceneError for an unknown key or a bad value, ...) and
    InputError; what is finished stays on disk.
    """
    from omniflow.io.jsonio import jsonable
    from omnisim.job import render_dataset

    from .leaderboard import scene_rows

    claim_run_folder(out, "omnivalidate sweep", SWEEP_NAMES)
    base = {"frames": frames, "render.width": resolution, "render.height": resolution}
    base.update(settings or {})
    rows: list[dict[str, Any]] = []
    for i, v in enumerate(values):
        t0 = time.perf_counter()
        tag = f"omnivalidate sweep: [{i + 1}/{len(values)}] {key} = {value_label(v)}"
        point = out / "points" / f"{i:02d}"
        log(f"{tag}: rendering {frames} frames at {resolution} px")
        res = render_dataset(scene, point / "render", {**base, key: v}, progress=progress)
        log(f"{tag}: {len(res.rendered)} frames rendered, {len(res.skipped)} already there")
        state = {"value": value_label(v), "methods": methods.key()}
        summary, how = score_dataset(point / "render", point / "report",
                                     point / "state.json", methods, progress, state)  # fmt: skip
        for r in scene_rows(f"{i:02d}", "", summary):
            rows.append({"value": value_label(v), "index": i, **r, **_range_figures(summary, r)})
        log(f"{tag}: {how} in {time.perf_counter() - t0:.1f} s")
    sweep = jsonable({
        "format": "omnivalidate-sweep/1",
        "scene": str(scene),
        "parameter": key,
        "values": [value_label(v) for v in values],
        "frames": frames,
        "resolution": resolution,
        "settings": dict(settings or {}),
        "methods": methods.key(),
        "command": command,
        "rows": rows,
    })  # fmt: skip
    write_sweep(sweep, out)
    return sweep


def _range_figures(summary: Mapping[str, Any], row: Mapping[str, Any]) -> dict[str, Any]:
    """The median relative range error of the method's stereo points and the median
    relative time-to-contact error (None for a method without them): where a rig error
    shows when the matches stay right."""
    for m in summary.get("methods", []):
        if m.get("name") == row["method"] and m.get("points") in ("own", "dense"):
            rel_r = ((m.get("stereo") or {}).get("all") or {}).get("rel_r") or {}
            ttc = (m.get("derived") or {}).get("ttc_relative_error") or {}
            return {"range_error": rel_r.get("median"), "ttc_error": ttc.get("median")}
    return {"range_error": None, "ttc_error": None}


def _csv(sweep: Mapping[str, Any]) -> str:
    cols = ["value", "method", *METRICS, "fl", "wauc", "coverage", "tangential_gain", "time_s"]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([sweep["parameter"], *cols[1:]])
    for r in sweep["rows"]:
        w.writerow([r.get(c) for c in cols])
    return buf.getvalue()


def _fmt(metric: str, v: Any) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    return f"{v:.3f}" if metric in ("epe", "radial_gain") else f"{100 * v:.1f} %"


def _markdown(sweep: Mapping[str, Any]) -> str:
    key = sweep["parameter"]
    lines = [
        f"# Sweep: {key} on {Path(sweep['scene']).name}",
        "",
        f"{len(sweep['values'])} renders at {sweep['resolution']} px, {sweep['frames']} frames "
        "each; every other key as in the scene file. Metrics: docs/suite.md.",
        "",
    ]
    if sweep.get("command"):
        lines += ["```", sweep["command"], "```", ""]
    lines += ["![metrics against the value](sweep.png)", "",
              f"| {key} | method | " + " | ".join(METRICS) + " |",
              "|---|---|" + "---|" * len(METRICS)]  # fmt: skip
    for r in sweep["rows"]:
        cells = " | ".join(_fmt(m, r.get(m)) for m in METRICS)
        lines.append(f"| {r['value']} | `{r['method']}` | {cells} |")
    return "\n".join(lines) + "\n"


def write_sweep(sweep: Mapping[str, Any], out: Path) -> None:
    """sweep.json, .csv, .md and .png in ``out``, each written to a temporary name."""
    atomic_write_text(out / "sweep.json", json.dumps(sweep, indent=1) + "\n")
    atomic_write_text(out / "sweep.csv", _csv(sweep))
    sweep_plot(sweep, out / "sweep.png")
    atomic_write_text(out / "sweep.md", _markdown(sweep))
