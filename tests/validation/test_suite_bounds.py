"""validation.suite_bounds: bounds derived from a leaderboard pass on it and catch a regression.

The leaderboards here are small dicts in the leaderboard.json layout; the shipped
validation/mini_bounds.toml is checked for consistency (each measured figure inside
its own bound), and CI checks it against a real mini-suite run (.ci/run).
"""

from __future__ import annotations

import copy
import subprocess
import sys
from pathlib import Path

import pytest

from validation.suite_bounds import (
    BoundsError,
    check_bounds,
    derive_bounds,
    load_bounds,
    main,
)

ROOT = Path(__file__).resolve().parents[2]


def _board() -> dict:
    """Two methods on the train split and one on test, figures like the mini suite's."""
    of = {
        "method": "omniflow:default",
        "kind": "omniflow",
        "1px": 0.573,
        "epe": 2.16,
        "fl": 0.29,
        "wauc": 0.498,
        "coverage": 1.0,
        "sparse_1px": 0.108,
        "density": 0.005,
        "stereo_outliers": 0.275,
        "radial_gain": 0.886,
        "tangential_gain": 0.784,
    }
    dis = {
        "method": "DIS-medium",
        "kind": "baseline",
        "1px": 0.439,
        "epe": 1.19,
        "fl": 0.08,
        "wauc": 0.637,
        "coverage": 1.0,
        "sparse_1px": None,
        "density": 1.0,
        "stereo_outliers": None,
        "radial_gain": 0.209,
        "tangential_gain": 0.686,
    }
    failed = dict(
        of,
        **{
            "1px": 1.0,
            "fl": 1.0,
            "wauc": 0.0,
            "coverage": 0.0,
            "density": 0.0,
            "epe": None,
            "sparse_1px": None,
            "stereo_outliers": None,
            "radial_gain": None,
            "tangential_gain": None,
        },
    )
    return {"suite": {"path": "scenes/suite/mini.toml", "split": "all"},
            "splits": {"train": [of, dis], "test": [failed]}}  # fmt: skip


def _failed(board, bounds):
    return [line for ok, line in check_bounds(board, bounds) if not ok]


def test_bounds_derived_from_a_leaderboard_pass_on_it():
    bounds, _ = derive_bounds(_board())
    assert bounds and _failed(_board(), bounds) == []


@pytest.mark.parametrize(
    ("metric", "factor", "split"),
    [("1px", 1.3, "train"), ("epe", 1.3, "train"), ("wauc", 0.75, "train"),
     ("density", 0.75, "train"), ("radial_gain", 0.5, "train"), ("stereo_outliers", 1.3, "train")],
)  # fmt: skip
def test_a_regression_beyond_the_margin_fails(metric, factor, split):
    bounds, _ = derive_bounds(_board())
    worse = copy.deepcopy(_board())
    worse["splits"][split][0][metric] *= factor
    failed = _failed(worse, bounds)
    assert len(failed) == 1 and f"omniflow:default [{split}] {metric}" in failed[0]


def test_a_missing_row_fails_every_bound_of_it():
    bounds, _ = derive_bounds(_board())
    board = copy.deepcopy(_board())
    board["splits"]["train"] = board["splits"]["train"][1:]
    failed = _failed(board, bounds)
    n = sum(b.method == "omniflow:default" and b.split == "train" for b in bounds)
    assert len(failed) == n > 0 and all("missing" in line for line in failed)


def test_a_bound_that_could_not_fail_is_listed_not_written():
    bounds, unguarded = derive_bounds(_board())
    assert not [b for b in bounds if b.split == "test"]
    assert "omniflow:default test 1px = 1" in unguarded
    assert "DIS-medium train radial_gain = 0.209" in unguarded  # a baseline's gain is no band


def test_written_bounds_read_back_the_same(tmp_path):
    board = tmp_path / "leaderboard.json"
    board.write_text(__import__("json").dumps(_board()))
    assert main([str(board), "--write", str(tmp_path / "b.toml")]) == 0
    assert load_bounds(tmp_path / "b.toml") == derive_bounds(_board())[0]


@pytest.mark.parametrize(
    ("text", "fragment"),
    [("", "expected [[bound]] entries"),
     ("[[bound]]\nmethod = 'a'\nsplit = 'dev'\nmetric = '1px'\nmax = 1\nmeasured = 0\n",
      "bound[0]: key 'split' = 'dev': expected one of"),
     ("[[bound]]\nmethod = 'a'\nsplit = 'test'\nmetric = '1px'\nmin = 1\nmeasured = 0\n",
      "bound[0]: key 'max': expected a number (1px takes max)"),
     ("[[bound]]\nmethod = 'a'\nsplit = 'test'\nmetric = 'wauc'\nmin = 1\nmax = 2\n"
      "measured = 0\n", "bound[0]: key 'max': wauc takes min only"),
     ("[[bound]]\nmethod = 'a'\nsplit = 'test'\nmetric = 'speed'\nmax = 1\nmeasured = 0\n",
      "key 'metric' = 'speed'"),
     ("[[bound]]\nmethod = 'a'\nsplit = 'test'\nmetric = '1px'\nmax = 1\nmeasured = 0\n"
      "note = 1\n", "unknown key 'note'"),
     ("[[bound]\n", "not valid TOML")],
)  # fmt: skip
def test_a_bad_bounds_file_is_one_line_naming_the_entry_and_key(tmp_path, text, fragment):
    path = tmp_path / "b.toml"
    path.write_text(text)
    with pytest.raises(BoundsError) as info:
        load_bounds(path)
    assert fragment in str(info.value) and str(path) in str(info.value)
    assert "\n" not in str(info.value)


def test_the_shipped_mini_bounds_hold_their_own_measured_figures():
    bounds = load_bounds(ROOT / "validation/mini_bounds.toml")
    assert len(bounds) >= 40
    for b in bounds:
        assert b.max is None or b.measured <= b.max
        assert b.min is None or b.measured >= b.min


def test_suite_check_with_a_bad_bounds_file_exits_2_before_rendering(tmp_path):
    bad = tmp_path / "b.toml"
    bad.write_text("[[bound]\n")
    run = subprocess.run([sys.executable, "-m", "validation.cli", "suite", "scenes/suite/mini.toml",
                          "--split", "test", "--out", str(tmp_path / "o"), "--check", str(bad)],
                         cwd=ROOT, capture_output=True, text=True, timeout=120)  # fmt: skip
    assert run.returncode == 2 and run.stderr.count("\n") == 1 and "--check" in run.stderr
    assert not (tmp_path / "o").exists()
