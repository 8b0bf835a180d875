"""Two-way threading of the flow step's independent work (the two units, halves of the lines).

numpy, SciPy's DCTs, OpenCV and the Numba kernels (``nogil=True``) release
the GIL, so the two units' fits and grids, or the robust matcher's halves
of the radial lines, run on two cores at once. The threads wait on futures
(no spinning barrier), so on a busy machine a late thread costs only its own
time. Each task is the same computation as in one thread: the results do not
depend on :data:`THREADS`.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

__all__ = ["THREADS", "map_tasks", "submit"]

#: Threads for the independent tasks of one flow step (1: all in the caller's thread).
#: Read at each call, so it can be changed at run time.
THREADS = min(2, os.cpu_count() or 1)

_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_lock = threading.Lock()
_NAME = "omniflow-parallel"


def _get_pool() -> ThreadPoolExecutor:
    global _pool, _pool_size
    with _lock:
        if _pool is None or _pool_size != THREADS - 1:
            if _pool is not None:
                _pool.shutdown(wait=False)
            _pool = ThreadPoolExecutor(THREADS - 1, _NAME)
            _pool_size = THREADS - 1
        return _pool


def _nested() -> bool:
    # a task that maps again runs its tasks itself: waiting on the pool from inside
    # it could wait for its own thread
    return threading.current_thread().name.startswith(_NAME)


def submit(fn: Callable, *args) -> Future:
    """``fn(*args)`` on the pool's thread while the caller goes on (run at once, in the
    caller's thread, when :data:`THREADS` < 2); its Future."""
    if THREADS < 2 or _nested():
        done: Future = Future()
        try:
            done.set_result(fn(*args))
        except BaseException as exc:  # raised by done.result(), as from the pool
            done.set_exception(exc)
        return done
    return _get_pool().submit(fn, *args)


def map_tasks(fn: Callable, *args_per_task: tuple) -> list:
    """``[fn(*args) for args in args_per_task]``, run on :data:`THREADS` threads.

    Results come in task order; the first task's exception (in task order) is
    raised. The caller's thread runs the first task itself.
    """
    if THREADS < 2 or len(args_per_task) < 2 or _nested():
        return [fn(*a) for a in args_per_task]
    pool = _get_pool()
    futures = [pool.submit(fn, *a) for a in args_per_task[1:]]
    try:
        first = fn(*args_per_task[0])
    except BaseException:
        for f in futures:
            f.cancel()
        for f in futures:
            if not f.cancelled():
                f.exception()  # wait: no task outlives the call
        raise
    return [first, *(f.result() for f in futures)]
