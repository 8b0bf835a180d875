"""End to end: make datasets, run the harness, hold the accuracy figures to their thresholds.

The datasets and the thresholds come from one reviewed file,
``validation/thresholds.toml``: each ``[scenes.KEY]`` names a scene and the
size, samples per pixel, frames and seed to render it with, and the figures
(with bounds measured by ``python -m validation.calibrate``) it must meet.

* ``test_synthetic_end_to_end`` needs no renderer: the closed-form scenes of
  :mod:`validation.synthdata` (the demo, and a pillar rising, which breaks
  eq. 14) written in the dataset contract.
* ``test_rendered_scene`` renders each scene with ``omnisim render`` (Mitsuba)
  at 128 px, 4 spp, 3 frames, and runs ``omnivalidate`` on it, including the
  scenes where the paper's assumptions break (vertical motion, large motion,
  low texture), whose thresholds document the failure.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from validation.calibrate import make_dataset
from validation.cli import main as omnivalidate
from validation.thresholds import load_thresholds

REPO = Path(__file__).resolve().parents[2]
THRESHOLDS = REPO / "validation" / "thresholds.toml"
SCENES = load_thresholds(THRESHOLDS)["scenes"]
SYNTHETIC = [k for k, v in SCENES.items() if str(v["scene"]).startswith("synthetic:")]
RENDERED = [k for k in SCENES if k not in SYNTHETIC]


def _run(key: str, tmp_path: Path, capsys) -> dict:
    spec = SCENES[key]
    ds = make_dataset(spec, tmp_path / "ds", int(spec.get("seed", 0)))
    out = tmp_path / "report"
    rc = omnivalidate(
        [
            str(ds),
            "--out",
            str(out),
            "--variants",
            spec.get("variants", "all"),
            "--check",
            str(THRESHOLDS),
            "--scene-key",
            key,
            "--no-progress",
        ]
    )
    text = capsys.readouterr().out
    failed = [line for line in text.splitlines() if line.startswith("FAIL")]
    assert rc == 0, (
        f"{key}: thresholds failed (report: {out / 'report.md'}):\n"
        + "\n".join(failed)
        + "\n"
        + text[-3000:]
    )
    assert "thresholds: " in text and " 0 failed" in text
    summary = json.loads((out / "summary.json").read_text())
    assert (out / "report.html").is_file()
    return summary


@pytest.mark.parametrize("key", SYNTHETIC)
@pytest.mark.slow  # 12.7 s and 10.3 s (docs/decisions/slow_tests.md)
def test_synthetic_end_to_end(key, tmp_path, capsys):
    summary = _run(key, tmp_path, capsys)
    names = [m["name"] for m in summary["methods"]]
    # Every selectable variant is its own row: all 2 x 2 x 2 x 2 combinations of the
    # matching rule, gradients, temporal derivative and solver; plus the paper's exact
    # configuration and the flow step on true matches (default and paper configurations).
    combos = {n for n in names
              if n.startswith("omniflow:default") and "matches=truth" not in n}  # fmt: skip
    assert len(combos) == 16, combos
    assert "omniflow:paper" in names
    assert {n for n in names if n.endswith("+matches=truth")} == {
        "omniflow:default+matches=truth", "omniflow:paper+matches=truth"}  # fmt: skip
    for b in ("DIS-medium", "Farneback", "DIS-medium-panorama"):
        assert b in names
    assert all(m["time_per_frame"]["median_s"] > 0 for m in summary["methods"])


@pytest.mark.render
@pytest.mark.slow
@pytest.mark.parametrize("key", RENDERED)
def test_rendered_scene(key, tmp_path, capsys):
    pytest.importorskip("mitsuba")
    _run(key, tmp_path, capsys)


def test_omnivalidate_entry_point_runs(tmp_path):
    """The installed command (pyproject: omnivalidate = validation.cli:main) answers --help."""
    proc = subprocess.run(
        [
            sys.executable,
            "-c",
            "from validation.cli import main; raise SystemExit(main(['--help']))",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0 and "omnivalidate" in proc.stdout
