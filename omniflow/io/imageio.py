"""Image files in and out: PNG (8 and 16 bit), JPEG, OpenEXR; atomic writes.

Every reader returns ``float32`` in the conventions of :mod:`omniflow.conventions`:
shape ``(H, W)`` for grey images and ``(H, W, 3)`` for colour (RGB order, not
OpenCV's BGR), indexed ``[row, col]``. Integer files are scaled to [0, 1] by
their dtype (``uint8`` / 255, ``uint16`` / 65535); no gamma is undone (brightness
constancy holds under any fixed monotonic tone curve). EXR values are returned
as stored (linear radiance).

Bad input raises :class:`ImageError` (a ``ValueError``) whose message names the
file and the problem in one line, so a command-line tool can print it as is.

Writers go through :func:`atomic_output`: the data is written under a temporary
name in the destination folder, fsynced, and moved into place with
:func:`os.replace` (the folder fsynced too), so a reader never sees a
half-written file, not even after a power cut. This is the project's one atomic
file writer (``omnisim`` writes ``dataset.json`` with it). A command that writes several files
that belong together stages them with :class:`OutputSet` and moves them into
place as a set, so a failed run never leaves a new file beside an old one.
"""

from __future__ import annotations

import contextlib
import errno
import os
import secrets
import shutil
import sys
import tempfile
import threading
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from types import TracebackType

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omniflow.conventions import LUMA_WEIGHTS

__all__ = [
    "ImageError",
    "OutputError",
    "OutputSet",
    "atomic_output",
    "atomic_write_bytes",
    "atomic_write_text",
    "check_finite",
    "fsync_dir",
    "native_output_captured",
    "pid_alive",
    "read_exr_channels",
    "read_image",
    "to_grey",
    "to_uint8",
    "write_exr",
    "write_png",
]

#: Suffixes read with OpenCV (``cv2.imread``); ``.exr`` is read with OpenEXR.
RASTER_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm", ".ppm")


class ImageError(ValueError):
    """An image file is missing, unreadable, or holds unusable pixels."""


class OutputError(ValueError):
    """An output location is unusable as given (a file where a folder is expected)."""


# -- atomic writes -------------------------------------------------------------


def fsync_dir(path: str | os.PathLike) -> None:
    """fsync a folder so a rename inside it is durable (a no-op where unsupported)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _fsync_file(path: Path) -> None:
    with open(path, "rb+") as fh:
        os.fsync(fh.fileno())


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success fsync it, move it onto
    ``path`` and fsync the folder.

    The temporary name is ``.<name>.tmp.<pid>.<random><suffix>``: hidden, marked
    ``.tmp.``, and with the suffix of ``path`` (so writers that choose the format
    by extension, such as ``cv2.imwrite``, still work). If the block raises, the
    temporary file is removed and ``path`` is left untouched.

    Examples
    --------
    >>> import tempfile
    >>> folder = Path(tempfile.mkdtemp())
    >>> with atomic_output(folder / "a.txt") as tmp:
    ...     _ = tmp.write_text("done")
    >>> (folder / "a.txt").read_text()
    'done'
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.{os.getpid()}.{secrets.token_hex(4)}{path.suffix}")
    try:
        yield tmp
        _fsync_file(tmp)
        os.replace(tmp, path)
    except OSError as exc:
        if exc.filename is not None:
            raise
        # a write to a full disk names no file: name the one the caller asked for
        raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
    fsync_dir(path.parent)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically and durably (:func:`atomic_output`)."""
    with atomic_output(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically; return the path."""
    return atomic_write_bytes(path, text.encode("utf-8"))


# -- a set of outputs, moved into place together ------------------------------------

#: Name prefix of the staging folders of :class:`OutputSet` (followed by the pid).
STAGING_PREFIX = ".omniflow-staging-"


class OutputSet:
    """Stage a command's output files, then move them into ``dest`` together.

    Files are written into a staging folder on the same file system as
    ``dest`` (inside ``dest`` if it exists, else in its nearest existing
    ancestor); nothing under ``dest`` changes until :meth:`commit`. If ``dest``
    did not exist, the commit is one :func:`os.rename` of the staging folder.
    If it did, each staged file replaces its namesake (:func:`os.replace`),
    files in ``owned`` that this run did not write are removed (so outputs of
    an earlier run with other options do not linger), and ``manifest`` is
    moved last, so it always describes the files beside it. Other files in
    ``dest`` are left alone. Leaving the ``with`` block by an exception
    removes the staging folder and leaves ``dest`` as it was.

    Parameters
    ----------
    dest : path-like
        The output folder.
    owned : iterable of str
        Every file name this command may write in ``dest``.
    manifest : str, optional
        The file moved into place last (it names the others).

    Raises
    ------
    OutputError
        ``dest``, an ancestor or one of the ``owned`` names is of the wrong
        kind (a file where a folder belongs or the reverse).
    OSError
        The file system refuses (permission, read-only, full); file names in
        the error are those under ``dest``, not the staging folder's.

    Examples
    --------
    >>> folder = Path(tempfile.mkdtemp()) / "result"
    >>> with OutputSet(folder, owned=["a.txt", "b.txt"], manifest="b.txt") as stage:
    ...     _ = (stage / "a.txt").write_text("1")
    ...     _ = (stage / "b.txt").write_text("2")
    >>> sorted(p.name for p in folder.iterdir())
    ['a.txt', 'b.txt']
    """

    def __init__(
        self, dest: str | os.PathLike, *, owned: Iterable[str], manifest: str | None = None
    ) -> None:
        self.dest = Path(dest)
        self.owned = tuple(owned)
        self.manifest = manifest
        self.staging: Path | None = None

    def __enter__(self) -> Path:
        return self.open()

    def __exit__(
        self,
        kind: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        try:
            if exc is None:
                try:
                    self.commit()
                except OSError as err:
                    raise self._renamed(err) from err
            elif isinstance(exc, OSError) and self._renamed(exc) is not exc:
                raise self._renamed(exc) from exc
        finally:
            self.discard()

    def open(self) -> Path:
        """Create the staging folder (this also proves the location writable)."""
        dest = self.dest
        if dest.exists() or dest.is_symlink():
            if not dest.is_dir():
                raise OutputError(f"{dest}: exists and is not a folder; expected a folder")
            for name in self.owned:
                target = dest / name
                if target.exists() and not target.is_file():
                    raise OutputError(
                        f"{target}: is a folder (or not a regular file); expected a file "
                        "this command can replace"
                    )
            parent = dest
        else:
            parent = dest.parent
            while not (parent.exists() or parent.is_symlink()):
                parent = parent.parent
            if not parent.is_dir():
                raise OutputError(f"{dest}: {parent} is a file, not a folder")
        _remove_orphans(parent)
        try:
            staging = tempfile.mkdtemp(prefix=f"{STAGING_PREFIX}{os.getpid()}-", dir=parent)
        except OSError as exc:  # name the folder that refused, not the staging name tried
            raise type(exc)(exc.errno, exc.strerror, str(parent)) from exc
        self.staging = Path(staging)
        return self.staging

    def commit(self) -> list[Path]:
        """Move the staged files into ``dest``; return their final paths."""
        if self.staging is None:
            raise RuntimeError("OutputSet.commit before open")
        staged = sorted(p.name for p in self.staging.iterdir() if p.is_file())
        if self.manifest in staged:  # moved last: it describes the files beside it
            staged.remove(self.manifest)
            staged.append(self.manifest)
        if self.staging.parent != self.dest:
            created = _make_parents(self.dest.parent)
            try:
                os.chmod(self.staging, 0o777 & ~_umask())  # mkdtemp made it 0700
                os.rename(self.staging, self.dest)
            except OSError:
                for folder in reversed(created):
                    with contextlib.suppress(OSError):
                        folder.rmdir()
                raise
            self.staging = None
            return [self.dest / name for name in staged]
        for name in staged:  # checked again: the folder may have changed while we ran
            target = self.dest / name
            if target.exists() and not target.is_file():
                raise OutputError(f"{target}: is a folder; expected a file")
        data = [name for name in staged if name != self.manifest]
        for name in data:
            os.replace(self.staging / name, self.dest / name)
        for stale in sorted(set(self.owned) - set(staged)):  # an earlier run's, not this one's
            with contextlib.suppress(FileNotFoundError):
                (self.dest / stale).unlink()
        if self.manifest in staged:
            os.replace(self.staging / self.manifest, self.dest / self.manifest)
        return [self.dest / name for name in staged]

    def discard(self) -> None:
        """Remove the staging folder and whatever is left in it."""
        if self.staging is not None:
            shutil.rmtree(self.staging, ignore_errors=True)
            self.staging = None

    def _renamed(self, err: OSError) -> OSError:
        """``err`` naming the path under ``dest`` (not the staging folder), or ``dest``."""
        name = getattr(err, "filename", None)
        staging = self.staging
        if name is None and err.errno is not None:  # a failed write() names no file
            return type(err)(err.errno, err.strerror, str(self.dest))
        if staging is None or not isinstance(name, str) or not name.startswith(str(staging)):
            return err
        shown = self.dest / Path(name).relative_to(staging)
        return type(err)(err.errno, err.strerror, str(shown))


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _make_parents(folder: Path) -> list[Path]:
    """Create ``folder`` and missing ancestors; return those created, outermost first."""
    missing = []
    while not (folder.exists() or folder.is_symlink()):
        missing.append(folder)
        folder = folder.parent
    created = []
    for path in reversed(missing):
        path.mkdir()
        created.append(path)
    return created


def _remove_orphans(parent: Path) -> None:
    """Remove staging folders in ``parent`` left by processes that no longer run (kill -9)."""
    with contextlib.suppress(OSError):
        for entry in parent.glob(f"{STAGING_PREFIX}*"):
            pid_text = entry.name[len(STAGING_PREFIX) :].split("-", 1)[0]
            if pid_text.isdigit() and not pid_alive(int(pid_text)):
                shutil.rmtree(entry, ignore_errors=True)


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs (another user's counts as running)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


# -- checks and conversions ----------------------------------------------------


def check_finite(image: ArrayLike, what: str = "image") -> NDArray:
    """Return ``image`` as an array; raise :class:`ImageError` if a pixel is NaN or inf.

    The message names ``what`` (usually the file), the number of bad pixels and
    the first one's row and column.
    """
    arr = np.asarray(image)
    if arr.dtype.kind == "f":
        bad = ~np.isfinite(arr)
        if bad.ndim == 3:
            bad = bad.any(axis=2)
        if bad.any():
            row, col = np.argwhere(bad)[0]
            raise ImageError(
                f"{what}: {int(bad.sum())} pixel(s) are NaN or infinite "
                f"(first at row {row}, col {col})"
            )
    return arr


def to_grey(image: ArrayLike) -> NDArray[np.float32]:
    """Luminance of an image: ``(H, W)`` as is, RGB(A) by Rec. 709 weights.

    Parameters
    ----------
    image : ndarray, shape (H, W), (H, W, 1), (H, W, 3) or (H, W, 4)
        Linear values; channel order R, G, B (alpha, if any, is dropped).

    Returns
    -------
    ndarray, shape (H, W), float32
        ``0.2126 R + 0.7152 G + 0.0722 B`` (:data:`omniflow.conventions.LUMA_WEIGHTS`).
    """
    arr = np.asarray(image)
    if arr.ndim == 2:
        return arr.astype(np.float32, copy=False)
    if arr.ndim == 3 and arr.shape[2] == 1:
        return arr[:, :, 0].astype(np.float32, copy=False)
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        w = np.asarray(LUMA_WEIGHTS, dtype=np.float32)
        return (arr[:, :, :3].astype(np.float32, copy=False) @ w).astype(np.float32)
    raise ValueError(f"to_grey: expected shape (H, W) or (H, W, 3), got {arr.shape}")


def to_uint8(image: ArrayLike, *, lo: float | None = 0.0, hi: float | None = 1.0) -> NDArray:
    """Map ``[lo, hi]`` to 0..255 (clipped). ``None`` picks the 1st / 99th percentile."""
    arr = np.asarray(image, dtype=np.float32)
    finite = arr[np.isfinite(arr)]
    if lo is None:
        lo = float(np.percentile(finite, 1)) if finite.size else 0.0
    if hi is None:
        hi = float(np.percentile(finite, 99)) if finite.size else 1.0
    if hi <= lo:
        hi = lo + 1.0
    out = np.clip((np.nan_to_num(arr, nan=lo) - lo) * (255.0 / (hi - lo)), 0, 255)
    return np.rint(out).astype(np.uint8)


# -- readers ---------------------------------------------------------------------


_NATIVE_LOCK = threading.RLock()


class _HeldLines(list):
    """The lines :func:`native_output_captured` held; ``echo`` as there."""

    echo = True


@contextlib.contextmanager
def native_output_captured() -> Iterator[list[str]]:
    """Hold what C libraries print on file descriptors 1 and 2 while a file is decoded.

    libpng and OpenEXR print their own lines on a corrupt file ("libpng error: Read
    Error"; "Warning: Exception raised reading pixel data ..." and the
    ``EXR_ERR_...`` reason) before the Python call fails, so a bad file gave two or
    three lines instead of one. The list yielded holds the non-empty captured lines
    once the block has exited (catch the error outside the ``with``, then put the
    library's reason into the one message). After a block that succeeds, the captured
    text is written back to standard error, delayed, not lost, unless the block set
    ``echo = False`` on the list (a failure the call reports by its return value, such
    as ``cv2.imread`` returning None).
    """
    lines = _HeldLines()
    try:
        sys.stdout.flush()
        sys.stderr.flush()
        os.fstat(1)
        os.fstat(2)
    except (OSError, ValueError):  # no such descriptors (embedded): nothing to hold
        yield lines
        return
    ok = False
    # One holder at a time: two threads swapping the process's descriptors would each
    # restore the other's temporary file (a reentrant lock, so a nested hold is fine).
    with _NATIVE_LOCK, tempfile.TemporaryFile() as tmp:
        saved = (os.dup(1), os.dup(2))
        os.dup2(tmp.fileno(), 1)
        os.dup2(tmp.fileno(), 2)
        try:
            yield lines
            ok = True
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
            tmp.seek(0)
            data = tmp.read()
            text = data.decode("utf-8", "replace")
            lines.extend(" ".join(x.split()) for x in text.splitlines() if x.strip())
            if ok and lines.echo and data:
                os.write(2, data)


def _native_reason(lines: list[str], exc: BaseException, path: os.PathLike | str) -> str:
    """The library's own reason for a failed decode of ``path`` (its ``EXR_ERR_`` /
    ``error`` line, without the path it starts with), else the exception's text."""
    for line in lines:
        if "EXR_ERR_" in line or "error" in line.lower():
            return line.removeprefix(f"{path}: ")
    return _one_line(exc)


def read_exr_channels(path: str | os.PathLike) -> dict[str, NDArray[np.float32]]:
    """All channels of an OpenEXR file by name (``R``, ``G``, ``B``, ``gt.r``, ...).

    Each value is a float32 array of shape (H, W).
    """
    path = Path(path)
    _require_file(path)
    import OpenEXR

    native: list[str] = []
    try:
        with (
            native_output_captured() as native,
            OpenEXR.File(str(path), separate_channels=True) as exr,
        ):
            chans = {name: np.asarray(ch.pixels) for name, ch in exr.channels().items()}
    except Exception as exc:  # the bindings raise RuntimeError / OSError variants
        reason = _native_reason(native, exc, path)
        raise ImageError(f"{path}: cannot be read as OpenEXR: {reason}") from exc
    return {name: px.astype(np.float32, copy=False) for name, px in chans.items()}


def read_image(
    path: str | os.PathLike, *, channel: str | None = None, grey: bool = False
) -> NDArray[np.float32]:
    """Read an image file as float32 (see the module docstring for scaling).

    Parameters
    ----------
    path : path-like
        PNG (8 or 16 bit), JPEG, TIFF, BMP, PGM/PPM (read by OpenCV), or
        OpenEXR (``.exr``).
    channel : str, optional
        EXR only: return this one channel (for example ``"gt.r"``). Without it
        an EXR gives its ``R``, ``G``, ``B`` channels, else ``Y``, else its only
        channel.
    grey : bool
        Reduce colour to luminance with :func:`to_grey`.

    Returns
    -------
    ndarray, shape (H, W) or (H, W, 3), float32

    Raises
    ------
    ImageError
        The file is missing or unreadable, the channel is absent, or a pixel is
        NaN or infinite.
    """
    path = Path(path)
    _require_file(path)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        image = _read_exr_image(path, channel)
    else:
        if channel is not None:
            raise ImageError(f"{path}: channel={channel!r} applies to EXR files only")
        image = _read_raster(path)
    check_finite(image, str(path))
    return to_grey(image) if grey else image


def _require_file(path: Path) -> None:
    if not path.exists():
        raise ImageError(f"{path}: image file not found")
    if not path.is_file():
        raise ImageError(f"{path}: not a file")
    if not os.access(path, os.R_OK):  # OpenCV would only say "cannot be read"
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))


def _read_exr_image(path: Path, channel: str | None) -> NDArray[np.float32]:
    chans = read_exr_channels(path)
    if channel is not None:
        if channel not in chans:
            raise ImageError(f"{path}: no channel {channel!r}; the file has {sorted(chans)}")
        return chans[channel]
    if all(c in chans for c in "RGB"):
        return np.stack([chans["R"], chans["G"], chans["B"]], axis=2)
    if "Y" in chans:
        return chans["Y"]
    if len(chans) == 1:
        return next(iter(chans.values()))
    raise ImageError(f"{path}: no R, G, B or Y channels; name one of {sorted(chans)} with channel=")


def _read_raster(path: Path) -> NDArray[np.float32]:
    import cv2

    native: list[str] = []
    try:
        with native_output_captured() as native:
            raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            native.echo = raw is not None  # None: the reason goes into the error below
    except cv2.error as exc:  # e.g. a header claiming more than OpenCV's 2^30-pixel limit
        raise ImageError(f"{path}: cannot be decoded: {_cv2_reason(exc)}") from exc
    if raw is None:
        said = f" ({native[0]})" if native else ""
        raise ImageError(
            f"{path}: cannot be read as an image{said} (expected PNG, 16-bit PNG, JPEG or EXR)"
        )
    if raw.ndim == 3:
        if raw.shape[2] == 4:
            raw = cv2.cvtColor(raw, cv2.COLOR_BGRA2RGB)
        elif raw.shape[2] == 3:
            raw = cv2.cvtColor(raw, cv2.COLOR_BGR2RGB)
        elif raw.shape[2] == 1:
            raw = raw[:, :, 0]
    if raw.dtype == np.uint8:
        return raw.astype(np.float32) / np.float32(255.0)
    if raw.dtype == np.uint16:
        return raw.astype(np.float32) / np.float32(65535.0)
    if raw.dtype.kind == "f":
        return raw.astype(np.float32, copy=False)
    raise ImageError(f"{path}: unsupported pixel type {raw.dtype} (expected 8/16-bit or float)")


# -- writers -----------------------------------------------------------------------


def write_png(path: str | os.PathLike, image: ArrayLike, *, bits: int = 16) -> Path:
    """Write a grey ``(H, W)`` or RGB ``(H, W, 3)`` image as PNG, atomically.

    Float input in [0, 1] is scaled to ``bits`` (8 or 16) and clipped; integer
    input of a matching dtype is written as is.
    """
    import cv2

    arr = np.asarray(image)
    if bits not in (8, 16):
        raise ValueError(f"write_png: bits must be 8 or 16, got {bits}")
    dtype = np.uint8 if bits == 8 else np.uint16
    if arr.dtype.kind == "f":
        check_finite(arr, str(path))
        arr = np.rint(np.clip(arr, 0.0, 1.0) * np.iinfo(dtype).max).astype(dtype)
    elif arr.dtype != dtype:
        raise ValueError(f"write_png: {arr.dtype} data with bits={bits}")
    if arr.ndim == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)
    ok, encoded = cv2.imencode(".png", arr)  # encoded in memory: a full disk is an OSError
    if not ok:
        raise ImageError(f"{path}: OpenCV could not encode a PNG of shape {arr.shape}")
    return atomic_write_bytes(Path(path).with_suffix(".png"), encoded.tobytes())


def write_exr(path: str | os.PathLike, channels: Mapping[str, ArrayLike] | ArrayLike) -> Path:
    """Write float channels to an OpenEXR file (ZIP compression, float32), atomically.

    ``channels`` is a mapping ``name -> (H, W)`` array, or one array: ``(H, W)``
    is written as ``Y``, ``(H, W, 3)`` as ``R``, ``G``, ``B``.
    """
    import OpenEXR

    if not isinstance(channels, Mapping):
        arr = np.asarray(channels)
        if arr.ndim == 2:
            channels = {"Y": arr}
        elif arr.ndim == 3 and arr.shape[2] == 3:
            channels = {"R": arr[:, :, 0], "G": arr[:, :, 1], "B": arr[:, :, 2]}
        else:
            raise ValueError(f"write_exr: expected (H, W) or (H, W, 3), got {arr.shape}")
    data = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}
    shapes = {v.shape for v in data.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"write_exr: channels must share one (H, W) shape, got {shapes}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_output(path) as tmp:
        OpenEXR.File(header, data).write(str(tmp))
    return Path(path)


def _cv2_reason(exc: BaseException) -> str:
    """The assertion of an OpenCV error without its source location."""
    text = _one_line(exc)
    return text.split("error: ", 1)[-1] if "error: " in text else text


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text or type(exc).__name__
