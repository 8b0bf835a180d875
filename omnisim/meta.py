"""What a render job is, apart from how it runs: the renderer, the scene, ``dataset.json``.

Shared by the local job (:mod:`omnisim.job`) and the Dask workers
(:mod:`omnisim.distributed`), which must build byte-identical metadata from the same
scene file: :func:`build_meta` is deterministic (no timestamps or host names) and
:func:`meta_digest` fingerprints it. ``dataset.json`` carries a fingerprint of every
input file (:func:`input_files`) and the versions of the packages that shape the
frames (:func:`versions`), so a resume after any of them changed is refused.

This module imports neither Mitsuba nor the scene model at import time.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import os
import platform
from collections.abc import Callable, Mapping
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from omniflow.io.dataset import (
    CHANNELS,
    FLO_UNKNOWN,
    FLO_UNKNOWN_THRESH,
    FORMAT_NAME,
    FORMAT_VERSION,
)
from omniflow.io.jsonio import jsonable
from omnisim.scene_checker import LIBRARY_PREFIX, resolve_scene_path

__all__ = [
    "DEFAULT_RENDERER",
    "VERSIONED",
    "build_meta",
    "input_files",
    "load_scene_for_job",
    "meta_digest",
    "resolve_renderer",
    "versions",
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
        full = resolve_scene_path(value, base)
        if value.startswith(LIBRARY_PREFIX):  # the same name on every machine
            name = value
        else:
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


def load_scene_for_job(path: str | Path, overrides: Mapping[str, Any] | None = None):
    """``omnisim.scene.load_scene(path, overrides)``; raises ``SceneError`` on a bad file."""
    from omnisim.scene import load_scene

    return load_scene(Path(path), dict(overrides or {}))


# -- dataset.json ----------------------------------------------------------------------


def _jsonable(obj: Any) -> Any:
    """:func:`omniflow.io.jsonio.jsonable`, arrays of more than 64 elements (an environment
    map, a texture) as a short description: too big for the metadata."""
    return jsonable(obj, max_array=64)


def versions() -> dict[str, str]:
    """Python's and each :data:`VERSIONED` distribution's version ("absent" if missing)."""
    out = {"python": platform.python_version()}
    for dist in VERSIONED:
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "absent"
    return out


def _pose_list(pose_fn: Callable[[int], Any], frames: int) -> list:
    return [np.asarray(pose_fn(k), dtype=float).reshape(4, 4).tolist() for k in range(frames)]


def _optics(scene: Any) -> dict[str, Any]:
    """``{"optics": ...}`` for a lens with a finite aperture; nothing for a pinhole (the
    default), so a pinhole dataset's metadata is what it was before lenses existed."""
    optics = _attr(scene, "optics")
    if optics is None or optics.pinhole:
        return {}
    return {"optics": optics.as_dict()}


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
        **_optics(scene),
        "flo": {"unknown_value": FLO_UNKNOWN, "unknown_threshold": FLO_UNKNOWN_THRESH},
        "versions": versions(),
    }
    return json.loads(json.dumps(meta, allow_nan=False))


def meta_digest(meta: Mapping[str, Any]) -> str:
    """SHA-256 of the metadata that determines the frames (scene path excluded)."""
    m = json.loads(json.dumps(meta))
    m.get("scene", {}).pop("path", None)
    return hashlib.sha256(json.dumps(m, sort_keys=True).encode()).hexdigest()
