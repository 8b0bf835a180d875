"""Accuracy bounds on a suite's leaderboard: the regression guard CI runs on the mini suite.

A bounds file (``validation/mini_bounds.toml``) holds, per method and split, an upper
bound on each error figure and a lower bound on each figure where higher is better, all
MEASURED: ``python -m validation.suite_bounds LEADERBOARD.json --write BOUNDS.toml``
derives them from a leaderboard by the rule of ``validation/thresholds.toml`` (1.25 x the
measured value plus a small absolute slack for an upper bound, 0.8 x for a lower one,
rounded outward). A bound that could not fail (an upper bound on a fraction at or above
1, a lower bound at or below 0) is not written: the file lists those figures as
unguarded instead, so a method that fails a whole split is seen, not hidden.
``omnivalidate suite ... --check BOUNDS.toml`` compares the leaderboard it just wrote and
exits 1 when a figure is outside its bound or a bounded row is missing.

Renders are deterministic for a seed (docs/decisions/render_same_bytes.md) and so are
the methods, so the margins cover platform differences, not noise. Timing is never
bounded (the machines are shared).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omniflow.input_files import InputFileError, parse_text, read_input
from omniflow.io.imageio import atomic_write_text

__all__ = ["Bound", "BoundsError", "check_bounds", "derive_bounds", "load_bounds", "main"]

LOWER_BETTER = ("1px", "epe", "fl", "sparse_1px", "stereo_outliers")
HIGHER_BETTER = ("wauc", "coverage", "density")
GAINS = ("radial_gain", "tangential_gain")  # a band: a method that halves a component falls out
FRACTIONS = ("1px", "fl", "sparse_1px", "stereo_outliers", "wauc", "coverage", "density")
SLACK = {"epe": 0.02}  # absolute slack of an upper bound, px; fractions get SLACK_FRACTION
SLACK_FRACTION = 0.005  # half a percentage point: a figure measured at 0 still gets a bound
UP, DOWN = 1.25, 0.8  # the rule of validation/thresholds.toml
SPLITS = ("train", "test")


class BoundsError(ValueError):
    """A bounds file that cannot be read, one line naming the file and key."""


@dataclass(frozen=True)
class Bound:
    """One figure of one method on one split of the leaderboard, and where it may go."""

    method: str
    split: str
    metric: str
    max: float | None
    min: float | None
    measured: float


def _row(board: dict[str, Any], method: str, split: str) -> dict[str, Any] | None:
    for row in board.get("splits", {}).get(split, []):
        if row.get("method") == method:
            return row
    return None


def _round_out(v: float, up: bool) -> float:
    """Round to 3 significant digits away from the measured value."""
    if v == 0:
        return 0.0
    step = 10 ** (math.floor(math.log10(abs(v))) - 2)
    return float(f"{(math.ceil if up else math.floor)(v / step) * step:.6g}")


def derive_bounds(board: dict[str, Any]) -> tuple[list[Bound], list[str]]:
    """The bounds of every figure of every method on each split, and the unguarded ones
    (``method split metric = value``: a bound there could not fail)."""
    bounds, unguarded = [], []
    for split in SPLITS:
        for row in board.get("splits", {}).get(split, []):
            for metric in (*LOWER_BETTER, *HIGHER_BETTER, *GAINS):
                v = row.get(metric)
                if v is None:
                    continue
                if metric in GAINS:  # banded only where the method measures a gain near 1
                    if 0.5 <= v <= 2.0 and row.get("kind") == "omniflow":
                        bounds.append(Bound(row["method"], split, metric,
                                            _round_out(UP * v, up=True),
                                            _round_out(DOWN * v, up=False), float(v)))  # fmt: skip
                    else:
                        unguarded.append(f"{row['method']} {split} {metric} = {v:.4g}")
                    continue
                lower_better = metric in LOWER_BETTER
                if lower_better:
                    slack = SLACK.get(metric, SLACK_FRACTION)
                    b = _round_out(UP * v + slack, up=True)
                    vacuous = metric in FRACTIONS and b >= 1.0
                else:
                    b = _round_out(DOWN * v, up=False)
                    vacuous = b <= 0.0
                if vacuous:
                    unguarded.append(f"{row['method']} {split} {metric} = {v:.4g}")
                    continue
                bounds.append(Bound(row["method"], split, metric,
                                    b if lower_better else None,
                                    None if lower_better else b, float(v)))  # fmt: skip
    return bounds, unguarded


def check_bounds(board: dict[str, Any], bounds: Sequence[Bound]) -> list[tuple[bool, str]]:
    """Each bound's verdict and a one-line description of it."""
    out = []
    for b in bounds:
        row = _row(board, b.method, b.split)
        v = None if row is None else row.get(b.metric)
        where = f"{b.method} [{b.split}] {b.metric}"
        if v is None:
            out.append(
                (False, f"{where}: missing from the leaderboard (measured {b.measured:.4g})")
            )
            continue
        ok = (b.max is None or v <= b.max) and (b.min is None or v >= b.min)
        limit = " and ".join([*([f"<= {b.max:.4g}"] if b.max is not None else []),
                              *([f">= {b.min:.4g}"] if b.min is not None else [])])  # fmt: skip
        out.append((ok, f"{where} = {v:.4g} (bound {limit}, measured {b.measured:.4g})"))
    return out


def load_bounds(path: str | os.PathLike[str]) -> list[Bound]:
    """Read a bounds file; BoundsError (one line) for anything that is not a bound."""
    path = Path(path)
    try:
        data = parse_text(read_input(path, "TOML bounds file"), path, "toml")
    except OSError as exc:
        raise BoundsError(f"{path}: cannot read: {exc}") from exc
    except InputFileError as exc:
        raise BoundsError(str(exc)) from None
    entries = data.get("bound")
    if not isinstance(entries, list) or not entries:
        raise BoundsError(f"{path}: expected [[bound]] entries")
    bounds = []
    for i, e in enumerate(entries):
        where = f"{path}: bound[{i}]"
        if not isinstance(e, dict):
            raise BoundsError(f"{where}: expected a table")
        unknown = sorted(set(e) - {"method", "split", "metric", "max", "min", "measured"})
        if unknown:
            raise BoundsError(f"{where}: unknown key {unknown[0]!r}")
        for key in ("method", "split", "metric"):
            if not isinstance(e.get(key), str):
                raise BoundsError(f"{where}: key {key!r}: expected a string")
        if e["split"] not in SPLITS:
            raise BoundsError(f"{where}: key 'split' = {e['split']!r}: expected one of {SPLITS}")
        metrics = (*LOWER_BETTER, *HIGHER_BETTER, *GAINS)
        if e["metric"] not in metrics:
            raise BoundsError(f"{where}: key 'metric' = {e['metric']!r}: expected one of "
                              f"{metrics}")  # fmt: skip
        keys = ("max",) if e["metric"] in LOWER_BETTER else ("min",)
        keys = ("max", "min") if e["metric"] in GAINS else keys
        for k in (*keys, "measured"):
            if not isinstance(e.get(k), int | float) or isinstance(e.get(k), bool):
                raise BoundsError(f"{where}: key {k!r}: expected a number ({e['metric']} "
                                  f"takes {' and '.join(keys)})")  # fmt: skip
        for other in {"max", "min"} - set(keys):
            if other in e:
                raise BoundsError(f"{where}: key {other!r}: {e['metric']} takes {keys[0]} only")
        bounds.append(Bound(e["method"], e["split"], e["metric"],
                            float(e["max"]) if "max" in keys else None,
                            float(e["min"]) if "min" in keys else None,
                            float(e["measured"])))  # fmt: skip
    return bounds


def _render(bounds: Sequence[Bound], unguarded: Sequence[str], source: str, command: str) -> str:
    lines = [
        f"# Accuracy bounds of {source}, derived by validation/suite_bounds.py from:",
        f"#   {command}",
        "# upper bound = 1.25 x measured + slack (0.005 for a fraction, 0.02 px for epe),",
        "# lower bound = 0.8 x measured (an omniflow gain in 0.5-2: both), rounded outward.",
        "# Re-derive after a change of defaults and review the diff:",
        "#   python -m validation.suite_bounds LEADERBOARD.json --write FILE",
        "#",
        "# Unguarded (a bound could not fail):",
        *[f"#   {u}" for u in unguarded],
        "",
    ]
    for b in bounds:
        lines += ["[[bound]]", f'method = "{b.method}"', f'split = "{b.split}"',
                  f'metric = "{b.metric}"',
                  *([f"max = {b.max:.6g}"] if b.max is not None else []),
                  *([f"min = {b.min:.6g}"] if b.min is not None else []),
                  f"measured = {b.measured:.6g}", ""]  # fmt: skip
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m validation.suite_bounds LEADERBOARD.json --write BOUNDS.toml``."""
    import json

    ap = argparse.ArgumentParser(
        prog="python -m validation.suite_bounds",
        description="Derive a bounds file from a suite leaderboard.",
    )
    ap.add_argument("leaderboard", help="leaderboard.json of an omnivalidate suite run")
    ap.add_argument("--write", required=True, metavar="BOUNDS.toml", help="bounds file to write")
    args = ap.parse_args(argv)
    try:
        board = json.loads(Path(args.leaderboard).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        print(f"suite_bounds: error: {args.leaderboard}: cannot read: {exc}", file=sys.stderr)
        return 2
    bounds, unguarded = derive_bounds(board)
    suite = board.get("suite", {})
    m = suite.get("methods", {})
    names = ",".join([*m.get("omniflow", []), *m.get("baselines", [])])
    command = (f"omnivalidate suite {suite.get('path', '?')} --split {suite.get('split', '?')} "
               f"--out OUT --methods {names}")  # fmt: skip
    text = _render(bounds, unguarded, suite.get("path", "a suite"), command)
    atomic_write_text(Path(args.write), text)
    print(f"suite_bounds: {len(bounds)} bounds, {len(unguarded)} unguarded figures: {args.write}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
