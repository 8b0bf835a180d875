"""Densified matches carry their seeds' smooth-profile flag (``Matches.ramp``;
omniflow.matching.dense.grown_from, used by omniflow.matching.radial).

A densified match is placed by a short search at its seeds' disparity, so where a seed is
a ramp's match (``edge_smooth``: NCC could not place it) its neighbours inherit the wrong
disparity whatever their own profile. On the rendered low_texture scene the dense preset
kept four such matches on a plain wall, 13-14 px off in h_2, whose own profiles were just
under ``dense_smooth`` (NCC with themselves 0.949-0.950) and whose pools' conditioning was
0.004-0.0045 (below ``edge_smooth_floor``): they alone moved the cam1 radial gain by -0.022
(docs/decisions/dense_mode.md). Flagged, the flow
step drops them like their seeds.
"""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest

import omniflow.pipeline as pipeline
from omniflow.matching.dense import grown_from
from omniflow.pipeline import OmniFlowConfig, estimate
from tests.helpers.scenes import paper_rig
from tests.omniflow.test_edge_smooth import _noisy, _smooth_wall, _wrong


def test_grown_from_reads_the_nearest_seed_on_each_side_within_reach():
    # seeds on line 0 at columns 10 (flagged) and 30; on line 1 at 50 (flagged)
    seed_k = np.array([0, 0, 1])
    seed_j = np.array([10, 30, 50])
    flags = np.array([True, False, True])
    k = np.array([0, 0, 0, 0, 0, 1, 1, 1, 2])
    j = np.array([5, 14, 21, 26, 40, 45, 60, 61, 50])
    # 5: left of the flagged seed; 14: 4 right of it; 21: 11 right of it, beyond reach
    # (its right seed, 9 away, unflagged); 26: the same, nearer the unflagged one; 40:
    # right of the unflagged seed; 45, 60: 5 and 10 either side of line 1's flagged
    # seed; 61: 11 away; line 2 has no seed
    got = grown_from(k, j, seed_k, seed_j, flags, reach=10)
    assert got.tolist() == [True, True, False, False, False, True, True, False, False]
    # between a flagged and an unflagged seed, both within reach: the match is flagged
    assert grown_from(np.array([0]), np.array([20]), seed_k, seed_j, flags, 10).tolist() == [True]
    # nothing flagged, no match: all False / empty
    assert not grown_from(k, j, seed_k, seed_j, np.zeros(3, bool), 10).any()
    assert grown_from(k[:0], j[:0], seed_k, seed_j, flags, 10).size == 0


@pytest.fixture(scope="module")
def smooth_wall_runs():
    """The swelling wall of test_edge_smooth.py matched by the dense preset with its own
    smooth-profile test off (``dense_smooth`` 1), so its ramp seeds grow neighbours: the
    matches handed to the flow step and the result."""
    rig = paper_rig(256)
    scene = _smooth_wall(rig)
    f1, f2 = _noisy(scene)
    seen = []
    solve = pipeline.flow_at_matches

    def spy(matches, *args, **kwargs):
        seen.append(matches)
        return solve(matches, *args, **kwargs)

    pipeline.flow_at_matches = spy
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cfg = OmniFlowConfig.dense(matching={"dense_smooth": None})
            cols = estimate(f1, f2, rig, cfg)
            unflagged = estimate(f1, f2, rig, cfg, matches=replace(seen[0], ramp=None))
    finally:
        pipeline.flow_at_matches = solve
    return scene, seen[0], cols, unflagged, cfg


def test_densified_matches_of_ramp_seeds_are_flagged(smooth_wall_runs):
    """Every match on the swell is wrong (measured 42 of 42: 12 edge matches, all flagged
    by ``edge_smooth``, and 30 densified within reach of them); all 42 are flagged (only
    the 12 seeds without the inheritance)."""
    scene, matches, _, unflagged, _ = smooth_wall_runs
    assert len(matches) >= 30  # measured 42
    assert matches.ramp is not None and matches.ramp.all()
    assert _wrong(scene, unflagged).all()


def test_flow_step_drops_inherited_flags_under_the_floor(smooth_wall_runs):
    """The flow step drops exactly the flagged points whose confidence is below
    ``edge_smooth_floor``: with every match flagged, none under it is left (measured 32
    of 42 kept; without the inheritance 39, 7 of them densified ones under the floor)."""
    _, matches, cols, unflagged, cfg = smooth_wall_runs
    floor = cfg.matching.edge_smooth_floor
    assert len(unflagged) == len(matches)  # no flag: every point solved
    under = unflagged["confidence"] < floor
    assert 5 <= under.sum() < len(matches)  # measured 10 of 42
    np.testing.assert_array_equal(cols["h1"], unflagged["h1"][~under])
    assert not np.any(cols["confidence"] < floor)
