"""validation: scoring a method we did not write (--method-output), and the CLI's input checks.

The dense path is proven by feeding DIS's own output (written by the example
script through the harness's image function) back in: its rows must equal the
built-in DIS-medium rows exactly (same float32 flow, same points). The
per-point path is proven with the truth oracle's columns written as CSV.
"""

from __future__ import annotations

import csv
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from validation.examples.dis_method_output import write_dis_outputs
from validation.external import ExternalOutput
from validation.inputs import InputError
from validation.oracle import OracleConfig, TruthOracle
from validation.report import write_report
from validation.runner import run_validation
from validation.summary import find_method
from validation.synthdata import demo_scene, write_synthetic_dataset


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("synth") / "ds"
    write_synthetic_dataset(d, demo_scene(64), 3, name="synthetic-demo", supersample=1)
    return d


def _strip_times(block):
    return {k: v for k, v in block.items() if k != "time_per_frame"}


def test_dis_output_scores_exactly_as_the_builtin_dis_row(synth, tmp_path):
    assert write_dis_outputs(synth, tmp_path / "dis") == 2
    res = run_validation(
        synth,
        variants=[("truth-oracle", OracleConfig())],
        estimate=TruthOracle(synth),
        baselines=["DIS-medium"],
        external=[ExternalOutput(tmp_path / "dis", "my-DIS")],
        progress=False,
    )
    summary = write_report(res, tmp_path / "r")
    for points in ("omniflow points", "dense"):
        builtin = find_method(summary, "DIS-medium", points)
        ours = find_method(summary, "my-DIS", points)
        assert ours["flow"] == builtin["flow"], points
        assert ours["flow"]["cam1"]["all"]["n"] > 50
    same = find_method(summary, "truth-oracle")["baselines_at_same_points"]
    assert same["my-DIS"] == same["DIS-medium"]
    assert "my-DIS" in (tmp_path / "r" / "report.md").read_text()


def test_per_point_csv_scores_as_the_method_that_wrote_it(synth, tmp_path):
    oracle = TruthOracle(synth)
    rig = oracle.ds.rig
    out = tmp_path / "pts"
    for t in (0, 1):
        cols = oracle(None, None, rig, OracleConfig(), t=0).columns
        keys = list(cols)
        path = out / "frames" / f"{t:06d}" / "flow.csv"
        path.parent.mkdir(parents=True)
        with path.open("w", newline="") as fh:
            fh.write("# units line, skipped\n")
            w = csv.writer(fh)
            w.writerow(keys)
            w.writerows(zip(*(np.asarray(cols[k]).tolist() for k in keys), strict=True))
    res = run_validation(
        synth,
        variants=[("truth-oracle", OracleConfig())],
        estimate=TruthOracle(synth),
        baselines=[],
        external=[ExternalOutput(out, "oracle-csv")],
        progress=False,
    )
    summary = write_report(res, tmp_path / "r")
    a, b = find_method(summary, "truth-oracle"), find_method(summary, "oracle-csv")
    assert b["kind"] == "external"
    for cam in ("cam1", "cam2"):
        fa, fb = a["flow"][cam]["all"], b["flow"][cam]["all"]
        assert fb["n"] == fa["n"] > 50
        # CSV text round-trips floats exactly (repr), so the errors are the oracle's own.
        assert fb["epe"] == pytest.approx(fa["epe"], abs=1e-12)
    assert b["stereo"]["all"]["outliers"] == 0.0


def test_missing_outputs_are_named(synth, tmp_path):
    write_dis_outputs(synth, tmp_path / "dis")
    (tmp_path / "dis" / "frames" / "000001" / "cam2.flo").unlink()
    with pytest.raises(InputError, match=r"missing .*000001/cam2\.flo \(1 of 4 files\)"):
        run_validation(synth, variants="default", baselines=[],
                       external=[ExternalOutput(tmp_path / "dis")], progress=False)  # fmt: skip
    with pytest.raises(InputError, match="found neither"):
        ExternalOutput(tmp_path)


# -- the command line refuses bad input in one line, exit 2, nothing written ------------------


def _cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "validation.cli", *args], capture_output=True, text=True, timeout=300
    )


def _one_line_exit_2(p, needle):
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("omnivalidate: error:"), p.stderr
    assert needle in lines[0], lines[0]


@pytest.mark.slow  # 6.3 s (docs/decisions/slow_tests.md)
def test_cli_refuses_bad_out_and_scene_key(synth, tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    base = [str(synth), "--variants", "default", "--baselines", "none", "--no-progress"]
    _one_line_exit_2(_cli(*base, "--out", str(afile)), "is a file")
    _one_line_exit_2(_cli(*base, "--out", str(afile / "sub")), "cannot write there")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("precious")
    _one_line_exit_2(_cli(*base, "--out", str(tmp_path / "mine")), "thesis.tex")
    assert (tmp_path / "mine" / "thesis.tex").read_text() == "precious"
    _one_line_exit_2(
        _cli(*base, "--out", str(tmp_path / "o"), "--check", "validation/thresholds.toml",
             "--scene-key", "nosuch"),
        "--scene-key 'nosuch'",
    )  # fmt: skip
    assert not (tmp_path / "o").exists()
    _one_line_exit_2(_cli(*base, "--out", str(tmp_path / "o"), "--scene-key", "default"),
                     "only with --check")  # fmt: skip
    _one_line_exit_2(_cli(*base, "--out", str(tmp_path / "o"), "--camera-sweep", "bits"),
                     "--camera-sweep 'bits'")  # fmt: skip
    assert not (tmp_path / "o").exists()
    assert not list(tmp_path.glob(".o.*"))  # no temporary directory left behind


def test_cli_refuses_a_bad_camera_parameter(synth, tmp_path):
    pytest.importorskip("omnisim.camera")
    base = [str(synth), "--variants", "default", "--baselines", "none", "--no-progress"]
    _one_line_exit_2(_cli(*base, "--out", str(tmp_path / "o"), "--camera", "bits=7"), "bits")
    _one_line_exit_2(_cli(*base, "--out", str(tmp_path / "o"), "--camera", "read_noise=-1"),
                     "read_noise")  # fmt: skip
    assert not (tmp_path / "o").exists()


@pytest.mark.slow  # 9.6 s (docs/decisions/slow_tests.md)
def test_cli_refuses_incomplete_dataset_and_nan_radiance(synth, tmp_path):
    from omnisim.dataset import read_exr, write_exr

    ds = tmp_path / "ds"
    shutil.copytree(synth, ds)
    base = ["--variants", "default", "--baselines", "none", "--no-progress"]
    # NaN radiance: one line naming the frame and camera.
    exr = ds / "frames" / "000001" / "cam2.exr"
    chans = read_exr(exr)
    chans["R"][3, 4] = np.nan
    write_exr(exr, chans)
    _one_line_exit_2(_cli(str(ds), "--out", str(tmp_path / "o"), *base), "non-finite radiance")
    # Incomplete: frame 2 missing; refused, saying how much; --partial scores pair 0 -> 1.
    shutil.copytree(synth, tmp_path / "ds2")
    (tmp_path / "ds2" / "frames" / "000002" / "cam1.exr").unlink()
    _one_line_exit_2(_cli(str(tmp_path / "ds2"), "--out", str(tmp_path / "o"), *base),
                     "1 of 3 frames missing (2)")  # fmt: skip
    p = _cli(str(tmp_path / "ds2"), "--out", str(tmp_path / "o"), *base, "--partial")
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "o" / "summary.json").is_file()
    # A second run replaces the previous report as a whole.
    p = _cli(str(tmp_path / "ds2"), "--out", str(tmp_path / "o"), *base, "--partial")
    assert p.returncode == 0, p.stderr
    assert sorted(x.name for x in tmp_path.iterdir() if x.name.startswith(".o")) == []
    # A truncated .flo of a scored frame: refused naming it (it was scored unnoticed).
    shutil.copytree(synth, tmp_path / "ds3")
    flo = tmp_path / "ds3" / "frames" / "000001" / "cam2.flo"
    flo.write_bytes(flo.read_bytes()[:100])
    _one_line_exit_2(_cli(str(tmp_path / "ds3"), "--out", str(tmp_path / "o3"), *base),
                     "000001/cam2.flo: .flo header says")  # fmt: skip
    assert not (tmp_path / "o3").exists()


# -- --row: any configuration of the flow step gets its own scored row -------------------------


def test_row_scores_a_configuration_the_variants_do_not_list(tmp_path):
    """``--row fit.flow_taper=0`` adds one row named after that knob; it runs the changed
    configuration (its figures differ from the default row's: the taper changes the flow
    fit at every point), and the default row is unchanged by the extra row. Mutation
    caught: a --row that is parsed but not run (same figures as the default) or not added.
    128 px frames: the 64 px fixture has no matched point, so every EPE would be None."""
    import json

    from validation.cli import main

    ds = tmp_path / "ds"
    write_synthetic_dataset(ds, demo_scene(128), 3, name="synthetic-demo", supersample=1)
    base = [str(ds), "--variants", "default", "--baselines", "none", "--no-progress"]
    assert main([*base, "--out", str(tmp_path / "a")]) == 0
    assert main([*base, "--out", str(tmp_path / "b"), "--row", "fit.flow_taper=0"]) == 0

    a = json.loads((tmp_path / "a" / "summary.json").read_text())["methods"]
    b = json.loads((tmp_path / "b" / "summary.json").read_text())["methods"]
    assert len(a) == 1 and len(b) == 2
    assert b[0]["name"] == a[0]["name"]
    assert b[1]["name"] == "omniflow:default+fit.flow_taper=0.0", b[1]["name"]
    assert b[1]["config"]["fit.flow_taper"] == 0.0  # the full config is in summary.json
    assert a[0]["flow"]["cam1"]["all"]["n"] > 0
    assert b[0]["flow"]["cam1"]["all"]["epe"] == a[0]["flow"]["cam1"]["all"]["epe"]
    assert b[1]["flow"]["cam1"]["all"]["epe"] != a[0]["flow"]["cam1"]["all"]["epe"]


def test_cli_refuses_a_bad_row(synth, tmp_path):
    base = [str(synth), "--variants", "default", "--baselines", "none", "--no-progress"]
    out = ["--out", str(tmp_path / "o")]
    _one_line_exit_2(_cli(*base, *out, "--row", "fit.flow_taper=2"), "--fit.flow-taper 2: expected")
    _one_line_exit_2(_cli(*base, *out, "--row", "nosuch=1"), "an OmniFlowConfig knob")
    _one_line_exit_2(
        _cli(*base, *out, "--row", "pooling.eiv=bogus"), "--pooling.eiv: invalid choice: 'bogus'"
    )
    # the default configuration again: already the first row
    _one_line_exit_2(_cli(*base, *out, "--row", "fit.flow_taper=0.5"), "already scored")
    assert not (tmp_path / "o").exists()


def test_row_presets_start_from_the_preset():
    """``--row dense`` and ``--row dense,NAME=VALUE`` (omniflow.cli.common.config_from_settings)
    start from OmniFlowConfig.dense(), ``paper`` from OmniFlowConfig.paper(); both at once
    is refused in one line. Mutation caught: a preset word ignored (the defaults)."""
    from omniflow.cli.common import CLIError, config_from_settings
    from omniflow.config import DENSE, OmniFlowConfig

    assert config_from_settings("dense") == OmniFlowConfig.dense() != OmniFlowConfig()
    assert config_from_settings("dense,pooling.pool_k=64") == OmniFlowConfig.dense(
        pooling={"pool_k": 64}
    )
    assert config_from_settings("paper") == OmniFlowConfig.paper()
    dense = OmniFlowConfig.dense()
    changed = {k for k, v in OmniFlowConfig().to_dict().items() if dense.to_dict()[k] != v}
    assert dense == OmniFlowConfig().with_settings({k: dense.to_dict()[k] for k in changed})
    assert changed == {
        f"{k}.{g}" if isinstance(v, dict) else k
        for k, v in DENSE.items()
        for g in (v if isinstance(v, dict) else [k])
    }
    with pytest.raises(CLIError, match="at most one preset"):
        config_from_settings("paper,dense")


def test_monocular_row_is_scored_on_cam1(tmp_path):
    """``--row monocular_gap=8``: the row's cam1-only flow (omniflow.solve.monocular) is scored
    as its own block (``monocular``, cam1 only), with DIS-medium at the same points and a
    headline line; rows without it have no such block. Mutation caught: the monocular
    points dropped, or scored at the stereo points (the counts would agree)."""
    import json

    from validation.cli import main

    ds = tmp_path / "ds"
    write_synthetic_dataset(ds, demo_scene(128), 3, name="synthetic-demo", supersample=1)
    args = [str(ds), "--variants", "default", "--baselines", "DIS-medium", "--no-progress",
            "--frames", "0", "--out", str(tmp_path / "o"), "--row", "monocular_gap=8"]  # fmt: skip
    assert main(args) == 0
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    rows = [m for m in summary["methods"] if m["kind"] == "omniflow"]
    assert "monocular" not in rows[0]
    mono = rows[1]["monocular"]
    assert set(mono["flow"]) == {"cam1"}
    n_mono, n_stereo = mono["flow"]["cam1"]["all"]["n"], rows[1]["flow"]["cam1"]["all"]["n"]
    assert n_mono > 0 and n_mono != n_stereo
    assert mono["flow"]["cam1"]["all"]["epe"]["median"] is not None
    assert mono["baselines_at_same_points"]["DIS-medium"]["cam1"]["n"] == n_mono
    assert any(line.startswith("cam1 alone (monocular_gap)") for line in summary["headline"])
    report = (tmp_path / "o" / "report.md").read_text()
    assert f"| {rows[1]['name']} | cam1 only |" in report  # the objects table's own line
