"""Deeply nested or huge input files are one line naming the file, exit status 2 (issue:
a 100000-deep list in a scene or dataset.json was an internal RecursionError)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from omniflow import input_files
from omniflow.input_files import InputFileError, parse_text, read_input

ROOT = Path(__file__).resolve().parents[1]
DEEP = "[" * 100_000 + "]" * 100_000


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)  # fmt: skip


def _one_line(run: subprocess.CompletedProcess, *fragments: str) -> None:
    lines = [ln for ln in run.stderr.splitlines() if ln.strip()]
    assert run.returncode == 2, run.stderr
    assert len(lines) == 1 and "Traceback" not in run.stderr, run.stderr
    assert all(f in lines[0] for f in fragments), lines[0]


def test_parse_and_read_refuse_depth_size_and_bytes(tmp_path, monkeypatch):
    with pytest.raises(InputFileError, match=r"x\.json: nested deeper than \d+ levels"):
        parse_text(DEEP, "x.json", "json")
    with pytest.raises(InputFileError, match=r"x\.toml: nested deeper than \d+ levels"):
        parse_text(f"a = {DEEP}\n", "x.toml", "toml")
    with pytest.raises(InputFileError, match=r"x\.toml: not valid TOML"):
        parse_text("a = [", "x.toml", "toml")
    big = tmp_path / "big.toml"
    big.write_text("a = 1\n" * 200)
    monkeypatch.setattr(input_files, "MAX_INPUT_BYTES", 1000)
    with pytest.raises(InputFileError, match=r"big\.toml: 1200 bytes; expected a TOML scene of "
                       "at most 0 MiB"):  # fmt: skip
        read_input(big, "TOML scene")
    (tmp_path / "bin.toml").write_bytes(b"a = 1\n\xff\n")
    with pytest.raises(InputFileError, match=r"bin\.toml: not UTF-8 text \(byte 6\)"):
        read_input(tmp_path / "bin.toml", "TOML scene")


def test_a_deep_scene_is_one_line(tmp_path):
    scene = tmp_path / "scene.toml"
    scene.write_text(f"a = {DEEP}\n")
    _one_line(_run("omnisim.cli", "render", str(scene), "--out", str(tmp_path / "o")),
              "scene.toml: nested deeper than")  # fmt: skip
    assert not (tmp_path / "o").exists()


def test_a_deep_rig_file_is_one_line(tmp_path):
    rig = tmp_path / "rig.json"
    rig.write_text(DEEP)
    files = [str(tmp_path / f"{n}.png") for n in "abcd"]
    _one_line(_run("omniflow.cli", "pair", *files, "--rig", str(rig), "--out",
                   str(tmp_path / "o")), "rig.json: nested deeper than")  # fmt: skip


def test_a_deep_dataset_json_is_one_line_for_every_command(tmp_path):
    from validation.synthdata import demo_scene, write_synthetic_dataset

    ds = write_synthetic_dataset(tmp_path / "ds", demo_scene(64), 2)
    meta = json.loads((Path(ds) / "dataset.json").read_text())
    text = json.dumps(meta)
    (Path(ds) / "dataset.json").write_text(text[:-1] + f', "deep": {DEEP}}}')
    commands = [
        ["omnisim.cli", "check", str(ds)],
        ["validation.cli", str(ds), "--out", str(tmp_path / "r")],
        ["omniflow.cli", "pair", "--dataset", str(ds), "--out", str(tmp_path / "f")],
    ]
    for cmd in commands:
        _one_line(_run(*cmd), "dataset.json: nested deeper than")
    assert not (tmp_path / "r").exists() and not (tmp_path / "f").exists()


def test_deep_suite_thresholds_and_bounds_files_are_one_line(tmp_path):
    from validation.suite import SuiteError, load_suite
    from validation.suite_bounds import BoundsError, load_bounds
    from validation.thresholds import ThresholdError, load_thresholds

    deep = tmp_path / "deep.toml"
    deep.write_text(f"a = {DEEP}\n")
    for load, error in ((load_suite, SuiteError), (load_thresholds, ThresholdError),
                        (load_bounds, BoundsError)):  # fmt: skip
        with pytest.raises(error, match=r"deep\.toml: nested deeper than") as info:
            load(deep)
        assert "\n" not in str(info.value)
