"""The omnisim command: errors, resume, interruption (atomic frames), determinism."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from omnisim.cli import main
from omnisim.dataset import open_dataset

ROOT = Path(__file__).resolve().parents[2]
DEFAULT = ROOT / "scenes" / "default.toml"
FAKE = ["--renderer", "tests.helpers.fakes:render_frame", "--no-progress"]
SMALL = ["--resolution", "32", "--spp", "1"]


def tree_bytes(d: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(d)): p.read_bytes()
        for p in sorted((d / "frames").rglob("*"))
        if p.is_file()
    }


def meta_text_without_timing(d: Path) -> str:
    """dataset.json of ``d`` as written, less its machine-dependent ``timing`` section."""
    meta = json.loads((d / "dataset.json").read_text())
    meta.pop("timing", None)
    return json.dumps(meta, indent=2)


def final_frames_complete(d: Path) -> list[str]:
    """Names under frames/: each final frame directory must hold all its files (format
    version 2: per camera the EXR, the .flo, its two mask PNGs and the camera image)."""
    names = []
    for p in sorted((d / "frames").iterdir()):
        names.append(p.name)
        if not p.name.startswith("."):
            assert sorted(f.name for f in p.iterdir()) == [
                f"{cam}.{ext}"
                for cam in ("cam1", "cam2")
                for ext in ("exr", "flo", "occluded.png", "outside.png", "png")
            ], p
    return names


def _env(**extra) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    env.update(extra)
    return env


# -- scene and option errors: one line, exit 2, nothing rendered ------------------------


def test_unknown_key_is_one_line_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    text, n = re.subn(
        r"(?m)^\[render\]\s*$", "[render]\nbogus_key = 1", DEFAULT.read_text(), count=1
    )
    assert n == 1
    bad.write_text(text)
    out = tmp_path / "out"
    assert main(["render", str(bad), "--out", str(out), *FAKE]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert str(bad) in err and "bogus_key" in err
    assert not out.exists()


def test_wrong_type_override_is_one_line_exit_2(tmp_path, capsys):
    out = tmp_path / "out"
    rc = main(["render", str(DEFAULT), "--out", str(out), "--set", 'render.spp="many"', *FAKE])
    assert rc == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "spp" in err and str(DEFAULT) in err
    assert not out.exists()


def test_missing_scene_file(tmp_path, capsys):
    assert main(["render", str(tmp_path / "nope.toml"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "nope.toml" in err


def test_not_toml(tmp_path, capsys):
    bad = tmp_path / "broken.toml"
    bad.write_text("frames = [1, 2\n")
    assert main(["render", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "broken.toml" in err


def test_bad_option_value(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["render", str(DEFAULT), "--out", "x", "--resolution", "big"])
    assert exc.value.code == 2


def test_scene_error_subprocess_exit_code(tmp_path):
    bad = tmp_path / "bad.toml"
    text, n = re.subn(r"(?m)^frames\s*=.*$", "frames = -3", DEFAULT.read_text(), count=1)
    assert n == 1
    bad.write_text(text)
    p = subprocess.run(
        [sys.executable, "-m", "omnisim.cli", "render", str(bad), "--out", str(tmp_path / "o")],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=120,
    )
    assert p.returncode == 2, p.stderr
    assert len(p.stderr.strip().splitlines()) == 1 and "frames" in p.stderr
    assert not (tmp_path / "o").exists()


# -- resume -------------------------------------------------------------------------------


def test_render_resume_and_refuse(tmp_path, capsys):
    out = tmp_path / "out"
    args = ["render", str(DEFAULT), "--out", str(out), "--frames", "3", *SMALL, *FAKE]
    assert main(args) == 0
    assert "3 rendered now" in capsys.readouterr().out
    ds = open_dataset(out)
    assert ds.complete and ds.frame_count == 3
    assert ds.meta["render"]["width"] == 32 and ds.meta["render"]["spp"] == 1
    assert ds.meta["scene"]["source"] == DEFAULT.read_text()
    assert len(ds.meta["robot"]["poses"]) == 3
    assert {o["id"] for o in ds.meta["objects"]} == set(ds.objects)
    before = tree_bytes(out)
    assert main(args) == 0  # nothing left to do
    assert "0 rendered now, 3 already done" in capsys.readouterr().out
    assert tree_bytes(out) == before
    # another seed / size / frame count: refused, one line, nothing touched
    for extra in (["--seed", "5"], ["--frames", "4"], ["--resolution", "40"]):
        a = ["render", str(DEFAULT), "--out", str(out), "--frames", "3", *SMALL, *FAKE, *extra]
        assert main(a) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "refusing to resume" in err
    assert tree_bytes(out) == before


def test_interrupted_in_process_resumes_identically(tmp_path):
    from omnisim.job import render_dataset

    kw = dict(renderer="tests.helpers.fakes:render_frame", progress=False)
    ov = {"frames": 4, "render.width": 32, "render.height": 32}
    ref = render_dataset(DEFAULT, tmp_path / "ref", ov, **kw)
    assert ref.rendered == [0, 1, 2, 3]
    part = render_dataset(DEFAULT, tmp_path / "part", ov, stop_after=2, **kw)
    assert part.rendered == [0, 1]
    rest = render_dataset(DEFAULT, tmp_path / "part", ov, **kw)
    assert rest.rendered == [2, 3] and rest.skipped == [0, 1]
    assert tree_bytes(tmp_path / "part") == tree_bytes(tmp_path / "ref")
    # dataset.json: the same bytes once its timing section (seconds per frame) is removed
    assert meta_text_without_timing(tmp_path / "part") == meta_text_without_timing(tmp_path / "ref")
    assert sorted(json.loads((tmp_path / "part/dataset.json").read_text())["timing"]["frames"]) == [
        "0", "1", "2", "3"
    ]  # fmt: skip


# -- killed by a signal: no partial file under a final name, resume is byte-identical --------


def _cmd(out: Path, frames: int = 6) -> list[str]:
    return [
        sys.executable, "-m", "omnisim.cli", "render", str(DEFAULT), "--out", str(out),
        "--frames", str(frames), *SMALL, *FAKE,
    ]  # fmt: skip


def _wait_for(path: Path, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    t0 = time.monotonic()
    while not path.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t0 < timeout, f"{path} never appeared"
        time.sleep(0.02)


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM], ids=["SIGKILL", "SIGTERM"])
@pytest.mark.slow  # 5.9 s and 5.4 s (docs/decisions/slow_tests.md)
def test_killed_render_resumes_byte_identical(tmp_path, sig):
    ref = tmp_path / "ref"
    subprocess.run(_cmd(ref), check=True, env=_env(), timeout=120, capture_output=True)
    out = tmp_path / "out"
    proc = subprocess.Popen(
        _cmd(out),
        env=_env(OMNISIM_FAKE_DELAY="0.4"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    _wait_for(out / "frames" / "000001", proc)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == (143 if sig == signal.SIGTERM else -signal.SIGKILL), err
    names = final_frames_complete(out)
    done = [n for n in names if not n.startswith(".")]
    assert 2 <= len(done) < 6
    if sig == signal.SIGTERM:
        assert b"resume" in err and not [n for n in names if n.startswith(".")]
    p = subprocess.run(_cmd(out), env=_env(), timeout=120, capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert f"{6 - len(done)} rendered now, {len(done)} already done" in p.stdout
    assert final_frames_complete(out) == [f"{k:06d}" for k in range(6)]
    assert tree_bytes(out) == tree_bytes(ref)


KILL_MID_WRITE = """
import os, signal, sys
from omnisim import dataset
real = dataset._write_synced
count = [0]
def dying(path, data):
    if path.parent.name.startswith(".000002.tmp"):
        count[0] += 1
        if count[0] == 3:  # two of frame 2's six files are on disk, in the temporary dir
            os.kill(os.getpid(), signal.SIGKILL)
    real(path, data)
dataset._write_synced = dying
from omnisim.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_killed_mid_frame_write(tmp_path):
    ref = tmp_path / "ref"
    subprocess.run(_cmd(ref, 4), check=True, env=_env(), timeout=120, capture_output=True)
    out = tmp_path / "out"
    args = _cmd(out, 4)[3:]
    p = subprocess.run(
        [sys.executable, "-c", KILL_MID_WRITE, *args], env=_env(), timeout=120, capture_output=True
    )
    assert p.returncode == -signal.SIGKILL
    names = final_frames_complete(out)
    assert [n for n in names if not n.startswith(".")] == ["000000", "000001"]
    (tmp,) = [n for n in names if n.startswith(".")]
    assert tmp.startswith(".000002.tmp.")
    assert sorted(f.name for f in (out / "frames" / tmp).iterdir()) == ["cam1.exr", "cam1.flo"]
    assert not open_dataset(out).is_done(2)
    p = subprocess.run(_cmd(out, 4), env=_env(), timeout=120, capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert final_frames_complete(out) == ["000000", "000001", "000002", "000003"]
    assert tree_bytes(out) == tree_bytes(ref)


# -- the real renderer --------------------------------------------------------------------


@pytest.mark.render
def test_real_render_deterministic_and_checked(tmp_path, capsys):
    common = ["--frames", "2", "--resolution", "64", "--spp", "2", "--no-progress"]
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["render", str(DEFAULT), "--out", str(a), *common, "--check"]) == 0
    out = capsys.readouterr().out
    assert "all checks passed" in out and "eq1" in out and "photometric" in out
    # the same scene, seed and versions: the same bytes, also when interrupted and resumed
    from omnisim.job import render_dataset

    ov = {"frames": 2, "render.width": 64, "render.height": 64, "render.spp": 2}
    assert render_dataset(DEFAULT, b, ov, stop_after=1, progress=False).rendered == [0]
    assert render_dataset(DEFAULT, b, ov, progress=False).rendered == [1]
    assert tree_bytes(a) == tree_bytes(b)
    assert main(["check", str(a)]) == 0
