"""A full disk under every ``omnisim`` command that writes (issue 25): the machine
refused, exit 1, one line naming the path, no "internal error", nothing half-written.

The disk is a 3 MiB tmpfs the test mounts (:mod:`tests.helpers.small_disk`; root only,
skipped elsewhere), filled but for a few KiB; the commands run as in
``test_bad_input.py`` (the console script, the fake renderer).
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from tests.helpers.small_disk import fill, small_tmpfs
from tests.omnisim.test_bad_input import OMNISIM, _dataset, _run, _scene, render_args

pytestmark = pytest.mark.skipif(OMNISIM is None, reason="the omnisim command is not installed")


def _refused_by_the_disk(res: subprocess.CompletedProcess, path: Path) -> str:
    lines = res.stderr.splitlines()
    assert "Traceback" not in res.stderr + res.stdout, res.stderr
    assert res.returncode == 1 and len(lines) == 1, (res.returncode, res.stderr)
    assert "internal error" not in lines[0] and "No space left on device" in lines[0], lines[0]
    assert str(path) in lines[0], lines[0]
    return lines[0]


@pytest.mark.parametrize("leave_kib", [0, 40, 200])
def test_render_on_a_full_disk(tmp_path, leave_kib):
    """The disk fills (measured on a 3 MiB tmpfs, 32 px fake frames) at the lock file
    (0 KiB left), in the EXR encoder's scratch file (40 KiB: OpenEXR's RuntimeError, an
    internal error before) and at a frame's files (200 KiB)."""
    scene = _scene(tmp_path)
    with small_tmpfs(tmp_path / "small") as mnt:
        fill(mnt, leave=leave_kib * 1024)
        out = mnt / "data"
        res = _run(render_args(scene, out, "--frames", "3", "--no-resource-check"))
        _refused_by_the_disk(res, out)


@pytest.mark.slow  # 5.5 s (docs/decisions/slow_tests.md)
def test_export_on_a_full_disk(tmp_path):
    """Nothing of the export is left (no OUT, no temporary folder) and OUT is named."""
    data = _dataset(tmp_path)
    with small_tmpfs(tmp_path / "small") as mnt:
        for leave in (0, 40 * 1024):  # at the first file; part-way through
            fill(mnt, leave=leave)
            out = mnt / "export"
            res = _run(["export", str(data), "--format", "sintel", "--out", str(out)])
            _refused_by_the_disk(res, out)
            assert sorted(os.listdir(mnt)) == ["filler"]


def test_check_json_on_a_full_disk(tmp_path):
    data = _dataset(tmp_path)
    with small_tmpfs(tmp_path / "small") as mnt:
        fill(mnt)
        res = _run(["check", str(data), "--json", str(mnt / "r.json")])
        _refused_by_the_disk(res, mnt / "r.json")
        assert sorted(os.listdir(mnt)) == ["filler"]
