"""``omnivalidate DATASET --out REPORT_DIR``: score omniflow and the baselines on a dataset.

Exit status: 0 done (and every threshold met when ``--check`` is given);
1 a threshold failed, or the machine refused (a full disk: the message names the path);
2 bad input (the one-line message names the problem); 130 interrupted by Ctrl-C, 143 by
SIGTERM (one line; nothing written to --out).
"""

from __future__ import annotations

import argparse
import contextlib
import shlex
import sys
import time
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from omniflow.interrupts import run_main

__all__ = ["main"]

_EPILOG = """\
outputs in REPORT_DIR:
  report.html, report.md   the report: inputs, panorama, flow vs truth, error maps,
                           error vs range / speed, the table of methods (accuracy, time)
  summary.json             pooled statistics per method (the thresholds read this)
  frames.csv               one row per frame pair, method, point set and camera
                           (EPE mean/median, radial/tangential gain and signed error,
                           density, stereo, time to contact)
  camera_sweep.csv         with --camera-sweep: accuracy per method at each level
  figures/                 the pictures
  (written into a temporary directory beside REPORT_DIR, renamed into place at the end)

methods: every omniflow variant (matching rule robust|paper, gradients first|average,
temporal difference|dct3d, solver direct|pooled), OpenCV DIS (medium) and Farneback
on the raw omni images, DIS on the unwarped panoramas, and zero flow (the floor), all on
the same frames (the dataset's camera model, with --camera overrides, else 8-bit luminance).
Flow is compared per frame interval: omniflow's velocities vs the true displacement.

scoring another method (--method-output DIR, repeatable; format in docs/validation.md):
  DIR/frames/NNNNNN/cam1.flo, cam2.flo   dense Middlebury flow (dx, dy) from frame NNNNNN to
                                         the next, scored like a baseline, or
  DIR/frames/NNNNNN/flow.csv             per-point CSV with omniflow's columns (x, y, dx, dy
                                         required; x2 y2 dx2 dy2 h2 r h dr_dt ... optional)
  python -m validation.examples.dis_method_output runs/default runs/dis-out
  omnivalidate runs/default --out runs/r --method-output runs/dis-out

a benchmark suite (every scene, every method, one leaderboard): omnivalidate suite --help
accuracy against one scene key, a render per value: omnivalidate sweep --help

examples:
  omnisim render scenes/default.toml --out runs/default --resolution 128 --spp 4 --frames 3
  omnivalidate runs/default --out runs/default-report
  omnivalidate runs/default --out runs/r --variants oat --check validation/thresholds.toml
  omnivalidate runs/default --out runs/r --variants default --camera-sweep read_noise=0,5,20,50
"""


class _Parser(argparse.ArgumentParser):
    """Usage errors as one line, like omniflow's and omnisim's (not the usage block)."""

    def error(self, message: str) -> typing.NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _thresholds_unmet(thresholds: dict, args: argparse.Namespace, variants: Any,
                      baselines: list[str]) -> str | None:  # fmt: skip
    """Why --check cannot be answered by this run (said before the run, not after it):
    the dataset's scene has no thresholds, or a threshold names a row not run."""
    import json

    from .variants import omniflow_variants

    key = args.scene_key
    if key is None:
        try:  # the scene's name, as the summary will give it; a broken file is named later
            scene = json.loads((Path(args.dataset) / "dataset.json").read_text()).get("scene")
            key = scene.get("name") if isinstance(scene, dict) else None
        except (OSError, ValueError, AttributeError, RecursionError):  # named by the loader
            return None
        if key not in thresholds["scenes"]:
            return (
                f"--check {args.check}: no thresholds for this dataset's scene {key!r}; "
                f"give --scene-key, one of {sorted(thresholds['scenes'])}"
            )
    if args.method_output:  # rows named by the outputs: known once they are read
        return None
    rows = omniflow_variants(variants) if isinstance(variants, str) else variants
    ran = {name for name, _ in rows} | set(baselines) | {"default"}
    missing = sorted({c["method"] for c in thresholds["scenes"][key]["check"]} - ran)
    if not missing:
        return None
    return (
        f"--check {args.check}: scenes.{key} checks {len(missing)} row(s) this run does not "
        f"score (first: {missing[0]}); use --variants oat or all, or the baselines it names"
    )


def _parser() -> argparse.ArgumentParser:
    ap = _Parser(
        prog="omnivalidate",
        description="Measure how accurate omniflow's variants and the OpenCV baselines are on an "
        "omnisim dataset (any directory in the dataset contract: dataset.json + "
        "frames/NNNNNN/cam1.exr, cam2.exr), and write a report.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("dataset", help="dataset directory (holds dataset.json)")
    ap.add_argument("--out", required=True, help="report directory (created if needed)")
    ap.add_argument(
        "--variants",
        default="all",
        choices=("all", "oat", "default"),
        help="omniflow rows: 'all' combinations of the four choices (16 rows), 'oat' "
        "the default plus one choice changed at a time; both also run the paper's "
        "exact configuration and the flow step on the true matches; 'default' only "
        "the default configuration (default: %(default)s)",
    )
    ap.add_argument(
        "--row",
        action="append",
        default=[],
        metavar="NAME=VALUE[,NAME=VALUE...]",
        help="one more omniflow row: the default configuration with these OmniFlowConfig "
        "knobs changed, a group's by its dotted name (e.g. --row fit.flow_taper=0 --row "
        "pooling.eiv=none,fit.sampling=exact), or a preset and changes (--row dense, --row "
        "dense,pooling.pool_k=64); the row is named after the nearest preset and the knobs "
        "that differ (omniflow:dense+pooling.pool_k=64); repeatable",
    )
    ap.add_argument(
        "--registration",
        default=None,
        metavar="recorded|none|RIG_FILE[,...]",
        help="what omniflow is told about the rig: 'recorded' the dataset's rig, with its "
        "true [rig.errors] if any (an oracle registration); 'none' the ideal rig of eq. (1), "
        "no rectification (an unregistered rig); or a rig file, e.g. from omniflow calibrate "
        "(a card's registration). Comma-separated: each omniflow row once per choice, named "
        "+registration=none / =card; the truth and the baselines are not affected "
        "(default: recorded)",
    )
    ap.add_argument(
        "--baselines",
        default="DIS-medium,Farneback,DIS-medium-panorama,zero-flow",
        help="comma-separated baselines, or 'none'; zero-flow predicts no motion, the floor "
        "every method must clearly beat; slower ones by name: DIS-fine, DeepFlow, DualTVL1, "
        "PCAFlow, RLOF, each also as NAME-panorama (default: %(default)s)",
    )
    ap.add_argument(
        "--frames",
        default=None,
        help="frame pairs to score, as first frames t (pair t -> t+1): e.g. '0,1' or "
        "'0-4' (default: every complete pair)",
    )
    ap.add_argument(
        "--check",
        metavar="THRESHOLDS_TOML",
        default=None,
        help="compare the summary with a thresholds file (validation/thresholds.toml) "
        "and exit 1 if a figure falls below its threshold",
    )
    ap.add_argument(
        "--scene-key",
        default=None,
        help="which [scenes.KEY] of the thresholds file applies (default: the "
        "dataset's scene name)",
    )
    ap.add_argument(
        "--method-output",
        action="append",
        default=[],
        metavar="DIR",
        help="score another method's outputs in DIR (dense .flo or per-point flow.csv per "
        "frame, laid out like the dataset; see below); repeatable",
    )
    ap.add_argument(
        "--method-name",
        action="append",
        default=[],
        metavar="NAME",
        help="row name of each --method-output, in order (default: the directory's name)",
    )
    ap.add_argument(
        "--camera",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="camera-model parameter (omnisim.camera: exposure, full_well, read_noise, gain, "
        "bits, response, vignetting, defocus, seed) applied to the radiance when the images "
        "are formed, over the dataset's own camera; repeatable",
    )
    ap.add_argument(
        "--camera-sweep",
        default=None,
        metavar="KEY=V1,V2,...",
        help="score the same render at each level of one camera parameter and write an "
        "accuracy-vs-level table and plot (camera_sweep.csv); the rest of the report is "
        "for the first level",
    )
    ap.add_argument(
        "--partial",
        action="store_true",
        help="score the complete pairs of an incomplete dataset (default: refuse it)",
    )
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    return ap


def _frames(text: str | None) -> list[int] | None:
    if text is None:
        return None
    out: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        if "-" in part:
            a, b = part.split("-", 1)
            out.extend(range(int(a), int(b) + 1))
        else:
            out.append(int(part))
    return out


def _closing_line(summary: dict, pairs: int, seconds: float, report: Path) -> str:
    """The run's last line: methods (a baseline scored at two point sets is one method in
    two table rows), pairs, time and the report."""
    methods = summary["methods"]
    names = len({m["name"] for m in methods})

    def count(n: int, word: str) -> str:
        return f"{n} {word}" + ("" if n == 1 else "s")

    return (f"omnivalidate: {count(names, 'method')} in {count(len(methods), 'table row')}, "
            f"{count(pairs, 'frame pair')} in {seconds:.1f} s; report: {report}")  # fmt: skip


#: What an interrupted run leaves (the report is renamed into place at the end).
NOTE = "nothing was written to --out"
#: What an interrupted ``omnivalidate suite`` leaves.
SUITE_NOTE = "finished scenes and frames are kept; run the same command again to resume"
#: What an interrupted ``omnivalidate sweep`` leaves.
SWEEP_NOTE = "finished renders and reports are kept; run the same command again to resume"


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``omnivalidate``: the exit status (module docstring); Ctrl-C or
    SIGTERM is one line, status 130 / 143 (:mod:`omniflow.interrupts`)."""
    keep = argv is None  # a console script: keep the handler for the shutdown
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["suite"]:
        return run_main("omnivalidate suite", lambda: _suite(argv[1:]), note=SUITE_NOTE, keep=keep)
    if argv[:1] == ["sweep"]:
        return run_main("omnivalidate sweep", lambda: _sweep(argv[1:]), note=SWEEP_NOTE, keep=keep)
    return run_main("omnivalidate", lambda: _main(argv), note=NOTE, keep=keep)


def _suite(argv: list[str]) -> int:
    from .suite_cli import main as suite_main  # the subcommand: omnivalidate suite ...

    return suite_main(argv)


def _sweep(argv: list[str]) -> int:
    from .sweep_cli import main as sweep_main  # omnivalidate sweep SCENE --key ...

    return sweep_main(argv)


def _main(argv: list[str]) -> int:
    args = _parser().parse_args(argv)
    from omniflow.cli.common import MACHINE_ERRNOS
    from omniflow.geometry.rig import RigError
    from omniflow.io.dataset import DatasetError

    from . import baselines as bl
    from .external import ExternalOutput
    from .report import check_out_dir, report_lock, write_report
    from .runner import InputError, run_validation
    from .summary import sweep_rows
    from .thresholds import ThresholdError, check_summary, format_checks, load_thresholds

    def fail(msg: str, status: int = 2) -> int:
        print(f"omnivalidate: error: {msg}", file=sys.stderr)
        return status

    try:
        frames = _frames(args.frames)
    except ValueError:
        return fail(f"--frames {args.frames!r}: expected numbers like '0,1' or '0-4'")
    names = (
        []
        if args.baselines.strip().lower() == "none"
        else [b.strip() for b in args.baselines.split(",") if b.strip()]
    )
    unknown = [b for b in names if b not in bl.BASELINES]
    if unknown:
        return fail(f"--baselines: unknown {unknown}; expected some of {list(bl.BASELINES)}")
    thresholds = None
    if args.check:
        try:
            thresholds = load_thresholds(args.check)
        except ThresholdError as exc:
            return fail(str(exc))
    if not Path(args.dataset).is_dir():
        return fail(f"{args.dataset}: no such dataset directory")
    if args.scene_key is not None and thresholds is None:
        return fail("--scene-key: only with --check THRESHOLDS_TOML")
    if args.scene_key is not None and thresholds is not None:
        if args.scene_key not in thresholds["scenes"]:
            return fail(
                f"--scene-key {args.scene_key!r}: not in {args.check}; expected one of "
                f"{sorted(thresholds['scenes'])}"
            )
    if len(args.method_name) > len(args.method_output):
        return fail("--method-name: more names than --method-output directories")
    variants: Any = args.variants
    if args.row:
        from omniflow.cli.common import CLIError, config_from_settings

        from .variants import omniflow_variants, variant_name

        variants = omniflow_variants(args.variants, true_matches=args.variants != "default")
        for text in args.row:
            try:
                config = config_from_settings(text)
            except CLIError as exc:
                return fail(f"--row {text}: {exc}")
            name = variant_name(config)
            if name in dict(variants):
                return fail(f"--row {text}: the row {name} is already scored")
            variants.append((name, config))
    if args.registration is not None:
        from .runner import InputError
        from .variants import omniflow_variants, with_registration

        if isinstance(variants, str):
            variants = omniflow_variants(variants, true_matches=variants != "default")
        try:
            variants = with_registration(variants, args.registration)
        except InputError as exc:
            return fail(str(exc))
    if thresholds is not None:
        problem = _thresholds_unmet(thresholds, args, variants, names)
        if problem:
            return fail(problem)
    levels: list[list[str]] = [[]]
    if args.camera_sweep is not None:
        key, sep, vals = args.camera_sweep.partition("=")
        values = [v.strip() for v in vals.split(",") if v.strip()]
        if not sep or not key.strip() or not values:
            return fail(f"--camera-sweep {args.camera_sweep!r}: expected KEY=V1,V2,...")
        levels = [[f"{key.strip()}={v}"] for v in values]

    start = time.perf_counter()
    with contextlib.ExitStack() as held:
        try:
            held.enter_context(report_lock(args.out))  # one run per --out
            check_out_dir(args.out)
            external = [
                ExternalOutput(d, args.method_name[i] if i < len(args.method_name) else None)
                for i, d in enumerate(args.method_output)
            ]
            sweep: list[dict] = []
            results = None
            for level in levels:
                res = run_validation(
                    args.dataset,
                    variants=variants,
                    baselines=names,
                    frames=frames,
                    progress=not args.no_progress,
                    external=external,
                    camera=[*args.camera, *level],
                    partial=args.partial,
                )
                if level:
                    from omniflow.io.jsonio import jsonable

                    from .summary import summarize

                    key, value = level[0].split("=", 1)
                    sweep += sweep_rows(jsonable(summarize(res)), key, value)
                results = results or res
            command = "omnivalidate " + " ".join(shlex.quote(a) for a in argv)
            summary = write_report(results, args.out, command=command, sweep=sweep or None)
        except (DatasetError, RigError, InputError) as exc:
            return fail(str(exc).splitlines()[0])
        except OSError as exc:
            if exc.errno in MACHINE_ERRNOS:  # a full disk: the machine refused (1), named by --out
                return fail(f"--out {args.out}: {exc.strerror or exc}; nothing was written", 1)
            return fail(f"{exc.filename or args.out}: {exc.strerror or exc}")
    print("\n".join(summary.get("headline", [])))
    print(_closing_line(summary, len(results.dataset["pairs"]), time.perf_counter() - start,
                        Path(args.out) / "report.html"))  # fmt: skip
    if thresholds is not None:
        key = args.scene_key or summary["dataset"]["scene"]
        try:
            checks = check_summary(summary, thresholds, key)
        except ThresholdError as exc:
            return fail(str(exc))
        print(format_checks(checks))
        if any(not c.passed for c in checks):
            return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
