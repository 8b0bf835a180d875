"""What a command may delete or replace: only what it can prove it wrote.

Every output folder that ``omnisim render``, ``omnivalidate`` and ``omniflow``
(``pair``, ``stream``) create holds a marker file, :data:`MARKER`
(``.omniflow-testbed.json``): the command, this package's name and version and a
random id. Before a command removes or replaces anything in a folder it asks
:func:`claim`: the folder must hold the marker (or, written before markers
existed, a manifest the command recognises, below), and every path the command
would remove must be one of the names it writes. Anything else in the way (a
user's photo in a frame folder, a paper figure in a report's ``figures/``, a
``report.md`` of one's own in a folder with no marker) raises
:class:`ForeignPathError`, one line naming the path, before anything is touched;
the commands report it with exit status 2.

Folders written before markers existed count as ours when they hold the
manifest of this project in its recognised structure, and nothing but names the
command writes: a dataset's ``dataset.json`` with ``"format": "omnisim-dataset"``
(frame folders holding only the dataset's file names), a report's
``summary.json`` with ``"format": "omnivalidate-summary/1"``, an ``omniflow``
output's ``flow.json`` or ``stream.json`` whose ``command`` starts with
``omniflow``. Each command passes its own test (``legacy``); the marker is added
the next time the command writes there.

A frame folder of a dataset carries no marker of its own: its files are
byte-identical between two renders of one scene (resume, Dask, load), which a
random id would break. The dataset folder's marker vouches for it, and the
writer removes a frame folder only when it holds nothing but the frame's files.

Temporary folders (a report staged beside ``--out``) carry the marker too, with
the process id: one whose process no longer runs, found under the output's lock,
is a dead run's and is removed (:func:`remove_dead_temporaries`).

One writer per output: :func:`lock` takes an exclusive ``fcntl`` lock on a file
and raises :class:`LockedError` at once when another process holds it; the lock
ends with the process, ``kill -9`` included (the renderer's lock, moved here so
that every command shares it).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shutil
import threading
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path, PurePosixPath
from typing import Any

from omniflow.io.imageio import OutputError, atomic_write_text, pid_alive

__all__ = [
    "MARKER",
    "PACKAGE",
    "ForeignPathError",
    "LockedError",
    "claim",
    "claim_names",
    "find_foreign",
    "has_marker",
    "held_lock",
    "lock",
    "lock_beside",
    "read_marker",
    "refusal",
    "remove_dead_temporaries",
    "unlock",
    "write_marker",
]

#: The marker file's name, in every output folder a command creates.
MARKER = ".omniflow-testbed.json"
#: The package named in every marker.
PACKAGE = "omniflow-testbed"
#: Markers and manifests are small; a bigger file there is not ours.
_MAX_MANIFEST_BYTES = 64 << 20


class ForeignPathError(OutputError):
    """A path a command would remove or replace was not written by this project."""


class LockedError(OutputError):
    """Another process holds the lock of an output (one line, names the output)."""


def _version() -> str:
    from omniflow import __version__

    return __version__


def write_marker(folder: str | os.PathLike, command: str, *, pid: bool = False) -> dict:
    """Write ``folder/MARKER`` (atomically) naming ``command``; return its content.

    ``pid``: record this process's id too (for temporary folders, so that a later
    run can tell a dead run's leftovers from a live one's).
    """
    body: dict[str, Any] = {
        "written_by": command,
        "package": PACKAGE,
        "version": _version(),
        "id": uuid.uuid4().hex,
    }
    if pid:
        body["pid"] = os.getpid()
    atomic_write_text(Path(folder) / MARKER, json.dumps(body, indent=1) + "\n")
    return body


def read_json(path: Path) -> Any:
    """The JSON object in ``path``, or None when it is missing, huge or not JSON."""
    try:
        if not path.is_file() or path.is_symlink() or path.stat().st_size > _MAX_MANIFEST_BYTES:
            return None
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):  # unreadable, not JSON: not ours
        return None


def read_marker(folder: str | os.PathLike) -> dict | None:
    """The marker of ``folder`` when it is one of this package's, else None."""
    body = read_json(Path(folder) / MARKER)
    if isinstance(body, dict) and body.get("package") == PACKAGE and "id" in body:
        return body
    return None


def has_marker(folder: str | os.PathLike) -> bool:
    return read_marker(folder) is not None


def find_foreign(folder: str | os.PathLike, owned: Callable[[PurePosixPath], bool]) -> Path | None:
    """The first path under ``folder`` (sorted, depth first) that ``owned`` rejects.

    ``owned`` gets each path relative to ``folder``; a folder it accepts is entered.
    A symbolic link is never ours (removing the tree would follow it).
    """
    root = Path(folder)

    def walk(d: Path) -> Path | None:
        for entry in sorted(d.iterdir()):
            rel = PurePosixPath(entry.relative_to(root).as_posix())
            if entry.is_symlink() or not owned(rel):
                return entry
            if entry.is_dir():
                bad = walk(entry)
                if bad is not None:
                    return bad
        return None

    return walk(root)


def refusal(path: Path, prog: str, folder: Path, *, marked: bool = False) -> ForeignPathError:
    """The one line refusing ``path``: its folder has no marker, or (``marked``) the
    folder is ours but the name is not one the command writes."""
    why = f"not a name {prog} writes" if marked else f"no {MARKER} in {folder}"
    return ForeignPathError(
        f"{path}: not written by {prog} ({why}); refusing to remove or replace it; move "
        "it away or choose another --out"
    )


def claim(
    folder: str | os.PathLike,
    *,
    prog: str,
    owned: Callable[[PurePosixPath], bool],
    legacy: Callable[[Path], bool] | None = None,
) -> bool:
    """Check that ``prog`` may remove or replace what is in ``folder``; True if it exists.

    A missing or empty folder is free. Otherwise the folder must be ours (its
    :data:`MARKER`, or ``legacy(folder)`` for a folder written before markers
    existed) and hold nothing ``owned`` rejects. Raises :class:`ForeignPathError`
    naming the first path in the way, or :class:`OutputError` when ``folder`` is
    not a folder.
    """
    folder = Path(folder)
    if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
        raise OutputError(f"{folder}: exists and is not a folder; expected a folder")
    if not folder.exists():
        return False
    entries = sorted(folder.iterdir())
    if not entries:
        return True
    if not (has_marker(folder) or (legacy is not None and legacy(folder))):
        raise refusal(entries[0], prog, folder)
    bad = find_foreign(folder, owned)
    if bad is not None:
        raise refusal(bad, prog, folder, marked=True)
    return True


def claim_names(
    folder: str | os.PathLike,
    *,
    prog: str,
    owned: Callable[[str], bool],
    legacy: Callable[[Path], bool] | None = None,
) -> None:
    """Check that ``prog`` may replace the files it writes in ``folder`` (others stay).

    For a command that writes a few names into a folder that may hold other files:
    when any name ``owned`` accepts is there, the folder must be ours (marker or
    ``legacy``) and each such name a regular file. Raises :class:`ForeignPathError`
    naming the first one in the way.
    """
    folder = Path(folder)
    if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
        raise OutputError(f"{folder}: exists and is not a folder; expected a folder")
    if not folder.is_dir():
        return
    ours = has_marker(folder) or (legacy is not None and legacy(folder))
    for entry in sorted(folder.iterdir()):
        if entry.name == MARKER or not owned(entry.name):
            continue
        if entry.is_symlink() or not entry.is_file():
            raise OutputError(
                f"{entry}: is a folder (or not a regular file); expected a file {prog} can replace"
            )
        if not ours:
            raise refusal(entry, prog, folder)


def remove_dead_temporaries(parent: str | os.PathLike, prefix: str) -> list[Path]:
    """Remove folders ``parent/prefix*`` whose marker names a process no longer running.

    Call it while holding the output's :func:`lock`; a folder with no marker of
    ours (or a live process's) is left alone. Returns the folders removed.
    """
    removed = []
    with contextlib.suppress(OSError):
        for entry in sorted(Path(parent).glob(f"{prefix}*")):
            if entry.is_symlink() or not entry.is_dir():
                continue
            body = read_marker(entry)
            pid = body.get("pid") if body else None
            if isinstance(pid, int) and pid != os.getpid() and not pid_alive(pid):
                shutil.rmtree(entry, ignore_errors=True)
                removed.append(entry)
    return removed


# -- one writer per output ---------------------------------------------------------

#: Locks this process holds: real path of the lock file -> [descriptor, users, the file
#: to remove or None, the folders to remove when empty].
#: A process may take one lock several times (tests, a threaded Dask worker); it is
#: released when the last user lets go.
_HELD: dict[str, list[Any]] = {}
_HELD_GUARD = threading.Lock()


def lock(path: str | os.PathLike, busy: str, *, remove: bool = False) -> str:
    """Take the exclusive lock of the file ``path`` (created); return its key for :func:`unlock`.

    Raises :class:`LockedError` with the message ``busy`` (``{pid}`` replaced by the
    holder's process id) at once, without waiting, when another process holds it.
    ``remove``: delete the lock file on :func:`unlock` (for a lock beside an output
    rather than in it); a lock file replaced or removed while we waited is detected
    and the lock taken again on the new file.
    """
    path = Path(path)
    key = os.path.join(os.path.realpath(path.parent), path.name)
    with _HELD_GUARD:
        if key in _HELD:
            _HELD[key][1] += 1
            return key
        while True:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 64, 0).decode("ascii", "replace").strip() or "?"
                os.close(fd)
                raise LockedError(busy.replace("{pid}", holder)) from None
            except BaseException:
                os.close(fd)
                raise
            try:
                same = os.stat(path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:  # the holder removed it as we took it
                same = False
            if same:
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        _HELD[key] = [fd, 1, path if remove else None, []]
        return key


def unlock(key: str) -> None:
    """Let go of a lock taken with :func:`lock` (the last user releases it)."""
    with _HELD_GUARD:
        held = _HELD.get(key)
        if held is None:
            return
        held[1] -= 1
        if held[1] <= 0:
            del _HELD[key]
            if held[2] is not None:
                with contextlib.suppress(OSError):
                    held[2].unlink()
            os.close(held[0])
            for folder in held[3]:  # made for the lock file, innermost first: only if empty
                with contextlib.suppress(OSError):
                    folder.rmdir()


def lock_beside(out: str | os.PathLike, busy: str) -> str:
    """:func:`lock` of output ``out`` by the file ``.NAME.lock`` beside it, removed on
    :func:`unlock` with the folders above ``out`` it had to create (when empty):
    ``out`` itself may not exist yet, or be replaced whole by a rename.

    Raises :class:`OutputError` when an ancestor of ``out`` is a file, and the
    ``OSError`` of a folder that refuses, naming ``out``.
    """
    out = Path(out)
    parent = out.absolute().parent
    missing = []
    while not (parent.exists() or parent.is_symlink()):
        missing.append(parent)
        parent = parent.parent
    if not parent.is_dir():
        raise OutputError(f"{out}: {parent} is a file, not a folder")
    created: list[Path] = []
    try:
        for folder in reversed(missing):
            folder.mkdir()
            created.append(folder)
        key = lock(out.absolute().parent / f".{out.name}.lock", busy, remove=True)
    except OSError as exc:
        for folder in reversed(created):
            with contextlib.suppress(OSError):
                folder.rmdir()
        if exc.errno is None:
            raise
        raise type(exc)(exc.errno, exc.strerror, str(out)) from exc
    with _HELD_GUARD:
        _HELD[key][3].extend(reversed(created))
    return key


@contextlib.contextmanager
def held_lock(out: str | os.PathLike, busy: str) -> Iterator[str]:
    """:func:`lock_beside` for the length of a ``with`` block."""
    key = lock_beside(out, busy)
    try:
        yield key
    finally:
        unlock(key)
