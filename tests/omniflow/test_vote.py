"""omniflow.matching.vote: the compiled consistency vote against scipy's k-d tree form."""

from __future__ import annotations

import numpy as np
import pytest

from omniflow.matching.vote import consistent, consistent_kdtree


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compiled_vote_takes_the_kdtree_forms_decisions(seed):
    """Matches on the matcher's grid (360 lines, whole-pixel h1, so many pairs lie
    exactly on the window's edge), clustered so the window holds several, with
    disparities from two surfaces, across the wrap at theta = +-pi: the same
    decisions as cKDTree.query_pairs, and both kinds occur (a vote keeping or
    dropping everything would fail)."""
    rng = np.random.default_rng(seed)
    n = 3000
    k = rng.integers(0, 360, n)
    theta = -np.pi + (2.0 * np.pi / 360) * (k + 0.5)
    h1 = 16.0 + rng.integers(0, 60, n).astype(float)
    disparity = np.where(rng.random(n) < 0.7, 20.0, 23.0) + rng.normal(0.0, 0.6, n)
    kw = dict(half_theta=0.05, half_h=16.0, tol=1.0, support=2)
    ref = consistent_kdtree(theta, h1, disparity, **kw)
    assert 0 < np.count_nonzero(ref) < n
    np.testing.assert_array_equal(consistent(theta, h1, disparity, **kw), ref)


def test_vote_window_wraps_around_theta():
    """Three agreeing matches either side of theta = 0 (where the vote's coordinate,
    theta mod 2 pi, wraps) count as neighbours: all kept; two of them apart from the
    third, each has one neighbour: dropped. Mutation caught: a scan that does not
    wrap."""
    theta = np.array([-0.01, 0.01, 0.02])
    h1 = np.array([30.0, 31.0, 30.0])
    d = np.array([10.0, 10.2, 10.1])
    kw = dict(half_theta=0.05, half_h=16.0, tol=1.0, support=2)
    assert consistent(theta, h1, d, **kw).all()
    assert not consistent(np.array([1.0, 1.01, np.pi / 2]), h1, d, **kw).any()
    assert consistent(theta[:0], h1[:0], d[:0], **kw).size == 0
