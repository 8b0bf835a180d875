"""Write the report: per-frame CSV, summary JSON, figures, Markdown and HTML.

Layout of ``REPORT_DIR``::

    report.md, report.html     the same content; images by relative path
    summary.json               pooled statistics per method (summary.FORMAT)
    frames.csv                 one row per frame pair, method, point set, camera
    figures/*.png              inputs, panorama, flow, error maps, plots

The set is written into a temporary directory beside ``REPORT_DIR`` and renamed
into place at the end, so a reader sees the old report or the new one, never a
mix; an existing ``REPORT_DIR`` is replaced only if it is a previous report (its
marker file, or a ``summary.json`` of this format written before markers existed)
holding nothing but a report's files (:func:`check_out_dir`,
:mod:`omniflow.io.ownership`). One run per ``REPORT_DIR`` (:func:`report_lock`): a
second is refused with one line; the temporary directories of a dead run are
removed by the next.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import shutil
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from omniflow.cli.common import MACHINE_ERRNOS
from omniflow.io import ownership
from omniflow.io.imageio import OutputError, atomic_write_text
from omniflow.io.jsonio import jsonable

from .report_doc import Doc, fmt
from .report_figures import draw_figures, sweep_figure
from .report_tables import (
    bias_speed_table,
    bias_table,
    calibration_table,
    derived_table,
    flags_table,
    headline_table,
    method_table,
    movers_table,
    objects_table,
    polar_table,
    range_table,
    speed_table,
)
from .results import Results
from .scoring_flags import BREAK_PX
from .summary import FORMAT, summarize

__all__ = ["OUTPUTS", "check_out_dir", "report_lock", "write_report"]

PROG = "omnivalidate"


#: What write_report puts in REPORT_DIR (an existing directory holding only these is replaced).
OUTPUTS = ("report.md", "report.html", "summary.json", "frames.csv", "figures", "camera_sweep.csv")


def _document(summary: Mapping[str, Any], figures: Mapping[str, str], command: str | None) -> Doc:
    ds = summary["dataset"]
    doc = Doc()
    doc.h(1, f"omnivalidate: {ds['scene']}")
    doc.p(
        f"Dataset `{ds['path']}`: {ds['size'][0]}x{ds['size'][1]} px, {ds['frames']} frames, "
        f"frame interval {ds['frame_interval_s']} s, rig d = {ds['rig']['d']} m, "
        f"R = {ds['rig']['R']} m, s = {ds['rig']['s']} m. Scored frame pairs t -> t + 1 for "
        f"t = {', '.join(str(t) for t in ds['pairs'])}."
    )
    if command:
        doc.p("Reproduce with:")
        doc.code(command)
    doc.p(
        "**Units.** Flow in pixels per frame interval. omniflow estimates velocities per frame "
        "interval (eq. 16 with t in frames); the ground truth is the displacement of each "
        "material point from frame t to t + 1, and the two are compared directly. Every method "
        "sees the same frames (see Inputs). Times are wall-clock seconds per frame pair for both "
        "cameras, measured in this run. Baselines are dense; they are scored at the points of "
        "the default omniflow variant (`omniflow points`), at every valid pixel (`dense`), and "
        "for each variant at that variant's own points (column `DIS same pts`)."
    )
    doc.h(2, "Headline")
    doc.p(
        "The default omniflow variant against each baseline at the same points, per camera. "
        "Verdicts: better / worse = both mean and median EPE more than 10 % lower / higher, "
        "else comparable; biased = radial or tangential gain (least-squares slope of the "
        "estimated against the true component, through the origin; 1 = unbiased) outside "
        "1 +- 0.2, judged only where that component's true rms is at least 0.05 px; a "
        "method must be below 0.8 x zero flow's mean and median EPE to be "
        "clearly below it. Time to contact counts points that truly approach but are "
        "estimated as receding or infinite as failures (infinite error)."
    )
    doc.ul(summary.get("headline", []))
    doc.table(*headline_table(summary))
    doc.h(2, "Inputs")
    doc.p(f"The images every method saw: {ds.get('images', 'n/a')}.")
    for key, alt in (("inputs", "input frames"), ("panorama", "unwarped panorama of cam1")):
        if key in figures:
            doc.img(figures[key], alt)
    doc.h(2, "Flow: estimated vs ground truth")
    for key, alt in (
        ("flow_cam1", "estimated vs ground-truth flow, cam1"),
        ("flow_cam2", "estimated vs ground-truth flow, cam2"),
        ("error_maps", "error maps, cam1"),
    ):
        if key in figures:
            doc.img(figures[key], alt)
    doc.h(2, "Methods side by side (accuracy and time)")
    doc.p(
        "EPE = endpoint error (px), noc / occ = non-occluded / occluded points "
        "(`gt.flow.valid`), AE = angular error, >1px / >3px = outlier rates, stereo >1px = "
        "matches whose h_2 is more than 1 px from `gt.stereo.h_other`; r rel err = median "
        "|r - r_gt| / r_gt; match rate = matches / significant points the other camera sees."
    )
    doc.table(*method_table(summary))
    doc.h(3, "Polar components and angular error")
    doc.table(*polar_table(summary))
    doc.h(2, "Bias: how much of the true motion each method recovers")
    doc.p(
        "Gain = least-squares slope through the origin of the estimated against the true "
        "component (radial `dh`, tangential `h dtheta`), slope = straight-line fit, mean "
        "signed = mean of estimated minus true (px). 1 / 1 / 0 is unbiased; zero flow has gain 0."
    )
    doc.table(*bias_table(summary))
    doc.h(3, "Radial gain by true speed (cam1, non-occluded)")
    doc.table(*bias_speed_table(summary))
    flags = flags_table(summary)
    if flags[1]:
        doc.h(3, "Points flagged by the eq. (14) test")
        doc.p(
            "omniflow flags a point (`coupled` = 0) where its two-model test rejects eq. (14): "
            "its flow and range are not confident answers. flagged = share of the points; "
            "precision / recall of the flag against the points whose true axial motion "
            f"violates eq. (14) by at least {BREAK_PX:g} px per frame "
            "(validation/scoring_flags.py). "
            "The flow of the unflagged and the flagged points, apart."
        )
        doc.table(*flags)
    doc.h(2, "Objects: where each method answers (cam1)")
    doc.p(
        "Per object (`gt.object`, named from dataset.json): points scored over all frame "
        "pairs, their share of the object's valid pixels, and EPE mean / median (px). "
        "0 = the method scored no point on it; not in view = the camera sees none of it."
    )
    doc.table(*objects_table(summary))
    movers = movers_table(summary)
    if movers[1]:
        doc.h(3, "Moving objects: their own motion recovered")
        doc.table(*movers)
    doc.h(2, "Flow error by speed (cam1, non-occluded)")
    doc.table(*speed_table(summary))
    if "error_vs_speed" in figures:
        doc.img(figures["error_vs_speed"], "error vs speed")
    doc.h(2, "Stereo by range")
    doc.table(*range_table(summary))
    if "error_vs_range" in figures:
        doc.img(figures["error_vs_range"], "error vs range")
    cal = calibration_table(summary)
    if cal[1]:
        doc.h(2, "Calibration of the predicted sigmas")
        doc.p(
            "For each method that predicts a standard deviation per point: the share of "
            "points whose error is within 1 and within 2 predicted sigma (cam1 and cam2: "
            "endpoint error against the predicted RMS endpoint error, px; range: |r - r_gt| "
            "against sigma_r, m). The target is 90-97 % within 2 sigma. The diagram bins the "
            "points by predicted sigma and plots the observed error quantiles against it."
        )
        doc.table(*cal)
        if "reliability" in figures:
            doc.img(figures["reliability"], "reliability diagram of the predicted sigmas")
    doc.h(2, "Derived quantities")
    doc.p(
        "dr/dt and time to contact (TTC, frames) against the objects' known motion from the "
        "poses in dataset.json (TTC over points whose true range shrinks by more than 0.1 % per "
        "frame); odometry (omniflow.applications.navigation.odometry, robust fit) against the "
        "robot's "
        "known motion."
    )
    doc.table(*derived_table(summary))
    if "accuracy_vs_time" in figures:
        doc.img(figures["accuracy_vs_time"], "accuracy vs time")
    sweep = summary.get("camera_sweep")
    if sweep:
        key = sweep[0]["parameter"]
        doc.h(2, f"Camera sweep: accuracy vs {key}")
        doc.p(
            f"The same render scored with the camera's `{key}` at each level (the images "
            f"re-formed from the EXR radiance, `camera_sweep.csv`); the sections above are for "
            f"`{key}={sweep[0]['value']}`. EPE in px at each method's scored points "
            "(baselines at the default variant's points)."
        )
        doc.table(
            ["method", "camera", key, "n", "EPE mean", "EPE median", "radial gain",
             "tangential gain"],
            [[r["method"], r["camera"], str(r["value"]), fmt(r["n"]), fmt(r["epe_mean"]),
              fmt(r["epe_median"]), fmt(r["radial_gain"], 2), fmt(r["tangential_gain"], 2)]
             for r in sweep],
        )  # fmt: skip
        if "camera_sweep" in figures:
            doc.img(figures["camera_sweep"], f"accuracy vs camera {key}")
    for note in summary.get("notes", []):
        doc.p(note)
    return doc


def _csv_text(rows: Sequence[Mapping[str, Any]]) -> str:
    keys: list[str] = []
    for r in rows:
        for k in r:
            if k not in keys:
                keys.append(k)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: _csv_cell(r.get(k)) for k in keys})
    return buf.getvalue()


def _csv_cell(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, float | np.floating):
        return "" if not math.isfinite(float(v)) else repr(float(v))
    return v


def _owned(rel: PurePosixPath) -> bool:
    """A name write_report writes (``figures/`` holds PNGs only)."""
    if len(rel.parts) == 1:
        return rel.name in OUTPUTS or rel.name == ownership.MARKER
    return (
        len(rel.parts) == 2
        and rel.parts[0] == "figures"
        and (rel.name.endswith(".png") or rel.name == ownership.MARKER)
    )


def _legacy(folder: Path) -> bool:
    """A report written before markers existed: a summary.json of this format."""
    body = ownership.read_json(folder / "summary.json")
    return isinstance(body, dict) and body.get("format") == FORMAT


def check_out_dir(out_dir: str | Path) -> Path:
    """Raise InputError (one line) unless ``out_dir`` can receive a report.

    It must be a new path, an empty directory, or a previous report (its marker or
    a summary.json of :data:`~validation.summary.FORMAT`, and only :data:`OUTPUTS`,
    ``figures/*.png`` and markers) in a directory where a sibling can be created.
    """
    from .inputs import InputError

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: is a file; expected a directory (new or a report)")
    try:
        ownership.claim(out, prog=PROG, owned=_owned, legacy=_legacy)
    except OutputError as exc:
        raise InputError(f"--out {exc}") from None
    parent = out.absolute().parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        probe = tempfile.mkdtemp(prefix=f".{out.name}.probe-", dir=parent)
        os.rmdir(probe)
    except OSError as exc:
        if exc.errno in MACHINE_ERRNOS:  # a full disk: the machine refused (exit 1), not the path
            raise
        raise InputError(f"--out {out}: cannot write there ({exc.strerror or exc})") from exc
    return out


@contextmanager
def report_lock(out_dir: str | Path) -> Iterator[None]:
    """Hold the lock of report ``out_dir`` (``.NAME.lock`` beside it, removed after).

    Raises InputError (one line) when another process holds it; removes the
    temporary directories of dead runs (:func:`omniflow.io.ownership.remove_dead_temporaries`).
    """
    from .inputs import InputError

    out = Path(out_dir)
    parent = out.absolute().parent
    busy = (
        f"--out {out}: another omnivalidate process (pid {{pid}}) is writing this report; "
        "wait for it to finish or choose another --out"
    )
    try:
        key = ownership.lock_beside(out, busy)
    except ownership.LockedError as exc:
        raise InputError(str(exc)) from None
    except OutputError as exc:  # an ancestor of --out is a file
        raise InputError(f"--out {out}: cannot write there ({exc})") from None
    except OSError as exc:
        if exc.errno in MACHINE_ERRNOS:  # a full disk: the machine refused (exit 1)
            raise
        raise InputError(f"--out {out}: cannot write there ({exc.strerror or exc})") from exc
    try:
        for prefix in (f".{out.name}.tmp-", f".{out.name}.old-"):
            ownership.remove_dead_temporaries(parent, prefix)
        yield
    finally:
        ownership.unlock(key)


def _install(tmp: Path, out: Path) -> None:
    """Rename the finished directory ``tmp`` onto ``out`` (replacing a previous report)."""
    if out.is_dir():
        old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.absolute().parent))
        ownership.write_marker(old, PROG, pid=True)
        os.replace(out, old / "report")
        os.replace(tmp, out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, out)


def write_report(
    results: Results,
    out_dir: str | Path,
    *,
    command: str | None = None,
    sweep: Sequence[Mapping[str, Any]] | None = None,
) -> dict:
    """Write CSV, JSON, figures, Markdown and HTML into ``out_dir``; return the summary.

    The files are written into a temporary directory beside ``out_dir`` and renamed
    into place together (see :func:`check_out_dir` for what ``out_dir`` may be).
    """
    with report_lock(out_dir):
        return _write_report(results, check_out_dir(out_dir), command, sweep)


def _write_report(
    results: Results, final: Path, command: str | None, sweep: Sequence[Mapping[str, Any]] | None
) -> dict:
    out = Path(tempfile.mkdtemp(prefix=f".{final.name}.tmp-", dir=final.absolute().parent))
    try:
        ownership.write_marker(out, PROG, pid=True)
        summary = jsonable(summarize(results))
        if sweep:
            summary["camera_sweep"] = jsonable(sweep)
        atomic_write_text(
            out / "summary.json", json.dumps(summary, indent=1, allow_nan=False) + "\n"
        )
        atomic_write_text(out / "frames.csv", _csv_text(results.rows))
        (out / "figures").mkdir()
        ownership.write_marker(out / "figures", PROG)
        figures = draw_figures(results, summary, out / "figures")
        if sweep:
            atomic_write_text(out / "camera_sweep.csv", _csv_text(sweep))
            figures.update(sweep_figure(sweep, out / "figures"))
        doc = _document(summary, figures, command)
        atomic_write_text(out / "report.md", doc.markdown())
        title = f"omnivalidate: {summary['dataset']['scene']}"
        atomic_write_text(out / "report.html", doc.html(title))
        os.chmod(out, 0o755)  # mkdtemp makes it 0700
        _install(out, final)
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise
    return summary
