"""The two-model test's pool fits as two tasks, and the grid sums' shared bins
(docs/decisions/speed.md).

* :func:`omniflow.solve.decoupled.start_pool_fits` answers as
  :func:`omniflow.solve.decoupled.pool_fits`
  (the two parts made in turn) bit for bit, on two threads, and hands the linear-gain
  test to the pool before the models' fits;
* :meth:`omniflow.solve.gridpool.GridPools.decouple_sums` takes the squared weights' count from
  the bins of its first filter: the same sums, bit for bit, as binning the count again;
* :meth:`omniflow.solve.gridpool.GridPools.linear_gain_sums` mirrors its Grams' upper triangle.

Each check has a mutation that it catches.
"""

from __future__ import annotations

import numpy as np
import pytest

from omniflow import parallel
from omniflow.solve import decoupled, gridpool
from omniflow.solve.gridpool import GridPools
from tests.omniflow.test_gridpool import (
    CELL,
    RADIUS,
    SHAPE,
    _brute_force_linear_gain,
    _cell_centre_case,
    _rel_err,
    _sums_case,
)


@pytest.fixture(scope="module")
def solver_call():
    """The arguments of the solver's own pool fits: the dense preset with the linear-gain
    test on a closed-form wall (as tests/omniflow/test_decoupled.py's early-fits test)."""
    from omniflow.pipeline import OmniFlowConfig, estimate
    from omniflow.solve import at_matches as solve_mod
    from omnisim.synthetic import Motion
    from tests.helpers.scenes import frames, paper_rig, wall_scene

    rig = paper_rig(256)
    f1, f2 = frames(wall_scene(rig, robot=Motion(velocity=(0.02, 0.01), yaw_rate=0.004)), 2)
    config = OmniFlowConfig.dense(brightness={"decouple_gain_tol": 60.0})
    seen = []
    real = solve_mod.start_pool_fits

    def spy(cols, rig_, config_, pools=None, brightness=None):
        seen.append((cols, brightness))
        return real(cols, rig_, config_, pools, brightness)

    solve_mod.start_pool_fits = spy
    try:
        estimate(f1, f2, rig, config)
    finally:
        solve_mod.start_pool_fits = real
    cols, brightness = seen[-1]
    return cols, rig, config, brightness


def _two_threads(monkeypatch):
    monkeypatch.setattr(parallel, "THREADS", 2)


def test_started_pool_fits_equal_pool_fits(solver_call, monkeypatch):
    """On two threads (the parts on the pool's thread, or the caller's when it takes one
    back) the same columns, bit for bit, as the parts made in turn; both parts' keys."""
    cols, rig, config, brightness = solver_call
    ref = decoupled.pool_fits(cols, rig, config, brightness=brightness)
    assert "gain_F" in ref and "F" in ref
    _two_threads(monkeypatch)
    for _ in range(3):
        got = decoupled.start_pool_fits(cols, rig, config, None, brightness).result()
        assert list(got) == list(ref)
        for k in ref:
            np.testing.assert_array_equal(got[k], ref[k], err_msg=k)


def test_started_pool_fits_check_catches_a_dropped_part(solver_call, monkeypatch):
    """The mutation: the joined result without the first-spawned part (the linear-gain
    test's columns lost)."""
    cols, rig, config, brightness = solver_call
    ref = decoupled.pool_fits(cols, rig, config, brightness=brightness)
    monkeypatch.setattr(decoupled._Joined, "result", lambda self: self.parts[-1].result())
    got = decoupled.start_pool_fits(cols, rig, config, None, brightness).result()
    assert list(got) != list(ref)


def test_the_linear_gain_test_is_spawned_first_and_cancel_drops_both(solver_call):
    """The longer part (the linear-gain test) goes to the pool first, the models' fits
    last (the caller makes them if the pool has not started them); cancel() reaches both."""
    cols, rig, config, brightness = solver_call
    spawned = []

    class Recorder(parallel.Task):
        def cancel(self):
            spawned.append(("cancel", self))
            super().cancel()

    def spawn(fn, *args):
        task = Recorder(fn, args, None)
        spawned.append(("spawn", task))
        return task

    task = decoupled.start_pool_fits(cols, rig, config, None, brightness, spawn=spawn)
    first, last = spawned[0][1], spawned[1][1]
    assert "gain_F" in first.result() and "F" in last.result() and "gain_F" not in last.result()
    spawned.clear()
    decoupled.start_pool_fits(cols, rig, config, None, brightness, spawn=spawn).cancel()
    assert [kind for kind, _ in spawned] == ["spawn", "spawn", "cancel", "cancel"]
    del task


@pytest.mark.parametrize("ranges", [False, True])
def test_decouple_sums_equal_the_count_binned_again(ranges):
    """decouple_sums bins [count, 10 products] once and filters the squared weights from
    its count channel: bit for bit the sums of binning the products with the count last
    and the count on its own (the code before)."""
    x, y, _, derivs, h1, r = _cell_centre_case(ranges=ranges)
    h2 = h1 * 1.6
    grid = GridPools(x, y, None, SHAPE, radius=RADIUS, cell=CELL, r=r, range_tol=0.1)
    np.testing.assert_array_equal(
        grid.decouple_sums(derivs, h1, h2), _old_decouple(grid, derivs, h1, h2)
    )


def test_decouple_sums_check_catches_the_wrong_channel(monkeypatch):
    """The mutation: the squared weights filtered from channel 1 (a product) of the bins."""
    x, y, _, derivs, h1, r = _cell_centre_case(ranges=True)
    h2 = h1 * 1.6
    grid = GridPools(x, y, None, SHAPE, radius=RADIUS, cell=CELL, r=r, range_tol=0.1)
    ref = _old_decouple(grid, derivs, h1, h2)
    shifted = lambda bins, c: [(np.ascontiguousarray(img[..., 1 : 1 + c]), *rest)  # noqa: E731
                               for img, *rest in bins]  # fmt: skip
    monkeypatch.setattr(gridpool, "_channels", shifted)
    assert not np.array_equal(grid.decouple_sums(derivs, h1, h2)[:, 11], ref[:, 11])


def _old_decouple(grid, derivs, h1, h2):
    """GridPools.decouple_sums as it was: the count binned with the products, last, and
    on its own for the squared weights (on-grid points only: every case here)."""
    f1h, f1th, f1t, f2h, f2th, f2t = derivs
    b1, b2 = f1h * h1, f2h * h2
    terms = [(f1h, f2h), (b1, b2), (f1th, f2th), (f1t, f2t)]
    pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2), (0, 3), (1, 3), (2, 3), (3, 3))
    parts = [terms[p][0] * terms[q][0] + terms[p][1] * terms[q][1] for p, q in pairs]
    n = h1.size
    g, g2 = grid.gauss, grid.gauss**2
    read = grid._filter(np.stack([*parts, np.ones(n)], axis=1), [(g, g, 1)])[0]
    read2 = grid._filter(np.ones((n, 1)), [(g2, g2, 2)])[0]
    return np.column_stack([read, read2[:, 0]])


def test_linear_gain_mirror_check_catches_the_wrong_triangle(monkeypatch):
    """The Grams' lower triangle from the upper (tests/omniflow/test_gridpool.py checks the
    sums against the definition); the mutation, the upper from the (empty) lower, fails
    that check."""
    x, y, _, derivs, h1, r, h2, f = _sums_case(True)
    grid = GridPools(x, y, None, SHAPE, radius=RADIUS, cell=CELL, r=r, range_tol=0.1)
    ref = _brute_force_linear_gain(x, y, derivs, f, h1, h2, r, 0.1, RADIUS)
    got = grid.linear_gain_sums(derivs, f, h1, h2, None, scale=RADIUS)
    assert _rel_err(got[0], ref[0]) < 1e-10  # measured 4e-16 (test_gridpool.py)
    monkeypatch.setattr(gridpool, "_LOWER", np.triu_indices(6, 1))
    got = grid.linear_gain_sums(derivs, f, h1, h2, None, scale=RADIUS)
    assert _rel_err(got[0], ref[0]) > 0.1  # measured 0.38 (the upper triangle zero)


def test_speculative_pool_fits_only_when_every_point_keeps_its_flow(monkeypatch):
    """On the grid, flow_at_matches starts every point's pool fits during the first solve:
    used (one start) where every point keeps its flow, as decouple's own fits of the final
    columns bit for bit; started again for the kept points where the first solve loses
    one. The mutation, the speculative fits used anyway, would hand decouple fits of one
    point more than its columns (checked: their lengths differ)."""
    from omniflow.pipeline import OmniFlowConfig, estimate
    from omniflow.solve import at_matches as solve_mod
    from omnisim.synthetic import Motion
    from tests.helpers.scenes import frames, paper_rig, wall_scene

    _two_threads(monkeypatch)
    rig = paper_rig(256)
    f1, f2 = frames(wall_scene(rig, robot=Motion(velocity=(0.02, 0.01), yaw_rate=0.004)), 2)
    config = OmniFlowConfig.dense(brightness={"decouple_gain_tol": 60.0})
    starts, seen = [], []
    real_start, real_decouple = solve_mod.start_pool_fits, solve_mod.decouple

    def start(cols, *args):
        starts.append((cols, args))
        return real_start(cols, *args)

    def spy(cols, rig_, config_, displacement, *, pools=None, fit=None, **kw):
        seen.append((cols, fit, kw))
        return real_decouple(cols, rig_, config_, displacement, pools=pools, fit=fit, **kw)

    monkeypatch.setattr(solve_mod, "start_pool_fits", start)
    monkeypatch.setattr(solve_mod, "decouple", spy)

    def check():
        cols, fit, kw = seen[-1]
        fresh = decoupled.pool_fits(cols, rig, config, brightness=kw["brightness"])
        assert list(fit) == list(fresh)
        for k in fresh:
            np.testing.assert_array_equal(fit[k], fresh[k], err_msg=k)
        return cols

    estimate(f1, f2, rig, config)
    assert len(starts) == 1
    n = check()["h1"].size
    assert starts[0][0]["h1"].size == n

    real_make = solve_mod.make_solver
    calls = []

    def make_solver(*args, **kw):  # the first solve loses its first point's flow
        inner = real_make(*args, **kw)

        def solve(*derivs, **opts):
            a, b, conf = inner(*derivs, **opts)
            if not calls:
                a = a.copy()
                a[0] = np.nan
            calls.append(1)
            return a, b, conf

        solve.pools = inner.pools
        return solve

    monkeypatch.setattr(solve_mod, "make_solver", make_solver)
    starts.clear()
    estimate(f1, f2, rig, config)
    assert [s[0]["h1"].size for s in starts] == [n, n - 1]
    assert check()["h1"].size == n - 1
    spec = decoupled.pool_fits(starts[0][0], rig, config, brightness=starts[0][1][-1])
    assert spec["F"].size != seen[-1][0]["h1"].size  # the mutation's fits: one point more


def test_take_runs_a_waiting_task_here_and_leaves_a_started_one(monkeypatch):
    """Task.take: a task the pool has not started runs in the caller's thread (once: its
    result is that run's); one the pool has started is left to it, without waiting (the
    mutation, take() as result(), waits for the pool: 0.5 s here, caught by the clock)."""
    import threading
    import time

    _two_threads(monkeypatch)
    release, started = threading.Event(), threading.Event()

    def busy():
        started.set()
        release.wait(5.0)
        return threading.current_thread().name

    runs = []

    def job():
        runs.append(threading.current_thread().name)
        return len(runs)

    first = parallel.submit(busy)
    started.wait(5.0)
    queued = parallel.submit(job)
    queued.take()  # the pool is busy: made here
    assert runs == [threading.current_thread().name]
    assert queued.result() == 1 and len(runs) == 1
    threading.Timer(0.5, release.set).start()
    t0 = time.perf_counter()
    first.take()  # started by the pool: left to it
    assert time.perf_counter() - t0 < 0.25
    assert first.result().startswith("omniflow-parallel")


def _dense_columns():
    from omniflow.pipeline import OmniFlowConfig, estimate
    from omnisim.synthetic import Motion
    from tests.helpers.scenes import frames, paper_rig, wall_scene

    rig = paper_rig(256)
    f1, f2 = frames(wall_scene(rig, robot=Motion(velocity=(0.02, 0.01), yaw_rate=0.004)), 2)
    return estimate(f1, f2, rig, OmniFlowConfig.dense()).columns


def test_densify_shares_equal_one_search(monkeypatch):
    """densify's NCC search in two row shares on two threads: the same matches and flow,
    bit for bit, as one ncc_offsets call over every candidate (the code before: map_tasks
    replaced by one call over the shares' union)."""
    from omniflow.matching import dense

    _two_threads(monkeypatch)
    got = _dense_columns()
    monkeypatch.setattr(dense, "map_tasks", lambda fn, *shares: fn(shares[0][0], shares[-1][1]))
    ref = _dense_columns()
    assert got["h1"].size == ref["h1"].size > 1000
    for k in ref:
        np.testing.assert_array_equal(got[k], ref[k], err_msg=k)


def test_densify_shares_check_catches_a_lost_share(monkeypatch):
    """The mutation: only the first share searched (the second's rows of S as allocated,
    zero here so that the outcome does not depend on what the memory held): other
    matches."""
    from omniflow.matching import dense

    ref = _dense_columns()
    real_empty = np.empty

    def first_only(fn, *shares):
        fn(*shares[0])

    monkeypatch.setattr(dense, "map_tasks", first_only)
    monkeypatch.setattr(dense.np, "empty", lambda *a, **k: np.zeros(*a, **k))
    try:
        got = _dense_columns()
    finally:
        monkeypatch.setattr(dense.np, "empty", real_empty)
    assert got["h1"].size != ref["h1"].size
