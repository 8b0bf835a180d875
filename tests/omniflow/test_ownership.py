"""omniflow.io.ownership: markers, what counts as ours, and the output lock."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path, PurePosixPath

import pytest

from omniflow.io import ownership
from omniflow.io.imageio import OutputError


def _only(*names: str):
    return lambda rel: str(rel) in names


def test_a_marker_names_the_command_version_and_a_random_id(tmp_path):
    a = ownership.write_marker(tmp_path, "omnitest", pid=True)
    body = json.loads((tmp_path / ownership.MARKER).read_text())
    assert body == a and body["written_by"] == "omnitest" and body["pid"] == os.getpid()
    assert body["package"] == "omniflow-testbed" and len(body["id"]) == 32
    assert ownership.write_marker(tmp_path, "omnitest")["id"] != a["id"]
    (tmp_path / ownership.MARKER).write_text('{"package": "other", "id": "1"}')
    assert not ownership.has_marker(tmp_path)  # another package's file is not ours


def test_claim_refuses_a_folder_without_marker_and_a_foreign_name(tmp_path):
    assert ownership.claim(tmp_path / "new", prog="t", owned=_only()) is False
    out = tmp_path / "out"
    out.mkdir()
    assert ownership.claim(out, prog="t", owned=_only()) is True  # empty: free
    (out / "a.txt").write_text("1")
    with pytest.raises(ownership.ForeignPathError, match=r"out/a\.txt: not written by t"):
        ownership.claim(out, prog="t", owned=_only("a.txt"))  # no marker
    assert ownership.claim(out, prog="t", owned=_only("a.txt"), legacy=lambda d: True)
    ownership.write_marker(out, "t")
    (out / "sub").mkdir()
    (out / "sub" / "mine.pdf").write_text("user")
    owned = _only("a.txt", ownership.MARKER, "sub")
    with pytest.raises(ownership.ForeignPathError, match=r"sub/mine\.pdf"):
        ownership.claim(out, prog="t", owned=owned)  # the marker vouches for no other name
    (out / "sub" / "mine.pdf").unlink()
    (out / "sub" / "link").symlink_to(tmp_path)
    with pytest.raises(ownership.ForeignPathError, match=r"sub/link"):
        ownership.claim(out, prog="t", owned=lambda rel: True)  # a link is never ours
    with pytest.raises(OutputError, match="not a folder"):
        ownership.claim(out / "a.txt", prog="t", owned=_only())


def test_find_foreign_walks_depth_first_in_order(tmp_path):
    for name in ("b/x", "b/y", "c"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text("")
    seen: list[PurePosixPath] = []
    assert ownership.find_foreign(tmp_path, lambda rel: seen.append(rel) or True) is None
    assert [str(p) for p in seen] == ["b", "b/x", "b/y", "c"]


def test_claim_names_checks_only_the_names_the_command_writes(tmp_path):
    (tmp_path / "notes.txt").write_text("the user's, left alone")
    ownership.claim_names(tmp_path, prog="t", owned=_only("flow.csv"))
    (tmp_path / "flow.csv").write_text("the user's")
    with pytest.raises(ownership.ForeignPathError, match=r"flow\.csv: not written by t"):
        ownership.claim_names(tmp_path, prog="t", owned=_only("flow.csv"))
    ownership.write_marker(tmp_path, "t")
    ownership.claim_names(tmp_path, prog="t", owned=_only("flow.csv"))


def test_dead_runs_temporaries_are_removed_live_and_unmarked_ones_kept(tmp_path):
    dead_pid = int(subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                                  capture_output=True, text=True, check=True).stdout)  # fmt: skip
    for name, pid in ((".r.tmp-dead", dead_pid), (".r.tmp-live", os.getppid())):
        (tmp_path / name).mkdir()
        body = {"package": ownership.PACKAGE, "id": name, "pid": pid}
        (tmp_path / name / ownership.MARKER).write_text(json.dumps(body))
    (tmp_path / ".r.tmp-mine").mkdir()  # the user's: no marker
    removed = ownership.remove_dead_temporaries(tmp_path, ".r.tmp-")
    assert removed == [tmp_path / ".r.tmp-dead"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [".r.tmp-live", ".r.tmp-mine"]


HOLD = """
import sys, time
from omniflow.io import ownership
ownership.lock_beside(sys.argv[1], "busy {pid}")
print("held", flush=True)
time.sleep(30)
"""


def test_the_lock_refuses_a_second_process_and_goes_with_the_first(tmp_path):
    out = tmp_path / "a" / "out"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(out)], stdout=subprocess.PIPE,
                              text=True, env=env)  # fmt: skip
    try:
        assert holder.stdout.readline() == "held\n"
        with pytest.raises(ownership.LockedError, match=f"busy {holder.pid}$"):
            ownership.lock_beside(out, "busy {pid}")
    finally:
        holder.kill()
        holder.communicate()
    key = ownership.lock_beside(out, "busy {pid}")  # the lock ended with the process
    assert ownership.lock_beside(out, "x") == key  # taken again in one process: shared
    ownership.unlock(key)
    assert (tmp_path / "a" / ".out.lock").exists()
    ownership.unlock(key)
    assert not (tmp_path / "a" / ".out.lock").exists()  # removed by the last user


def test_the_lock_removes_the_folders_it_made(tmp_path):
    key = ownership.lock_beside(tmp_path / "x" / "y" / "out", "busy")
    assert (tmp_path / "x" / "y" / ".out.lock").is_file()
    ownership.unlock(key)
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "afile").write_text("")
    with pytest.raises(OutputError, match="afile is a file, not a folder"):
        ownership.lock_beside(tmp_path / "afile" / "out", "busy")
