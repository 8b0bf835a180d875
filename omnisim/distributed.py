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

Failures of the cluster are :class:`ClusterError` with one line naming the address: a
scheduler that does not answer within ``timeout`` seconds, a scheduler without workers
(or whose workers all left) for ``timeout`` seconds, a lost connection, a frame whose
task failed on a worker.
"""

from __future__ import annotations

import functools
import json
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from omnisim.meta import build_meta, load_scene_for_job, meta_digest, resolve_renderer, versions

__all__ = ["SCHEDULER_TIMEOUT", "ClusterError", "render_on_cluster", "render_task"]

#: Seconds to wait for the scheduler to answer, and for at least one worker to be there.
SCHEDULER_TIMEOUT = 10.0
#: Seconds between checks that the cluster still has workers while frames are pending.
POLL = 1.0


class ClusterError(RuntimeError):
    """The Dask cluster failed (address, what happened); ``exit_status`` 1 (environment)
    or 2 (a malformed address)."""

    def __init__(self, msg: str, exit_status: int = 1):
        super().__init__(msg)
        self.exit_status = exit_status


@functools.lru_cache(maxsize=4)
def _worker_state(scene_path: str, overrides_json: str, renderer: str):
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
        raise RuntimeError(
            f"worker would render a different dataset than the client for {scene_path}: "
            f"check the scene file and package versions on the worker ({versions()})"
        )
    frame = render_fn(scene, k)
    if out is None:
        return k, encode_frame(frame, [c["name"] for c in meta["cameras"]], k=k, meta=meta)
    writer = DatasetWriter(out, meta, cleanup=False, lock=False)  # the client holds the lock
    assert not compare_meta(writer.meta, meta)
    writer.write_frame(k, frame)
    return k, None


def _connect(scheduler: str, timeout: float):
    from distributed import Client
    from distributed.comm.addressing import parse_address, parse_host_port
    from distributed.comm.registry import get_backend

    try:  # a malformed address is refused before a Client exists (its __del__ complains)
        scheme, location = parse_address(scheduler)
        get_backend(scheme)
        if scheme in ("tcp", "tls"):  # 'nonsense' is tcp://nonsense: no port
            parse_host_port(location)
    except (ValueError, TypeError) as exc:
        raise ClusterError(
            f"--scheduler {scheduler!r}: not a scheduler address ({exc}); expected e.g. "
            "tcp://host:8786",
            exit_status=2,
        ) from None
    try:
        return Client(scheduler, timeout=timeout, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise ClusterError(
            f"--scheduler {scheduler}: no Dask scheduler answered within {timeout:g} s; "
            "expected a running scheduler at that address (start one with: dask scheduler)"
        ) from exc
    except (ValueError, TypeError) as exc:
        raise ClusterError(
            f"--scheduler {scheduler!r}: not a scheduler address ({exc}); expected e.g. "
            "tcp://host:8786",
            exit_status=2,
        ) from exc


def render_on_cluster(
    scheduler: str | Any,
    scene_path: Path,
    overrides: Mapping[str, Any],
    todo: list[int],
    writer,
    meta: Mapping[str, Any],
    renderer: str,
    write_on: str = "client",
    timeout: float = SCHEDULER_TIMEOUT,
) -> Iterator[int]:
    """Run the frames ``todo`` as tasks on ``scheduler``; yield each frame index once it is
    on disk. ``scheduler`` is an address or a ``distributed.Client``. Raises
    :class:`ClusterError` when the cluster fails (module docstring)."""
    from distributed import Client, wait

    if write_on not in ("client", "worker"):
        raise ValueError(f"write_on = {write_on!r}: expected 'client' or 'worker'")
    if not todo:
        return
    own = not isinstance(scheduler, Client)
    client = _connect(str(scheduler), timeout) if own else scheduler
    where = f"--scheduler {scheduler}" if own else "the Dask cluster"
    try:
        try:
            client.wait_for_workers(1, timeout=timeout)
        except (TimeoutError, OSError) as exc:
            raise ClusterError(
                f"{where}: the scheduler has no workers (waited {timeout:g} s); expected at "
                "least one (start one with: dask worker ADDRESS)"
            ) from exc
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

        running = {submit(pending.pop(0)): None for _ in range(min(window, len(pending)))}
        lonely_since = None
        while running:
            try:
                # distributed.wait looks up the default client; with an address and no
                # Client of the caller's (omnisim render --scheduler) there is none.
                with client.as_current():
                    done, _ = wait(list(running), timeout=POLL, return_when="FIRST_COMPLETED")
            except TimeoutError:
                done = set()
            except OSError as exc:
                raise ClusterError(f"{where}: lost the connection to the scheduler: {exc}") from exc
            if not done:
                if client.scheduler_info().get("workers"):
                    lonely_since = None
                elif lonely_since is None:
                    lonely_since = time.monotonic()
                elif time.monotonic() - lonely_since > timeout:
                    raise ClusterError(
                        f"{where}: all Dask workers are gone ({len(running)} frames pending for "
                        f"{timeout:g} s); restart the workers and run the same command again "
                        "to resume"
                    )
                continue
            for fut in done:
                running.pop(fut)
                k, files = _result(fut, where)
                fut.release()
                if files is not None:
                    writer.write_frame_files(k, files)
                elif not writer.is_done(k):
                    raise ClusterError(f"worker reported frame {k} written but it is not in {out}")
                if pending:
                    running[submit(pending.pop(0))] = None
                yield k
    finally:
        if own:
            client.close()


def _result(fut, where: str):
    """The future's result; a failure of the task or its workers as ClusterError."""
    from omniflow.io.dataset import DatasetError

    try:
        return fut.result()
    except DatasetError:
        raise
    except Exception as exc:
        name = str(fut.key).rsplit("-", 1)[-1]
        raise ClusterError(
            f"{where}: frame {name.lstrip('0') or '0'} failed on a worker: "
            f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]}"
        ) from exc
