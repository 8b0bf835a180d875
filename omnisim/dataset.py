"""The omnisim dataset on disk: the contract other tools read (written and read here only).

Layout (see ``docs/dataset_format.md`` for every key and channel)::

    DIR/dataset.json                 metadata: format, scene, rig, cameras, poses, ...
    DIR/frames/000000/cam1.exr       one multi-channel float32 EXR per camera and frame
    DIR/frames/000000/cam1.flo       Middlebury optical flow (dx, dy) of that camera
    DIR/frames/000000/cam1.png       the camera model's image of the radiance (when
                                     dataset.json has a "camera" section; 8 or 16 bit)
    DIR/frames/000000/cam2.exr
    DIR/frames/000000/cam2.flo
    DIR/frames/000001/...

Atomicity: a frame is rendered into a hidden temporary directory
``DIR/frames/.000000.tmp.<pid>.<random>``, every file is fsynced, and the
directory is renamed to its final name ``000000``. A frame is done exactly when
its final directory exists with all its files; no partial file is ever visible
under a final name. ``dataset.json`` is written the same way (temporary name,
fsync, rename) before any frame.

This module imports neither Mitsuba nor the scene model, so readers (validation,
the omniflow command) need only numpy and OpenEXR.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import shutil
import uuid
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from omniflow.rig import Rig, RigError, rig_from_dict

__all__ = [
    "CHANNELS",
    "FLO_MAGIC",
    "FLO_UNKNOWN",
    "FLO_UNKNOWN_THRESH",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "GT_CHANNELS",
    "Dataset",
    "DatasetError",
    "DatasetMismatchError",
    "DatasetWriter",
    "atomic_write_bytes",
    "atomic_write_json",
    "camera_from_meta",
    "compare_meta",
    "encode_frame",
    "exr_bytes",
    "flo_bytes",
    "frame_name",
    "open_dataset",
    "read_exr",
    "read_flo",
    "write_exr",
    "write_flo",
]

#: ``dataset.json["format"]`` and ``["format_version"]``.
FORMAT_NAME = "omnisim-dataset"
FORMAT_VERSION = 1

#: Ground-truth channel names, exactly as the contract spells them.
GT_CHANNELS: tuple[str, ...] = (
    "gt.valid",
    "gt.r",
    "gt.theta",
    "gt.h",
    "gt.X",
    "gt.Y",
    "gt.Z",
    "gt.object",
    "gt.flow.dx",
    "gt.flow.dy",
    "gt.flow.dh",
    "gt.flow.hdtheta",
    "gt.flow.valid",
    "gt.stereo.h_other",
    "gt.stereo.valid",
)
#: Every channel of a camera's EXR: linear radiance R, G, B, then the ground truth.
CHANNELS: tuple[str, ...] = ("R", "G", "B", *GT_CHANNELS)

#: Middlebury .flo magic number (the float32 whose bytes read "PIEH").
FLO_MAGIC = 202021.25
#: Value written for invalid (unknown) flow: Middlebury's ``UNKNOWN_FLOW`` (1e10).
FLO_UNKNOWN = 1e10
#: Middlebury's ``UNKNOWN_FLOW_THRESH``: a component with |value| >= 1e9 (or NaN) is unknown.
#: (Middlebury's own code tests ``> 1e9``; this reader also treats exactly 1e9 as unknown.)
FLO_UNKNOWN_THRESH = 1e9

META_NAME = "dataset.json"
FRAMES_DIR = "frames"
_FRAME_RE = re.compile(r"^\d{6}$")
_TMP_RE = re.compile(r"^\.(\d{6}|dataset\.json)\.tmp\.")


class DatasetError(ValueError):
    """A dataset directory is missing, malformed or incomplete; the message says where."""


class DatasetMismatchError(DatasetError):
    """A render would resume into a directory made from a different scene or settings."""


def frame_name(k: int) -> str:
    """Directory name of frame ``k``: six digits, ``000000``."""
    if isinstance(k, bool) or int(k) != k or k < 0 or k > 999_999:
        raise ValueError(f"frame index {k!r}: expected an integer in [0, 999999]")
    return f"{int(k):06d}"


# -- atomic file helpers ----------------------------------------------------------


def _fsync_dir(path: Path) -> None:
    """fsync a directory so a rename inside it is durable (no-op where unsupported)."""
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


def _write_synced(path: Path, data: bytes) -> None:
    with open(path, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary name in the same directory, fsync, rename."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp.{os.getpid()}.{uuid.uuid4().hex[:8]}")
    try:
        _write_synced(tmp, data)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    _fsync_dir(path.parent)


def _json_text(obj: Any) -> str:
    return json.dumps(obj, indent=2, sort_keys=False, allow_nan=False) + "\n"


def atomic_write_json(path: str | Path, obj: Any) -> None:
    """Write ``obj`` as indented JSON (no NaN/inf) atomically."""
    atomic_write_bytes(path, _json_text(obj).encode("utf-8"))


# -- EXR -------------------------------------------------------------------------


def _check_channels(channels: Mapping[str, NDArray], where: str) -> tuple[int, int]:
    names = list(channels)
    if set(names) != set(CHANNELS) or len(names) != len(CHANNELS):
        missing = [c for c in CHANNELS if c not in channels]
        extra = [c for c in names if c not in CHANNELS]
        raise DatasetError(
            f"{where}: channels must be exactly {list(CHANNELS)}; missing {missing}, extra {extra}"
        )
    shape = None
    for name in CHANNELS:
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
    with OpenEXR.File(header, chans) as exr:
        exr.write(str(path))
    with open(path, "rb+") as fh:
        os.fsync(fh.fileno())


def read_exr(path: str | Path) -> dict[str, NDArray[np.float32]]:
    """All channels of an EXR by name, each a float32 (H, W) array (R, G, B kept separate)."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: EXR file not found")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            return {
                name: np.asarray(ch.pixels, dtype=np.float32).copy()
                for name, ch in exr.channels().items()
            }
    except Exception as exc:  # OpenEXR raises RuntimeError/OSError on corrupt files
        raise DatasetError(f"{path}: cannot read EXR: {exc}") from exc


def exr_bytes(
    channels: Mapping[str, NDArray],
    *,
    attributes: Mapping[str, str] | None = None,
    scratch_dir: str | Path | None = None,
) -> bytes:
    """The bytes :func:`write_exr` would write (via a scratch file; OpenEXR writes to paths)."""
    import tempfile

    with tempfile.TemporaryDirectory(dir=scratch_dir) as tmp:
        p = Path(tmp) / "x.exr"
        write_exr(p, channels, attributes=attributes)
        return p.read_bytes()


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


def read_flo(path: str | Path) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Read a Middlebury .flo: ``(flow (H, W, 2) float32 [dx, dy], valid (H, W) bool)``.

    ``valid`` is false where either component is NaN or has |value| >= 1e9.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read .flo: {exc}") from exc
    if len(raw) < 12:
        raise DatasetError(f"{path}: .flo file too short ({len(raw)} bytes)")
    magic = np.frombuffer(raw, "<f4", 1, 0)[0]
    if magic != np.float32(FLO_MAGIC):
        raise DatasetError(f"{path}: bad .flo magic {magic!r}: expected {FLO_MAGIC}")
    w, h = (int(v) for v in np.frombuffer(raw, "<i4", 2, 4))
    if w <= 0 or h <= 0 or len(raw) != 12 + 8 * w * h:
        raise DatasetError(f"{path}: .flo header says {w}x{h} but the file has {len(raw)} bytes")
    flow = np.frombuffer(raw, "<f4", 2 * w * h, 12).reshape(h, w, 2).astype(np.float32)
    with np.errstate(invalid="ignore"):
        valid = np.all(np.isfinite(flow) & (np.abs(flow) < FLO_UNKNOWN_THRESH), axis=-1)
    return flow, valid


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

    ``frame`` maps camera name to its channels (exactly :data:`CHANNELS`). The bytes are
    what :meth:`DatasetWriter.write_frame` writes, so local and distributed runs agree.
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
        attrs = {"omnisim.camera": cam}
        if k is not None:
            attrs["omnisim.frame"] = str(int(k))
        files[f"{cam}.exr"] = exr_bytes(chans, attributes=attrs, scratch_dir=scratch_dir)
        files[f"{cam}.flo"] = flo_bytes(
            chans["gt.flow.dx"], chans["gt.flow.dy"], chans["gt.flow.valid"]
        )
        if camera is not None:
            unit = getattr(rig, cam)
            rgb = np.stack([chans["R"], chans["G"], chans["B"]], axis=-1)
            dn = camera.apply(rgb, frame=int(k), cam=cam, centre=(unit.x_c, unit.y_c), r_m=unit.r_m)
            files[f"{cam}.png"] = camera.png_bytes(dn)
    return files


def camera_from_meta(meta: Mapping[str, Any]) -> tuple[Any, Rig | None]:
    """``(CameraModel, Rig)`` of a dataset.json with a ``camera`` section, else ``(None, None)``.

    Raises :class:`DatasetError` when the section or the rig is malformed.
    """
    section = meta.get("camera")
    if section is None:
        return None, None
    from omnisim.camera import CameraError, CameraModel

    try:
        model = CameraModel.from_mapping(section, where="dataset.json")
        rig = rig_from_dict(meta, where="dataset.json")
    except (CameraError, RigError) as exc:
        raise DatasetError(str(exc)) from exc
    return model, rig


def _expected_files(cameras: Iterable[str], images: bool = False) -> list[str]:
    exts = ("exr", "flo", "png") if images else ("exr", "flo")
    return [f"{cam}.{ext}" for cam in cameras for ext in exts]


def _camera_names(meta: Mapping[str, Any]) -> list[str]:
    return [str(c["name"]) for c in meta.get("cameras", [])]


def _canonical(meta: Mapping[str, Any]) -> Any:
    """The meta as it reads back from disk (tuples -> lists, float repr round trip)."""
    return json.loads(_json_text(meta))


#: Keys of dataset.json that do not make a directory a different dataset.
_IGNORED_FOR_RESUME = {("scene", "path")}


def _diff_paths(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[tuple[str, ...]]:
    diffs: list[tuple[str, ...]] = []

    def walk(a: Any, b: Any, key: tuple[str, ...]) -> None:
        if key in _IGNORED_FOR_RESUME:
            return
        if isinstance(a, dict) and isinstance(b, dict):
            for name in list(a) + [n for n in b if n not in a]:
                if name not in a or name not in b:
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


def _describe(meta: Mapping[str, Any], key: tuple[str, ...]) -> str:
    cur: Any = meta
    for part in key:
        if not isinstance(cur, dict) or part not in cur:
            return "<absent>"
        cur = cur[part]
    text = json.dumps(cur)
    return text if len(text) <= 60 else text[:57] + "..."


class DatasetWriter:
    """Create (or resume) a dataset directory and write frames atomically.

    ``DatasetWriter(dir, meta)`` writes ``dataset.json`` atomically if the directory
    has none; if it has one, it must describe the same dataset (:func:`compare_meta`),
    else :class:`DatasetMismatchError` names the differing keys. Leftover temporary
    frame directories of an interrupted run are removed.
    """

    def __init__(self, dir: str | Path, meta: Mapping[str, Any], *, cleanup: bool = True):
        self.dir = Path(dir)
        self.meta = _canonical(meta)
        if self.meta.get("format") != FORMAT_NAME:
            raise DatasetError(f"meta['format'] must be {FORMAT_NAME!r}")
        self.cameras = _camera_names(self.meta)
        if not self.cameras:
            raise DatasetError("meta['cameras'] lists no camera")
        self.expected_files = _expected_files(self.cameras, "camera" in self.meta)
        self.frame_count = int(self.meta["frames"])
        if self.dir.exists() and not self.dir.is_dir():
            raise DatasetError(f"{self.dir}: exists and is not a directory")
        meta_path = self.dir / META_NAME
        if meta_path.exists():
            old = _load_meta(meta_path)
            diffs = _diff_paths(old, self.meta)
            if diffs:
                shown = "; ".join(
                    f"{'.'.join(k)}: {_describe(old, k)} in the directory vs "
                    f"{_describe(self.meta, k)} now"
                    for k in diffs[:3]
                )
                more = f" and {len(diffs) - 3} more" if len(diffs) > 3 else ""
                raise DatasetMismatchError(
                    f"{self.dir}: refusing to resume: it holds a dataset made from a different "
                    f"scene or settings ({shown}{more}); use another --out directory or delete it"
                )
        else:
            if self.dir.exists() and any(
                p.name != FRAMES_DIR for p in self.dir.iterdir() if not p.name.startswith(".")
            ):
                raise DatasetError(
                    f"{self.dir}: not empty and has no {META_NAME}: refusing to write a "
                    "dataset into it; use an empty or new --out directory"
                )
            self.dir.mkdir(parents=True, exist_ok=True)
            atomic_write_json(meta_path, self.meta)
        self.frames_dir.mkdir(exist_ok=True)
        _fsync_dir(self.dir)
        if cleanup:
            self.remove_temporaries()

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
                if _TMP_RE.match(p.name):
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
            _fsync_dir(tmp)
            if final.exists() and not self.is_done(k):
                # An incomplete final directory (someone deleted a file): move it aside.
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
        _fsync_dir(self.frames_dir)
        return final


# -- reading -------------------------------------------------------------------------


def _load_meta(path: Path) -> dict[str, Any]:
    try:
        meta = json.loads(path.read_text())
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read: {exc}") from exc
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}: not valid JSON: {exc}") from exc
    if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
        raise DatasetError(f"{path}: 'format' is not {FORMAT_NAME!r}: not an omnisim dataset")
    ver = meta.get("format_version")
    if not isinstance(ver, int) or ver > FORMAT_VERSION:
        raise DatasetError(
            f"{path}: format_version {ver!r}: this omnisim reads versions <= {FORMAT_VERSION}"
        )
    for key in ("rig", "cameras", "frames"):
        if key not in meta:
            raise DatasetError(f"{path}: key {key!r} missing")
    return meta


@dataclass
class Dataset:
    """A dataset directory opened for reading (:func:`open_dataset`)."""

    dir: Path
    meta: dict[str, Any]
    rig: Rig
    cameras: list[str] = field(default_factory=list)

    @property
    def frame_count(self) -> int:
        """Frames the dataset declares (``meta['frames']``); see :meth:`frames_done`."""
        return int(self.meta["frames"])

    @property
    def frame_interval(self) -> float:
        """Seconds between frames."""
        return float(self.meta["frame_interval"])

    @property
    def objects(self) -> dict[int, str]:
        """gt.object id -> object name (0 means no object / background)."""
        return {int(o["id"]): str(o["name"]) for o in self.meta.get("objects", [])}

    def unit(self, cam: str):
        """The :class:`omniflow.rig.Unit` of camera ``cam``."""
        if cam not in ("cam1", "cam2"):
            raise DatasetError(
                f"{self.dir}: unknown camera {cam!r}; expected one of {self.cameras}"
            )
        return getattr(self.rig, cam)

    def frame_dir(self, k: int) -> Path:
        return self.dir / FRAMES_DIR / frame_name(k)

    def path(self, k: int, cam: str, ext: str = "exr") -> Path:
        """Path of frame ``k``'s file for camera ``cam`` (``ext`` "exr", "flo" or "png")."""
        return self.frame_dir(k) / f"{cam}.{ext}"

    def is_done(self, k: int) -> bool:
        d = self.frame_dir(k)
        images = "camera" in self.meta
        return d.is_dir() and all((d / f).is_file() for f in _expected_files(self.cameras, images))

    def frames_done(self) -> list[int]:
        """Indices of frames whose directory is complete."""
        return [k for k in range(self.frame_count) if self.is_done(k)]

    @property
    def complete(self) -> bool:
        return len(self.frames_done()) == self.frame_count

    def _check(self, k: int, cam: str) -> None:
        if cam not in self.cameras:
            raise DatasetError(
                f"{self.dir}: unknown camera {cam!r}; expected one of {self.cameras}"
            )
        if isinstance(k, bool) or int(k) != k or not 0 <= k < self.frame_count:
            raise DatasetError(f"{self.dir}: frame {k!r} outside 0..{self.frame_count - 1}")
        if not self.is_done(k):
            raise DatasetError(f"{self.frame_dir(k)}: frame {k} not rendered (or incomplete)")

    def read_frame(self, k: int, cam: str) -> dict[str, NDArray[np.float32]]:
        """Channels of frame ``k``, camera ``cam``: name -> float32 (H, W)."""
        self._check(k, cam)
        path = self.path(k, cam, "exr")
        chans = read_exr(path)
        missing = [c for c in CHANNELS if c not in chans]
        if missing:
            raise DatasetError(f"{path}: channels {missing} missing")
        unit = self.unit(cam)
        shape = chans["R"].shape
        if shape != (unit.height, unit.width):
            raise DatasetError(
                f"{path}: image is {shape[1]}x{shape[0]}, dataset.json says "
                f"{unit.width}x{unit.height}"
            )
        return chans

    def read_rgb(self, k: int, cam: str) -> NDArray[np.float32]:
        """Linear RGB (H, W, 3) of frame ``k``, camera ``cam``."""
        c = self.read_frame(k, cam)
        return np.stack([c["R"], c["G"], c["B"]], axis=-1)

    def read_grey(self, k: int, cam: str) -> NDArray[np.float32]:
        """Rec. 709 luminance (H, W) of frame ``k``, camera ``cam``."""
        from omniflow.conventions import LUMA_WEIGHTS

        c = self.read_frame(k, cam)
        wr, wg, wb = LUMA_WEIGHTS
        return (wr * c["R"] + wg * c["G"] + wb * c["B"]).astype(np.float32)

    @property
    def camera(self):
        """The dataset's :class:`omnisim.camera.CameraModel` (dataset.json ``camera``), or
        None for a dataset written without one (no PNGs)."""
        return camera_from_meta(self.meta)[0]

    def read_camera_dn(self, k: int, cam: str) -> NDArray[np.unsignedinteger]:
        """Digital numbers (H, W, 3) of the camera image ``cam.png`` of frame ``k``:
        ``uint8`` for 8 bits, else ``uint16`` in ``[0, 2^bits - 1]``."""
        import cv2

        self._check(k, cam)
        model = self.camera
        path = self.path(k, cam, "png")
        if model is None:
            raise DatasetError(f"{self.dir}: dataset.json has no camera section: no camera images")
        pixels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if pixels is None:
            raise DatasetError(f"{path}: cannot read the camera image")
        if pixels.ndim == 3:
            pixels = pixels[..., ::-1]  # OpenCV's BGR -> RGB
        unit = self.unit(cam)
        if pixels.shape[:2] != (unit.height, unit.width):
            raise DatasetError(
                f"{path}: image is {pixels.shape[1]}x{pixels.shape[0]}, dataset.json says "
                f"{unit.width}x{unit.height}"
            )
        try:
            return model.dn_from_png(pixels)
        except ValueError as exc:
            raise DatasetError(f"{path}: {exc}") from exc

    def read_camera_image(self, k: int, cam: str, *, grey: bool = False) -> NDArray[np.float32]:
        """The stored camera image of frame ``k`` as float32 in [0, 1]: RGB (H, W, 3), or
        with ``grey=True`` its Rec. 709 luma (H, W), as omniflow reads it."""
        model = self.camera
        dn = self.read_camera_dn(k, cam)
        return model.grey(dn) if grey else model.to_float(dn)

    def read_flo(self, k: int, cam: str) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """The .flo of frame ``k``, camera ``cam``: (flow (H, W, 2), valid (H, W))."""
        self._check(k, cam)
        return read_flo(self.path(k, cam, "flo"))


def open_dataset(dir: str | Path) -> Dataset:
    """Open a dataset directory for reading; :class:`DatasetError` if it is not one."""
    d = Path(dir)
    meta_path = d / META_NAME
    if not meta_path.is_file():
        raise DatasetError(f"{d}: no {META_NAME}: not an omnisim dataset directory")
    meta = _load_meta(meta_path)
    try:
        rig = rig_from_dict(meta, where=str(meta_path))
    except RigError as exc:
        raise DatasetError(str(exc)) from exc
    frames = meta["frames"]
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise DatasetError(f"{meta_path}: frames = {frames!r}: expected a positive integer")
    fi = meta.get("frame_interval")
    if not isinstance(fi, int | float) or not math.isfinite(fi) or fi <= 0:
        raise DatasetError(f"{meta_path}: frame_interval = {fi!r}: expected seconds > 0")
    return Dataset(dir=d, meta=meta, rig=rig, cameras=_camera_names(meta))
