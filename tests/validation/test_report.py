"""validation: the harness end to end on a perfect method, the report files, thresholds, CLI.

A truth oracle (validation.oracle) scored by the harness must come out with
zero error: that tests the plumbing (sampling, polar conversion, pooling,
tables) independently of any method's accuracy.
"""

from __future__ import annotations

import csv
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import pytest

from validation.oracle import OracleConfig, TruthOracle
from validation.report import write_report
from validation.runner import run_validation
from validation.summary import find_method, flat_table, get_path
from validation.synthdata import demo_scene, write_synthetic_dataset
from validation.thresholds import (
    ThresholdError,
    check_summary,
    format_checks,
    load_thresholds,
)


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("synth") / "ds"
    write_synthetic_dataset(d, demo_scene(64), 3, name="synthetic-demo", supersample=1)
    return d


@pytest.fixture(scope="module")
def oracle_report(synth, tmp_path_factory):
    res = run_validation(
        synth,
        variants=[("truth-oracle", OracleConfig())],
        estimate=TruthOracle(synth),
        progress=False,
    )
    out = tmp_path_factory.mktemp("report")
    summary = write_report(res, out, command="pytest")
    return res, summary, out


def test_oracle_scores_zero_error(oracle_report):
    _, summary, _ = oracle_report
    m = find_method(summary, "truth-oracle")
    for cam in ("cam1", "cam2"):
        f = m["flow"][cam]["all"]
        assert f["n"] > 50
        # cam1 points sit on pixel centres (exact); cam2's are sub-pixel (bilinear truth).
        tol = 1e-6 if cam == "cam1" else 0.02
        assert f["epe"]["p90"] <= tol, cam
        assert f["dh"]["p90"] <= tol and f["hdtheta"]["p90"] <= tol, cam
    st = m["stereo"]
    assert st["all"]["outliers"] == 0.0
    assert st["all"]["rel_r"]["p90"] < 1e-6
    assert st["match_rate"] == pytest.approx(1.0)
    # The robot's true motion reaches the derived block (odometry from the poses).
    assert m["time_per_frame"]["frames"] == 2


def test_baselines_are_scored_at_the_same_points(oracle_report):
    _, summary, _ = oracle_report
    oracle = find_method(summary, "truth-oracle")
    for name in ("DIS-medium", "Farneback", "DIS-medium-panorama"):
        at_pts = find_method(summary, name, "omniflow points")
        dense = find_method(summary, name, "dense")
        assert at_pts["flow"]["cam1"]["all"]["n"] == oracle["flow"]["cam1"]["all"]["n"]
        assert dense["flow"]["cam1"]["all"]["n"] > at_pts["flow"]["cam1"]["all"]["n"]
        same = oracle["baselines_at_same_points"][name]["cam1"]["median"]
        assert same == pytest.approx(at_pts["flow"]["cam1"]["all"]["epe"]["median"])
        # Sub-pixel motion of a smooth closed-form scene: every baseline is well under 1 px.
        assert dense["flow"]["cam1"]["noc"]["epe"]["median"] < 0.5
        assert at_pts["time_per_frame"]["median_s"] > 0


def test_report_files(oracle_report):
    _, summary, out = oracle_report
    for name in ("report.md", "report.html", "summary.json", "frames.csv"):
        assert (out / name).is_file(), name
    # summary.json is strict JSON (no NaN) and equals what write_report returned.
    assert json.loads((out / "summary.json").read_text()) == summary
    with (out / "frames.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert {
        "frame",
        "method",
        "points",
        "camera",
        "epe_median",
        "noc_epe_median",
        "out1",
        "out3",
        "time_s",
    } <= set(rows[0])
    assert {r["frame"] for r in rows} == {"0", "1"}
    assert {r["method"] for r in rows} == {
        "truth-oracle",
        "DIS-medium",
        "Farneback",
        "DIS-medium-panorama",
        "zero-flow",
    }
    assert {"radial_gain", "tangential_gain", "radial_mean_signed", "density_valid"} <= set(rows[0])
    md = (out / "report.md").read_text()
    html = (out / "report.html").read_text()
    md_imgs = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    html_imgs = re.findall(r'<img src="([^"]+)"', html)
    assert md_imgs == html_imgs and len(md_imgs) >= 8
    for src in md_imgs:
        assert not Path(src).is_absolute() and (out / src).is_file(), src
        assert (out / src).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for needle in ("Methods side by side", "per frame interval", "truth-oracle", "DIS-medium"):
        assert needle in md and needle in html
    table = flat_table(summary)
    assert [r["method"] for r in table][:1] == ["truth-oracle"]
    assert all(math.isfinite(r["time_ms"]) for r in table)


def test_a_failing_method_is_reported_not_fatal(synth, tmp_path):
    def broken(*args, **kwargs):
        raise ValueError("no matches\nsecond line")

    res = run_validation(
        synth,
        variants=[("broken", OracleConfig())],
        estimate=broken,
        baselines=["DIS-medium"],
        progress=False,
    )
    assert res.notes == [
        "broken failed on frame pair(s) 0 -> 1, 1 -> 2: ValueError: no matches "
        "(scored as no points)"
    ]
    summary = write_report(res, tmp_path / "r")
    assert find_method(summary, "broken")["flow"]["cam1"]["all"]["n"] == 0
    assert "failed on frame pair(s) 0 -> 1, 1 -> 2" in (tmp_path / "r" / "report.md").read_text()


def test_the_first_call_s_warm_up_is_not_timed(synth):
    """A configuration's first estimate() in a process loads its kernels (about 0.5 s
    against 0.05 s warm at 512 px): untimed, or a run of one pair reports it as the
    method's time per frame."""
    import time

    from omniflow.pipeline import OmniFlowConfig

    oracle = TruthOracle(synth)
    calls = []

    def cold_first_call(g1, g2, rig, config, *, t=0):
        if not calls:
            time.sleep(0.5)
        calls.append(1)
        return oracle(g1, g2, rig, OracleConfig(), t=t)

    res = run_validation(
        synth,
        variants=[("cold", OmniFlowConfig())],
        estimate=cold_first_call,
        baselines=["zero-flow"],
        frames=[0],
        progress=False,
    )
    assert res.times["cold"][0] < 0.4


# -- thresholds --------------------------------------------------------------------------------


def test_the_reviewed_thresholds_file_is_valid():
    data = load_thresholds()
    for name, scene in data["scenes"].items():
        for c in scene["check"]:
            assert "measured" in c and c["margin"].strip(), (name, c)
            lo, hi = c.get("min", -math.inf), c.get("max", math.inf)
            # The value the bound was set from must itself pass.
            assert lo <= c["measured"] <= hi, (name, c)


def _write(tmp_path, text):
    p = tmp_path / "t.toml"
    p.write_text(text)
    return p


def test_threshold_checks_pass_and_fail(oracle_report, tmp_path):
    _, summary, _ = oracle_report
    p = _write(
        tmp_path,
        """
[scenes.x]
[[scenes.x.check]]
method = "default"
metric = "flow.cam1.all.epe.median"
max = 0.001
measured = 0.0
margin = "oracle"
[[scenes.x.check]]
method = "DIS-medium"
points = "dense"
metric = "flow.cam1.all.epe.median"
max = 1e-9
measured = 0.0
margin = "deliberately impossible"
""",
    )
    checks = check_summary(summary, load_thresholds(p), "x")
    assert [c.passed for c in checks] == [True, False]
    text = format_checks(checks)
    assert "1 passed, 1 failed" in text and "FAIL x: DIS-medium @dense" in text
    assert get_path(find_method(summary, "truth-oracle"), "flow.cam1.all.n") > 0


@pytest.mark.parametrize(
    "text, message",
    [
        ("[scenes.x]\n", "expected [[scenes.x.check]]"),
        (
            "[scenes.x]\n[[scenes.x.check]]\nmethod='a'\nmetric='b'\nmeasured=1\nmargin='m'\n",
            "expected 'min' and/or 'max'",
        ),
        ("[scenes.x]\n[[scenes.x.check]]\nmethod='a'\nmetric='b'\nmax=1\n", "needs 'measured'"),
        (
            "[scenes.x]\n[[scenes.x.check]]\nmethod='a'\nmetric='b'\nmax=1\nmeasured=1\nmargin='m'\n"
            "colour='red'\n",
            "unknown key",
        ),
        ("scenes = 3\n", "expected [scenes.NAME] tables"),
        ("[scenes.x\n", "not valid TOML"),
    ],
)
def test_threshold_file_errors(tmp_path, text, message):
    with pytest.raises(ThresholdError, match=re.escape(message)):
        load_thresholds(_write(tmp_path, text))


def test_threshold_names_an_absent_method_or_metric(oracle_report, tmp_path):
    _, summary, _ = oracle_report
    base = "[scenes.x]\n[[scenes.x.check]]\nmax=1\nmeasured=0\nmargin='m'\n"
    with pytest.raises(ThresholdError, match="'nope' is not in the summary"):
        check_summary(
            summary, load_thresholds(_write(tmp_path, base + "method='nope'\nmetric='a'\n")), "x"
        )
    with pytest.raises(ThresholdError, match="no key 'cam9'"):
        check_summary(
            summary,
            load_thresholds(_write(tmp_path, base + "method='default'\nmetric='flow.cam9.all'\n")),
            "x",
        )
    with pytest.raises(ThresholdError, match=r"no \[scenes.y\]"):
        check_summary(
            summary,
            load_thresholds(_write(tmp_path, base + "method='default'\nmetric='flow'\n")),
            "y",
        )


# -- command line ------------------------------------------------------------------------------


def _cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "validation.cli", *args], capture_output=True, text=True, timeout=120
    )


def test_cli_help():
    p = _cli("--help")
    assert p.returncode == 0
    for word in ("--out", "--variants", "--baselines", "--check", "report.html", "summary.json",
                 "frames.csv", "--method-output", "cam1.flo", "flow.csv", "--camera",
                 "--camera-sweep", "--partial", "zero-flow"):  # fmt: skip
        assert word in p.stdout


@pytest.mark.parametrize(
    "args, needle",
    [
        (["{missing}", "--out", "{out}"], "no such dataset directory"),
        (["{ds}", "--out", "{out}", "--baselines", "RAFT"], "unknown ['RAFT']"),
        (["{ds}", "--out", "{out}", "--frames", "x"], "--frames 'x'"),
        (["{ds}", "--out", "{out}", "--frames", "7"], "no complete frame pair"),
        (["{notds}", "--out", "{out}"], "not an omnisim dataset"),
        (["{ds}", "--out", "{out}", "--check", "{missing}"], "cannot read"),
        (["{ds}", "--out", "{out}", "--variants", "some"], "invalid choice: 'some'"),
        (
            [
                "{ds}",
                "--out",
                "{out}",
                "--variants",
                "default",
                "--check",
                "{thr}",
                "--scene-key",
                "default",
            ],
            "scenes.default checks 3 row(s) this run does not score",
        ),
        (
            ["{ds}", "--out", "{out}", "--check", "{thr}"],
            "no thresholds for this dataset's scene 'synthetic-demo'; give --scene-key",
        ),
        (["{ds}"], "required: --out"),
    ],
)
def test_cli_bad_input_exits_2_with_one_line(synth, tmp_path, args, needle):
    (tmp_path / "notds").mkdir()
    subs = {
        "missing": str(tmp_path / "missing"),
        "out": str(tmp_path / "out"),
        "ds": str(synth),
        "notds": str(tmp_path / "notds"),
        "thr": str(Path(__file__).resolve().parents[2] / "validation" / "thresholds.toml"),
    }
    p = _cli(*[a.format(**subs) for a in args])
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("omnivalidate: error:"), p.stderr
    assert needle in lines[0]


def test_cli_on_a_full_disk_exits_1_naming_the_path(synth, tmp_path):
    """A full disk is the machine refusing (exit 1), not bad input (2, before issue 25)."""
    from tests.helpers.small_disk import fill, small_tmpfs

    with small_tmpfs(tmp_path / "small") as mnt:
        fill(mnt)
        out = mnt / "report"
        p = _cli(str(synth), "--out", str(out), "--variants", "default", "--baselines", "none",
                 "--no-progress")  # fmt: skip
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 1 and len(lines) == 1, (p.returncode, p.stderr)
    assert lines[0].startswith(f"omnivalidate: error: --out {out}: No space left"), lines[0]
    assert "Traceback" not in p.stderr


def test_calibrate_rounds_bounds_outward():
    from validation.calibrate import _round_out

    assert _round_out(0.043212, up=True) == 0.0433
    assert _round_out(0.043212, up=False) == 0.0432
    assert _round_out(1234.5, up=True) == 1240.0
    assert _round_out(0.0, up=True) == 0.0


def test_calibrate_keeps_unmeasurable_checks_pending(tmp_path):
    from validation.calibrate import _render_file

    check = {"method": "default", "metric": "flow.cam1.all.epe.mean", "max": 0.2,
             "measured": 0.1, "margin": "m"}  # fmt: skip
    waiting = {"method": "default", "metric": "derived.objects.box.ttc.median",
               "max": math.nan, "measured": math.nan, "margin": "not measurable"}  # fmt: skip
    text = _render_file("# header", {"s": {"scene": "x", "check": [check], "pending": [waiting]}})
    path = tmp_path / "t.toml"
    path.write_text(text)
    data = load_thresholds(path)
    assert data["scenes"]["s"]["pending"][0]["metric"] == waiting["metric"]
    assert [c["metric"] for c in data["scenes"]["s"]["check"]] == [check["metric"]]


def test_legend_labels_wrap_between_settings_not_inside_one():
    """The accuracy-vs-time legend's long row names break after a comma: every line fits
    110 characters and every setting stands whole on one line (textwrap's mid-word
    breaks gave 'deco' / 'uple_gain_tol')."""
    from validation.report_figures import _wrap_at_commas

    name = ("omniflow[paper,grad1,diff,direct;band=0.25,flow_band=0.25,flow_taper=0.0,eiv=none,"
            "brightness_gate=None,decouple_gain_tol=None,sampling=exact,iterations=0,"
            "iterate_min_px=0.0,rim_fill=none]")  # fmt: skip
    lines = _wrap_at_commas(f"6: {name} (1.289 px, 312 ms) - off scale", 110).split("\n")
    assert len(lines) == 3 and all(len(s) <= 110 for s in lines)
    assert all(s.startswith("    ") for s in lines[1:])
    for setting in name.split(","):
        assert any(setting in s for s in lines), setting
    assert _wrap_at_commas("1: omniflow[robust] (0.017 px, 82 ms)", 110).count("\n") == 0
    # the short row names (validation.variants.variant_name) break after a "+"
    plus = "omniflow:default+match_method=paper+gradients=first+temporal=dct3d+solver=direct"
    lines = _wrap_at_commas(f"6: {plus} (1.289 px, 312 ms)", 60).split("\n")
    assert len(lines) == 2 and all(len(s) <= 60 for s in lines), lines
    for setting in plus.split("+"):
        assert any(setting in s for s in lines), setting


def test_closing_line_counts_methods_not_their_rows():
    """A baseline scored at two point sets is one method in two table rows; counts are
    singular at 1 ("1 rows" before; mutation: len(methods) as the method count says 3)."""
    from validation.cli import _closing_line

    summary = {"methods": [{"name": "omniflow[robust]"}, {"name": "DIS-medium"},
                           {"name": "DIS-medium"}]}  # fmt: skip
    line = _closing_line(summary, 1, 2.04, Path("r/report.html"))
    assert line == ("omnivalidate: 2 methods in 3 table rows, 1 frame pair in 2.0 s; "
                    "report: r/report.html")  # fmt: skip
    assert "1 method in 1 table row, 3 frame pairs" in _closing_line(
        {"methods": [{"name": "x"}]}, 3, 1.0, Path("r"))  # fmt: skip


def test_binned_lines_of_equal_rows_stay_apart():
    """Two rows with the same errors: the second line gets another style and marker (hollow
    markers), so it does not hide the first (mutation: one style for all, caught)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from validation.report_figures import _binned, _edges

    x = np.linspace(0.5, 5.0, 200)
    y = 0.01 * x
    fig, ax = plt.subplots()
    for label in ("default", "default,monocular_gap=24"):
        _binned(ax, x, y, _edges(x), label)
    a, b = ax.get_lines()
    np.testing.assert_array_equal(a.get_ydata(), b.get_ydata())
    assert a.get_linestyle() != b.get_linestyle() and a.get_marker() != b.get_marker()
    plt.close(fig)
