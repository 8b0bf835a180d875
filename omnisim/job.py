"""The render job: scene -> dataset directory, resumable, locally or on a Dask cluster.

:func:`render_dataset` loads the scene (a :class:`omnisim.scene.SceneError` is raised
before anything is written), builds ``dataset.json`` (:func:`build_meta`), opens the
directory with :class:`omnisim.dataset.DatasetWriter` (which writes the metadata
atomically, or checks it against an existing directory and refuses a mismatch), and
renders the frames that are not done yet, each written atomically. A killed run
restarts where it stopped. With ``scheduler`` the frames run as Dask tasks
(:mod:`omnisim.distributed`); the files are byte-identical to a local run.

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
import platform
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from omnisim.dataset import (
    CHANNELS,
    FLO_UNKNOWN,
    FLO_UNKNOWN_THRESH,
    FORMAT_NAME,
    FORMAT_VERSION,
    DatasetWriter,
)

__all__ = [
    "DEFAULT_RENDERER",
    "JobResult",
    "build_meta",
    "load_scene_for_job",
    "meta_digest",
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

    Raises ``omnisim.scene.SceneError`` for a bad scene file and
    :class:`omnisim.dataset.DatasetMismatchError` when ``out`` holds another dataset,
    both before any rendering starts.
    """
    t0 = time.perf_counter()
    overrides = dict(overrides or {})
    scene_path = Path(scene_path).resolve()
    scene = load_scene_for_job(scene_path, overrides)
    meta = build_meta(scene, overrides, renderer=renderer)
    render_fn = resolve_renderer(renderer) if scheduler is None else None
    writer = DatasetWriter(out, meta)
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
            from omnisim.distributed import render_on_cluster

            for k in render_on_cluster(
                scheduler, scene_path, overrides, todo, writer, meta, renderer, write_on
            ):
                rendered.append(k)
                bar.update(1)
                if on_frame is not None:
                    on_frame(k)
    finally:
        bar.close()
    return JobResult(
        out=Path(out),
        frames=writer.frame_count,
        rendered=rendered,
        skipped=skipped,
        seconds=time.perf_counter() - t0,
    )
