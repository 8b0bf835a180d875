"""omnivalidate's --out (issue 25): it replaces only a report it wrote, one run at a time,
and the temporary folders of a dead run go with the next run.

Canary files sit where the command writes: in --out, in its figures/ and beside it
(the parent holds the temporary and lock files). Every refusal is one line, exit 2,
and leaves every byte under the test's folder as it was.
"""

from __future__ import annotations

import fcntl
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from omniflow.io.ownership import MARKER
from validation.summary import FORMAT
from validation.synthdata import demo_scene, write_synthetic_dataset

ROOT = Path(__file__).resolve().parents[2]
#: The cheapest run: one omniflow row, no baseline (about 4 s here).
FAST = ["--variants", "default", "--baselines", "none", "--no-progress"]
PDF = b"%PDF-1.7 the user's paper figure"


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("synth") / "ds"
    write_synthetic_dataset(d, demo_scene(64), 3, name="synthetic-demo", supersample=1)
    return d


def _cli(*args: object) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "validation.cli", *map(str, args)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env, cwd=ROOT)


def _tree(d: Path) -> dict[str, bytes]:
    """Every file under d (dotfiles included), by relative path."""
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def _legacy_report(out: Path) -> None:
    """A report of this project written before markers existed."""
    (out / "figures").mkdir(parents=True)
    (out / "summary.json").write_text(json.dumps({"format": FORMAT, "methods": []}))
    (out / "report.md").write_text("# omnivalidate: old\n")
    (out / "figures" / "inputs.png").write_bytes(b"old png")


def _paper_figure_in_legacy_report(out: Path) -> str:
    _legacy_report(out)
    (out / "figures" / "my_paper_fig1.pdf").write_bytes(PDF)
    return "r/figures/my_paper_fig1.pdf"


def _paper_figure_in_marked_report(out: Path) -> str:
    _legacy_report(out)
    (out / MARKER).write_text(json.dumps({"package": "omniflow-testbed", "id": "x"}))
    (out / "figures" / "my_paper_fig1.pdf").write_bytes(PDF)
    return "r/figures/my_paper_fig1.pdf"


def _own_report_md(out: Path) -> str:
    out.mkdir()
    (out / "report.md").write_text("# my own report\n")
    return "r/report.md"


def _own_summary_json(out: Path) -> str:
    out.mkdir()
    (out / "summary.json").write_text('{"my": "numbers"}\n')
    return "r/summary.json"


@pytest.mark.parametrize(
    "setup",
    [
        _paper_figure_in_legacy_report,
        _paper_figure_in_marked_report,
        _own_report_md,
        _own_summary_json,
    ],
)
def test_a_folder_omnivalidate_did_not_write_is_refused(synth, tmp_path, setup):
    (tmp_path / "canary.txt").write_text("beside --out")
    named = setup(tmp_path / "r")
    before = _tree(tmp_path)
    p = _cli(synth, "--out", tmp_path / "r", *FAST)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(lines) == 1, p.stderr
    assert lines[0].startswith("omnivalidate: error: --out ") and str(tmp_path / named) in lines[0]
    assert "not written by omnivalidate" in lines[0]
    assert _tree(tmp_path) == before


def _dead_pid() -> int:
    proc = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)  # fmt: skip
    return int(proc.stdout)


def test_a_report_is_replaced_and_a_dead_run_s_leftovers_removed(synth, tmp_path):
    out = tmp_path / "r"
    first = _cli(synth, "--out", out, *FAST)
    assert first.returncode == 0, first.stderr
    assert json.loads((out / MARKER).read_text())["written_by"] == "omnivalidate"
    assert (out / "figures" / MARKER).is_file()
    # canaries beside --out: a file, and a folder with a temporary's name but no marker
    (tmp_path / "canary.txt").write_text("beside --out")
    (tmp_path / ".r.tmp-mine").mkdir()
    (tmp_path / ".r.tmp-mine" / "keep.txt").write_text("no marker: not ours")
    # a killed run's temporary folder: its marker names a process that has ended
    dead = tmp_path / ".r.tmp-k1ll3d"
    dead.mkdir()
    (dead / "summary.json").write_text("{}")
    body = {"written_by": "omnivalidate", "package": "omniflow-testbed", "id": "d",
            "pid": _dead_pid()}  # fmt: skip
    (dead / MARKER).write_text(json.dumps(body))
    canaries = {k: v for k, v in _tree(tmp_path).items() if not k.startswith(("r/", ".r.tmp-k"))}
    old_id = json.loads((out / MARKER).read_text())["id"]
    second = _cli(synth, "--out", out, *FAST)
    assert second.returncode == 0, second.stderr
    assert json.loads((out / MARKER).read_text())["id"] != old_id  # the new report
    assert not dead.exists()
    after = _tree(tmp_path)
    assert {k: after.get(k) for k in canaries} == canaries
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == [".r.tmp-mine"]


def test_a_second_run_into_one_out_is_refused(synth, tmp_path):
    out = tmp_path / "r"
    _legacy_report(out)
    before = _tree(tmp_path)
    # "another run" holds the lock beside --out, as a running omnivalidate does
    fd = os.open(tmp_path / ".r.lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.write(fd, b"4242\n")
        p = _cli(synth, "--out", out, *FAST)
    finally:
        os.close(fd)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(lines) == 1, p.stderr
    assert f"--out {out}: another omnivalidate process (pid 4242)" in lines[0]
    assert {k: v for k, v in _tree(tmp_path).items() if k != ".r.lock"} == before


def test_two_runs_into_one_out_the_second_is_refused(synth, tmp_path):
    # issue 25: without the lock, both exited 0 and the last silently replaced the other
    out = tmp_path / "r"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "validation.cli", str(synth), "--out", str(out), *FAST]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              env=env, cwd=ROOT) for _ in range(2)]  # fmt: skip
    results = [(p.wait(timeout=300), p.communicate()[1]) for p in procs]
    assert sorted(status for status, _ in results) == [0, 2], results  # they overlap: seconds each
    for status, err in results:
        if status == 2:
            assert len(err.strip().splitlines()) == 1 and "another omnivalidate process" in err
    assert json.loads((out / MARKER).read_text())["written_by"] == "omnivalidate"
    assert [p.name for p in tmp_path.iterdir()] == ["r"]  # no temporary folder, no lock
