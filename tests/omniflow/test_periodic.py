"""omniflow.matching.periodic: the periodic-alias test on closed-form polar tables.

Each table is built from a closed-form row (a sinusoid: a period; two equal
bumps: one lone recurrence) so what the test must decide is known exactly:
drop a match when an alias a period away exists in image 2 (or cannot be
looked at and image 1 shows a period), keep it when image 2 rules the alias
out. The scene-level figures (striped, periodic and room walls; the rendered
low-texture scene) are in tests/omniflow/test_matching.py and
docs/decisions/matching.md.
"""

from __future__ import annotations

import numpy as np

from omniflow.matching.periodic import line_edges, not_periodic, profiles
from omniflow.matching.tables import local_maxima

N_LINES, N_COLS = 8, 260
W, STRIDE = 8, 2  # profiles of +-16 columns, 17 samples
D = 30  # the true disparity, columns
WINDOW = (10, 110)  # disparity window, columns
LAGS = ((W * STRIDE) // 2, WINDOW[1] - WINDOW[0])


def _table(row: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.broadcast_to(row, (N_LINES, row.size)), dtype=np.float32)


def _edges(table: np.ndarray) -> np.ndarray:
    a = np.abs(np.gradient(table, axis=1))
    e = local_maxima(a) & (a > 0.2 * a.max())
    e[:, : W * STRIDE] = e[:, N_COLS - W * STRIDE :] = False  # whole profiles only, as the matcher
    return e


def _shift(row: np.ndarray, d: int) -> np.ndarray:
    """Image 2's row: image 1's content d columns further out (disparity d)."""
    out = np.full_like(row, row[0])
    out[d:] = row[:-d]
    return out


def _bumps(signs=(1.0, 1.0), centres=(80, 140), sigma=4.0) -> np.ndarray:
    c = np.arange(N_COLS, dtype=float)
    pairs = zip(signs, centres, strict=True)
    return 0.5 + sum(s * 0.3 * np.exp(-0.5 * ((c - m) / sigma) ** 2) for s, m in pairs)


def _call(t1, t2, j, *, columns2=None, image2=True, edges=None):
    k = np.array([3])
    j = np.array([j])
    kw = dict(w=W, stride=STRIDE, lags=LAGS, alias_score=0.9)
    if image2:
        kw.update(table2=t2, j2=(j + D).astype(float), window=WINDOW, alias2_score=0.9,
                  columns2=columns2)  # fmt: skip
    return bool(not_periodic(t1, _edges(t1) if edges is None else edges, k, j, **kw)[0])


def test_profiles_are_zero_mean_unit_norm_samples_of_the_line():
    rng = np.random.default_rng(0)
    t = rng.random((6, 50)).astype(np.float32)
    p = profiles(t, np.array([0, 5]), np.array([20, 30]), w=3, stride=2)
    # line 0, columns 14, 16, ..., 26; line 5, columns 24, ..., 36
    for row, (line, col) in enumerate(((0, 20), (5, 30))):
        raw = t[line, col - 6 : col + 7 : 2]
        raw = raw - raw.mean()
        np.testing.assert_allclose(p[row], raw / np.linalg.norm(raw), atol=1e-6)
    assert p.shape == (2, 7)
    # a constant profile is all zeros (NCC 0 with anything), not NaN
    assert np.all(profiles(np.ones((3, 40), np.float32), np.array([1]), np.array([20]),
                           w=3, stride=1) == 0)  # fmt: skip


def test_line_edges_lists_each_lines_columns_in_order():
    e = np.zeros((3, 10), dtype=bool)
    e[0, [2, 7]] = True
    e[2, [1, 4, 9]] = True
    cols, exists = line_edges(e, np.array([2, 1, 0]))
    assert exists.sum(axis=1).tolist() == [3, 0, 2]
    assert cols[0].tolist() == [1, 4, 9] and cols[2, :2].tolist() == [2, 7]


def test_a_period_with_its_alias_in_image_2_is_dropped():
    """A sinusoid of period 24 columns along the line: the profile recurs at
    +-24, +-48, ... and image 2 (the same content D further out) holds an
    alias a period from any match: dropped, with or without image 2."""
    c = np.arange(N_COLS, dtype=float)
    row = 0.5 + 0.3 * np.sin(2 * np.pi * c / 24.0)
    t1, t2 = _table(row), _table(_shift(row, D))
    j = int(np.nonzero(_edges(t1)[3, 100:])[0][0]) + 100
    assert not _call(t1, t2, j)
    assert not _call(t1, t2, j, image2=False)


def test_a_lone_recurrence_is_kept_when_image_2_rules_the_alias_out():
    """Two equal bumps 60 columns apart: image 1's profile recurs once. If
    image 2 shows the second bump dark (no alias at j2 + 60) the match is
    kept; if image 2 shows it bright (an alias exists) it is dropped. The old
    rule (no image 2) drops both. Mutation caught: ignoring image 2."""
    t1 = _table(_bumps())
    j = int(np.nonzero(_edges(t1)[3, 60:80])[0][0]) + 60  # the first bump's rising flank
    no_alias = _table(_shift(_bumps(signs=(1.0, -1.0)), D))
    alias = _table(_shift(_bumps(), D))
    assert _call(t1, no_alias, j)
    assert not _call(t1, alias, j)
    assert not _call(t1, no_alias, j, image2=False)


def test_an_alias_past_the_rim_is_dropped_only_where_image_1_shows_a_period():
    """Image 2's usable columns (columns2) end just past the match: the alias
    a recurrence away cannot be looked at. A period (the sinusoid: several
    recurrences) drops the match; a lone recurrence (two bumps) keeps it.
    Mutation caught: treating a hidden alias as absent (the sinusoid kept)."""
    c = np.arange(N_COLS, dtype=float)
    sine = _table(0.5 + 0.3 * np.sin(2 * np.pi * c / 24.0))
    j = int(np.nonzero(_edges(sine)[3, 100:])[0][0]) + 100
    rim = (W * STRIDE, j + D + 4)  # the match's own profile fits; j2 + 24 does not
    assert not _call(sine, _table(_shift(sine[0], D)), j, columns2=rim)
    t1 = _table(_bumps())
    jb = int(np.nonzero(_edges(t1)[3, 60:80])[0][0]) + 60
    rim_b = (W * STRIDE, jb + D + 4)
    assert _call(t1, _table(_shift(_bumps(), D)), jb, columns2=rim_b)


def test_a_smooth_ramp_is_not_a_period():
    """A linear ramp correlates with itself at every lag (NCC 1) without ever
    falling below 0: not a recurrence, so the match is kept although image 2
    (the same ramp) would confirm any alias. Mutation caught: counting a
    recurrence without the fall before it."""
    row = 0.1 + 0.003 * np.arange(N_COLS, dtype=float)
    t1, t2 = _table(row), _table(_shift(row, D))
    edges = np.zeros(t1.shape, dtype=bool)
    edges[:, W * STRIDE : N_COLS - W * STRIDE : 10] = True
    j = 10 * (100 // 10)
    assert _call(t1, t2, j, edges=edges)
    assert _call(t1, t2, j, edges=edges, image2=False)


def _textured_pair(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Image 1: a period-24 sinusoid plus smoothed noise along every line (lines differ);
    image 2: the same content D columns further out."""
    rng = np.random.default_rng(seed)
    c = np.arange(N_COLS, dtype=float)
    noise = rng.standard_normal((N_LINES * 8, N_COLS))
    kernel = np.exp(-0.5 * (np.arange(-6, 7) / 2.0) ** 2)
    noise = np.apply_along_axis(lambda r: np.convolve(r, kernel, mode="same"), 1, noise)
    amp = rng.uniform(0.0, 0.3, (N_LINES * 8, 1))  # from no period to a strong one
    t1 = (0.5 + amp * np.sin(2 * np.pi * c / 24.0) + 0.05 * noise).astype(np.float32)
    t2 = np.empty_like(t1)
    t2[:, D:] = t1[:, :-D]
    t2[:, :D] = t1[:, :1]
    return t1, t2


def test_compiled_test_takes_the_numpy_rules_decisions():
    """not_periodic (compiled) against not_periodic_numpy, its reference form, on
    every edge of 64 lines from periodic to aperiodic, with and without image 2,
    with a rim hiding part of image 2, on one thread and split over two: the same
    decisions, and both kinds occur (so a test that kept or dropped everything
    would fail)."""
    from omniflow import parallel
    from omniflow.matching.periodic import not_periodic_numpy

    t1, t2 = _textured_pair(3)
    wide = np.zeros(t1.shape, dtype=bool)
    wide[:] = local_maxima(np.abs(np.gradient(t1, axis=1)))
    wide[:, : W * STRIDE] = wide[:, N_COLS - W * STRIDE :] = False
    k, j = np.nonzero(wide)
    rng = np.random.default_rng(4)
    j2 = j + D + rng.uniform(-0.6, 0.6, j.size)
    base = dict(w=W, stride=STRIDE, lags=LAGS, alias_score=0.9)
    cases = [
        {},
        dict(table2=t2, j2=j2, window=WINDOW, alias2_score=0.9),
        dict(table2=t2, j2=j2, window=WINDOW, alias2_score=0.9, columns2=(W * STRIDE, 150)),
    ]
    for extra in cases:
        ref = not_periodic_numpy(t1, wide, k, j, **base, **extra)
        assert 0 < np.count_nonzero(ref) < ref.size
        for threads in (1, 2):
            out = not_periodic(t1, wide, k, j, **base, **extra, threads=threads,
                               per_range=parallel.map_tasks)  # fmt: skip
            np.testing.assert_array_equal(out, ref)
