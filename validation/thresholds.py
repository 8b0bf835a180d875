"""Accuracy thresholds: read ``validation/thresholds.toml`` and check a summary against it.

File layout (TOML)::

    [scenes.KEY]                      # KEY: the dataset's scene name (dataset.json scene.name)
    dataset = "how the dataset was made (command, size, spp, frames, seed)"

    [[scenes.KEY.check]]
    method = "omniflow:default"       # a row of summary.json (validation.variants
                                      # .variant_name); "default": the default row too
    points = "own"                    # optional: "own" | "omniflow points" | "dense"
    metric = "flow.cam1.noc.epe.median"   # dotted path inside that row
    max = 0.20                        # and/or min = ...
    measured = 0.15                   # the value the current method gave
    margin = "why max is where it is"
    fixed = true                      # optional: a bound set by what the figure means (e.g.
                                      # radial gain in [0.8, 1.2] for an unbiased method),
                                      # which calibration keeps; it updates only `measured`

    [[scenes.KEY.pending]]            # a check the current method cannot be measured on
    ...                               # (no points at this seed): not checked, re-tried by
                                      # every `python -m validation.calibrate`

A check passes when the value is finite and within [min, max]. A figure that
improves beyond its threshold's margin should tighten the threshold (see
docs/validation.md).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omniflow.input_files import InputFileError, parse_text, read_input

from .summary import get_path

__all__ = [
    "SCENE_KEYS",
    "Check",
    "ThresholdError",
    "check_summary",
    "format_checks",
    "load_thresholds",
]

_DEFAULT_FILE = Path(__file__).with_name("thresholds.toml")
_CHECK_KEYS = {"method", "points", "metric", "max", "min", "measured", "margin", "note", "fixed"}
#: Keys of a [scenes.KEY] table besides its checks: how the end-to-end test makes the dataset.
SCENE_KEYS = {
    "scene",
    "resolution",
    "spp",
    "frames",
    "seed",
    "variants",
    "description",
    "dataset",
    "check",
    "dropped",
    "pending",
}


class ThresholdError(ValueError):
    """The thresholds file is malformed, or names a method/metric the summary lacks."""


@dataclass(frozen=True)
class Check:
    scene: str
    method: str
    points: str | None
    metric: str
    value: float
    min: float | None
    max: float | None
    measured: float | None
    passed: bool
    note: str = ""

    def line(self) -> str:
        bound = " and ".join(
            b
            for b in (
                None if self.min is None else f">= {self.min:g}",
                None if self.max is None else f"<= {self.max:g}",
            )
            if b
        )
        pts = f" @{self.points}" if self.points else ""
        meas = "" if self.measured is None else f" (measured {self.measured:g})"
        return (
            f"{'PASS' if self.passed else 'FAIL'} {self.scene}: {self.method}{pts} "
            f"{self.metric} = {self.value:.4g}, required {bound}{meas}"
        )


def load_thresholds(path: str | Path | None = None) -> dict[str, Any]:
    """Parse and validate a thresholds file (default: the one beside this module)."""
    path = Path(path) if path is not None else _DEFAULT_FILE
    try:
        data = parse_text(read_input(path, "TOML thresholds file"), path, "toml")
    except OSError as exc:
        raise ThresholdError(f"{path}: cannot read: {exc}") from exc
    except InputFileError as exc:
        raise ThresholdError(str(exc)) from None
    scenes = data.get("scenes")
    if not isinstance(scenes, dict) or not scenes:
        raise ThresholdError(f"{path}: expected [scenes.NAME] tables")
    for name, scene in scenes.items():
        if not isinstance(scene, dict):
            raise ThresholdError(f"{path}: scenes.{name}: expected a table")
        unknown = set(scene) - SCENE_KEYS
        if unknown:
            raise ThresholdError(
                f"{path}: scenes.{name}: unknown key(s) {sorted(unknown)}; "
                f"expected {sorted(SCENE_KEYS)}"
            )
        checks = scene.get("check")
        if not isinstance(checks, list) or not checks:
            raise ThresholdError(f"{path}: scenes.{name}: expected [[scenes.{name}.check]] entries")
        for i, c in enumerate(checks):
            where = f"{path}: scenes.{name}.check[{i}]"
            unknown = set(c) - _CHECK_KEYS
            if unknown:
                raise ThresholdError(f"{where}: unknown key(s) {sorted(unknown)}")
            for key in ("method", "metric"):
                if not isinstance(c.get(key), str):
                    raise ThresholdError(f"{where}.{key}: expected a string")
            if "min" not in c and "max" not in c:
                raise ThresholdError(f"{where}: expected 'min' and/or 'max'")
            for key in ("min", "max", "measured"):
                if key in c and (isinstance(c[key], bool) or not isinstance(c[key], int | float)):
                    raise ThresholdError(f"{where}.{key}: expected a number")
            if "measured" not in c or not isinstance(c.get("margin"), str):
                raise ThresholdError(
                    f"{where}: every threshold needs 'measured' (the value it was set from) and "
                    "'margin' (why the bound sits where it does)"
                )
    return data


def _method_entry(summary: Mapping[str, Any], method: str, points: str | None) -> dict:
    for m in summary["methods"]:
        name_ok = m["name"] == method or (method == "default" and m.get("default"))
        if name_ok and (points is None or m["points"] == points):
            return m
    raise ThresholdError(
        f"method {method!r}"
        + (f" at points {points!r}" if points else "")
        + " is not in the summary (was it run? see --variants / --baselines)"
    )


def check_summary(
    summary: Mapping[str, Any], thresholds: Mapping[str, Any], scene: str
) -> list[Check]:
    """Evaluate every check of ``scene``; a missing or non-finite figure fails."""
    scenes = thresholds["scenes"]
    if scene not in scenes:
        raise ThresholdError(f"no [scenes.{scene}] in the thresholds file (has {sorted(scenes)})")
    out = []
    for c in scenes[scene]["check"]:
        entry = _method_entry(summary, c["method"], c.get("points"))
        try:
            value = get_path(entry, c["metric"])
        except KeyError as exc:
            raise ThresholdError(f"scenes.{scene}: {c['method']}: metric {exc}") from exc
        value = math.nan if value is None else float(value)
        ok = math.isfinite(value)
        if "min" in c:
            ok &= value >= c["min"]
        if "max" in c:
            ok &= value <= c["max"]
        out.append(
            Check(
                scene=scene,
                method=entry["name"],
                points=c.get("points"),
                metric=c["metric"],
                value=value,
                min=c.get("min"),
                max=c.get("max"),
                measured=c.get("measured"),
                passed=bool(ok),
                note=c.get("note", ""),
            )
        )
    return out


def format_checks(checks: Sequence[Check]) -> str:
    lines = [c.line() for c in checks]
    n_fail = sum(not c.passed for c in checks)
    lines.append(f"thresholds: {len(checks) - n_fail} passed, {n_fail} failed")
    return "\n".join(lines)
