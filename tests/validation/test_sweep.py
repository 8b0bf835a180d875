"""omnivalidate sweep: one render per value, every method scored, a figure, resumable;
bad input is one line with exit status 2."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from validation.sweep import parse_values, value_label

ROOT = Path(__file__).resolve().parents[2]


def _sweep(*args: str, timeout: int = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "validation.cli", "sweep", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)  # fmt: skip


def test_values_are_toml_values_and_label_as_written():
    assert parse_values("2.8,4,inf") == [2.8, 4, float("inf")]
    assert parse_values("[[0, 0], [0.1, 0]]") == [[0, 0], [0.1, 0]]
    assert [value_label(v) for v in parse_values("2.8,4,inf,[0.1, 0]")] == [
        "2.8", "4", "inf", "[0.1, 0]"]  # fmt: skip


@pytest.mark.parametrize(
    ("args", "fragment"),
    [(["--key", "camera.exposure", "--values", "1"], "--values '1': expected at least two"),
     (["--key", "camera.exposure", "--values", "1,,2"], "--values '1,,2': expected V1,V2"),
     (["--key", "camera.exposure", "--values", "1,2", "--set", "camera.exposure=3"],
      "--set camera.exposure: that is the swept --key"),
     (["--key", "camera.exposure", "--values", "1,2", "--methods", "nope"],
      "unknown method 'nope'"),
     (["--key", "camera.exposure", "--values", "1,2", "--registration", "recorded,nope"],
      "--registration 'nope': no such rig file"),
     (["--key", "camera.colour", "--values", "1,2"], "colour"),
     (["--key", "camera.exposure", "--values", "1,-2"], "exposure")],
)  # fmt: skip
def test_bad_input_is_one_line_exit_2(tmp_path, args, fragment):
    run = _sweep("scenes/default.toml", "--out", str(tmp_path / "o"), "--resolution", "32",
                 "--frames", "2", "--no-progress", "--methods", "zero-flow", *args)  # fmt: skip
    err = [ln for ln in run.stderr.splitlines() if ln.strip()]
    assert run.returncode == 2, run.stderr
    assert len(err) == 1 and fragment in err[0] and "Traceback" not in run.stderr


@pytest.mark.render
def test_a_sweep_scores_every_value_draws_it_and_resumes(tmp_path):
    pytest.importorskip("mitsuba")
    out = tmp_path / "sw"
    args = ["scenes/default.toml", "--key", "camera.exposure", "--values", "0.25,2",
            "--out", str(out), "--resolution", "48", "--frames", "2", "--no-progress",
            "--methods", "omniflow:default,zero-flow"]  # fmt: skip
    run = _sweep(*args)
    assert run.returncode == 0, run.stderr
    sweep = json.loads((out / "sweep.json").read_text())
    assert sweep["values"] == ["0.25", "2"]
    assert {(r["value"], r["method"]) for r in sweep["rows"]} == {
        (v, m) for v in ("0.25", "2") for m in ("omniflow:default", "zero-flow")}  # fmt: skip
    for f in ("sweep.md", "sweep.csv", "sweep.png"):
        assert (out / f).stat().st_size > 0
    # each row is the point's own report (the suite protocol), and the two renders differ
    for i in (0, 1):
        summary = json.loads((out / "points" / f"0{i}" / "report" / "summary.json").read_text())
        zero = next(
            m for m in summary["methods"] if m["name"] == "zero-flow" and m.get("points") == "dense"
        )
        row = next(r for r in sweep["rows"] if r["index"] == i and r["method"] == "zero-flow")
        assert row["epe"] == pytest.approx(zero["protocol"]["all"]["epe"], rel=1e-12)
    png = [(out / "points" / f"0{i}" / "render" / "frames" / "000000" / "cam1.png").read_bytes()
           for i in (0, 1)]  # fmt: skip
    assert png[0] != png[1]  # the exposure reached the camera images
    again = _sweep(*args)
    assert again.returncode == 0 and again.stdout.count("scored before") == 2, again.stdout


@pytest.mark.parametrize("command", ["sweep", "suite"])
def test_an_out_holding_the_users_files_is_refused(tmp_path, command):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.md").write_text("mine\n")
    if command == "sweep":
        args = ["sweep", "scenes/default.toml", "--key", "camera.exposure", "--values", "1,2",
                "--out", str(out), "--methods", "zero-flow", "--resolution", "32"]  # fmt: skip
    else:
        args = ["suite", "scenes/suite/mini.toml", "--split", "test", "--out", str(out)]
    run = subprocess.run([sys.executable, "-m", "validation.cli", *args, "--no-progress"],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1, run.stderr
    assert "notes.md: not written by omnivalidate" in run.stderr
    assert sorted(p.name for p in out.iterdir()) == ["notes.md"]
    assert (out / "notes.md").read_text() == "mine\n"


def test_a_run_from_before_markers_is_ours(tmp_path):
    from validation.suite_run import _legacy_run

    (tmp_path / "sweep.json").write_text('{"format": "omnivalidate-sweep/1"}')
    assert _legacy_run(tmp_path)
    (tmp_path / "sweep.json").write_text('{"format": "mine"}')
    assert not _legacy_run(tmp_path)


def test_registration_twins_share_a_colour_and_differ_in_style():
    from validation.sweep_figure import _styles

    st = _styles(["omniflow:default", "DIS-medium", "omniflow:default+registration=none",
                  "omniflow:default+registration=card"])  # fmt: skip
    (lab0, c0, s0), (_, c1, _), (_, c2, s2), (_, c3, s3) = (st[n] for n in st)
    assert c0 == c2 == c3 != c1 and len({s0, s2, s3}) == 3
    assert lab0 == "omniflow:default (recorded rig: its true errors)"
    assert _styles(["omniflow:default"])["omniflow:default"][0] == "omniflow:default"


def test_each_panel_is_titled_by_its_metric(monkeypatch, tmp_path):
    import validation.sweep_figure as sf

    seen = {}
    monkeypatch.setattr(sf, "save", lambda fig, path: seen.update(fig=fig))
    rows = [
        {"index": i, "method": m, "epe": 0.1 * (i + 1), "1px": 0.01}
        for i in (0, 1)
        for m in ("DIS-medium", "omniflow:default+registration=none")
    ]
    sf.sweep_plot(
        {
            "parameter": "camera.exposure",
            "values": ["1", "2"],
            "rows": rows,
            "scene": "s.toml",
            "resolution": 64,
            "frames": 2,
        },
        tmp_path / "p.png",
    )
    titles = [ax.get_title() for ax in seen["fig"].axes]
    assert titles == list(sf.METRICS.values())
