"""benchmarks/probe_ring_gates.py's arithmetic on hand-made points (no dataset):
the gates of ``decouple_gain_tol``'s test as built, issue 9's mean-flow error, and the
rule carried over from the previous pair."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import probe_ring_gates as pr  # a script, not a package


def _pair(F, dof, edge, x=None, mover=None):
    """Points with the test's statistics (ratio = 1 + F / dof), the answer without the test
    dh 0.1 (both units), h dtheta 0, the test's answer dh 0.5, truth dh 0.4, h dtheta 0.3."""
    F, dof = np.asarray(F, float), np.asarray(dof, float)
    n = F.size
    x = np.arange(n, dtype=float) * 100.0 if x is None else np.asarray(x, float)
    mover = np.ones(n, bool) if mover is None else np.asarray(mover, bool)
    return dict(
        F=F, dof=dof, ratio=1.0 + F / dof, edge=np.asarray(edge, bool), fin=np.ones(n, bool),
        x=x, y=np.zeros(n), h=(np.full(n, 100.0), np.full(n, 230.0)),
        off=(np.full(n, 0.1), np.full(n, 0.1), np.zeros(n)),
        gain=(np.full(n, 0.5), np.full(n, 0.5), np.full(n, 0.003)),
        truth=[(np.full(n, 0.4), np.full(n, 0.3)), (np.full(n, 0.4), np.full(n, 0.69))],
        mover=mover, name=np.where(mover, "ring", "wall"),
    )  # fmt: skip


def test_the_gates_as_built():
    """F_U 12 passes on a range-edge pool only; 25 passes both; 25 with 3 residual degrees
    of freedom (MIN_RESIDUAL_DOF 4) and 15 with 20 (ratio 1.75 < 2) never."""
    d = _pair([12, 12, 25, 25, 25, 15], [10, 10, 10, 10, 3, 20], [1, 0, 0, 1, 1, 1])
    assert pr.switched(d, 10.0, 20.0).tolist() == [True, False, True, True, False, False]
    assert pr.switched(d, 10.0, 20.0, ratio=1.5).tolist()[-1]


def test_the_mean_flow_error():
    """Unswitched: mean (0.1, 0) against (0.4, 0.3): |(-0.3, -0.3)| / 0.5 = 84.85 %; the
    test's answer at both points: (0.5, 0.3) against (0.4, 0.3), 20 %; cam2 (0.5, 0.69)
    (h dtheta 230 x 0.003) against (0.4, 0.69), 12.5 %. Static EPE: the wall's point only."""
    d = _pair([25, 25, 25], [10, 10, 10], [0, 0, 0], mover=[True, True, False])
    err, static = pr.score([d], [np.zeros(3, bool)])
    np.testing.assert_allclose(err["ring"][0], 100 * np.hypot(0.3, 0.3) / 0.5)
    assert static[0] == np.hypot(0.3, 0.3)
    err, static = pr.score([d], [np.ones(3, bool)])
    np.testing.assert_allclose(err["ring"], [20.0, 100 * 0.1 / np.hypot(0.4, 0.69)])
    np.testing.assert_allclose(static[0], 0.1)


def test_carried_over_from_the_previous_pair():
    """A point within 8 px of one the previous pair switched takes the answer whatever its
    F_U; one 20 px away keeps its own gate."""
    first = _pair([25.0], [10.0], [0], x=[0.0])
    second = _pair([1.0, 1.0], [10.0, 10.0], [0, 0], x=[5.0, 20.0])
    masks = pr.after([first, second], lambda d: pr.switched(d, 10.0, 20.0))
    assert masks[0].tolist() == [True] and masks[1].tolist() == [True, False]
