"""Frames as Dask tasks (``omnisim render --scheduler ADDRESS``).

Each task is one frame: the worker loads the scene from its path itself (cached per
worker process), checks that it builds the same ``dataset.json`` content as the client
(same scene text, settings and package versions, else the task fails with a message
saying what differs), renders the frame with the same renderer and encodes it with
:func:`omnisim.dataset.encode_frame`, so the files are byte-identical to a local run.

Writing, atomic either way:

``write_on="client"`` (default)
    the worker returns the encoded file bytes; the client writes them with
    :meth:`omnisim.dataset.DatasetWriter.write_frame_files` (temporary directory,
    fsync, rename). Needs no shared file system, only the scene file (and the mesh and
    texture files it names) at the same path on the workers.
``write_on="worker"``
    the worker writes the frame directory into the dataset itself, the same way; the
    dataset directory must be on a file system shared by workers and client.

At most ``2 x (worker threads)`` frames are in flight, so a long sequence does not pile
finished frames up in worker memory.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

__all__ = ["render_on_cluster", "render_task"]


@functools.lru_cache(maxsize=4)
def _worker_state(scene_path: str, overrides_json: str, renderer: str):
    from omnisim.job import build_meta, load_scene_for_job, meta_digest, resolve_renderer

    overrides = json.loads(overrides_json)
    scene = load_scene_for_job(scene_path, overrides)
    meta = build_meta(scene, overrides, renderer=renderer)
    return scene, meta, meta_digest(meta), resolve_renderer(renderer)


def render_task(
    scene_path: str,
    overrides_json: str,
    k: int,
    renderer: str,
    digest: str,
    out: str | None = None,
) -> tuple[int, dict[str, bytes] | None]:
    """Render frame ``k`` on a worker. Returns ``(k, files)``, or ``(k, None)`` when the
    worker wrote the frame into ``out`` itself."""
    from omnisim.dataset import DatasetWriter, compare_meta, encode_frame

    scene, meta, wdigest, render_fn = _worker_state(scene_path, overrides_json, renderer)
    if wdigest != digest:
        from omnisim.job import _versions

        raise RuntimeError(
            f"worker would render a different dataset than the client for {scene_path}: "
            f"check the scene file and package versions on the worker ({_versions()})"
        )
    frame = render_fn(scene, k)
    if out is None:
        return k, encode_frame(frame, [c["name"] for c in meta["cameras"]], k=k, meta=meta)
    writer = DatasetWriter(out, meta, cleanup=False)
    assert not compare_meta(writer.meta, meta)
    writer.write_frame(k, frame)
    return k, None


def render_on_cluster(
    scheduler: str | Any,
    scene_path: Path,
    overrides: Mapping[str, Any],
    todo: list[int],
    writer,
    meta: Mapping[str, Any],
    renderer: str,
    write_on: str = "client",
) -> Iterator[int]:
    """Run the frames ``todo`` as tasks on ``scheduler``; yield each frame index once it is
    on disk. ``scheduler`` is an address or a ``distributed.Client``."""
    from distributed import Client, as_completed

    from omnisim.job import meta_digest

    if write_on not in ("client", "worker"):
        raise ValueError(f"write_on = {write_on!r}: expected 'client' or 'worker'")
    if not todo:
        return
    own = not isinstance(scheduler, Client)
    client = Client(scheduler) if own else scheduler
    try:
        digest = meta_digest(meta)
        ov_json = json.dumps(dict(overrides), sort_keys=True)
        out = str(Path(writer.dir).resolve()) if write_on == "worker" else None
        nthreads = sum(client.nthreads().values()) or 1
        window = max(2, 2 * nthreads)
        pending = list(todo)

        def submit(k: int):
            return client.submit(
                render_task,
                str(scene_path),
                ov_json,
                k,
                renderer,
                digest,
                out,
                key=f"omnisim-frame-{digest[:16]}-{k:06d}",
                pure=False,
                retries=1,
            )

        ac = as_completed([submit(pending.pop(0)) for _ in range(min(window, len(pending)))])
        for fut in ac:
            k, files = fut.result()
            fut.release()
            if files is not None:
                writer.write_frame_files(k, files)
            elif not writer.is_done(k):
                raise RuntimeError(f"worker reported frame {k} written but it is not in {out}")
            if pending:
                ac.add(submit(pending.pop(0)))
            yield k
    finally:
        if own:
            client.close()
