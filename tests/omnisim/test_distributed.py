"""Frames as Dask tasks on a local two-worker cluster: the same bytes as a local run."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

distributed = pytest.importorskip("distributed")

from omnisim.dataset import open_dataset  # noqa: E402
from omnisim.job import render_dataset  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
DEFAULT = ROOT / "scenes" / "default.toml"
FAKE = "tests.helpers.fakes:render_frame"


def frame_bytes(d: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(d)): p.read_bytes()
        for p in sorted((d / "frames").rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def cluster():
    from distributed import Client, LocalCluster

    path = os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])
    with (
        LocalCluster(
            n_workers=2,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            env={"PYTHONPATH": path},
        ) as lc,
        Client(lc) as client,
    ):
        yield lc, client


@pytest.mark.parametrize("write_on", ["client", "worker"])
def test_cluster_matches_local_fake_renderer(tmp_path, cluster, write_on):
    lc, client = cluster
    ov = {"frames": 5, "render.width": 32, "render.height": 32, "render.spp": 1}
    local = render_dataset(DEFAULT, tmp_path / "local", ov, renderer=FAKE, progress=False)
    dist = render_dataset(
        DEFAULT,
        tmp_path / "dist",
        ov,
        renderer=FAKE,
        scheduler=lc.scheduler_address,
        write_on=write_on,
        progress=False,
    )
    assert sorted(dist.rendered) == local.rendered == [0, 1, 2, 3, 4]
    assert frame_bytes(tmp_path / "dist") == frame_bytes(tmp_path / "local")
    # the same dataset.json, less the local run's seconds per frame (not recorded on Dask)
    local_meta = json.loads((tmp_path / "local/dataset.json").read_text())
    local_meta.pop("timing")
    assert json.loads((tmp_path / "dist/dataset.json").read_text()) == local_meta
    assert not [p for p in (tmp_path / "dist/frames").iterdir() if p.name.startswith(".")]
    # both workers took part
    assert len(client.nthreads()) == 2


def test_cli_scheduler_option(tmp_path, cluster, capsys):
    from omnisim.cli import main

    lc, _ = cluster
    common = ["--frames", "3", "--resolution", "32", "--renderer", FAKE, "--no-progress"]
    assert main(["render", str(DEFAULT), "--out", str(tmp_path / "a"), *common]) == 0
    args = ["--scheduler", lc.scheduler_address]
    assert main(["render", str(DEFAULT), "--out", str(tmp_path / "b"), *common, *args]) == 0
    assert "3 rendered now" in capsys.readouterr().out
    assert frame_bytes(tmp_path / "b") == frame_bytes(tmp_path / "a")


def test_cluster_resumes_partial_local_run(tmp_path, cluster):
    _, client = cluster
    ov = {"frames": 4, "render.width": 32, "render.height": 32}
    ref = tmp_path / "ref"
    render_dataset(DEFAULT, ref, ov, renderer=FAKE, progress=False)
    out = tmp_path / "out"
    render_dataset(DEFAULT, out, ov, renderer=FAKE, progress=False, stop_after=1)
    res = render_dataset(DEFAULT, out, ov, renderer=FAKE, scheduler=client, progress=False)
    assert sorted(res.rendered) == [1, 2, 3] and res.skipped == [0]
    assert frame_bytes(out) == frame_bytes(ref)


@pytest.mark.render
def test_cluster_matches_local_mitsuba(tmp_path, cluster):
    """Workers load the scene from its path and render with Mitsuba: byte-identical EXRs."""
    lc, _ = cluster
    ov = {"frames": 2, "render.width": 48, "render.height": 48, "render.spp": 2}
    render_dataset(DEFAULT, tmp_path / "local", ov, progress=False)
    res = render_dataset(
        DEFAULT, tmp_path / "dist", ov, scheduler=lc.scheduler_address, progress=False
    )
    assert sorted(res.rendered) == [0, 1]
    a, b = frame_bytes(tmp_path / "local"), frame_bytes(tmp_path / "dist")
    assert sorted(a) == sorted(b) and any(k.endswith(".exr") for k in a)
    assert a == b
    assert open_dataset(tmp_path / "dist").complete


def test_cli_scheduler_in_a_fresh_process(tmp_path, cluster):
    """The command line's case: an address and no Client of the caller's in the process
    (the fixture's default Client hides that distributed.wait looks one up)."""
    import subprocess
    import sys

    lc, _ = cluster
    path = os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])
    cmd = [sys.executable, "-m", "omnisim.cli", "render", str(DEFAULT), "--out",
           str(tmp_path / "d"), "--frames", "2", "--resolution", "32", "--renderer", FAKE,
           "--no-progress", "--scheduler", lc.scheduler_address]  # fmt: skip
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=300,
                       env={**os.environ, "PYTHONPATH": path})  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert "2 rendered now" in p.stdout


# -- a cluster of `dask scheduler` and `dask worker` commands (issue 25 item 3) ------------

DASK = shutil.which("dask")


def _env() -> dict[str, str]:
    return {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }


def _start(argv: list[str], log: Path, **env: str) -> subprocess.Popen:
    """A process in its own session (so it and its children are stopped together)."""
    with log.open("w") as err:  # the child keeps its own descriptor
        return subprocess.Popen(argv, cwd=ROOT, env={**_env(), **env},
                                stdout=subprocess.DEVNULL, stderr=err,
                                start_new_session=True)  # fmt: skip


def _stop(procs: list[subprocess.Popen]) -> None:
    """SIGTERM each process group, then SIGKILL what is left after 20 s."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        for p in procs:
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, sig)
        for p in procs:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=20)
        if all(p.poll() is not None for p in procs):
            return


def _render_cli(out: Path, *more: str, frames: int = 2) -> list[str]:
    """``omnisim render`` of the default scene, 32 px frames, as a fresh process's argv."""
    return [sys.executable, "-m", "omnisim.cli", "render", str(DEFAULT), "--out", str(out),
            "--frames", str(frames), "--resolution", "32", "--spp", "1", "--renderer", FAKE,
            "--no-progress", *more]  # fmt: skip


def _run(argv: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(argv, capture_output=True, text=True, timeout=300, cwd=ROOT, env=_env())


def _wait_for(done, what: str, seconds: float = 60.0) -> None:
    deadline = time.monotonic() + seconds
    while not done():
        assert time.monotonic() < deadline, f"{what}: not within {seconds:g} s"
        time.sleep(0.05)


def _address(info: Path) -> str | None:
    """The address in a scheduler file, None while it is not (completely) written."""
    try:
        return json.loads(info.read_text())["address"]
    except (OSError, ValueError, KeyError):
        return None


@contextlib.contextmanager
def _dask_commands(tmp_path: Path, workers: int = 2, **env: str):
    """``dask scheduler`` on 127.0.0.1 and ``workers`` one-thread ``dask worker`` processes
    (``env`` added to theirs), each registered; yields (address, worker processes) and
    stops every process afterwards. Each also exits by itself should the test die: the
    scheduler when idle for 300 s, a worker 60 s after its scheduler is gone."""
    info = tmp_path / "scheduler.json"
    # the dashboards on a free port of 127.0.0.1 (--no-dashboard still binds 0.0.0.0:8787)
    local = ["--dashboard-address", "127.0.0.1:0"]
    procs = [_start([DASK, "scheduler", "--host", "127.0.0.1", "--port", "0", *local,
                     "--idle-timeout", "300", "--scheduler-file", str(info)],
                    tmp_path / "scheduler.log")]  # fmt: skip
    try:
        _wait_for(lambda: _address(info) or procs[0].poll() is not None, "the scheduler file")
        assert procs[0].poll() is None, (tmp_path / "scheduler.log").read_text()
        address = _address(info)
        assert address.startswith("tcp://127.0.0.1:")
        logs = [tmp_path / f"worker{i}.log" for i in range(workers)]
        for i, log in enumerate(logs):
            procs.append(_start([DASK, "worker", "--scheduler-file", str(info), "--nthreads",
                                 "1", *local, "--death-timeout", "60", "--local-directory",
                                 str(tmp_path / f"w{i}")], log, **env))  # fmt: skip
        for log in logs:
            _wait_for(lambda log=log: "Registered to" in log.read_text(), f"{log.name}")
        yield address, procs[1:]
    finally:
        _stop(procs)


def _same_dataset(dist: Path, local: Path) -> None:
    """The same frame files and dataset.json, less the local run's timing section (the
    seconds per frame, not recorded on Dask)."""
    assert frame_bytes(dist) == frame_bytes(local)
    local_meta = json.loads((local / "dataset.json").read_text())
    local_meta.pop("timing")
    assert json.loads((dist / "dataset.json").read_text()) == local_meta


@pytest.mark.slow  # 14-18 s (docs/decisions/slow_tests.md)
@pytest.mark.skipif(DASK is None, reason="the dask command is not installed")
def test_cli_scheduler_on_dask_scheduler_and_dask_worker(tmp_path):
    """``omnisim render --scheduler tcp://...`` as a user runs it: a scheduler and two
    one-thread workers started by the ``dask`` command, the render a fresh process with
    no Client of its own (item 3 of issue 25: "No clients found" before the fix)."""
    with _dask_commands(tmp_path) as (address, _):
        dist = _run(_render_cli(tmp_path / "dist", "--scheduler", address))
    assert dist.returncode == 0 and "2 rendered now" in dist.stdout, dist.stderr
    local = _run(_render_cli(tmp_path / "local"))
    assert local.returncode == 0, local.stderr
    _same_dataset(tmp_path / "dist", tmp_path / "local")


@pytest.mark.slow  # 18 s (docs/decisions/slow_tests.md)
@pytest.mark.skipif(DASK is None, reason="the dask command is not installed")
def test_cli_scheduler_survives_a_worker_killed_mid_run(tmp_path):
    """One of two workers is killed (SIGKILL, with its nanny) once frame 0 is on disk,
    frames 0.5 s each: the scheduler gives its frames to the other; the same bytes."""
    with _dask_commands(tmp_path, OMNISIM_FAKE_DELAY="0.5") as (address, workers):
        argv = _render_cli(tmp_path / "dist", "--scheduler", address, frames=8)
        render = subprocess.Popen(argv, cwd=ROOT, env=_env(), text=True,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
        try:
            first = tmp_path / "dist" / "frames" / "000000"
            _wait_for(lambda: first.is_dir() or render.poll() is not None, "frame 0", 120)
            assert render.poll() is None, render.communicate(timeout=60)  # still running
            os.killpg(workers[0].pid, signal.SIGKILL)
            workers[0].wait(timeout=20)
            out, err = render.communicate(timeout=240)
        finally:
            if render.poll() is None:
                render.kill()
                render.wait(timeout=20)
        done_after_kill = sorted(p.name for p in (tmp_path / "dist" / "frames").iterdir())
    log = (tmp_path / "scheduler.log").read_text()  # the worker left while the render ran
    assert "Remove worker" in log and log.index("Remove worker") < log.index("Remove client")
    assert render.returncode == 0 and "8 rendered now" in out, err
    assert len(done_after_kill) == 8
    local = _run(_render_cli(tmp_path / "local", frames=8))
    assert local.returncode == 0, local.stderr
    _same_dataset(tmp_path / "dist", tmp_path / "local")
