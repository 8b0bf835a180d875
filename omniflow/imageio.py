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
name in the destination folder and moved into place with :func:`os.replace`, so
a reader never sees a half-written file.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterator, Mapping
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omniflow.conventions import LUMA_WEIGHTS

__all__ = [
    "ImageError",
    "atomic_output",
    "atomic_write_bytes",
    "atomic_write_text",
    "check_finite",
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


# -- atomic writes -------------------------------------------------------------


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success move it onto ``path``.

    The temporary name keeps the suffix of ``path`` (so writers that choose the
    format by extension, such as ``cv2.imwrite``, still work). If the block
    raises, the temporary file is removed and ``path`` is left untouched.

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
    tmp = path.with_name(f".{path.stem}.{secrets.token_hex(4)}.partial{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; return the path."""
    with atomic_output(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically; return the path."""
    return atomic_write_bytes(path, text.encode("utf-8"))


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


def read_exr_channels(path: str | os.PathLike) -> dict[str, NDArray[np.float32]]:
    """All channels of an OpenEXR file by name (``R``, ``G``, ``B``, ``gt.r``, ...).

    Each value is a float32 array of shape (H, W).
    """
    path = Path(path)
    _require_file(path)
    import OpenEXR

    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            chans = {name: np.asarray(ch.pixels) for name, ch in exr.channels().items()}
    except Exception as exc:  # the bindings raise RuntimeError / OSError variants
        raise ImageError(f"{path}: cannot be read as OpenEXR: {_one_line(exc)}") from exc
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

    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ImageError(
            f"{path}: cannot be read as an image (expected PNG, 16-bit PNG, JPEG or EXR)"
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
    with atomic_output(Path(path).with_suffix(".png")) as tmp:
        if not cv2.imwrite(str(tmp), arr):
            raise ImageError(f"{path}: OpenCV could not write the PNG")
    return Path(path).with_suffix(".png")


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


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text or type(exc).__name__
