"""``omnisim export``: a dataset in the layouts other optical-flow tools read.

``omnisim export DATASET --format sintel|kitti|png --out OUT`` writes, from a complete
dataset (``docs/dataset_format.md``), files that OpenCV, the MPI-Sintel and KITTI
loaders (and the many training codes that copy them) read without omnisim:

``sintel`` (the MPI-Sintel training layout; one "scene" folder per camera)::

    OUT/README.txt                                  what is where, the source, the exposure
    OUT/training/clean/<scene>_<cam>/frame_0001.png      8-bit sRGB of the radiance, frames 1..N
    OUT/training/final/<scene>_<cam>/frame_0001.png      the camera model's image, when the
                                                         dataset has one (camK.png), else absent
    OUT/training/flow/<scene>_<cam>/frame_0001.flo       flow frame_0001 -> frame_0002 (N - 1)
    OUT/training/occlusions/<scene>_<cam>/frame_0001.png 255: hidden at t + 1 (gt.flow.occluded)
    OUT/training/outside/<scene>_<cam>/frame_0001.png    255: off the mirror at t + 1
    OUT/training/invalid/<scene>_<cam>/frame_0001.png    255: no flow (nothing hit, no next
                                                         position); the .flo holds 0 there
    OUT/training/depth/<scene>_<cam>/frame_0001.dpt      range gt.r (m), Sintel .dpt; 0: no hit
    OUT/training/segmentation/<scene>_<cam>/frame_0001.png  gt.object, indexed PNG (frames 1..N)

``kitti`` (the KITTI 2015 flow layout; one root per camera; pair k = frames k, k + 1)::

    OUT/README.txt
    OUT/<cam>/training/image_2/000000_10.png   8-bit sRGB of frame k; 000000_11.png frame k + 1
    OUT/<cam>/training/flow_occ/000000_10.png  16-bit flow, every defined flow valid
    OUT/<cam>/training/flow_noc/000000_10.png  16-bit flow, valid only where seen at t + 1
    OUT/<cam>/training/obj_map/000000_10.png   gt.object of frame k, indexed PNG

``png`` (images for viewers)::

    OUT/README.txt
    OUT/<cam>/image/000000.png          sRGB of the radiance, 8 or 16 bit (``--bits``)
    OUT/<cam>/camera/000000.png         the camera model's image, when the dataset has one
    OUT/<cam>/segmentation/000000.png   gt.object, indexed PNG

The tone map is one exposure for the whole export: the 99th percentile of frame 0's
Rec. 709 luminance on the mirror (both cameras, ``gt.valid``) maps to 1, then the sRGB
transfer function and rounding. Segmentation: a palette PNG whose pixel values are the
``gt.object`` ids (0: nothing hit, black), colours from matplotlib's ``tab20``; ids above
255 do not fit a palette: then a 16-bit greyscale PNG of the ids.

KITTI flow PNG: 16-bit RGB, R = dx * 64 + 2^15, G = dy * 64 + 2^15, B = 1 where valid
(stored by OpenCV in BGR order, as the devkit reads it); a flow with |component| >= 512 px
does not fit and is marked invalid.

Everything is written into a hidden temporary directory beside OUT and renamed to OUT
at the end; OUT must not exist (or be an empty directory). Refused as bad input (one
line naming the file, exit 2, no OUT): radiance holding NaN or infinity (the tone map
and the integer cast would turn it into garbage), a camera image ``camK.png`` that does
not decode to the dataset's size and bit depth (:mod:`omnisim.check_files`).
The export needs a complete dataset of format version 2 for ``sintel`` and ``kitti``
(version 1 has no occlusion masks); ``png`` reads either version.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import io
import os
import re
import shutil
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from omniflow.io.dataset import Dataset, DatasetError, grey_of, open_dataset
from omnisim.check_files import camera_png_problem
from omnisim.dataset import flo_bytes

__all__ = [
    "FORMATS",
    "ExportError",
    "add_export_parser",
    "dpt_bytes",
    "export_dataset",
    "kitti_flow_png",
    "linear_to_srgb",
    "run_cli",
    "segmentation_png",
]

FORMATS = ("sintel", "kitti", "png")
#: Sintel's .dpt tag: the same float32 202021.25 ("PIEH") as the .flo magic.
DPT_TAG = 202021.25
#: The luminance percentile of frame 0 on the mirror that the tone map maps to white.
EXPOSURE_PERCENTILE = 99.0


class ExportError(DatasetError):
    """The dataset cannot be exported as asked (bad input: the message says why)."""


# -- encoders (bytes) -----------------------------------------------------------------------


def linear_to_srgb(x: NDArray) -> NDArray:
    """The sRGB transfer function (IEC 61966-2-1) of linear values, clipped to [0, 1]."""
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _png(img: NDArray) -> bytes:
    """PNG bytes of a uint8/uint16 (H, W) or (H, W, 3) RGB array (OpenCV writes BGR)."""
    import cv2

    if img.ndim == 3:
        img = np.ascontiguousarray(img[..., ::-1])
    ok, buf = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover - OpenCV fails only on unsupported dtypes
        raise ExportError(f"cannot encode a {img.dtype} {img.shape} PNG")
    return buf.tobytes()


def _mask_png(mask: NDArray) -> bytes:
    return _png(np.where(mask, 255, 0).astype(np.uint8))


def dpt_bytes(depth: NDArray) -> bytes:
    """MPI-Sintel .dpt: float32 tag 202021.25, int32 width, int32 height, then the float32
    depth row by row, little-endian (the layout of the Sintel SDK's ``depth_read``)."""
    depth = np.asarray(depth, "<f4")
    h, w = depth.shape
    head = np.array([DPT_TAG], "<f4").tobytes() + np.array([w, h], "<i4").tobytes()
    return head + depth.tobytes()


def kitti_flow_png(dx: NDArray, dy: NDArray, valid: NDArray) -> tuple[bytes, int]:
    """KITTI 16-bit flow PNG bytes and the number of valid pixels dropped because their
    flow does not fit the encoding (|component| >= 512 px)."""
    dx = np.asarray(dx, np.float64)
    dy = np.asarray(dy, np.float64)
    valid = np.asarray(valid, bool)
    fits = (np.abs(dx) < 512) & (np.abs(dy) < 512)
    ok = valid & fits
    img = np.zeros((*dx.shape, 3), np.uint16)
    img[..., 0] = np.where(ok, np.rint(dx * 64 + 2**15), 2**15)
    img[..., 1] = np.where(ok, np.rint(dy * 64 + 2**15), 2**15)
    img[..., 2] = ok
    return _png(img), int((valid & ~fits).sum())


def segmentation_png(obj: NDArray) -> bytes:
    """``gt.object`` ids as an indexed (palette) PNG; ids > 255: 16-bit greyscale PNG."""
    ids = np.rint(np.asarray(obj, np.float64)).astype(np.int64)
    if ids.min(initial=0) < 0:
        raise ExportError(f"gt.object holds a negative id {ids.min()}")
    if ids.max(initial=0) > 255:
        return _png(ids.astype(np.uint16))
    from matplotlib import colormaps
    from PIL import Image

    tab = (np.asarray(colormaps["tab20"].colors) * 255).round().astype(np.uint8)
    palette = np.zeros((256, 3), np.uint8)
    palette[1:] = tab[np.arange(255) % len(tab)]
    img = Image.fromarray(ids.astype(np.uint8), mode="P")
    img.putpalette(palette.ravel().tolist())
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return buf.getvalue()


# -- the export -------------------------------------------------------------------------------


def _radiance(ds: Dataset, k: int, cam: str) -> dict[str, NDArray]:
    """Frame ``k``'s channels; :class:`ExportError` naming the EXR when its radiance holds
    NaN or infinity (the tone map and the 8/16-bit cast would turn it into garbage)."""
    ch = ds.read_frame(k, cam)
    rgb = np.stack([ch["R"], ch["G"], ch["B"]])
    nan, inf = int(np.isnan(rgb).sum()), int(np.isinf(rgb).sum())
    if nan or inf:
        raise ExportError(
            f"{ds.path(k, cam)}: the radiance R, G, B holds {nan} NaN and {inf} infinite "
            "values; expected finite linear radiance (render the frame again)"
        )
    return ch


def _exposure(ds: Dataset) -> float:
    """Scale that maps :data:`EXPOSURE_PERCENTILE` of frame 0's luminance on the mirror to 1."""
    lum = []
    for cam in ds.cameras:
        ch = _radiance(ds, 0, cam)
        lum.append(grey_of(ch)[ch["gt.valid"] > 0.5])
    values = np.concatenate(lum)
    white = float(np.percentile(values, EXPOSURE_PERCENTILE)) if values.size else 0.0
    return 1.0 / white if white > 0 else 1.0


def _image(ds: Dataset, k: int, cam: str, scale: float, bits: int) -> bytes:
    ch = _radiance(ds, k, cam)
    rgb = np.stack([ch["R"], ch["G"], ch["B"]], axis=-1) * scale
    top = 2**bits - 1
    return _png(np.rint(linear_to_srgb(rgb) * top).astype(np.uint8 if bits == 8 else np.uint16))


def _camera_png(ds: Dataset, k: int, cam: str) -> bytes | None:
    """The camera model's image of the frame (``camK.png``), when the dataset has one;
    :class:`ExportError` naming it when it does not decode (:mod:`omnisim.check_files`)."""
    p = ds.path(k, cam, "png")
    if not p.is_file():
        return None
    problem = camera_png_problem(ds, k, cam)
    if problem is not None:
        raise ExportError(f"{p}: {problem}; expected the camera model's image of the frame")
    return p.read_bytes()


def _scene_name(ds: Dataset) -> str:
    name = str(ds.meta.get("scene", {}).get("name", "") or "scene")
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)


def _sintel(ds: Dataset, put: Callable[[str, bytes], None], scale: float) -> None:
    scene = _scene_name(ds)
    n = ds.frame_count
    for cam in ds.cameras:
        folder = f"{scene}_{cam}"
        for k in range(n):
            name = f"frame_{k + 1:04d}"
            ch = ds.read_frame(k, cam)
            put(f"training/clean/{folder}/{name}.png", _image(ds, k, cam, scale, 8))
            cam_png = _camera_png(ds, k, cam)
            if cam_png is not None:
                put(f"training/final/{folder}/{name}.png", cam_png)
            depth = np.where(ch["gt.valid"] > 0.5, ch["gt.r"], 0.0)
            put(f"training/depth/{folder}/{name}.dpt", dpt_bytes(depth))
            put(f"training/segmentation/{folder}/{name}.png", segmentation_png(ch["gt.object"]))
            if k + 1 >= n:
                continue  # Sintel: N images, N - 1 flows
            known = ds.flo_known(ch)
            # Sintel's .flo files are finite everywhere (the invalid mask says where to
            # ignore them): 0 where no flow exists, not the dataset .flo's 1e10
            dx, dy = (np.where(known, ch[f"gt.flow.{c}"], 0.0) for c in ("dx", "dy"))
            put(f"training/flow/{folder}/{name}.flo", flo_bytes(dx, dy))
            put(f"training/occlusions/{folder}/{name}.png", _mask_png(ch["gt.flow.occluded"] > 0.5))
            put(f"training/outside/{folder}/{name}.png", _mask_png(ch["gt.flow.outside"] > 0.5))
            put(f"training/invalid/{folder}/{name}.png", _mask_png(~known))


def _kitti(ds: Dataset, put: Callable[[str, bytes], None], scale: float) -> list[str]:
    notes = []
    for cam in ds.cameras:
        images = {k: _image(ds, k, cam, scale, 8) for k in range(ds.frame_count)}
        dropped = 0
        for k in range(ds.frame_count - 1):
            ch = ds.read_frame(k, cam)
            root = f"{cam}/training"
            put(f"{root}/image_2/{k:06d}_10.png", images[k])
            put(f"{root}/image_2/{k:06d}_11.png", images[k + 1])
            occ, n_occ = kitti_flow_png(ch["gt.flow.dx"], ch["gt.flow.dy"], ds.flo_known(ch))
            noc, _ = kitti_flow_png(ch["gt.flow.dx"], ch["gt.flow.dy"], ch["gt.flow.valid"] > 0.5)
            dropped += n_occ
            put(f"{root}/flow_occ/{k:06d}_10.png", occ)
            put(f"{root}/flow_noc/{k:06d}_10.png", noc)
            put(f"{root}/obj_map/{k:06d}_10.png", segmentation_png(ch["gt.object"]))
        notes.append(f"{cam}: {dropped} flow_occ pixels with |flow| >= 512 px marked invalid")
    return notes


def _png_layout(ds: Dataset, put: Callable[[str, bytes], None], scale: float, bits: int) -> None:
    for cam in ds.cameras:
        for k in range(ds.frame_count):
            put(f"{cam}/image/{k:06d}.png", _image(ds, k, cam, scale, bits))
            cam_png = _camera_png(ds, k, cam)
            if cam_png is not None:
                put(f"{cam}/camera/{k:06d}.png", cam_png)
            ch = ds.read_frame(k, cam)
            put(f"{cam}/segmentation/{k:06d}.png", segmentation_png(ch["gt.object"]))


def _readme(ds: Dataset, fmt: str, scale: float, bits: int, notes: list[str]) -> str:
    doc = (__doc__ or "").split("\n\n")
    layout = next((i for i, p in enumerate(doc) if p.startswith(f"``{fmt}``")), None)
    text = [
        f"omnisim export --format {fmt} of {ds.dir.resolve()}",
        f"scene {ds.meta.get('scene', {}).get('name', '')!r}, format_version {ds.version}, "
        f"{ds.frame_count} frames, cameras {', '.join(ds.cameras)}",
        f"tone map: linear radiance x {scale!r}, clipped, sRGB, {bits}-bit "
        "(the 99th percentile of frame 0's luminance on the mirror maps to white)",
        "flow: pixels, x right, y down, frame t -> t + 1, as the dataset's gt.flow.dx/dy; "
        "see docs/dataset_format.md of omniflow-testbed for the geometry (rig, cameras)",
        *notes,
        "",
    ]
    if layout is not None:
        text += [doc[layout], doc[layout + 1], ""]
    return "\n".join(text)


#: errno values of a machine that refused the export (exit 1), not of a bad --out (exit 2).
_MACHINE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO}


def _refused(exc: OSError, out: Path, doing: str) -> OSError:
    """``exc`` naming ``out`` (a write to a full disk names no file) and what was written;
    the export is removed, so OUT is not there afterwards."""
    reason = exc.strerror or str(exc)
    return OSError(exc.errno, f"{reason} while {doing}; nothing of the export was kept", str(out))


def export_dataset(dataset: str | Path, out: str | Path, fmt: str, *, bits: int = 8) -> Path:
    """Export the complete dataset ``dataset`` to the new directory ``out`` as ``fmt``.

    Raises :class:`ExportError` (a :class:`DatasetError`) on bad input: not a dataset,
    incomplete, a version 1 dataset for ``sintel``/``kitti``, ``out`` not empty.
    """
    if fmt not in FORMATS:
        raise ExportError(f"--format {fmt!r}: expected one of {', '.join(FORMATS)}")
    if bits not in (8, 16):
        raise ExportError(f"--bits {bits!r}: expected 8 or 16")
    ds = open_dataset(dataset)
    missing = sorted(set(range(ds.frame_count)) - set(ds.frames_done()))
    if missing:
        raise ExportError(
            f"{ds.dir}: frames {missing[:5]}{' ...' if len(missing) > 5 else ''} of "
            f"{ds.frame_count} are not rendered; finish the render (run it again) first"
        )
    if fmt in ("sintel", "kitti") and ds.version < 2:
        raise ExportError(
            f"{ds.dir}: format_version {ds.version} has no occlusion masks; --format {fmt} "
            "needs version 2 (render it again with this omnisim)"
        )
    if fmt == "kitti" and ds.frame_count < 2:
        raise ExportError(f"{ds.dir}: 1 frame: --format kitti needs pairs of frames")
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ExportError(f"{out}: exists and is not an empty directory; choose another --out")
    tmp = out.parent / f".{out.name}.tmp.{os.getpid()}.{uuid.uuid4().hex[:8]}"
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp.mkdir()
    except OSError as exc:
        if exc.errno in _MACHINE_ERRNOS:
            raise _refused(exc, out, "creating it") from exc
        raise ExportError(f"{out}: cannot create the output directory: {exc}") from exc

    def put(rel: str, data: bytes) -> None:
        p = tmp / rel
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_bytes(data)
        except OSError as exc:
            raise _refused(exc, out, f"writing {rel}") from exc

    try:
        scale = _exposure(ds)
        notes: list[str] = []
        if fmt == "sintel":
            _sintel(ds, put, scale)
        elif fmt == "kitti":
            notes = _kitti(ds, put, scale)
        else:
            _png_layout(ds, put, scale, bits)
        put("README.txt", _readme(ds, fmt, scale, bits if fmt == "png" else 8, notes).encode())
        if out.exists():
            out.rmdir()  # empty (checked above)
        os.rename(tmp, out)
    except BaseException:
        with contextlib.suppress(OSError):
            shutil.rmtree(tmp)
        raise
    return out


# -- the command ------------------------------------------------------------------------------


def add_export_parser(sub) -> argparse.ArgumentParser:
    """Add ``export`` to the ``omnisim`` command's subparsers."""
    e = sub.add_parser(
        "export",
        help="write a dataset as Sintel, KITTI or PNG files other tools read",
        description="Export a complete dataset DIR into a new directory OUT: "
        "sintel (.flo, occlusion/outside/invalid mask PNGs, .dpt range, indexed "
        "segmentation, sRGB images), kitti (16-bit flow PNGs flow_occ/flow_noc, images, "
        "obj_map), png (images at --bits 8 or 16, segmentation). See omnisim/export.py.",
    )
    e.add_argument("dir", type=Path, metavar="DIR", help="dataset directory")
    e.add_argument("--format", "-f", required=True, choices=FORMATS, help="the layout")
    e.add_argument("--out", "-o", type=Path, required=True, metavar="OUT", help="new directory")
    e.add_argument(
        "--bits", type=int, choices=(8, 16), default=8, help="png: image bit depth (default 8)"
    )
    return e


def run_cli(args: argparse.Namespace) -> int:
    """Run ``omnisim export`` from parsed arguments; bad input raises :class:`ExportError`."""
    out = export_dataset(args.dir, args.out, args.format, bits=args.bits)
    files = sum(1 for p in out.rglob("*") if p.is_file())
    print(f"{out}: {args.format} export of {args.dir}, {files} files")
    return 0
