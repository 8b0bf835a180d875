"""Measure the bounds of ``validation/thresholds.toml`` from the current method.

    python -m validation.calibrate [--seeds 0 1 2] [--work runs/calibrate] [--scenes KEY ...]
                                   [--write]

The thresholds file says *what* is checked (scene, method, metric, and whether
the figure has an upper bound ``max`` or a lower bound ``min``); this tool says
*where* each bound goes, so that no threshold is guessed:

1. For each ``[scenes.KEY]`` it makes the dataset the end-to-end test makes
   (``omnisim render SCENE --resolution R --spp S --frames F --seed N``, or the
   closed-form demo of :mod:`validation.synthdata` for ``scene =
   "synthetic:demo"`` or ``"synthetic:vertical"``), once per seed, and runs the harness on it.
2. ``measured`` is the figure at the table's own ``seed`` (what CI sees: renders
   are deterministic for a seed).
3. The margin covers what legitimately moves a figure: render noise (the spread
   over the seeds, which re-draws every pixel's noise; for the closed-form scene,
   the texture) and platform differences (LLVM, OpenCV builds). An upper bound is
   1.25 x the worst value over the seeds; a lower bound 0.8 x the lowest (both
   rounded outward to 3 significant digits). A worse figure beyond that is a
   regression; a better one should be re-measured (the check prints
   ``[improved: tighten this threshold]``).

The tool prints the new file; ``--write`` replaces ``validation/thresholds.toml``.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import time
import tomllib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from omniflow.io import ownership
from omniflow.io.dataset import FORMAT_NAME

from .summary import get_path

__all__ = ["main", "make_dataset"]

HERE = Path(__file__).resolve().parent
DEFAULT_FILE = HERE / "thresholds.toml"
REPO = HERE.parent
UPPER = 1.25
LOWER = 0.8
#: Metrics that are fractions: an upper bound above 1 is capped at 1.
FRACTIONS = {"outliers", "out1", "out3", "match_rate"}


def _a_dataset(folder: Path) -> bool:
    """A dataset written before markers existed: a dataset.json of the omnisim format."""
    body = ownership.read_json(folder / "dataset.json")
    return isinstance(body, dict) and body.get("format") == FORMAT_NAME


def make_dataset(spec: dict[str, Any], out: Path, seed: int) -> Path:
    """Make the dataset a ``[scenes.KEY]`` table describes (render or closed form) in a
    new directory ``out`` (an old one is removed: scene files change; only a dataset
    this project wrote, :mod:`omniflow.io.ownership`)."""
    if ownership.claim(out, prog="validation.calibrate", owned=lambda rel: True,
                       legacy=_a_dataset):  # fmt: skip
        shutil.rmtree(out)
    scene = spec["scene"]
    if scene.startswith("synthetic:"):
        from .synthdata import SCENES, write_synthetic_dataset

        kind = scene.split(":", 1)[1]
        if kind not in SCENES:
            raise ValueError(f"scene {scene!r}: expected synthetic:{'|'.join(SCENES)}")
        make = SCENES[kind]
        write_synthetic_dataset(out, make(int(spec["resolution"]), seed=3 + seed),
                                int(spec["frames"]), name=f"synthetic-{kind}")  # fmt: skip
        return out
    cmd = [
        sys.executable,
        "-m",
        "omnisim.cli",
        "render",
        str(REPO / scene),
        "--out",
        str(out),
        "--resolution",
        str(spec["resolution"]),
        "--spp",
        str(spec["spp"]),
        "--frames",
        str(spec["frames"]),
        "--seed",
        str(seed),
        "--no-progress",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"render failed ({' '.join(cmd)}):\n{proc.stderr[-3000:]}")
    return out


def _summary(spec: dict[str, Any], dataset: Path, report: Path) -> dict[str, Any]:
    from .report import write_report
    from .runner import run_validation

    res = run_validation(dataset, variants=spec.get("variants", "all"), progress=False)
    return write_report(res, report)


def _entry(summary: dict[str, Any], method: str, points: str | None) -> dict[str, Any]:
    for m in summary["methods"]:
        if (m["name"] == method or (method == "default" and m.get("default"))) and (
            points is None or m["points"] == points
        ):
            return m
    raise KeyError(f"method {method!r} ({points}) not in the summary")


def _round_out(v: float, up: bool) -> float:
    if v == 0 or not math.isfinite(v):
        return v
    e = math.floor(math.log10(abs(v))) - 2
    q = v / 10**e
    q = math.ceil(q) if up else math.floor(q)
    return float(f"{q * 10**e:.6g}")


def _fmt(v: Any) -> str:
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        return repr(float(f"{v:.6g}"))
    return str(v)


def _render_file(header: str, scenes: dict[str, Any]) -> str:
    out = [header.rstrip(), ""]
    for key, spec in scenes.items():
        out.append(f"[scenes.{key}]")
        for k in ("description", "scene", "resolution", "spp", "frames", "seed", "variants"):
            if k in spec:
                out.append(f"{k} = {_fmt(spec[k])}")
        if spec.get("dropped"):
            out.append(
                "# checks the current method cannot be measured on (no points at this seed):"
            )
            out.append("dropped = [")
            out.extend(f"    {_fmt(d)}," for d in spec["dropped"])
            out.append("]")
        out.append("")
        for c in spec["check"] + [dict(c, _pending=True) for c in spec.get("pending", [])]:
            kind = "pending" if c.pop("_pending", False) else "check"
            out.append(f"[[scenes.{key}.{kind}]]")
            for k in ("method", "points", "metric", "min", "max", "measured", "margin", "note",
                      "fixed"):  # fmt: skip
                if k in c:
                    out.append(f"{k} = {_fmt(c[k])}")
            out.append("")
    return "\n".join(out).rstrip() + "\n"


def _header(text: str) -> str:
    lines = []
    for line in text.splitlines():
        if line.startswith("[") or (line.strip() and not line.startswith("#")):
            break
        lines.append(line)
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m validation.calibrate",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument(
        "--file", default=str(DEFAULT_FILE), help="thresholds file (default: %(default)s)"
    )
    ap.add_argument(
        "--seeds",
        type=int,
        nargs="+",
        default=[0, 1, 2],
        help="render seeds to measure over (default: 0 1 2)",
    )
    ap.add_argument(
        "--work", default="runs/calibrate", help="datasets and reports (default: %(default)s)"
    )
    ap.add_argument("--scenes", nargs="*", default=None, help="only these [scenes.KEY] tables")
    ap.add_argument("--write", action="store_true", help="replace the thresholds file")
    args = ap.parse_args(argv)

    start = time.perf_counter()
    path = Path(args.file)
    text = path.read_text()
    data = tomllib.loads(text)
    scenes = data["scenes"]
    work = Path(args.work)
    for key, spec in scenes.items():
        if args.scenes and key not in args.scenes:
            continue
        seeds = sorted(set(args.seeds) | {int(spec.get("seed", 0))})
        # Checks that could not be measured last time are tried again (a better render may
        # give them points); those still unmeasurable stay pending, not lost.
        spec["check"] = list(spec.get("check", [])) + list(spec.pop("pending", []))
        values: dict[int, list[float]] = {i: [] for i in range(len(spec["check"]))}
        own: dict[int, float] = {}
        for seed in seeds:
            ds = make_dataset(spec, work / f"{key}-seed{seed}", seed)
            summary = _summary(spec, ds, work / f"{key}-seed{seed}-report")
            for i, c in enumerate(spec["check"]):
                try:
                    v = get_path(_entry(summary, c["method"], c.get("points")), c["metric"])
                except KeyError as exc:
                    print(f"{key} seed {seed}: {exc}", file=sys.stderr)
                    v = None
                v = math.nan if v is None else float(v)
                values[i].append(v)
                if seed == int(spec.get("seed", 0)):
                    own[i] = v
            print(f"{key} seed {seed}: done", file=sys.stderr)
        kept, pending = [], []
        for i, c in enumerate(spec["check"]):
            vals = [v for v in values[i] if math.isfinite(v)]
            shown = ", ".join(f"{v:.4g}" for v in values[i])
            c["measured"] = own[i]
            if not math.isfinite(own[i]):
                # CI would see this NaN: the check waits in [[scenes.KEY.pending]], said so.
                c["margin"] = (
                    f"not measurable at seed {spec.get('seed', 0)} (seeds {seeds}: {shown}); "
                    "re-tried by every calibration"
                )
                pending.append(c)
                pts = f" @{c['points']}" if c.get("points") else ""
                print(f"{key}: pending {c['method']}{pts} {c['metric']}", file=sys.stderr)
                continue
            if c.get("fixed"):
                kept.append(c)  # the bound is what the figure means; only `measured` moves
                continue
            if "max" in c:
                worst = max(vals)
                # 25 % of the value's size above it (also for negative values, e.g. a gain).
                bound = worst + (UPPER - 1) * abs(worst) if worst != 0 else 0.01
                c["max"] = _round_out(bound, up=True)
                c["margin"] = (
                    f"the worst of seeds {seeds} ({shown}) + {UPPER - 1:g} x its size, rounded up; "
                    "covers render noise and platform differences"
                )
                if c["metric"].rsplit(".", 1)[-1] in FRACTIONS and c["max"] > 1.0:
                    c["max"] = 1.0
                    c["margin"] += " (a fraction: capped at 1)"
            if "min" in c:
                low = min(vals)
                c["min"] = _round_out(low - (1 - LOWER) * abs(low), up=False)
                upper = c["margin"] + "; " if "max" in c else ""
                c["margin"] = upper + (
                    f"the lowest of seeds {seeds} ({shown}) - {1 - LOWER:.2g} x its size, rounded "
                    "down; "
                    "covers render noise and platform differences"
                )
            kept.append(c)
        spec["check"] = kept
        if pending:
            spec["pending"] = pending
    new = _render_file(_header(text), scenes)
    if args.write:
        from omniflow.io.imageio import atomic_write_text

        atomic_write_text(path, new)  # a reader never sees half a file
        print(f"wrote {path} in {time.perf_counter() - start:.0f} s", file=sys.stderr)
    else:
        print(new)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
