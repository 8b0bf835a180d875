"""omniflow.parallel: task order, errors, tasks taken back, thread-independent results."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from omniflow import parallel


@pytest.fixture
def two_threads(monkeypatch):
    monkeypatch.setattr(parallel, "THREADS", 2)


def test_map_tasks_keeps_order_and_uses_a_second_thread(two_threads):
    names = []

    def task(i):
        names.append(threading.current_thread().name)
        time.sleep(0.02)
        return i * i

    assert parallel.map_tasks(task, *((i,) for i in range(4))) == [0, 1, 4, 9]
    assert any(n.startswith("omniflow-parallel") for n in names)
    assert threading.current_thread().name in names  # the caller runs tasks too


def test_map_tasks_raises_the_first_error_in_task_order(two_threads):
    def task(i):
        if i in (1, 2):
            raise ValueError(f"task {i}")
        return i

    with pytest.raises(ValueError, match="task 1"):
        parallel.map_tasks(task, (0,), (1,), (2,))


def test_task_not_started_runs_in_the_caller(two_threads):
    gate = threading.Event()
    blocker = parallel.submit(gate.wait, 5.0)  # keeps the one pool thread busy
    task = parallel.submit(threading.current_thread)
    assert task.result() is threading.current_thread()  # taken back, not waited for
    gate.set()
    assert blocker.result() is True


def test_one_thread_runs_everything_in_the_caller(monkeypatch):
    monkeypatch.setattr(parallel, "THREADS", 1)
    me = threading.current_thread()
    assert parallel.map_tasks(lambda: threading.current_thread(), (), ()) == [me, me]
    assert parallel.submit(threading.current_thread).result() is me


def test_nested_map_in_a_pool_task_does_not_wait_on_itself(two_threads):
    def inner():
        return parallel.map_tasks(lambda i: i + 1, (1,), (2,))

    assert parallel.submit(inner).result() == [2, 3]


def test_estimate_columns_do_not_depend_on_threads(monkeypatch):
    """Two threads or one: every column bit for bit the same (closed-form frames)."""
    from omniflow.pipeline import OmniFlowConfig, estimate
    from omnisim.synthetic import Motion
    from tests.helpers.scenes import frames, paper_rig, wall_scene

    rig = paper_rig(256)
    f1, f2 = frames(wall_scene(rig, robot=Motion(velocity=(0.01, 0.005), yaw_rate=0.002)), 2)
    out = {}
    for threads in (1, 2):
        monkeypatch.setattr(parallel, "THREADS", threads)
        out[threads] = estimate(f1, f2, rig, OmniFlowConfig())
    assert len(out[1]) > 100
    for k in out[1].columns:
        np.testing.assert_array_equal(out[2][k], out[1][k], err_msg=k)


def test_dense_preset_columns_do_not_depend_on_threads(monkeypatch):
    """The dense preset's grid pools (jobs shared between the threads), refinement (the
    units' evaluations on both threads) and two-model test (its pool fits made on the
    other thread while the flow is refined): every column bit for bit the same on one
    thread and two, on a scene moving fast enough that the refinement has points."""
    from omniflow.pipeline import OmniFlowConfig, estimate
    from omnisim.synthetic import Motion
    from tests.helpers.scenes import frames, paper_rig, wall_scene

    rig = paper_rig(256)
    f1, f2 = frames(wall_scene(rig, robot=Motion(velocity=(0.06, 0.03), yaw_rate=0.02)), 2)
    out = {}
    for threads in (1, 2):
        monkeypatch.setattr(parallel, "THREADS", threads)
        out[threads] = estimate(f1, f2, rig, OmniFlowConfig.dense())
    plain = estimate(f1, f2, rig, OmniFlowConfig.dense(iterations=0))
    assert len(out[1]) > 100
    assert not np.array_equal(plain["dh1_dt"], out[1]["dh1_dt"])  # the refinement ran
    for k in out[1].columns:
        np.testing.assert_array_equal(out[2][k], out[1][k], err_msg=k)
