"""The omnisim dataset contract: its names, and the reader every package uses.

Layout (see ``docs/dataset_format.md`` for every key and channel)::

    DIR/dataset.json                 metadata: format, scene, rig, cameras, poses, ...
    DIR/frames/000000/cam1.exr       one multi-channel float32 EXR per camera and frame
    DIR/frames/000000/cam1.flo       Middlebury optical flow (dx, dy) of that camera
    DIR/frames/000000/cam1.occluded.png  (version 2) 0/255: the point is hidden at t + 1
    DIR/frames/000000/cam1.outside.png   (version 2) 0/255: the point leaves the mirror
    DIR/frames/000000/cam1.png       the camera model's image of the radiance (when
                                     dataset.json has a "camera" section; 8 or 16 bit)
    DIR/frames/000000/cam2.exr
    DIR/frames/000000/cam2.flo
    DIR/frames/000001/...

A frame is done exactly when its final directory exists with all its files
(:meth:`Dataset.is_done`); the writer (:mod:`omnisim.dataset`) renames a complete
temporary directory into place, so a reader never sees a partial frame.

This module is the contract's one definition (channel names, units, file names,
format versions) and its reader. It lives in ``omniflow`` so that every package
(the omniflow command, validation, omnisim's checks and exporters) reads a dataset
without importing the renderer: it needs only numpy, OpenEXR and OpenCV.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from omniflow.geometry.rig import Rig, RigError, rig_from_dict
from omniflow.input_files import InputFileError, parse_text, read_input
from omniflow.io.imageio import _native_reason, native_output_captured, to_grey

__all__ = [
    "CHANNELS",
    "CHANNELS_V1",
    "CHANNEL_INFO",
    "FLO_MAGIC",
    "FLO_UNKNOWN",
    "FLO_UNKNOWN_THRESH",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "FRAMES_DIR",
    "FRAME_RE",
    "GT_CHANNELS",
    "GT_CHANNELS_V1",
    "MASK_FILES",
    "META_NAME",
    "READ_VERSIONS",
    "Dataset",
    "DatasetError",
    "camera_names",
    "channels_for",
    "check_poses",
    "expected_files",
    "flo_known",
    "frame_name",
    "grey_of",
    "load_meta",
    "open_dataset",
    "read_exr",
    "read_flo",
    "read_mask_png",
    "show_key",
]


#: The bit depths of a recorded camera (``dataset.json`` ``camera.bits``; omnisim.camera).
CAMERA_BITS = (8, 10, 12, 16)
#: ``dataset.json["format"]`` and ``["format_version"]``.
FORMAT_NAME = "omnisim-dataset"
FORMAT_VERSION = 2
#: Format versions this module reads (and writes: a frame of version 1 channels is
#: written as version 1, e.g. by ``omnisim.synthetic``, which has no backward flow).
READ_VERSIONS = (1, 2)

#: Ground-truth channel names of format version 1.
GT_CHANNELS_V1: tuple[str, ...] = (
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
#: Channels format version 2 adds: why forward flow is not visible at t + 1, and the
#: backward flow (t to t - 1) with the same three masks.
_V2_ADDED: tuple[str, ...] = (
    "gt.flow.occluded",
    "gt.flow.outside",
    "gt.bflow.dx",
    "gt.bflow.dy",
    "gt.bflow.dh",
    "gt.bflow.hdtheta",
    "gt.bflow.valid",
    "gt.bflow.occluded",
    "gt.bflow.outside",
)
#: Ground-truth channel names (the current version), exactly as the contract spells them:
#: version 1's with the added ones after ``gt.flow.valid``.
GT_CHANNELS: tuple[str, ...] = (
    *GT_CHANNELS_V1[: GT_CHANNELS_V1.index("gt.flow.valid") + 1],
    *_V2_ADDED,
    *GT_CHANNELS_V1[GT_CHANNELS_V1.index("gt.flow.valid") + 1 :],
)
#: Every channel of a camera's EXR: linear radiance R, G, B, then the ground truth.
CHANNELS: tuple[str, ...] = ("R", "G", "B", *GT_CHANNELS)
#: The channels of a version 1 EXR.
CHANNELS_V1: tuple[str, ...] = ("R", "G", "B", *GT_CHANNELS_V1)

#: Unit and one-line meaning of every channel; written into each version 2 EXR's header
#: (``omnisim.channel.<name>``) so one file is understood without dataset.json.
CHANNEL_INFO: dict[str, tuple[str, str]] = {
    "R": ("radiance", "linear red radiance (Mitsuba, no tone mapping); 0 outside the rim"),
    "G": ("radiance", "linear green radiance"),
    "B": ("radiance", "linear blue radiance"),
    "gt.valid": ("0/1", "1 where the pixel centre sees a scene object through the mirror"),
    "gt.r": ("m", "range of the seen point: distance from the rig axis"),
    "gt.theta": ("rad", "azimuth of the seen point in the rig frame, atan2(Y, X), [-pi, pi)"),
    "gt.h": ("m", "height of the seen point in the rig frame, above cam2's cone tip"),
    "gt.X": ("m", "world X of the seen point"),
    "gt.Y": ("m", "world Y of the seen point"),
    "gt.Z": ("m", "world Z (height) of the seen point; NOT a depth or distance"),
    "gt.object": ("id", "object id of dataset.json objects[], 0 where nothing is hit"),
    "gt.flow.dx": ("px", "flow t -> t+1, x (right); 0 where the next position is undefined"),
    "gt.flow.dy": ("px", "flow t -> t+1, y (down); 0 where the next position is undefined"),
    "gt.flow.dh": ("px", "flow t -> t+1, radial: image radius at t+1 minus at t"),
    "gt.flow.hdtheta": ("px", "flow t -> t+1, tangential: h_i(t) wrap(theta_i(t+1) - theta_i)"),
    "gt.flow.valid": ("0/1", "1 where the point is seen at t+1 (on the mirror, unoccluded)"),
    "gt.flow.occluded": ("0/1", "1 where the point is on the mirror at t+1 but hidden"),
    "gt.flow.outside": ("0/1", "1 where the point's image at t+1 is off the mirror"),
    "gt.bflow.dx": ("px", "flow t -> t-1, x; 0 where undefined (all of frame 0)"),
    "gt.bflow.dy": ("px", "flow t -> t-1, y; 0 where undefined (all of frame 0)"),
    "gt.bflow.dh": ("px", "flow t -> t-1, radial"),
    "gt.bflow.hdtheta": ("px", "flow t -> t-1, tangential"),
    "gt.bflow.valid": ("0/1", "1 where the point was seen at t-1; 0 on frame 0"),
    "gt.bflow.occluded": ("0/1", "1 where the point was on the mirror at t-1 but hidden"),
    "gt.bflow.outside": ("0/1", "1 where the point's image at t-1 was off the mirror"),
    "gt.stereo.h_other": ("px", "image radius of the point in the other unit, eq. (3)/(4)"),
    "gt.stereo.valid": ("0/1", "1 where the other unit sees the point"),
}

#: Version 2 mask images beside each camera's .flo: file suffix -> channel (0 or 255).
MASK_FILES: dict[str, str] = {
    "occluded.png": "gt.flow.occluded",
    "outside.png": "gt.flow.outside",
}


def channels_for(version: int) -> tuple[str, ...]:
    """The EXR channels of a dataset of format ``version`` (1 or 2)."""
    if version == 1:
        return CHANNELS_V1
    if version == 2:
        return CHANNELS
    raise DatasetError(f"format_version {version!r}: this omnisim reads {list(READ_VERSIONS)}")


#: Middlebury .flo magic number (the float32 whose bytes read "PIEH").
FLO_MAGIC = 202021.25
#: Value written for invalid (unknown) flow: Middlebury's ``UNKNOWN_FLOW`` (1e10).
FLO_UNKNOWN = 1e10
#: Middlebury's ``UNKNOWN_FLOW_THRESH``: a component with |value| >= 1e9 (or NaN) is unknown.
#: (Middlebury's own code tests ``> 1e9``; this reader also treats exactly 1e9 as unknown.)
FLO_UNKNOWN_THRESH = 1e9

META_NAME = "dataset.json"
FRAMES_DIR = "frames"
#: A final frame directory's name (six digits).
FRAME_RE = re.compile(r"^\d{6}$")


class DatasetError(ValueError):
    """A dataset directory is missing, malformed or incomplete; the message says where."""


def frame_name(k: int) -> str:
    """Directory name of frame ``k``: six digits, ``000000``."""
    if isinstance(k, bool) or int(k) != k or k < 0 or k > 999_999:
        raise ValueError(f"frame index {k!r}: expected an integer in [0, 999999]")
    return f"{int(k):06d}"


# -- EXR -------------------------------------------------------------------------


def read_exr(path: str | Path) -> dict[str, NDArray[np.float32]]:
    """All channels of an EXR by name, each a float32 (H, W) array (R, G, B kept separate)."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: EXR file not found")
    native: list[str] = []
    try:
        with (
            native_output_captured() as native,
            OpenEXR.File(str(path), separate_channels=True) as exr,
        ):
            return {
                name: np.asarray(ch.pixels, dtype=np.float32).copy()
                for name, ch in exr.channels().items()
            }
    except Exception as exc:  # OpenEXR raises RuntimeError/OSError on corrupt files
        raise DatasetError(f"{path}: cannot read EXR: {_native_reason(native, exc, path)}") from exc


def flo_known(channels: Mapping[str, NDArray], version: int = FORMAT_VERSION) -> NDArray:
    """Where a dataset's .flo holds a flow (elsewhere Middlebury's unknown, 1e10).

    Version 1: where ``gt.flow.valid`` is 1. Version 2: wherever the point's position
    at t + 1 is defined, ``gt.flow.valid`` + ``gt.flow.occluded`` + ``gt.flow.outside``
    (disjoint 0/1 masks).
    """
    if version == 1:
        return np.asarray(channels["gt.flow.valid"]) > 0.5
    known = sum(
        np.asarray(channels[f"gt.flow.{m}"], np.float64) for m in ("valid", "occluded", "outside")
    )
    return (known > 0.5) & (np.asarray(channels["gt.valid"]) > 0.5)


def read_mask_png(path: str | Path) -> NDArray[np.bool_]:
    """A mask PNG (:data:`MASK_FILES`) as bool (H, W): True where the pixel is > 127."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2:
        raise DatasetError(f"{path}: cannot read as a greyscale mask PNG")
    return img > 127


# -- Middlebury .flo ---------------------------------------------------------------


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


def grey_of(channels: Mapping[str, NDArray]) -> NDArray[np.float32]:
    """Rec. 709 luminance (H, W) float32 of a frame's linear ``R``, ``G``, ``B`` channels
    (:func:`omniflow.io.imageio.to_grey`, the project's one luma)."""
    return to_grey(np.stack([channels["R"], channels["G"], channels["B"]], axis=-1))


# -- dataset.json ------------------------------------------------------------------


def camera_grey(dn: NDArray, bits: int) -> NDArray[np.float32]:
    """omniflow's grey input from a camera image's digital numbers (H, W) or (H, W, 3):
    the Rec. 709 luma of ``DN / (2^bits - 1)``, and for 8 bits or fewer that luma
    rounded to 8 bits again (an 8-bit grey image, as an ordinary image reader gives
    it). The one definition: ``omniflow --dataset`` and the harness use it."""
    f = (np.asarray(dn, dtype=np.float32) / np.float32((1 << bits) - 1)).astype(np.float32)
    grey = to_grey(f).astype(np.float32)
    if bits <= 8:
        grey = np.clip(np.rint(grey * 255.0), 0, 255).astype(np.uint8).astype(np.float32) / 255.0
    return grey


def expected_files(
    cameras: Iterable[str], images: bool = False, version: int = FORMAT_VERSION
) -> list[str]:
    """Files a complete frame directory holds: ``cam1.exr``, ``cam1.flo``, the version 2
    masks and, with ``images``, the camera model's ``cam1.png``; the same for each camera."""
    exts = ("exr", "flo", *(MASK_FILES if version >= 2 else ()), *(("png",) if images else ()))
    return [f"{cam}.{ext}" for cam in cameras for ext in exts]


def camera_names(meta: Mapping[str, Any]) -> list[str]:
    """The camera names of a dataset.json (``cameras[].name``), in file order."""
    return [str(c["name"]) for c in meta.get("cameras", [])]


def show_key(meta: Mapping[str, Any], key: tuple[str, ...]) -> str:
    """The JSON text of ``meta`` at the nested ``key`` (``"<absent>"`` if missing), cut to
    60 characters: for one-line messages that name a dataset.json value."""
    cur: Any = meta
    for part in key:
        if not isinstance(cur, dict) or part not in cur:
            return "<absent>"
        cur = cur[part]
    text = json.dumps(cur)
    return text if len(text) <= 60 else text[:57] + "..."


def load_meta(path: Path) -> dict[str, Any]:
    """Read and check a dataset.json: format name, a readable version and the keys
    ``rig``, ``cameras``, ``frames``; :class:`DatasetError` naming the file otherwise."""
    try:
        meta = parse_text(read_input(path, "dataset's JSON"), path, "json")
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    except InputFileError as exc:
        raise DatasetError(str(exc)) from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
        raise DatasetError(f"{path}: 'format' is not {FORMAT_NAME!r}: not an omnisim dataset")
    ver = meta.get("format_version")
    if isinstance(ver, bool) or ver not in READ_VERSIONS:
        raise DatasetError(
            f"{path}: format_version = {ver!r}: this omnisim reads versions {list(READ_VERSIONS)}"
        )
    for key in ("rig", "cameras", "frames"):
        if key not in meta:
            raise DatasetError(f"{path}: key {key!r} missing")
    return meta


def check_poses(meta: Mapping[str, Any], where: Path, frames: int) -> None:
    """Raise DatasetError unless robot.poses and every objects[].poses hold ``frames``
    4x4 matrices (the readers index them by frame)."""
    lists = [
        (
            "robot.poses",
            meta.get("robot", {}).get("poses") if isinstance(meta.get("robot"), dict) else None,
        )
    ]
    objs = meta.get("objects", [])
    if not isinstance(objs, list):
        raise DatasetError(f"{where}: objects = {show_key(meta, ('objects',))}: expected a list")
    for i, o in enumerate(objs):
        if not isinstance(o, dict) or "id" not in o:
            raise DatasetError(f"{where}: objects[{i}]: expected a table with id, name, poses")
        lists.append((f"objects[{i}].poses", o.get("poses")))
    for key, poses in lists:
        if key == "robot.poses" and poses is None:
            continue  # a dataset of images without robot motion (e.g. from a real rig)
        if not isinstance(poses, list) or len(poses) != frames:
            n = len(poses) if isinstance(poses, list) else poses
            raise DatasetError(
                f"{where}: {key} has {n!r} entries; expected one 4x4 matrix per frame "
                f"(frames = {frames})"
            )
        try:
            arr = np.asarray(poses, dtype=float)
        except (TypeError, ValueError):
            arr = np.zeros(0)
        if arr.shape != (frames, 4, 4):
            raise DatasetError(
                f"{where}: {key}: expected {frames} 4x4 matrices (shape ({frames}, 4, 4)), "
                f"got shape {arr.shape}"
            )
        bad = np.argwhere(~np.isfinite(arr))
        if bad.size:
            k, i, j = (int(v) for v in bad[0])
            raise DatasetError(
                f"{where}: {key}[{k}][{i}][{j}] = {arr[k, i, j]!r}: expected finite numbers "
                f"({len(bad)} entries are NaN or infinite)"
            )


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

    @property
    def version(self) -> int:
        """``format_version`` of the dataset (1 or 2)."""
        return int(self.meta["format_version"])

    @property
    def channels(self) -> tuple[str, ...]:
        """The EXR channels of this dataset's format version."""
        return channels_for(self.version)

    def unit(self, cam: str):
        """The :class:`omniflow.geometry.rig.Unit` of camera ``cam``."""
        if cam not in ("cam1", "cam2"):
            raise DatasetError(
                f"{self.dir}: unknown camera {cam!r}; expected one of {self.cameras}"
            )
        return getattr(self.rig, cam)

    def frame_dir(self, k: int) -> Path:
        return self.dir / FRAMES_DIR / frame_name(k)

    def path(self, k: int, cam: str, ext: str = "exr") -> Path:
        """Path of frame ``k``'s file for camera ``cam`` (``ext`` "exr", "flo", "png",
        "occluded.png" or "outside.png")."""
        return self.frame_dir(k) / f"{cam}.{ext}"

    def is_done(self, k: int) -> bool:
        d = self.frame_dir(k)
        images = "camera" in self.meta
        return d.is_dir() and all(
            (d / f).is_file() for f in expected_files(self.cameras, images, self.version)
        )

    def frames_done(self) -> list[int]:
        """Indices of frames whose directory is complete."""
        return [k for k in range(self.frame_count) if self.is_done(k)]

    @property
    def complete(self) -> bool:
        return len(self.frames_done()) == self.frame_count

    def check_frame(self, k: int, cam: str) -> None:
        """:class:`DatasetError` unless camera ``cam`` of frame ``k`` is rendered and complete."""
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
        self.check_frame(k, cam)
        path = self.path(k, cam, "exr")
        chans = read_exr(path)
        missing = [c for c in self.channels if c not in chans]
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
        """Rec. 709 luminance (H, W) of frame ``k``, camera ``cam`` (:func:`grey_of`)."""
        return grey_of(self.read_frame(k, cam))

    @property
    def camera_bits(self) -> int | None:
        """Bits per sample of the recorded camera (its images are ``camN.png``); None
        for a dataset without a camera section (no camera images)."""
        cam = self.meta.get("camera")
        if not isinstance(cam, Mapping):
            return None
        bits = cam.get("bits", 8)
        if isinstance(bits, bool) or bits not in CAMERA_BITS:
            raise DatasetError(f"{self.dir / 'dataset.json'}: camera.bits = {bits!r}: "
                               f"expected one of {', '.join(map(str, CAMERA_BITS))}")  # fmt: skip
        return int(bits)

    def read_image(self, k: int, cam: str) -> NDArray[np.float32]:
        """The camera image ``camN.png`` of frame ``k`` as omniflow's grey input
        (:func:`camera_grey`): what the harness scores every method on. DatasetError
        (one line) for a dataset without camera images or an unreadable file."""
        import cv2

        self.check_frame(k, cam)
        bits = self.camera_bits
        path = self.path(k, cam, "png")
        if bits is None:
            raise DatasetError(f"{self.dir / 'dataset.json'}: no camera section, so no "
                               "camera images; read the radiance instead")  # fmt: skip
        with native_output_captured():
            pixels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if pixels is None:
            raise DatasetError(f"{path}: cannot read the camera image (missing or not a PNG)")
        unit = self.unit(cam)
        if pixels.shape[:2] != (unit.height, unit.width):
            raise DatasetError(f"{path}: image is {pixels.shape[1]}x{pixels.shape[0]}, "
                               f"dataset.json says {unit.width}x{unit.height}")  # fmt: skip
        want = np.uint8 if bits <= 8 else np.uint16
        if pixels.dtype != want:
            raise DatasetError(f"{path}: {pixels.dtype} pixels; expected {np.dtype(want).name} "
                               f"for a {bits}-bit camera")  # fmt: skip
        if pixels.ndim == 3:
            pixels = pixels[..., 2::-1]  # OpenCV's BGR(A) -> RGB
        max_dn = (1 << bits) - 1
        dn = pixels if bits <= 8 else np.rint(pixels * (max_dn / 65535.0)).astype(np.uint16)
        return camera_grey(dn, bits)

    def read_flo(self, k: int, cam: str) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """The .flo of frame ``k``, camera ``cam``: (flow (H, W, 2), valid (H, W))."""
        self.check_frame(k, cam)
        return read_flo(self.path(k, cam, "flo"))

    def read_flow_masks(self, k: int, cam: str) -> dict[str, NDArray[np.bool_]]:
        """The mask PNGs beside frame ``k``'s .flo: ``{"gt.flow.occluded": (H, W) bool,
        "gt.flow.outside": ...}`` (version 2; a version 1 dataset has none: {})."""
        self.check_frame(k, cam)
        if self.version < 2:
            return {}
        return {name: read_mask_png(self.path(k, cam, sfx)) for sfx, name in MASK_FILES.items()}

    def flo_known(self, channels: Mapping[str, NDArray]) -> NDArray[np.bool_]:
        """Where this dataset's .flo holds a flow, from the frame's channels (:func:`flo_known`)."""
        return flo_known(channels, self.version)


def open_dataset(dir: str | Path) -> Dataset:
    """Open a dataset directory for reading; :class:`DatasetError` if it is not one."""
    d = Path(dir)
    meta_path = d / META_NAME
    if not meta_path.is_file():
        raise DatasetError(f"{d}: no {META_NAME}: not an omnisim dataset directory")
    meta = load_meta(meta_path)
    try:
        rig = rig_from_dict(meta, where=str(meta_path))
    except RigError as exc:
        raise DatasetError(str(exc)) from exc
    for i, unit in enumerate((rig.cam1, rig.cam2)):
        if unit.r_m > max(unit.width, unit.height):
            raise DatasetError(
                f"{meta_path}: cameras[{i}] ({unit.name}).r_m = {unit.r_m:g} px: larger than "
                f"the {unit.width}x{unit.height} image; expected the rim radius in pixels, "
                "inside the image"
            )
    frames = meta["frames"]
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise DatasetError(f"{meta_path}: frames = {frames!r}: expected a positive integer")
    fi = meta.get("frame_interval")
    if not isinstance(fi, int | float) or not math.isfinite(fi) or fi <= 0:
        raise DatasetError(f"{meta_path}: frame_interval = {fi!r}: expected seconds > 0")
    check_poses(meta, meta_path, frames)
    return Dataset(dir=d, meta=meta, rig=rig, cameras=camera_names(meta))
