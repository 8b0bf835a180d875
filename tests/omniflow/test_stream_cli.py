"""``omniflow-stream``: per-pair CSVs of a sequence, whole files only, resumable."""

from __future__ import annotations

import json

import numpy as np
import pytest

from omniflow.cli.stream import main
from omniflow.io.imageio import read_image, to_grey, write_png
from omniflow.io.ownership import MARKER
from omniflow.pipeline import OmniFlowConfig, estimate
from omnisim.synthetic import Motion
from tests.helpers.scenes import paper_rig, wall_scene
from tests.omniflow.test_cli import read_csv

FRAMES = 4
# CSV values are written with 9 significant digits ("%.9g"), and the stream
# equals estimate() to 6.6e-6 of each column's largest value (tests/omniflow/
# test_stream.py); 1e-4 of the column's largest value bounds both.
REL_TOL = 1e-4


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """Four 16-bit PNG stereo frames (cam1_K.png, cam2_K.png) and rig.json, 128 px."""
    d = tmp_path_factory.mktemp("seq")
    rig = paper_rig(128)
    scene = wall_scene(rig, robot=Motion(velocity=(0.01, 0.005), yaw_rate=0.002))
    for k in range(FRAMES):
        for cam in ("cam1", "cam2"):
            write_png(d / f"{cam}_{k}.png", scene.render(cam, k), bits=16)
    (d / "rig.json").write_text(json.dumps(rig.to_dict()))
    return d, rig


def _stream(folder, out, *extra) -> int:
    d, _ = folder
    return main([str(d), "--rig", str(d / "rig.json"), "--out", str(out),
                 "--quiet", *map(str, extra)])  # fmt: skip


def _frames(folder):
    d, _ = folder
    read = lambda cam: [to_grey(read_image(d / f"{cam}_{k}.png")) for k in range(FRAMES)]  # noqa: E731
    return read("cam1"), read("cam2")


@pytest.mark.parametrize("extra", [[], ["--background"]], ids=["plain", "background"])
def test_one_csv_per_pair_equal_to_estimate(folder, tmp_path, capsys, extra):
    out = tmp_path / "out"
    assert _stream(folder, out, *extra) == 0
    said = capsys.readouterr().out
    assert "3 pair(s) written" in said
    # the first pair (loading the compiled kernels) is timed apart from the median of the
    # others (mutation: the first in the median again, its own figure gone: caught)
    assert "ms per pair after the first (the first " in said
    names = sorted(p.name for p in out.iterdir())
    pairs = [f"flow_00000{k}_00000{k + 1}.csv" for k in range(3)]
    assert names == [MARKER, *pairs, "stream.json"]
    meta = json.loads((out / "stream.json").read_text())
    assert meta["complete"] and meta["pairs_in_out"] == 3 and meta["this_run"]["pairs"] == 3
    assert meta["this_run"]["points"] == sum(len(read_csv(out / n)["x"]) for n in pairs)
    f1, f2 = _frames(folder)
    for k in range(3):
        cols = read_csv(out / f"flow_{k:06d}_{k + 1:06d}.csv")
        ref = estimate(f1, f2, folder[1], OmniFlowConfig(), t=k).columns
        assert len(cols["x"]) == len(ref["x"]) > 100
        for name, val in ref.items():
            scale = np.max(np.abs(val))
            assert np.max(np.abs(cols[name] - val)) <= REL_TOL * scale, name
        assert "time_to_contact" in cols


def test_monocular_gap_writes_one_monocular_csv_per_pair(folder, tmp_path):
    """``--monocular-gap`` adds monocular_K0_K1.csv beside each flow CSV: cam1's flow alone
    (omniflow.solve.monocular), equal to the pair's in-process result at the points both have
    (tests/omniflow/test_stream.py::_same_monocular)."""
    from tests.omniflow.test_stream import _same_monocular

    out = tmp_path / "out"
    assert _stream(folder, out, "--monocular-gap", "4") == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == (
        [MARKER]
        + [f"flow_00000{k}_00000{k + 1}.csv" for k in range(3)]
        + [f"monocular_00000{k}_00000{k + 1}.csv" for k in range(3)]
        + ["stream.json"]
    )
    f1, f2 = _frames(folder)
    for k in range(3):
        got = read_csv(out / f"monocular_{k:06d}_{k + 1:06d}.csv")
        want = estimate(f1, f2, folder[1], OmniFlowConfig(monocular_gap=4.0), t=k).monocular
        assert got["x"].size > 50
        _same_monocular(got, want)


def test_rerun_resumes_and_rewrites_only_what_is_missing(folder, tmp_path, capsys):
    out = tmp_path / "out"
    assert _stream(folder, out) == 0
    before = (out / "flow_000001_000002.csv").read_bytes()
    (out / "flow_000001_000002.csv").unlink()
    kept = (out / "flow_000002_000003.csv").stat().st_mtime_ns
    capsys.readouterr()
    assert _stream(folder, out) == 0
    assert "1 pair(s) written, 3 in" in capsys.readouterr().out
    assert (out / "flow_000001_000002.csv").read_bytes() == before
    assert (out / "flow_000002_000003.csv").stat().st_mtime_ns == kept
    assert json.loads((out / "stream.json").read_text())["complete"]


def test_other_options_in_the_same_folder_are_refused(folder, tmp_path, capsys):
    out = tmp_path / "out"
    assert _stream(folder, out, "--stop", 2) == 0
    capsys.readouterr()
    assert _stream(folder, out, "--band", 0.25) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "stream.json: written with another config" in err


def test_a_bad_frame_stops_with_whole_files_only(folder, tmp_path, capsys):
    d, _ = folder
    bad = tmp_path / "bad"
    bad.mkdir()
    for p in d.iterdir():
        (bad / p.name).write_bytes(p.read_bytes())
    (bad / "cam2_2.png").write_bytes(b"not a png")
    out = tmp_path / "out"
    status = main([str(bad), "--rig", str(bad / "rig.json"), "--out", str(out),
                   "--quiet"])  # fmt: skip
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1 and "cam2_2.png" in err
    # the first pair was written whole, nothing half-written or temporary is left
    names = sorted(p.name for p in out.iterdir())
    assert names == [MARKER, "flow_000000_000001.csv", "stream.json"]
    assert not json.loads((out / "stream.json").read_text())["complete"]
    assert len(read_csv(out / "flow_000000_000001.csv")["x"]) > 100


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--stop", 9], "expected 0 <= start, start + 2 <= stop <= 4"),
        (["--start", 3], "expected 0 <= start, start + 2 <= stop <= 4"),
    ],
)
def test_bad_ranges_are_one_line(folder, tmp_path, capsys, args, fragment):
    assert _stream(folder, tmp_path / "out", *args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and fragment in err
    assert not (tmp_path / "out").exists()


def test_a_folder_without_frames_or_rig(folder, tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main([str(empty), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "0 cam1 and 0 cam2 image(s)" in capsys.readouterr().err
    d, _ = folder
    assert main([str(d), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "needs --rig FILE" in capsys.readouterr().err


def test_constant_frames_warn_once_under_this_command_s_name(folder, tmp_path, capsys):
    """No stereo match is an answer: exit 0, empty CSVs, one warning line naming
    omniflow-stream (not omniflow)."""
    _, rig = folder
    d = tmp_path / "grey"
    d.mkdir()
    for k in range(2):
        for cam in ("cam1", "cam2"):
            write_png(d / f"{cam}_{k}.png", np.full((128, 128), 0.5), bits=8)
    (d / "rig.json").write_text(json.dumps(rig.to_dict()))
    out = tmp_path / "out"
    assert main([str(d), "--rig", str(d / "rig.json"), "--out", str(out), "--quiet"]) == 0
    captured = capsys.readouterr()
    warning = [x for x in captured.err.splitlines() if "warning" in x]
    assert len(warning) == 1 and warning[0].startswith("omniflow-stream: warning: no stereo")
    assert len(read_csv(out / "flow_000000_000001.csv")["x"]) == 0


def test_module_entry_point_runs():
    """``python -m omniflow.cli.stream`` (the ``omniflow-stream`` script's module) answers."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "omniflow.cli.stream", "--help"],
                          capture_output=True, text=True, timeout=120, check=False)  # fmt: skip
    assert proc.returncode == 0 and "usage: omniflow-stream" in proc.stdout


def test_a_users_file_with_an_output_name_is_refused(folder, tmp_path, capsys):
    # issue 25: a flow_K0_K1.csv in an --out with no marker is the user's, not a pair done
    out = tmp_path / "out"
    out.mkdir()
    (out / "flow_000000_000001.csv").write_text("my,own\n1,2\n")
    assert _stream(folder, out) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{out / 'flow_000000_000001.csv'}: not written by" in err
    assert sorted(p.name for p in out.iterdir()) == ["flow_000000_000001.csv"]
    assert (out / "flow_000000_000001.csv").read_text() == "my,own\n1,2\n"
