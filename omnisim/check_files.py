"""Do a dataset's per-camera files decode? The camera images, mask PNGs and ``.flo`` files.

``omnisim check`` reports what this finds as its ``files`` check; ``omnisim export``
refuses a camera image that does not pass (it would copy it byte for byte). A file is
sound when it is:

``camK.png`` (dataset.json has a ``camera`` section)
    a complete PNG (signature, IHDR, ends with the IEND chunk) that OpenCV decodes to
    the camera's W x H with 3 channels, 8-bit for an 8-bit camera, else 16-bit.
``camK.occluded.png``, ``camK.outside.png`` (format version 2)
    a complete PNG that decodes to W x H, one 8-bit channel.
``camK.flo``
    a Middlebury ``.flo`` (magic, header, length) of W x H whose every value is finite
    (unknown flow is stored as 1e10, never NaN or infinity).

The header's size is compared before decoding, so a PNG that claims a huge image is
refused without allocating it.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from omniflow.io.dataset import MASK_FILES, Dataset, DatasetError, read_flo
from omniflow.io.imageio import native_output_captured
from omnisim.camera import dataset_camera

__all__ = ["camera_png_problem", "dataset_file_problems", "flo_problem", "png_problem"]

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: The last 12 bytes of every complete PNG: the empty IEND chunk and its CRC.
_IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"


def png_problem(path: Path, width: int, height: int, channels: int, dtype) -> str | None:
    """What is wrong with the PNG ``path`` (expected ``width`` x ``height``, ``channels``
    channels of ``dtype``), or None when it is sound."""
    import cv2

    try:
        data = path.read_bytes()
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    if not data.startswith(_SIGNATURE) or data[12:16] != b"IHDR" or len(data) < 33:
        return f"not a PNG ({len(data)} bytes, no PNG signature and header)"
    w, h = struct.unpack(">II", data[16:24])
    if (w, h) != (width, height):
        return f"is {w}x{h}; expected {width}x{height} (the dataset's image size)"
    if not data.endswith(_IEND):
        return f"truncated ({len(data)} bytes, no IEND chunk at the end)"
    with native_output_captured() as native:
        native.echo = False  # libpng's own complaint goes into the message, not stderr
        try:
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        except cv2.error:  # OpenCV raises on some malformed headers
            img = None
    if img is None:
        said = f": {native[0]}" if native else ""
        return f"does not decode as a PNG{said}"
    got = 1 if img.ndim == 2 else img.shape[2]
    if got != channels or img.dtype != np.dtype(dtype):
        return (
            f"holds {got} channel(s) of {img.dtype}; expected {channels} of {np.dtype(dtype).name}"
        )
    return None


def flo_problem(path: Path, width: int, height: int) -> str | None:
    """What is wrong with the ``.flo`` file ``path`` (expected ``width`` x ``height``,
    every value finite), or None when it is sound."""
    try:
        flow, _ = read_flo(path)
    except DatasetError as exc:
        return str(exc).removeprefix(f"{path}: ")
    h, w = flow.shape[:2]
    if (w, h) != (width, height):
        return f"is {w}x{h}; expected {width}x{height} (the dataset's image size)"
    bad = int((~np.isfinite(flow)).sum())
    if bad:
        return (
            f"holds {bad} non-finite values (NaN or infinity); expected finite flow, "
            "1e10 where it is unknown"
        )
    return None


def _camera_dtype(ds: Dataset):
    model = dataset_camera(ds)
    return None if model is None else model.dtype


def camera_png_problem(ds: Dataset, k: int, cam: str) -> str | None:
    """What is wrong with frame ``k``'s camera image ``cam.png``, or None when it is sound
    or the dataset has no camera images."""
    dtype = _camera_dtype(ds)
    if dtype is None:
        return None
    unit = ds.unit(cam)
    return png_problem(ds.path(k, cam, "png"), unit.width, unit.height, 3, dtype)


def dataset_file_problems(ds: Dataset, frames: Iterable[int]) -> tuple[dict[Path, str], int]:
    """``({path: what is wrong}, files looked at)`` over the camera PNGs, mask PNGs and
    ``.flo`` files of ``frames`` (module docstring)."""
    dtype = _camera_dtype(ds)
    problems: dict[Path, str] = {}
    n = 0
    for k in frames:
        for cam in ds.cameras:
            unit = ds.unit(cam)
            w, h = unit.width, unit.height
            flo = ds.path(k, cam, "flo")
            found = {flo: flo_problem(flo, w, h)}
            if dtype is not None:
                png = ds.path(k, cam, "png")
                found[png] = png_problem(png, w, h, 3, dtype)
            if ds.version >= 2:
                for sfx in MASK_FILES:
                    mask = ds.path(k, cam, sfx)
                    found[mask] = png_problem(mask, w, h, 1, np.uint8)
            n += len(found)
            problems.update({p: why for p, why in found.items() if why is not None})
    return problems, n
