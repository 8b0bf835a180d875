"""A full disk for the tests: a 3 MiB tmpfs mounted by the test, filled on demand.

Mounting needs root (``os.geteuid() == 0``) and a container that allows it; elsewhere the
tests that use :func:`small_tmpfs` are skipped, saying why.
"""

from __future__ import annotations

import contextlib
import errno
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

__all__ = ["fill", "small_tmpfs"]


@contextlib.contextmanager
def small_tmpfs(where: Path, size: str = "3m") -> Iterator[Path]:
    """Mount a tmpfs of ``size`` on the new folder ``where``; unmount it afterwards."""
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    where.mkdir(parents=True)
    cmd = ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=30)
    if res.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {res.stderr.strip()}")
    try:
        yield where
    finally:
        if subprocess.run(["umount", str(where)], capture_output=True, timeout=60).returncode:
            subprocess.run(["umount", "-l", str(where)], capture_output=True, timeout=60)


def fill(mnt: Path, leave: int = 0) -> None:
    """Fill the file system of ``mnt`` with one file, then give ``leave`` bytes back."""
    path = mnt / "filler"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        chunk = b"\0" * 65536
        while True:
            try:
                os.write(fd, chunk)
            except OSError as exc:
                assert exc.errno == errno.ENOSPC, exc
                break
    finally:
        os.close(fd)
    os.truncate(path, max(0, path.stat().st_size - leave))
