"""``omnivalidate DATASET --out REPORT_DIR``: score omniflow and the baselines on a dataset.

Exit status: 0 done (and every threshold met when ``--check`` is given);
1 a threshold failed; 2 bad input (the one-line message names the problem).
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path

__all__ = ["main"]

_EPILOG = """\
outputs in REPORT_DIR:
  report.html, report.md   the report: inputs, panorama, flow vs truth, error maps,
                           error vs range / speed, the table of methods (accuracy, time)
  summary.json             pooled statistics per method (the thresholds read this)
  frames.csv               one row per frame pair, method, point set and camera
  figures/                 the pictures

methods: every omniflow variant (matching rule robust|paper, gradients first|average,
temporal difference|dct3d, solver direct|pooled), OpenCV DIS (medium) and Farneback
on the raw omni images, and DIS on the unwarped panoramas, all on the same 8-bit frames.
Flow is compared per frame interval: omniflow's velocities vs the true displacement.

examples:
  omnisim render scenes/default.toml --out runs/default --width 128 --spp 4 --frames 3
  omnivalidate runs/default --out runs/default-report
  omnivalidate runs/default --out runs/r --variants oat --check validation/thresholds.toml
"""


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
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
        "--baselines",
        default="DIS-medium,Farneback,DIS-medium-panorama",
        help="comma-separated baselines, or 'none' (default: %(default)s)",
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


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    from omniflow.dataset import DatasetError
    from omniflow.rig import RigError

    from . import baselines as bl
    from .report import write_report
    from .runner import InputError, run_validation
    from .thresholds import ThresholdError, check_summary, format_checks, load_thresholds

    def fail(msg: str) -> int:
        print(f"omnivalidate: error: {msg}", file=sys.stderr)
        return 2

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

    start = time.perf_counter()
    try:
        results = run_validation(
            args.dataset,
            variants=args.variants,
            baselines=names,
            frames=frames,
            progress=not args.no_progress,
        )
    except (DatasetError, RigError, InputError) as exc:
        return fail(str(exc).splitlines()[0])
    command = "omnivalidate " + " ".join(
        shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:])
    )
    summary = write_report(results, args.out, command=command)
    print(
        f"omnivalidate: {len(summary['methods'])} rows, {len(results.dataset['pairs'])} frame "
        f"pair(s) in {time.perf_counter() - start:.1f} s; report: "
        f"{Path(args.out) / 'report.html'}"
    )
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
