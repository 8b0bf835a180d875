"""The omnisim dataset writer: dataset.json and frames, written atomically.

The contract itself (layout, channel names, units, format versions) and its reader
live in :mod:`omniflow.io.dataset`, so a dataset is read without this package; see
``docs/dataset_format.md`` for every key and channel. The contract's names are
re-exported here so ``from omnisim.dataset import open_dataset, CHANNELS`` keeps
working.

Atomicity: a frame is rendered into a hidden temporary directory
``DIR/frames/.000000.tmp.<pid>.<random>``, every file is fsynced, and the
directory is renamed to its final name ``000000``. A frame is done exactly when
its final directory exists with all its files; no partial file is ever visible
under a final name. ``dataset.json`` is written the same way (temporary name,
fsync, rename) before any frame.

One writer at a time: :class:`DatasetWriter` holds an exclusive ``fcntl`` lock on
``DIR/.omnisim.lock`` while it writes, so a second render into the same directory
is refused with one line (:class:`DatasetLockedError`) instead of racing the first.
Every temporary name starts with a dot and contains ``.tmp.`` (frame directories,
``dataset.json``, the EXR encoder's scratch directories ``frames/.exr.tmp.XXXX``);
the writer removes them, under the lock, when it opens the directory, together
with the ``frames/tmpXXXXXXXX/`` scratch directories of older versions.

Never delete what it did not write (:mod:`omniflow.io.ownership`): the dataset
directory gets the project's marker file; a directory with neither marker nor
``dataset.json`` is written into only when empty (the lock, temporaries and an
empty ``frames/`` aside), and a frame folder holding anything but the frame's
files is refused (:class:`DatasetForeignError`, one line) before anything is touched.

This module imports neither Mitsuba nor the scene model.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import shutil
import uuid
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

# Markers and the one fcntl lock: what the writer may remove (omniflow.io.ownership).
from omniflow.io import ownership

# The contract and the reader, re-exported (their home is omniflow.io.dataset).
from omniflow.io.dataset import (
    CHANNEL_INFO,
    CHANNELS,
    CHANNELS_V1,
    FLO_MAGIC,
    FLO_UNKNOWN,
    FLO_UNKNOWN_THRESH,
    FORMAT_NAME,
    FORMAT_VERSION,
    FRAME_RE,
    FRAMES_DIR,
    GT_CHANNELS,
    GT_CHANNELS_V1,
    MASK_FILES,
    META_NAME,
    READ_VERSIONS,
    Dataset,
    DatasetError,
    camera_names,
    channels_for,
    expected_files,
    flo_known,
    frame_name,
    load_meta,
    open_dataset,
    read_exr,
    read_flo,
    read_mask_png,
    show_key,
)

# The one atomic, fsynced file writer (re-exported for old imports).
from omniflow.io.imageio import atomic_write_bytes, fsync_dir
from omnisim.camera import camera_from_meta

__all__ = [
    "CHANNELS",
    "CHANNELS_V1",
    "CHANNEL_INFO",
    "FLO_MAGIC",
    "FLO_UNKNOWN",
    "FLO_UNKNOWN_THRESH",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "GT_CHANNELS",
    "GT_CHANNELS_V1",
    "MASK_FILES",
    "READ_VERSIONS",
    "TIMING_KEY",
    "Dataset",
    "DatasetError",
    "DatasetForeignError",
    "DatasetLockedError",
    "DatasetMismatchError",
    "DatasetWriter",
    "atomic_write_bytes",
    "atomic_write_json",
    "camera_from_meta",
    "channels_for",
    "compare_meta",
    "encode_frame",
    "exr_bytes",
    "exr_header",
    "flo_bytes",
    "flo_known",
    "frame_name",
    "open_dataset",
    "read_exr",
    "read_flo",
    "read_mask_png",
    "timing_section",
    "write_exr",
    "write_flo",
]

LOCK_NAME = ".omnisim.lock"
#: dataset.json's section of seconds per frame (:meth:`DatasetWriter.record_timing`).
TIMING_KEY = "timing"
_TMP_RE = re.compile(r"^\.(\d{6}|dataset\.json|exr)\.tmp\.")
#: Scratch directories of the EXR encoder before it used ``.exr.tmp.`` names
#: (``tempfile``'s default ``tmpXXXXXXXX``), removed when they hold nothing but ``x.exr``.
_OLD_SCRATCH_RE = re.compile(r"^tmp[a-z0-9_]{8}$")


class DatasetMismatchError(DatasetError):
    """A render would resume into a directory made from a different scene or settings."""


class DatasetLockedError(DatasetError):
    """Another process holds the dataset directory's write lock."""


class DatasetForeignError(DatasetError):
    """A frame folder holds a file the writer did not write (it is not replaced)."""


def _lock_dir(d: Path) -> str:
    """Take the exclusive write lock of dataset directory ``d``; return its key.

    Raises :class:`DatasetLockedError` at once (no waiting) when another process
    holds it. The lock file stays; the lock itself ends with the descriptor
    (:func:`_unlock_dir`, or the process's end, ``kill -9`` included).
    """
    busy = (
        f"{d}: another omnisim process (pid {{pid}}) is writing this dataset; wait "
        "for it to finish (then run again to resume) or use another --out directory"
    )
    try:
        return ownership.lock(d / LOCK_NAME, busy)
    except ownership.LockedError as exc:
        raise DatasetLockedError(str(exc)) from None


_unlock_dir = ownership.unlock


# -- atomic file helpers ----------------------------------------------------------


def _write_synced(path: Path, data: bytes) -> None:
    with open(path, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


def _json_text(obj: Any) -> str:
    return json.dumps(obj, indent=2, sort_keys=False, allow_nan=False) + "\n"


def atomic_write_json(path: str | Path, obj: Any) -> None:
    """Write ``obj`` as indented JSON (no NaN/inf) atomically."""
    atomic_write_bytes(path, _json_text(obj).encode("utf-8"))


# -- EXR -------------------------------------------------------------------------


def _check_channels(channels: Mapping[str, NDArray], where: str) -> tuple[int, int]:
    names = list(channels)
    expected = CHANNELS_V1 if set(names) == set(CHANNELS_V1) else CHANNELS
    if set(names) != set(expected) or len(names) != len(expected):
        missing = [c for c in CHANNELS if c not in channels]
        extra = [c for c in names if c not in CHANNELS]
        raise DatasetError(
            f"{where}: channels must be exactly {list(CHANNELS)} (or version 1's "
            f"{list(CHANNELS_V1)}); missing {missing}, extra {extra}"
        )
    shape = None
    for name in expected:
        arr = np.asarray(channels[name])
        if arr.ndim != 2:
            raise DatasetError(f"{where}: channel {name} has shape {arr.shape}: expected (H, W)")
        if shape is None:
            shape = arr.shape
        elif arr.shape != shape:
            raise DatasetError(f"{where}: channel {name} has shape {arr.shape}, others {shape}")
    assert shape is not None
    return shape


def write_exr(
    path: str | Path,
    channels: Mapping[str, NDArray],
    *,
    attributes: Mapping[str, str] | None = None,
) -> None:
    """Write a single-part scanline EXR, ZIP compression, every channel float32 (H, W).

    Not atomic by itself (the frame directory is what is renamed); the file is fsynced.
    ``attributes`` adds string header attributes (deterministic; no timestamps).
    """
    import OpenEXR

    # OpenEXR.File replaces the dict's values by Channel objects: give it a fresh dict.
    chans = {name: np.ascontiguousarray(channels[name], dtype=np.float32) for name in channels}
    header: dict[str, Any] = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for key, value in (attributes or {}).items():
        header[key] = str(value)
    path = Path(path)
    try:
        with OpenEXR.File(header, chans) as exr:
            exr.write(str(path))
    except RuntimeError as exc:  # how OpenEXR reports a failed write (a full disk)
        full = "No space left on device" in str(exc)
        raise OSError(
            errno.ENOSPC if full else errno.EIO,
            os.strerror(errno.ENOSPC) if full else f"cannot write the EXR ({exc})",
            str(path),
        ) from exc
    with open(path, "rb+") as fh:
        os.fsync(fh.fileno())


def exr_bytes(
    channels: Mapping[str, NDArray],
    *,
    attributes: Mapping[str, str] | None = None,
    scratch_dir: str | Path | None = None,
) -> bytes:
    """The bytes :func:`write_exr` would write (via a scratch file; OpenEXR writes to paths)."""
    import tempfile

    with tempfile.TemporaryDirectory(dir=scratch_dir, prefix=".exr.tmp.") as tmp:
        p = Path(tmp) / "x.exr"
        write_exr(p, channels, attributes=attributes)
        return p.read_bytes()


def _channels_version(channels: Mapping[str, NDArray]) -> int:
    """Format version of a frame's channel set (checked by :func:`_check_channels`)."""
    return 1 if "gt.flow.occluded" not in channels else 2


def exr_header(meta: Mapping[str, Any], cam: str) -> dict[str, str]:
    """Version 2 EXR header attributes that make one file self-describing.

    The rig (``omnisim.rig.d``, ``.R``, ``.s``), the camera (``omnisim.cam.tip_h``,
    ``.x_c``, ``.y_c``, ``.r_m``, ``.v``), units and each channel's unit and meaning
    (``omnisim.channel.<name>``), all as strings: numbers are Python's shortest
    round-trip decimal of the float64 in dataset.json (an EXR ``float`` attribute is
    float32 and would lose the digits eq. (1) needs).
    """
    rig = meta.get("rig", {})
    unit = next((c for c in meta.get("cameras", []) if c.get("name") == cam), None)
    if unit is None:
        raise DatasetError(f"dataset.json: camera {cam!r} not in cameras")
    attrs = {
        "omnisim.format": f"{FORMAT_NAME} {FORMAT_VERSION}",
        "omnisim.units": "lengths m (rig, gt.r, gt.h, gt.X/Y/Z), angles rad, image "
        "quantities px; pixel centre of column j at x = j + 0.5, y down; rig frame: "
        "h up the axis from cam2's cone tip; world = dataset.json robot.poses[k] x rig",
        "omnisim.note": "gt.Z is the world height of the seen point, not depth "
        "(OpenImageIO takes a channel named *Z as depth)",
    }
    for key in ("d", "R", "s"):
        attrs[f"omnisim.rig.{key}"] = repr(float(rig[key]))
    for key in ("tip_h", "x_c", "y_c", "r_m", "v"):
        attrs[f"omnisim.cam.{key}"] = repr(float(unit[key]))
    if "frame_interval" in meta:
        attrs["omnisim.frame_interval"] = repr(float(meta["frame_interval"]))
    for name in CHANNELS:
        u, text = CHANNEL_INFO[name]
        attrs[f"omnisim.channel.{name}"] = f"[{u}] {text}"
    return attrs


def _mask_png(mask: NDArray) -> bytes:
    """An 8-bit greyscale PNG, 255 where ``mask`` > 0.5, else 0 (Sintel's mask style)."""
    import cv2

    ok, buf = cv2.imencode(".png", np.where(np.asarray(mask) > 0.5, 255, 0).astype(np.uint8))
    if not ok:
        raise DatasetError("cannot encode a mask PNG")
    return buf.tobytes()


# -- Middlebury .flo ---------------------------------------------------------------


def flo_bytes(dx: NDArray, dy: NDArray, valid: NDArray | None = None) -> bytes:
    """Middlebury .flo: float32 magic 202021.25, int32 width, int32 height, then (dx, dy)
    interleaved row by row, all little-endian. Where ``valid`` is false (or dx/dy are not
    finite) both components are :data:`FLO_UNKNOWN` (1e10)."""
    dx = np.asarray(dx, dtype=np.float32)
    dy = np.asarray(dy, dtype=np.float32)
    if dx.shape != dy.shape or dx.ndim != 2:
        raise ValueError(f"flow components must be equal (H, W) arrays, got {dx.shape}, {dy.shape}")
    ok = np.isfinite(dx) & np.isfinite(dy)
    if valid is not None:
        ok &= np.asarray(valid) > 0.5
    h, w = dx.shape
    uv = np.empty((h, w, 2), dtype="<f4")
    uv[..., 0] = np.where(ok, dx, FLO_UNKNOWN)
    uv[..., 1] = np.where(ok, dy, FLO_UNKNOWN)
    head = np.array([FLO_MAGIC], "<f4").tobytes() + np.array([w, h], "<i4").tobytes()
    return head + uv.tobytes()


def write_flo(path: str | Path, dx: NDArray, dy: NDArray, valid: NDArray | None = None) -> None:
    """Write :func:`flo_bytes` to ``path`` (fsynced, not renamed)."""
    _write_synced(Path(path), flo_bytes(dx, dy, valid))


# -- frames ------------------------------------------------------------------------


def encode_frame(
    frame: Mapping[str, Mapping[str, NDArray]],
    cameras: Iterable[str],
    *,
    k: int | None = None,
    scratch_dir: str | Path | None = None,
    meta: Mapping[str, Any] | None = None,
) -> dict[str, bytes]:
    """Encode one rendered frame into file bytes ``{"cam1.exr": ..., "cam1.flo": ..., ...}``.

    ``frame`` maps camera name to its channels (exactly :data:`CHANNELS`, or
    :data:`CHANNELS_V1` for a version 1 dataset). The bytes are what
    :meth:`DatasetWriter.write_frame` writes, so local and distributed runs agree.
    Version 2 adds the mask PNGs (:data:`MASK_FILES`) and, given ``meta``
    (dataset.json), the header attributes of :func:`exr_header`.
    When ``meta`` (dataset.json) has a ``camera`` section, its camera model
    (:mod:`omnisim.camera`) is applied to each camera's radiance and ``cam1.png``, ...
    are added (``k`` is then required: it seeds the noise).
    """
    camera, rig = camera_from_meta(meta) if meta is not None else (None, None)
    if camera is not None and k is None:
        raise DatasetError("encode_frame: the frame index k is needed to apply the camera model")
    files: dict[str, bytes] = {}
    for cam in cameras:
        if cam not in frame:
            raise DatasetError(f"frame {k}: camera {cam!r} missing (got {sorted(frame)})")
        chans = frame[cam]
        _check_channels(chans, f"frame {k} {cam}")
        version = _channels_version(chans)
        if meta is not None and meta.get("format_version") != version:
            raise DatasetError(
                f"frame {k} {cam}: channels of format version {version}, but dataset.json "
                f"says format_version {meta.get('format_version')!r}"
            )
        attrs = {"omnisim.camera": cam}
        if k is not None:
            attrs["omnisim.frame"] = str(int(k))
        if version >= 2 and meta is not None:
            attrs.update(exr_header(meta, cam))
        files[f"{cam}.exr"] = exr_bytes(chans, attributes=attrs, scratch_dir=scratch_dir)
        files[f"{cam}.flo"] = flo_bytes(
            chans["gt.flow.dx"], chans["gt.flow.dy"], flo_known(chans, version)
        )
        if camera is not None:
            unit = getattr(rig, cam)
            rgb = np.stack([chans["R"], chans["G"], chans["B"]], axis=-1)
            dn = camera.apply(rgb, frame=int(k), cam=cam, centre=(unit.x_c, unit.y_c), r_m=unit.r_m)
            files[f"{cam}.png"] = camera.png_bytes(dn)
        if version >= 2:
            for suffix, name in MASK_FILES.items():
                files[f"{cam}.{suffix}"] = _mask_png(chans[name])
    return files


def _canonical(meta: Mapping[str, Any]) -> Any:
    """The meta as it reads back from disk (tuples -> lists, float repr round trip)."""
    return json.loads(_json_text(meta))


#: Keys of dataset.json that do not make a directory a different dataset: the scene
#: file's path, and the seconds each frame took (``timing``, machine-dependent).
_IGNORED_FOR_RESUME = {("scene", "path"), (TIMING_KEY,)}


def _diff_paths(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[tuple[str, ...]]:
    diffs: list[tuple[str, ...]] = []

    def walk(a: Any, b: Any, key: tuple[str, ...]) -> None:
        if key in _IGNORED_FOR_RESUME:
            return
        if isinstance(a, dict) and isinstance(b, dict):
            for name in list(a) + [n for n in b if n not in a]:
                if name not in a or name not in b:
                    if (*key, name) not in _IGNORED_FOR_RESUME:
                        diffs.append((*key, name))
                else:
                    walk(a[name], b[name], (*key, name))
        elif a != b:
            diffs.append(key)

    walk(_canonical(old), _canonical(new), ())
    # Settings first, then the scene text and its parsed copy (they repeat the settings).
    return sorted(diffs, key=lambda k: (k[:1] == ("scene",), k[:2] == ("scene", "data")))


def compare_meta(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[str]:
    """Dotted keys where two dataset.json contents differ (ignoring ``scene.path``).

    Empty when a render with ``new`` may resume into a directory holding ``old``.
    """
    return [".".join(k) or "<root>" for k in _diff_paths(old, new)]


def _frame_timings(meta: Mapping[str, Any]) -> dict[str, dict[str, float]]:
    """The per-frame seconds of an existing dataset.json (empty when it has none)."""
    frames = (meta.get(TIMING_KEY) or {}).get("frames") if isinstance(meta, Mapping) else None
    if not isinstance(frames, Mapping):
        return {}
    return {
        str(k): {n: float(v) for n, v in rec.items() if isinstance(v, int | float)}
        for k, rec in frames.items()
        if isinstance(rec, Mapping)
    }


def timing_section(
    meta: Mapping[str, Any],
    frames: Mapping[str, Mapping[str, float]],
    context: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The ``timing`` section of dataset.json: seconds per frame and their medians.

    ``frames`` maps a frame index (as text) to its seconds; ``context`` adds what the
    seconds depend on (CPU and Dr.Jit thread counts, the load average). The render
    settings that set the cost (integrator, spp, denoiser, variant) are repeated from
    ``meta["render"]`` so the section reads on its own.
    """
    r = meta.get("render") or {}
    keys = sorted({n for rec in frames.values() for n in rec})
    order = sorted(frames, key=int)
    return {
        "integrator": r.get("integrator"),
        "spp": r.get("spp"),
        "max_depth": r.get("max_depth"),
        "denoise": r.get("denoise"),
        "variant": r.get("variant"),
        **dict(context or {}),
        "median_s": {
            n: float(np.median([frames[k][n] for k in order if n in frames[k]])) for n in keys
        },
        "frames": {k: dict(frames[k]) for k in order},
    }


class DatasetWriter:
    """Create (or resume) a dataset directory and write frames atomically.

    ``DatasetWriter(dir, meta)`` writes ``dataset.json`` atomically if the directory
    has none; if it has one, it must describe the same dataset (:func:`compare_meta`),
    else :class:`DatasetMismatchError` names the differing keys. Leftover temporary
    frame directories of an interrupted run are removed.
    """

    def __init__(
        self,
        dir: str | Path,
        meta: Mapping[str, Any],
        *,
        cleanup: bool = True,
        lock: bool = True,
    ):
        self.dir = Path(dir)
        self.meta = _canonical(meta)
        if self.meta.get("format") != FORMAT_NAME:
            raise DatasetError(f"meta['format'] must be {FORMAT_NAME!r}")
        self.cameras = camera_names(self.meta)
        if not self.cameras:
            raise DatasetError("meta['cameras'] lists no camera")
        self.version = self.meta.get("format_version")
        if self.version not in READ_VERSIONS:
            raise DatasetError(
                f"meta['format_version'] = {self.version!r}: expected one of {list(READ_VERSIONS)}"
            )
        self.expected_files = expected_files(self.cameras, "camera" in self.meta, self.version)
        self.frame_count = int(self.meta["frames"])
        self._lock_key: str | None = None
        self._made: list[Path] = []  # what this writer created, newest last (see abandon)
        self._timing: dict[str, dict[str, float]] = {}  # frame index -> seconds (record_timing)
        self._timing_context: dict[str, Any] = {}  # what the seconds depend on (the last given)
        existed = self.dir.exists()
        if existed and not self.dir.is_dir():
            raise DatasetError(f"{self.dir}: exists and is not a directory; expected a directory")
        meta_path = self.dir / META_NAME
        if existed and not meta_path.exists():
            self._refuse_foreign()
        if not existed:
            missing = [p for p in (self.dir, *self.dir.parents) if not p.exists()]
            self.dir.mkdir(parents=True, exist_ok=True)
            self._made.extend(reversed(missing))
        try:
            if lock:
                had_lock = (self.dir / LOCK_NAME).exists()
                self._lock_key = _lock_dir(self.dir)
                if not had_lock:
                    self._made.append(self.dir / LOCK_NAME)
            if meta_path.exists():
                old = load_meta(meta_path)
                self._check_resume(old)
                self._timing = _frame_timings(old)
                if cleanup:  # the opener holding the lock; Dask workers skip the scan
                    self._refuse_foreign_frames()
            else:
                self._refuse_foreign()
                self._refuse_foreign_frames()
                atomic_write_json(meta_path, self.meta)
                self._made.append(meta_path)
            if not ownership.has_marker(self.dir):
                ownership.write_marker(self.dir, "omnisim render")
                self._made.append(self.dir / ownership.MARKER)
            if not self.frames_dir.exists():
                self.frames_dir.mkdir()
                self._made.append(self.frames_dir)
            fsync_dir(self.dir)
            if cleanup:
                self.remove_temporaries()
        except BaseException:
            self.abandon()
            raise

    def _refuse_foreign(self) -> None:
        """A directory with no dataset.json: refuse it unless it is empty, or ours (its
        marker), or holds nothing but the lock, temporaries and an empty ``frames/``."""
        if not self.dir.exists() or ownership.has_marker(self.dir):
            return
        for p in sorted(self.dir.iterdir()):
            if p.name == LOCK_NAME or (_TMP_RE.match(p.name) and not p.is_symlink()):
                continue
            if p.name == FRAMES_DIR and p.is_dir() and not p.is_symlink():
                inner = [c for c in sorted(p.iterdir()) if not _TMP_RE.match(c.name)]
                if not inner:
                    continue
                p = inner[0]
            raise DatasetError(
                f"{p}: in {self.dir}, which is not empty and has no {META_NAME}: refusing "
                "to write a dataset into it; use an empty or new --out directory"
            )

    def _refuse_foreign_frames(self) -> None:
        """Refuse (one line, nothing touched) a frame folder that holds anything but
        the frame's files, or a frame name that is not a folder: the writer would
        replace an incomplete frame folder, and removes only what it writes."""
        if self.frames_dir.is_dir():
            for p in sorted(self.frames_dir.iterdir()):
                if FRAME_RE.match(p.name):
                    self._refuse_foreign_frame(p)

    def _refuse_foreign_frame(self, p: Path) -> None:
        if p.is_symlink() or (p.exists() and not p.is_dir()):
            why = ownership.refusal(p, "omnisim render", self.dir, marked=True)
            raise DatasetForeignError(f"{why} (a frame name that is not a folder)")
        names = set(self.expected_files)
        with contextlib.suppress(FileNotFoundError):  # moved aside meanwhile: nothing to check
            bad = ownership.find_foreign(p, lambda rel: str(rel) in names)
            if bad is not None:
                raise DatasetForeignError(
                    str(ownership.refusal(bad, "omnisim render", self.dir, marked=True))
                )

    def _check_resume(self, old: Mapping[str, Any]) -> None:
        diffs = _diff_paths(old, self.meta)
        if not diffs:
            return
        changed = [k for k in diffs if k[:2] == ("inputs", "files") and len(k) > 2]
        if changed:
            name = changed[0][2]
            scene_dir = Path(str(self.meta.get("scene", {}).get("path", "."))).parent
            raise DatasetMismatchError(
                f"{scene_dir / name}: changed since the dataset in {self.dir} was started "
                f"(sha256 {show_key(old, ('inputs', 'files', name, 'sha256'))[1:13]}... "
                f"then, {show_key(self.meta, ('inputs', 'files', name, 'sha256'))[1:13]}... "
                "now); restore the file or render into another --out directory"
            )
        shown = "; ".join(
            f"{'.'.join(k)}: {show_key(old, k)} in the directory vs {show_key(self.meta, k)} now"
            for k in diffs[:3]
        )
        more = f" and {len(diffs) - 3} more" if len(diffs) > 3 else ""
        raise DatasetMismatchError(
            f"{self.dir}: refusing to resume: it holds a dataset made from a different "
            f"scene or settings ({shown}{more}); use another --out directory or delete it"
        )

    def close(self) -> None:
        """Release the directory's write lock (also done when the process ends)."""
        if self._lock_key is not None:
            _unlock_dir(self._lock_key)
            self._lock_key = None

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def abandon(self) -> None:
        """Undo this writer's start when no frame was written: remove the dataset.json,
        frames/, lock file and directories it created (nothing that existed before),
        then release the lock. A failure before the first frame (a renderer that cannot
        start, say) thus leaves no half-made dataset to block the corrected rerun."""
        if self.frames_dir.is_dir() and any(
            FRAME_RE.match(p.name) for p in self.frames_dir.iterdir()
        ):
            self.close()
            return
        if self.frames_dir in self._made:
            self.remove_temporaries()
        for p in reversed(self._made):
            with contextlib.suppress(OSError):
                if p.is_dir():
                    p.rmdir()  # only when empty
                else:
                    p.unlink()
        self._made.clear()
        self.close()

    @property
    def frames_dir(self) -> Path:
        return self.dir / FRAMES_DIR

    def frame_dir(self, k: int) -> Path:
        return self.frames_dir / frame_name(k)

    def remove_temporaries(self) -> list[Path]:
        """Delete temporary frame directories/files left by an interrupted run."""
        removed = []
        for parent in (self.dir, self.frames_dir):
            if not parent.is_dir():
                continue
            for p in parent.iterdir():
                old = (
                    parent == self.frames_dir
                    and _OLD_SCRATCH_RE.match(p.name)
                    and p.is_dir()
                    and {c.name for c in p.iterdir()} <= {"x.exr"}
                )
                if _TMP_RE.match(p.name) or old:
                    if p.is_dir():
                        shutil.rmtree(p, ignore_errors=True)
                    else:
                        with contextlib.suppress(OSError):
                            p.unlink()
                    removed.append(p)
        return removed

    def is_done(self, k: int) -> bool:
        """True when frame ``k``'s final directory exists with every expected file."""
        d = self.frame_dir(k)
        return d.is_dir() and all((d / f).is_file() for f in self.expected_files)

    def done_frames(self) -> list[int]:
        return [k for k in range(self.frame_count) if self.is_done(k)]

    def todo_frames(self) -> list[int]:
        return [k for k in range(self.frame_count) if not self.is_done(k)]

    def record_timing(
        self, k: int, seconds: Mapping[str, float], context: Mapping[str, Any] | None = None
    ) -> None:
        """Add frame ``k``'s seconds (``render``, ``denoise``, ``groundtruth``, ``total``)
        to the ``timing`` section of ``dataset.json``, rewritten atomically.

        The section (:func:`timing_section`) is the one part of ``dataset.json`` that
        differs between two renders of the same scene: it is ignored when resuming, and
        the records of frames rendered by an earlier run are kept. ``context`` (CPU and
        thread counts, load) is kept until the next call that gives one.
        """
        self._timing[str(int(k))] = {key: float(v) for key, v in seconds.items()}
        if context is not None:
            self._timing_context = dict(context)
        section = timing_section(self.meta, self._timing, self._timing_context)
        atomic_write_json(self.dir / META_NAME, {**self.meta, TIMING_KEY: section})

    def write_frame(self, k: int, frame: Mapping[str, Mapping[str, NDArray]]) -> Path:
        """Encode and write frame ``k`` (camera -> channels) atomically; returns its directory."""
        return self.write_frame_files(
            k, encode_frame(frame, self.cameras, k=k, scratch_dir=self.frames_dir, meta=self.meta)
        )

    def write_frame_files(self, k: int, files: Mapping[str, bytes]) -> Path:
        """Write pre-encoded frame files (:func:`encode_frame`) atomically.

        The files go into ``frames/.NNNNNN.tmp.<pid>.<rand>/``, each fsynced, and the
        directory is renamed to ``frames/NNNNNN``. If another writer finished the
        same frame first, its complete directory is kept.
        """
        if not 0 <= k < self.frame_count:
            raise DatasetError(f"frame {k} outside 0..{self.frame_count - 1}")
        expected = self.expected_files
        if sorted(files) != sorted(expected):
            raise DatasetError(f"frame {k}: files {sorted(files)}; expected {sorted(expected)}")
        final = self.frame_dir(k)
        tmp = self.frames_dir / f".{frame_name(k)}.tmp.{os.getpid()}.{uuid.uuid4().hex[:8]}"
        tmp.mkdir()
        try:
            for name in expected:
                _write_synced(tmp / name, files[name])
            fsync_dir(tmp)
            if final.exists() and not self.is_done(k):
                # An incomplete final directory (someone deleted a file): move it aside,
                # when it holds nothing but the frame's files (checked again: it may
                # have changed since the writer opened the dataset).
                self._refuse_foreign_frame(final)
                trash = self.frames_dir / f".{frame_name(k)}.tmp.stale.{uuid.uuid4().hex[:8]}"
                os.rename(final, trash)
                shutil.rmtree(trash, ignore_errors=True)
            try:
                os.rename(tmp, final)
            except OSError:
                if not self.is_done(k):
                    raise
                shutil.rmtree(tmp, ignore_errors=True)  # a concurrent writer won
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        fsync_dir(self.frames_dir)
        return final
