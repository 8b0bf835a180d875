"""Ctrl-C and SIGTERM as one line (issue 25): every command, signalled at a few moments.

Each command runs in a subprocess and gets SIGINT (or SIGTERM) at a fixed time after
its start: 0.3 s (the interpreter, the imports) and 2 s (numpy, numba or Mitsuba
starting, or the work itself; 1 s for ``omniflow pair``, which takes about 2 s). It
must exit 130 (SIGTERM: 143) with at most one line on stderr, ``PROG: interrupted
(...)``, no traceback, no temporary file left, and every finished unit whole. A
command that finished before its signal (exit 0) skips that moment instead of
failing: the moment proves nothing about the handler.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from omniflow.io.dataset import FRAME_RE, camera_names, expected_files, load_meta

ROOT = Path(__file__).resolve().parent.parent
FAKE = ["--renderer", "tests.helpers.fakes:render_frame"]
MOMENTS = [0.3, 2.0]  # seconds after the start


def _command(script: str, module: str) -> list[str]:
    """The installed console script, else ``python -m`` of its module (the same main)."""
    exe = shutil.which(script)
    return [exe] if exe else [sys.executable, "-m", module]


def _env(**extra: str) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT), **extra}


def _handler_installed(pid: int) -> bool:
    """Whether process ``pid`` catches SIGTERM (Python itself catches only SIGINT, so
    this is the command's handler); True where /proc cannot say."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return True
    caught = int(next(ln.split()[1] for ln in text.splitlines() if ln.startswith("SigCgt:")), 16)
    return bool(caught & (1 << (signal.SIGTERM - 1)))


def _interrupt(argv: list[str], at: float, sig: int = signal.SIGINT, **env: str):
    """(exit status, stderr) of ``argv`` sent ``sig`` ``at`` s after its start; skips
    the case when the command had ended by then. On a loaded machine the interpreter
    may still be starting at ``at``: the signal then waits for the handler (a signal
    before it is the interpreter's, not the command's)."""
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=_env(**env), cwd=ROOT)  # fmt: skip
    time.sleep(at)
    t0 = time.monotonic()
    while proc.poll() is None and not _handler_installed(proc.pid):
        assert time.monotonic() - t0 < 30, "the command never installed its handler"
        time.sleep(0.01)
    if proc.poll() is None:
        proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    if proc.returncode == 0:
        pytest.skip(f"finished before the signal at {at} s")
    return proc.returncode, err


def _one_line(status: int, err: str, prog: str, sig: int = signal.SIGINT) -> None:
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert status == 128 + sig, (status, err)
    assert len(lines) == 1 and lines[0].startswith(f"{prog}: interrupted"), err


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    from validation.synthdata import demo_scene, write_synthetic_dataset

    d = tmp_path_factory.mktemp("ds") / "ds"
    write_synthetic_dataset(d, demo_scene(256), 2, name="synthetic-demo", supersample=1)
    return d


def _frames_whole(out: Path) -> list[str]:
    """The frame folders of dataset ``out``, each checked whole; no temporary left."""
    leftovers = [p.name for p in out.rglob("*") if ".tmp." in p.name]
    assert leftovers == []
    if not (out / "dataset.json").exists():
        return []
    meta = load_meta(out / "dataset.json")
    want = sorted(expected_files(camera_names(meta), "camera" in meta, meta["format_version"]))
    names = sorted(p.name for p in (out / "frames").iterdir())
    for name in names:
        assert FRAME_RE.match(name), name
        assert sorted(f.name for f in (out / "frames" / name).iterdir()) == want, name
    return names


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
@pytest.mark.parametrize("at", MOMENTS)
def test_omnisim_render(tmp_path, at, sig):
    out = tmp_path / "out"
    argv = [*_command("omnisim", "omnisim.cli"), "render", str(ROOT / "scenes/default.toml"),
            "--out", str(out), "--frames", "40", "--resolution", "32", "--spp", "1",
            "--no-progress", "--no-resource-check", *FAKE]  # fmt: skip
    status, err = _interrupt(argv, at, sig, OMNISIM_FAKE_DELAY="0.2")
    _one_line(status, err, "omnisim", sig)
    assert "finished frames are kept" in err
    assert len(_frames_whole(out)) < 40 if out.exists() else True


@pytest.mark.render
@pytest.mark.parametrize("at", MOMENTS)
def test_omnisim_render_with_mitsuba_starting(tmp_path, at):
    pytest.importorskip("mitsuba")
    out = tmp_path / "out"
    argv = [*_command("omnisim", "omnisim.cli"), "render", str(ROOT / "scenes/default.toml"),
            "--out", str(out), "--frames", "40", "--resolution", "32", "--spp", "1",
            "--no-progress", "--no-resource-check"]  # fmt: skip
    status, err = _interrupt(argv, at)
    _one_line(status, err, "omnisim")
    if out.exists():
        _frames_whole(out)


@pytest.mark.parametrize("at", MOMENTS)
def test_omnivalidate(dataset, tmp_path, at):
    out = tmp_path / "r"
    argv = [*_command("omnivalidate", "validation.cli"), str(dataset), "--out", str(out),
            "--no-progress"]  # fmt: skip
    status, err = _interrupt(argv, at)
    _one_line(status, err, "omnivalidate")
    assert not out.exists()  # the report is renamed into place at the end
    assert [p.name for p in tmp_path.iterdir()] == []  # no temporary folder, no lock file


@pytest.mark.parametrize("at", [0.3, 1.0])  # a pair takes about 2 s here, imports included
def test_omniflow_pair(dataset, tmp_path, at):
    out = tmp_path / "out"
    argv = [*_command("omniflow", "omniflow.cli"), "pair", "--dataset", str(dataset),
            "--frame", "0", "--out", str(out)]  # fmt: skip
    status, err = _interrupt(argv, at, sig=signal.SIGINT)
    _one_line(status, err, "omniflow pair")
    assert not out.exists()  # the outputs move into --out together, at the end
    assert [p.name for p in tmp_path.iterdir()] == []  # no staging folder, no lock file


def test_a_second_signal_is_ignored_and_the_line_stays_one(tmp_path):
    out = tmp_path / "out"
    argv = [*_command("omnisim", "omnisim.cli"), "render", str(ROOT / "scenes/default.toml"),
            "--out", str(out), "--frames", "40", "--resolution", "32", "--spp", "1",
            "--no-progress", "--no-resource-check", *FAKE]  # fmt: skip
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=_env(OMNISIM_FAKE_DELAY="0.2"), cwd=ROOT)  # fmt: skip
    t0 = time.monotonic()
    while not (out / "frames" / "000000").exists():  # rendering: the first frame is done
        assert proc.poll() is None and time.monotonic() - t0 < 60, proc.communicate()
        time.sleep(0.02)
    proc.send_signal(signal.SIGINT)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    _one_line(proc.returncode, err, "omnisim")
    assert len(_frames_whole(out)) >= 1


def test_run_main_in_process(capsys):
    """A status passes through, an error without a signal is re-raised, a
    KeyboardInterrupt (no signal) is SIGINT's one line, and the handlers are restored."""
    from omniflow.interrupts import run_main

    before = signal.getsignal(signal.SIGINT)
    assert run_main("prog", lambda: 3) == 3
    with pytest.raises(ZeroDivisionError):
        run_main("prog", lambda: 1 // 0)
    assert signal.getsignal(signal.SIGINT) is before

    def interrupted() -> int:
        raise KeyboardInterrupt

    assert run_main("prog", interrupted, note="all kept") == 130
    assert capsys.readouterr().err == "prog: interrupted (all kept)\n"
    assert run_main("prog", lambda: 0) == 0  # the next run starts afresh
    assert signal.getsignal(signal.SIGINT) is before
