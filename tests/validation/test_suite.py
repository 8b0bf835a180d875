"""validation: the suite file's checks, the leaderboard's ranking, and ``omnivalidate suite``
end to end on a two-scene library suite (rendered at 96 px, 2 frames), resumed, with an
external method plugged in through the per-scene submission layout.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import pytest

from validation.leaderboard import leaderboard
from validation.suite import SuiteError, load_suite, scene_text

REPO = Path(__file__).resolve().parents[2]


def _suite(tmp_path: Path, scenes: str, head: str | None = None) -> Path:
    head = head or 'name = "t"\nframes = 2\nresolution = 96\n'
    path = tmp_path / "suite.toml"
    path.write_text(f"[suite]\n{head}\n{scenes}")
    return path


def _file_entry(name: str, scene: str, split: str = "test") -> str:
    return f'[[scenes]]\nname = "{name}"\nfile = "{REPO / "scenes" / scene}"\nsplit = "{split}"\n'


def test_load_suite_and_select(tmp_path):
    path = _suite(tmp_path, _file_entry("a", "default.toml") + _file_entry("b", "glossy.toml",
                  "train"))  # fmt: skip
    s = load_suite(path)
    assert (s.name, s.frames, s.resolution) == ("t", 2, 96)
    assert [x.name for x in s.select("test")] == ["a"]
    assert [x.name for x in s.select("train")] == ["b"]
    assert [x.name for x in s.select("all")] == ["a", "b"]
    assert scene_text(s.scenes[0]) == (REPO / "scenes" / "default.toml").read_text()


@pytest.mark.parametrize(
    ("scenes", "head", "fragment"),
    [
        (_file_entry("a", "default.toml", "val"), None, "scenes[0] (a): key 'split' = 'val'"),
        (_file_entry("a", "default.toml") * 2, None, "scenes[1] (a): key 'name' = 'a': already"),
        ('[[scenes]]\nname = "a"\nfile = "nope.toml"\nsplit = "test"\n', None,
         "scenes[0] (a): key 'file' = 'nope.toml': no such file"),
        ('[[scenes]]\nname = "a"\nfamily = "room"\nseed = 1\nfile = "x"\nsplit = "test"\n',
         None, "scenes[0] (a): expected either 'file' or both 'family' and 'seed'"),
        ('[[scenes]]\nname = "a"\nfamily = "room"\nseed = "one"\nsplit = "test"\n', None,
         "scenes[0] (a): key 'seed': expected an integer"),
        ('[[scenes]]\nname = "a b"\nfamily = "room"\nseed = 1\nsplit = "test"\n', None,
         "key 'name' = 'a b': expected a short id"),
        (_file_entry("a", "default.toml").replace("split", "spp = 4\nsplit"), None,
         "scenes[0] (a): unknown key 'spp'"),
        (_file_entry("a", "default.toml"), 'name = "t"\nframes = 1\nresolution = 96\n',
         "[suite]: key 'frames' = 1: expected 2 to"),
        (_file_entry("a", "default.toml"), 'name = "t"\nframes = 2\n',
         "[suite]: key 'resolution': expected an integer, got None"),
        ("", None, "no [[scenes]] entries"),
    ],
)  # fmt: skip
def test_bad_suite_files_name_the_entry_and_key(tmp_path, scenes, head, fragment):
    with pytest.raises(SuiteError) as info:
        load_suite(_suite(tmp_path, scenes, head))
    msg = str(info.value)
    assert fragment in msg and "\n" not in msg and str(tmp_path / "suite.toml") in msg


def test_a_family_entry_without_the_generator_is_one_line(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "omnisim.generate", None)  # import fails
    s = load_suite(_suite(tmp_path, '[[scenes]]\nname = "r"\nfamily = "room"\nseed = 7\n'
                                    'split = "train"\n'))  # fmt: skip
    with pytest.raises(SuiteError, match=r"scenes\[0\] \(r\): key 'family': generated scenes "
                       "need omnisim.generate"):  # fmt: skip
        scene_text(s.scenes[0])


def _summary(rows):
    """A summary with one dense baseline entry per (name, 1px, epe, n)."""
    return {"methods": [{"name": n, "kind": "baseline", "points": "dense",
                         "protocol": {"all": {"n": k, "1px": a, "epe": e, "fl": 0.0,
                                              "wauc": 0.5}, "density": 1.0}}
                        for n, a, e, k in rows]}  # fmt: skip


def test_leaderboard_ranks_by_1px_and_counts_a_missing_scene_as_failed():
    board = leaderboard(
        [("s1", "test", _summary([("A", 0.10, 0.5, 10), ("B", 0.20, 0.4, 10)])),
         ("s2", "test", _summary([("A", 0.30, 0.7, 10), ("B", None, None, 0)]))],
        suite={"name": "t"},
    )  # fmt: skip
    agg = {r["method"]: r for r in board["methods"]}
    # A: mean of 0.10 and 0.30 = 0.20; B: 0.20 and, for the scene it gave nothing on, 1.0:
    # 0.60. A ranks first although B was better on s1's EPE.
    assert agg["A"]["1px"] == pytest.approx(0.20) and agg["A"]["rank"] == 1
    assert agg["B"]["1px"] == pytest.approx(0.60) and agg["B"]["missing"] == 1
    assert math.isnan(agg["B"]["epe"])  # undefined, not the mean of the scene it scored
    assert agg["A"]["epe"] == pytest.approx(0.6)
    assert [r["method"] for r in board["scenes"]["s2"]] == ["A", "B"]
    assert board["splits"] == {}  # one split: its aggregate is the whole board's


def test_leaderboard_aggregates_each_split_when_both_are_scored():
    board = leaderboard(
        [("s1", "train", _summary([("A", 0.10, 0.5, 10), ("B", 0.20, 0.4, 10)])),
         ("s2", "test", _summary([("A", 0.30, 0.7, 10), ("B", 0.05, 0.2, 10)]))],
        suite={"name": "t"},
    )  # fmt: skip
    # train: A 0.10 < B 0.20; test: B 0.05 < A 0.30; all: A 0.20 > B 0.125.
    assert [r["method"] for r in board["splits"]["train"]] == ["A", "B"]
    assert [r["method"] for r in board["splits"]["test"]] == ["B", "A"]
    assert [r["method"] for r in board["methods"]] == ["B", "A"]
    assert board["methods"][0]["1px"] == pytest.approx(0.125)


@pytest.mark.render
@pytest.mark.slow
def test_omnivalidate_suite_end_to_end(tmp_path, capsys):
    from validation.cli import main as omnivalidate
    from validation.examples.suite_submission import write_submission
    from validation.suite_run import method_catalogue

    suite = _suite(tmp_path, _file_entry("default", "default.toml")
                   + _file_entry("turn", "turn_in_place.toml"))  # fmt: skip
    default_row = method_catalogue()[1][0][0]
    out = tmp_path / "run"
    argv = ["suite", str(suite), "--split", "test", "--out", str(out), "--no-progress",
            "--methods", f"{default_row},DIS-medium,zero-flow"]  # fmt: skip
    t0 = time.perf_counter()
    assert omnivalidate(argv) == 0
    first = time.perf_counter() - t0
    text = capsys.readouterr().out
    assert "[1/2] default: rendering 2 frames at 96 px" in text and "[2/2] turn" in text
    for name in ("md", "html", "csv", "json"):
        assert (out / f"leaderboard.{name}").is_file()
    board = json.loads((out / "leaderboard.json").read_text())
    assert list(board["scenes"]) == ["default", "turn"]
    assert {r["method"] for r in board["methods"]} == {default_row, "DIS-medium", "zero-flow"}
    assert [r["rank"] for r in board["methods"]] == [1, 2, 3]
    ones = [r["1px"] for r in board["methods"]]
    assert ones == sorted(ones)
    for scene in ("default", "turn"):
        assert (out / "scenes" / f"{scene}.toml").is_file()
        assert (out / "scenes" / scene / "summary.json").is_file()
    # The omniflow row carries its sparse score and density beside the dense one.
    omni = next(r for r in board["scenes"]["default"] if r["method"] == default_row)
    assert omni["density"] is not None and 0 < omni["density"] < 1
    # Measured: 29.8 s for this first run from the command line (load average 19 on 2
    # cores shared by several users); the bound is the brief's "under a minute".
    assert first < 60, f"omnivalidate suite took {first:.0f} s"

    # Resumed: nothing rendered or scored again.
    assert omnivalidate(argv) == 0
    text = capsys.readouterr().out
    assert text.count("scored before") == 2 and "0 frames rendered, 2 already there" in text

    # An external method, one folder per scene in the --method-output layout (the
    # documented example writes DIS flow as a submission).
    ext = tmp_path / "mine"
    assert write_submission(out, ext) == {"default": 1, "turn": 1}
    assert omnivalidate([*argv, "--method-output", f"mine={ext}"]) == 0
    board = json.loads((out / "leaderboard.json").read_text())
    rows = {r["method"]: r for r in board["methods"]}
    # The same DIS flow read back from .flo files scores as the built-in row does.
    assert rows["mine"]["1px"] == pytest.approx(rows["DIS-medium"]["1px"], abs=1e-6)
    capsys.readouterr()


def test_omnivalidate_suite_bad_input_is_one_line(tmp_path, capsys):
    from validation.cli import main as omnivalidate

    suite = _suite(tmp_path, _file_entry("a", "default.toml", "val"))
    assert omnivalidate(["suite", str(suite), "--split", "test", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("omnivalidate suite: error: ") and "key 'split'" in err
    assert "\n" not in err
    good = _suite(tmp_path, _file_entry("a", "default.toml"))
    assert omnivalidate(["suite", str(good), "--split", "test", "--out", str(tmp_path / "o"),
                         "--methods", "nope"]) == 2  # fmt: skip
    assert "--methods: unknown method 'nope'" in capsys.readouterr().err
    assert omnivalidate(["suite", str(good), "--split", "test", "--out", str(tmp_path / "o"),
                         "--registration", "none,none"]) == 2  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert "--registration 'none,none': each of recorded, none, card at most once" in err
    assert "\n" not in err
    assert omnivalidate(["suite", str(good), "--split", "train", "--out", str(tmp_path / "o")]) == 2
    assert "no scene in split 'train'" in capsys.readouterr().err


def test_omnivalidate_suite_on_a_full_disk_exits_1(tmp_path, capsys, monkeypatch):
    """A full disk is the machine refusing (1), not bad input (2), naming --out. Simulated:
    run_suite raises the OSError a write to a full disk raises (no file name)."""
    import errno
    import os

    import validation.suite_run as suite_run
    from validation.cli import main as omnivalidate

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(suite_run, "run_suite", full)
    good = _suite(tmp_path, _file_entry("a", "default.toml"))
    out = tmp_path / "o"
    assert omnivalidate(["suite", str(good), "--split", "test", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"omnivalidate suite: error: --out {out}: No space left on device")
    assert err.count("\n") == 1


def test_registration_multiplies_the_omniflow_rows_and_keys_the_card(tmp_path):
    from omniflow.cli.calibrate import rig_toml
    from omniflow.geometry.rig import Rig
    from validation.suite_run import resolve_methods

    card = tmp_path / "rig.toml"
    card.write_text(rig_toml(Rig.symmetric(d=0.1, R=0.05, s=0.3, size=64)))
    m = resolve_methods(["omniflow:default", "DIS-medium"], registration=f"none,{card}")
    assert m.key()["omniflow"] == ["omniflow:default+registration=none",
                                   "omniflow:default+registration=card"]  # fmt: skip
    assert m.baselines == ["DIS-medium"]
    assert m.key()["registration_rig"] == {"omniflow:default+registration=card": str(card)}
    assert "registration_rig" not in resolve_methods(["omniflow:default"]).key()
