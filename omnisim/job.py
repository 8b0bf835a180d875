"""The render job: scene -> dataset directory, resumable, locally or on a Dask cluster.

:func:`render_dataset` loads the scene (a :class:`omnisim.scene.SceneError` is raised
before anything is written), builds ``dataset.json`` (:func:`build_meta`), opens the
directory with :class:`omnisim.dataset.DatasetWriter` (which writes the metadata
atomically, or checks it against an existing directory and refuses a mismatch), and
renders the frames that are not done yet, each written atomically. A killed run
restarts where it stopped. With ``scheduler`` the frames run as Dask tasks
(:mod:`omnisim.distributed`); the files are byte-identical to a local run.

``dataset.json`` carries a fingerprint of every input file (``inputs.files``: the
sha256 of each mesh, texture and environment map the scene names) next to the scene
text and the resolved settings, so a resume after any of them changed is refused
with one line naming the file.

Before anything is written, :func:`preflight` estimates the memory and disk the
request needs (:data:`RENDER_BYTES_PER_PIXEL`, :data:`DISK_BYTES_PER_PIXEL`,
:data:`META_BYTES_PER_POSE`) and refuses, with one line, what this machine cannot
hold (``omnisim render --no-resource-check`` skips it). A sequence has at most
``omnisim.scene.MAX_FRAMES`` frames.

The renderer is a function ``render_frame(scene, frame) -> {cam: {channel: (H, W)}}``
named by a ``"module:function"`` string (default :data:`DEFAULT_RENDERER`), so that
Dask workers and test doubles resolve it by import.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import json
import math
import os
import platform
import shutil
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from omniflow.dataset import (
    CHANNELS,
    FLO_UNKNOWN,
    FLO_UNKNOWN_THRESH,
    FORMAT_NAME,
    FORMAT_VERSION,
)
from omnisim.dataset import DatasetWriter

__all__ = [
    "DEFAULT_RENDERER",
    "JobResult",
    "ResourceError",
    "build_meta",
    "check_variant",
    "input_files",
    "load_scene_for_job",
    "meta_digest",
    "preflight",
    "render_dataset",
    "resolve_renderer",
]

#: The Mitsuba renderer (helper D1's :func:`omnisim.render.render_frame`).
DEFAULT_RENDERER = "omnisim.render:render_frame"

#: Distributions whose versions are recorded in dataset.json (determinism is promised for
#: the same scene, seed and versions; a resume with other versions is refused).
VERSIONED = ("omniflow-testbed", "mitsuba", "drjit", "numpy", "scipy", "OpenEXR", "trimesh")


def resolve_renderer(spec: str | Callable) -> Callable:
    """The render function named by ``"package.module:function"`` (or the callable itself)."""
    if callable(spec):
        return spec
    mod_name, sep, attr = str(spec).partition(":")
    if not sep or not mod_name or not attr:
        raise ValueError(f"renderer {spec!r}: expected 'package.module:function'")
    func = getattr(importlib.import_module(mod_name), attr, None)
    if not callable(func):
        raise ValueError(f"renderer {spec!r}: {mod_name} has no function {attr!r}")
    return func


class ResourceError(ValueError):
    """The request does not fit this machine's memory or disk (:func:`preflight`)."""


#: Peak resident memory of rendering one stereo frame, bytes per image pixel (one
#: camera's W x H), above :data:`RENDER_BASE_BYTES`: Mitsuba's film and sample buffers,
#: the ground truth's float64 Dr.Jit arrays, the encoded EXR. Measured peak RSS of
#: ``render_dataset`` on scenes/default.toml, 1 frame, spp 1: 296 / 379 / 544 MiB at
#: 128 / 384 / 768 px, slopes 664 and 410 B/px; the larger, rounded up.
RENDER_BYTES_PER_PIXEL = 700
#: The render process before its first image: Python, numpy, Mitsuba, the scene.
RENDER_BASE_BYTES = 300 * 2**20
#: Disk of one stereo frame, bytes per pixel, upper bound: 2 cameras x (18 float32
#: channels before ZIP + 8 bytes of .flo).
DISK_BYTES_PER_PIXEL = 2 * (18 * 4 + 8)
#: dataset.json per frame and pose (the robot's, each object's): measured 397 B of
#: indented JSON text, and a peak memory of 4030-4400 B while it is built, parsed back
#: and written (scenes/turn_in_place.toml, 9 poses per frame, 5000 and 20000 frames:
#: 17.9 / 71.5 MB of text, peak RSS 320 / 903 MiB against 147 MiB for 1 frame).
META_BYTES_PER_POSE = 400
META_MEMORY_PER_POSE = 4400


def _available_memory() -> int:
    """Bytes of memory available to a new allocation (``MemAvailable``)."""
    try:
        import psutil

        return int(psutil.virtual_memory().available)
    except ImportError:  # pragma: no cover - psutil comes with dask[distributed]
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def _gib(n: float) -> str:
    if n >= 2**28:
        return f"{n / 2**30:.2f} GiB"
    return f"{n / 2**20:.0f} MiB" if n >= 2**20 else f"{n / 2**10:.0f} KiB"


def preflight(scene: Any, out: str | Path, *, local: bool = True) -> dict[str, int]:
    """Refuse (:class:`ResourceError`, one line) a render this machine cannot hold.

    Memory: :data:`RENDER_BYTES_PER_PIXEL` x W x H for a frame rendered here (``local``)
    plus the dataset.json being built; disk: the frames not yet on disk at
    :data:`DISK_BYTES_PER_PIXEL` plus dataset.json, against the free space of the file
    system that will hold ``out``. Returns the estimates in bytes.
    """
    w, h = int(scene.render.width), int(scene.render.height)
    frames = int(scene.frames)
    poses = frames * (1 + len(scene.objects))
    out = Path(out)
    frames_dir = out / "frames"
    done = 0
    if frames_dir.is_dir():
        done = sum(1 for p in frames_dir.iterdir() if p.name.isdigit())
    need_mem = poses * META_MEMORY_PER_POSE
    if local:
        need_mem += RENDER_BASE_BYTES + RENDER_BYTES_PER_PIXEL * w * h
    need_disk = max(frames - done, 0) * DISK_BYTES_PER_PIXEL * w * h + poses * META_BYTES_PER_POSE
    have_mem = _available_memory()
    if need_mem > have_mem:
        what = (
            f"frames = {frames} with {len(scene.objects)} objects"
            if poses * META_MEMORY_PER_POSE > RENDER_BYTES_PER_PIXEL * w * h
            else f"render.width x height = {w}x{h}"
        )
        raise ResourceError(
            f"{what}: needs about {_gib(need_mem)} of memory, this machine has "
            f"{_gib(have_mem)} available; render fewer frames or smaller images "
            "(or pass --no-resource-check)"
        )
    probe = next((p for p in (out, *out.parents) if p.exists()), Path("."))
    have_disk = shutil.disk_usage(probe).free
    if need_disk > have_disk:
        raise ResourceError(
            f"{out}: {frames - done} frames of {w}x{h} need up to {_gib(need_disk)} of disk, "
            f"{_gib(have_disk)} free there; render fewer frames or smaller images, or free "
            "space (or pass --no-resource-check)"
        )
    return {"memory": need_mem, "disk": need_disk}


def input_files(scene: Any) -> dict[str, dict[str, Any]]:
    """The files the scene reads (meshes, image textures, environment maps): path
    relative to the scene file's directory -> ``{"key", "bytes", "sha256"}``.

    Every ``path`` value under ``objects`` and ``lights`` of the parsed file counts
    (the scene checker has already made sure each one exists).
    """
    base = Path(scene.path).resolve().parent
    data = _attr(scene, "data", {}) or {}
    found: list[tuple[str, str]] = []

    def walk(node: Any, key: str) -> None:
        if isinstance(node, Mapping):
            for k, v in node.items():
                sub = f"{key}.{k}" if key else str(k)
                if k == "path" and isinstance(v, str):
                    found.append((sub, v))
                else:
                    walk(v, sub)
        elif isinstance(node, list):
            for i, v in enumerate(node):
                walk(v, f"{key}[{i}]")

    for top in ("objects", "lights"):
        walk(data.get(top), top)
    files: dict[str, dict[str, Any]] = {}
    for key, value in found:
        p = Path(value)
        full = p if p.is_absolute() else base / p
        name = os.path.relpath(full.resolve(), base) if not p.is_absolute() else str(full)
        if name in files:
            continue
        digest = hashlib.sha256()
        size = 0
        with open(full, "rb") as fh:
            while chunk := fh.read(1 << 20):
                digest.update(chunk)
                size += len(chunk)
        files[name] = {"key": key, "bytes": size, "sha256": digest.hexdigest()}
    return files


def check_variant(scene: Any) -> None:
    """Raise ``SceneError`` naming ``render.variant`` when Mitsuba cannot use it here
    (``cuda_ad_rgb`` without a CUDA device, say), before anything is written."""
    from omnisim.scene import SceneError
    from omnisim.sensor import ensure_mitsuba

    variant = str(scene.render.variant)
    try:
        ensure_mitsuba(variant)
    except ModuleNotFoundError:
        raise  # Mitsuba itself is missing: the sim extra (reported by the command)
    except Exception as exc:  # Dr.Jit raises ImportError for a backend it cannot start
        import mitsuba

        avail = [v for v in mitsuba.variants() if v.endswith("_rgb") and "_ad_" in v]
        raise SceneError(
            f"{scene.path}: render.variant = {variant!r}: Mitsuba cannot use it on this "
            f"machine ({' '.join(str(exc).split())[:120]}); expected one of {avail} that "
            "works here, e.g. 'llvm_ad_rgb'"
        ) from exc


def load_scene_for_job(path: str | Path, overrides: Mapping[str, Any] | None = None):
    """``omnisim.scene.load_scene(path, overrides)``; raises ``SceneError`` on a bad file."""
    from omnisim.scene import load_scene

    return load_scene(Path(path), dict(overrides or {}))


# -- dataset.json ------------------------------------------------------------------------


def _jsonable(obj: Any) -> Any:
    """A JSON-safe copy: dataclasses -> dicts, arrays -> lists, paths -> str, floats finite."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        if obj.size > 64:  # an image (environment map, texture): too big for the metadata
            return f"<array {obj.dtype} {list(obj.shape)}>"
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return _jsonable(obj.item())
    if isinstance(obj, bool | int | str) or obj is None:
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else str(obj)
    if isinstance(obj, Path):
        return str(obj)
    return repr(obj) if not hasattr(obj, "isoformat") else obj.isoformat()


def _versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for dist in VERSIONED:
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "absent"
    return out


def _pose_list(pose_fn: Callable[[int], Any], frames: int) -> list:
    return [np.asarray(pose_fn(k), dtype=float).reshape(4, 4).tolist() for k in range(frames)]


def _attr(obj: Any, name: str, default: Any = None) -> Any:
    if isinstance(obj, Mapping):
        return obj.get(name, default)
    return getattr(obj, name, default)


def build_meta(
    scene: Any,
    overrides: Mapping[str, Any] | None = None,
    *,
    renderer: str = DEFAULT_RENDERER,
) -> dict[str, Any]:
    """The content of ``dataset.json`` for ``scene`` (see docs/dataset_format.md).

    Deterministic: no timestamps or host names, so a resumed or distributed run
    builds the same metadata and :func:`omnisim.dataset.compare_meta` can check it.
    """
    path = Path(scene.path).resolve()
    source = _attr(scene, "source")
    if not isinstance(source, str):
        source = path.read_text()
    frames = int(scene.frames)
    render = _jsonable(scene.render)
    seed = _attr(scene.render, "seed")
    objects = []
    for obj in scene.objects:
        objects.append(
            {
                "id": int(obj.id),
                "name": str(obj.name),
                "kind": str(_attr(obj, "kind", "")),
                "material": _jsonable(_attr(obj, "material")),
                "poses": _pose_list(obj.pose, frames),
            }
        )
    meta: dict[str, Any] = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "scene": {
            "name": str(scene.name),
            "description": _jsonable(_attr(scene, "description", "")),
            "path": str(path),
            "sha256": hashlib.sha256(source.encode("utf-8")).hexdigest(),
            "source": source,
            "overrides": _jsonable(dict(overrides or {})),
            "data": _jsonable(_attr(scene, "data", {})),
        },
        "inputs": {"files": input_files(scene)},
        **scene.rig.to_dict(),
        "frames": frames,
        "frame_interval": float(scene.frame_interval),
        "render": render,
        "seed": _jsonable(seed),
        "renderer": renderer,
        "robot": {"poses": _pose_list(scene.robot.pose, frames)},
        "objects": objects,
        "lights": _jsonable(list(_attr(scene, "lights", []) or [])),
        "channels": list(CHANNELS),
        **({"camera": scene.camera.to_dict()} if _attr(scene, "camera") is not None else {}),
        "flo": {"unknown_value": FLO_UNKNOWN, "unknown_threshold": FLO_UNKNOWN_THRESH},
        "versions": _versions(),
    }
    return json.loads(json.dumps(meta, allow_nan=False))


def meta_digest(meta: Mapping[str, Any]) -> str:
    """SHA-256 of the metadata that determines the frames (scene path excluded)."""
    m = json.loads(json.dumps(meta))
    m.get("scene", {}).pop("path", None)
    return hashlib.sha256(json.dumps(m, sort_keys=True).encode()).hexdigest()


# -- the job -----------------------------------------------------------------------------


@dataclass
class JobResult:
    """What :func:`render_dataset` did."""

    out: Path
    frames: int
    rendered: list[int]
    skipped: list[int]
    seconds: float


def _progress(total: int, initial: int, enabled: bool):
    from tqdm import tqdm

    return tqdm(
        total=total,
        initial=initial,
        unit="frame",
        desc="omnisim render",
        disable=not enabled,
        dynamic_ncols=True,
        smoothing=0.3,
    )


def render_dataset(
    scene_path: str | Path,
    out: str | Path,
    overrides: Mapping[str, Any] | None = None,
    *,
    renderer: str = DEFAULT_RENDERER,
    scheduler: str | Any | None = None,
    write_on: str = "client",
    progress: bool = True,
    stop_after: int | None = None,
    on_frame: Callable[[int], None] | None = None,
    resource_check: bool = True,
    scheduler_timeout: float | None = None,
) -> JobResult:
    """Render the scene at ``scene_path`` into dataset directory ``out`` (resumable).

    Parameters
    ----------
    overrides : dotted scene keys -> values, passed to ``load_scene`` (``frames``,
        ``render.width``, ``render.height``, ``render.spp``, ``render.seed``, ...).
    renderer : ``"module:function"`` of the render function.
    scheduler : a Dask scheduler address (``"tcp://host:8786"``) or a
        ``distributed.Client``; frames then run as Dask tasks.
    write_on : with a scheduler, ``"client"`` (workers return encoded files, this
        process writes them; no shared file system needed) or ``"worker"`` (workers
        write into ``out``, which must be on a shared file system).
    stop_after : render at most this many frames, then return (tests, batches).
    on_frame : called with each frame index once it is on disk.
    resource_check : run :func:`preflight` (memory and disk against this machine).
    scheduler_timeout : seconds to wait for the scheduler and its workers
        (default :data:`omnisim.distributed.SCHEDULER_TIMEOUT`).

    Raises ``omnisim.scene.SceneError`` for a bad scene file (or a Mitsuba variant
    this machine cannot run), :class:`ResourceError` from :func:`preflight`,
    :class:`omnisim.dataset.DatasetMismatchError` when ``out`` holds another dataset
    (or one made from other input files) and
    :class:`omnisim.dataset.DatasetLockedError` when another process writes it, all
    before any rendering starts. If the run fails before its first frame is on disk,
    what it created in ``out`` is removed again.
    """
    t0 = time.perf_counter()
    overrides = dict(overrides or {})
    scene_path = Path(scene_path).resolve()
    scene = load_scene_for_job(scene_path, overrides)
    if resource_check:
        preflight(scene, out, local=scheduler is None)
    render_fn = resolve_renderer(renderer) if scheduler is None else None
    if scheduler is None and renderer == DEFAULT_RENDERER:
        check_variant(scene)
    meta = build_meta(scene, overrides, renderer=renderer)
    writer = DatasetWriter(out, meta)
    try:
        return _render_frames(
            writer,
            scene,
            scene_path,
            overrides,
            meta,
            renderer,
            render_fn,
            scheduler,
            write_on=write_on,
            progress=progress,
            stop_after=stop_after,
            on_frame=on_frame,
            t0=t0,
            timeout=scheduler_timeout,
        )
    except BaseException:
        writer.abandon()  # removes only what this run created, and only before frame 0
        raise
    finally:
        writer.close()


def _render_frames(
    writer,
    scene,
    scene_path,
    overrides,
    meta,
    renderer,
    render_fn,
    scheduler,
    *,
    write_on,
    progress,
    stop_after,
    on_frame,
    t0,
    timeout,
) -> JobResult:
    """The frame loop of :func:`render_dataset` (local or on a Dask cluster)."""
    todo = writer.todo_frames()
    skipped = [k for k in range(writer.frame_count) if k not in set(todo)]
    if stop_after is not None:
        todo = todo[: max(0, int(stop_after))]
    rendered: list[int] = []
    bar = _progress(writer.frame_count, len(skipped), progress and bool(todo))
    try:
        if scheduler is None:
            assert render_fn is not None
            for k in todo:
                frame = render_fn(scene, k)
                writer.write_frame(k, frame)
                rendered.append(k)
                bar.update(1)
                if on_frame is not None:
                    on_frame(k)
        else:
            from omnisim.distributed import SCHEDULER_TIMEOUT, render_on_cluster

            for k in render_on_cluster(
                scheduler,
                scene_path,
                overrides,
                todo,
                writer,
                meta,
                renderer,
                write_on,
                timeout=SCHEDULER_TIMEOUT if timeout is None else float(timeout),
            ):
                rendered.append(k)
                bar.update(1)
                if on_frame is not None:
                    on_frame(k)
    finally:
        bar.close()
    return JobResult(
        out=writer.dir,
        frames=writer.frame_count,
        rendered=rendered,
        skipped=skipped,
        seconds=time.perf_counter() - t0,
    )
