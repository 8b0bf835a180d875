"""The render job: scene -> dataset directory, resumable, locally or on a Dask cluster.

:func:`render_dataset` loads the scene (a :class:`omnisim.scene.SceneError` is raised
before anything is written), builds ``dataset.json`` (:func:`omnisim.meta.build_meta`), opens the
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

import inspect
import os
import shutil
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omniflow import interrupts
from omnisim.dataset import DatasetWriter

# What the job is (renderer, scene, dataset.json) lives in omnisim.meta, shared with the
# Dask workers; re-exported here for the old import paths.
from omnisim.meta import (
    DEFAULT_RENDERER,
    VERSIONED,
    build_meta,
    input_files,
    load_scene_for_job,
    meta_digest,
    resolve_renderer,
)

__all__ = [
    "DEFAULT_RENDERER",
    "VERSIONED",
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
        if scheduler is None:  # under the lock, every temporary is this run's (or a dead
            writer.remove_temporaries()  # run's); one an interruption cut short goes too
        writer.abandon()  # removes only what this run created, and only before frame 0
        raise
    finally:
        writer.close()


def _takes_timings(render_fn: Callable) -> bool:
    """Whether the renderer accepts ``timings=`` (the Mitsuba one does; test doubles may not)."""
    try:
        return "timings" in inspect.signature(render_fn).parameters
    except (TypeError, ValueError):  # a builtin or C callable without a signature
        return False


def _timing_context() -> dict[str, Any]:
    """What the seconds in dataset.json's ``timing`` depend on: CPUs, threads, load."""
    ctx: dict[str, Any] = {"cpus": os.cpu_count()}
    try:
        import drjit as dr

        ctx["drjit_threads"] = int(dr.thread_count())
    except ImportError:  # a test renderer without Mitsuba: no Dr.Jit thread pool
        pass
    if hasattr(os, "getloadavg"):
        ctx["load_average_start"] = round(os.getloadavg()[0], 2)
    return ctx


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
            timed = _takes_timings(render_fn)
            context = _timing_context()
            for k in todo:
                interrupts.check()  # Mitsuba's start-up may have swallowed a Ctrl-C
                tm: dict[str, float] = {}
                t_frame = time.perf_counter()
                frame = render_fn(scene, k, timings=tm) if timed else render_fn(scene, k)
                writer.write_frame(k, frame)
                writer.record_timing(k, {**tm, "total": time.perf_counter() - t_frame}, context)
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
