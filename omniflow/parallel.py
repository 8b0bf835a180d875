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

__all__ = ["THREADS", "Task", "map_tasks", "submit"]

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


class Task:
    """``fn(*args)`` handed to the pool's thread; :meth:`result` runs it in the caller's
    thread instead when the pool has not started it yet (the pool may be busy with
    earlier work), else waits for it."""

    def __init__(self, fn: Callable, args: tuple, future: Future | None):
        self._fn, self._args, self._future = fn, args, future
        self._done = False
        self._value = None

    def result(self):
        if not self._done:
            if self._future is None or self._future.cancel():
                self._value = self._fn(*self._args)
            else:
                self._value = self._future.result()
            self._done = True
        return self._value

    def take(self) -> None:
        """Run it now in the caller's thread if the pool has not started it; else leave it
        to the pool (without waiting)."""
        if not self._done and (self._future is None or self._future.cancel()):
            self._value = self._fn(*self._args)
            self._done = True

    def cancel(self) -> None:
        """Drop the task if not started; wait for it if it is (its result is ignored)."""
        if self._future is not None and not self._future.cancel():
            self._future.exception()
        self._done = True


def submit(fn: Callable, *args) -> Task:
    """``fn(*args)`` on the pool's thread while the caller goes on (when :data:`THREADS`
    < 2, in the caller's thread when its result is asked for)."""
    if THREADS < 2 or _nested():
        return Task(fn, args, None)
    return Task(fn, args, _get_pool().submit(fn, *args))


def map_tasks(fn: Callable, *args_per_task: tuple) -> list:
    """``[fn(*args) for args in args_per_task]``, run on :data:`THREADS` threads.

    Results come in task order; every task runs, then the first exception in
    task order is raised. The caller's thread runs the first task, then takes
    back the others from the end of the queue while the pool's thread works
    from its front (so the two meet in the middle, neither waiting idle).
    """
    if THREADS < 2 or len(args_per_task) < 2 or _nested():
        return [fn(*a) for a in args_per_task]
    tasks = [submit(fn, *a) for a in args_per_task[1:]]
    outcomes: list = [None] * len(args_per_task)

    def attempt(i: int, call: Callable) -> None:
        try:
            outcomes[i] = (True, call())
        except BaseException as exc:
            outcomes[i] = (False, exc)

    attempt(0, lambda: fn(*args_per_task[0]))
    for i in range(len(tasks) - 1, -1, -1):
        attempt(i + 1, tasks[i].result)
    for ok, value in outcomes:
        if not ok:
            raise value
    return [value for _, value in outcomes]
