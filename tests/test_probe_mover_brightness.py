"""benchmarks/probe_mover_brightness.py's pooled models against a closed-form pool.

One pool of 30 points with random gradients, a flow that breaks eq. (14)
(dh_u = U - h_u W, the decoupled model's) and a brightness change along it that
is a gain varying linearly across the pool, r = f (beta + beta_u u + beta_h dh).
The decoupled model with the linear gain must return the flow exactly; the
models that lack a piece of it (the single gain, eq. 14 imposed) must not, so a
column dropped or miswired in the probe fails here.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import probe_mover_brightness as pm  # a script, not a package

N, SCALE = 30, 8.0
U, W, DTHETA = 0.3, -0.004, 0.002  # dh_u = U - h_u W (px/frame), rad/frame
BETA, BETA_U, BETA_H = 0.02, 0.01, -0.015  # the gain and its slopes across the pool


def _pool(beta_u: float = BETA_U, beta_h: float = BETA_H):
    rng = np.random.default_rng(7)
    h1 = rng.uniform(100.0, 110.0, N)
    h2 = h1 * rng.uniform(2.2, 2.4, N)
    theta = rng.uniform(-0.05, 0.05, N)
    d = dict(h1=h1, h2=h2, theta=theta)
    truth = {}
    for un, h in ((1, h1), (2, h2)):
        fh, fq, f = rng.normal(0, 0.02, N), rng.normal(0, 0.02, N), rng.uniform(0.2, 0.6, N)
        dh = U - h * W
        # the probe's offsets for neighbour j of point 0 (its pool's own point)
        u = (theta - theta[0]) * h1[0] / SCALE
        dh_off = (h1 - h1[0]) / SCALE
        r = f * (BETA + beta_u * u + beta_h * dh_off)
        d.update({f"f{un}_h": fh, f"f{un}_theta": fq, f"f{un}": f, f"r{un}": r,
                  f"f{un}_t": r - fh * dh - fq * DTHETA})  # fmt: skip
        truth[un] = dh
    idx = np.tile(np.arange(N), (N, 1))  # every point pools all; point 0 is checked
    return d, idx, np.ones((N, N)), truth


def _flow(d, idx, w, terms, decoupled):
    """Point 0's (dh1, dh2, dtheta) from the probe's pooled solve."""
    model = "constant" if decoupled else "linear"
    a1, a2, b, _ = pm.pooled(d, idx, w, model=model, scale=SCALE, terms=terms, noise=(0.0, 0.0),
                             min_conditioning=0.0, decoupled=decoupled)  # fmt: skip
    return a1[0], a2[0], b[0]


def test_the_decoupled_model_with_the_linear_gain_recovers_the_flow():
    d, idx, w, truth = _pool()
    a1, a2, b = _flow(d, idx, w, pm.MODELS["L"], decoupled=True)
    assert a1 == pytest.approx(truth[1][0], abs=1e-9)
    assert a2 == pytest.approx(truth[2][0], abs=1e-9)
    assert b == pytest.approx(DTHETA, abs=1e-12)


@pytest.mark.parametrize(
    ("terms", "decoupled"),
    [(pm.MODELS["C"], True), (pm.MODELS["A"], True), (pm.MODELS["L"], False)],
    ids=["single gain", "no gain", "eq. 14 imposed"],
)
def test_a_model_missing_a_piece_does_not(terms, decoupled):
    """The mutations: the single gain (no slopes), no gain, or the coupled model.
    Their cam1 radial errors here are 0.008, 0.044 and 0.144 px (seed 7, printed from
    _flow), the full model's 3e-15: 1e-3 lies between."""
    d, idx, w, truth = _pool()
    a1, _, _ = _flow(d, idx, w, terms, decoupled=decoupled)
    assert abs(a1 - truth[1][0]) > 1e-3


def test_the_single_gain_suffices_when_the_gain_is_uniform():
    d, idx, w, truth = _pool(beta_u=0.0, beta_h=0.0)
    a1, a2, _ = _flow(d, idx, w, pm.MODELS["C"], decoupled=True)
    assert a1 == pytest.approx(truth[1][0], abs=1e-9)
    assert a2 == pytest.approx(truth[2][0], abs=1e-9)


def test_the_split_adds_up_and_the_perfect_part_is_the_truth():
    """plain = perfect + r (the solve is linear in its right side); with the decoupled
    model and the change removed ("dec perfect") the flow is exact; the change's
    error under the decoupled model with the linear gain is zero."""
    d, idx, w, truth = _pool()
    parts = pm.decomposition(d, idx, w, model="linear", scale=SCALE)
    for pre in ("", "dec "):
        assert parts[pre + "plain"][0] == pytest.approx(
            parts[pre + "perfect"][0] + parts[pre + "r"][0], abs=1e-12
        )
    assert parts["dec perfect"][0] == pytest.approx(truth[1][0], abs=1e-9)
    assert abs(parts["dec r"][0]) > 1e-3  # 0.044 px: the change does move the plain solve
    _, err_l, _ = pm.r_analysis(d, idx, w, model="linear", scale=SCALE, terms=pm.MODELS["L"],
                                decoupled=True)  # fmt: skip
    assert err_l[0] == pytest.approx(0.0, abs=1e-9)
