"""Eq. (14) tested with a linear gain (``OmniFlowConfig.decouple_gain_tol``) against truth.

1. One closed-form pool whose flow breaks eq. (14) (dh_u = U - h_u W) under a gain
   varying linearly across it (the pool of the deleted probe test, at 5662375): the decoupled
   model with the linear gain (:func:`omniflow.solve.gain.decoupled_linear_gain`) returns the
   flow exactly, and its sums equal a brute-force numpy design's.
2. End to end through :func:`omniflow.pipeline.estimate`: the striped wall of
   tests/helpers/scenes.py (256 px, true matches at 3 % of the pixels, 419 points)
   rising 1 mm per frame (eq. 14 fails at every point; true cam1 radial flow 0.18 px),
   frame t + 1 of both units multiplied by 1 + 0.02 sin(2 theta) (a brightness change
   varying across the image, the same at a surface point in both units, as shading on a
   body turning under fixed lights). Errors are cam1 endpoint errors, px per frame;
   figures measured with these exact scenes (python -m pytest -s prints them).
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

import omniflow.solve.decoupled as decoupled_mod
import omniflow.solve.gain as gain_mod
from omniflow.config import OmniFlowConfig
from omniflow.solve.gain import decoupled_linear_gain
from omnisim.synthetic import Motion
from tests.helpers.scenes import wall_under_gain_field

N, SCALE = 30, 8.0
U, W, DTHETA = 0.3, -0.004, 0.002  # dh_u = U - h_u W (px/frame), rad/frame
BETA, BETA_U, BETA_H = 0.02, 0.01, -0.015  # the gain and its slopes across the pool
DERIVS = ("f1_h", "f1_theta", "f1_t", "f2_h", "f2_theta", "f2_t")


def _pool(seed: int = 7, noise: float = 0.0, axial: float = U, gain: float = 1.0):
    """N points pooling all N (unit weights), point 0's offsets as the gain's; ``axial`` the
    axial share U (0: eq. 14 holds); ``gain`` times (BETA, BETA_U, BETA_H) the gain (0: no
    brightness change)."""
    rng = np.random.default_rng(seed)
    h1 = rng.uniform(100.0, 110.0, N)
    h2 = h1 * rng.uniform(2.2, 2.4, N)
    theta = rng.uniform(-0.05, 0.05, N)
    d = dict(h1=h1, h2=h2, theta=theta)
    u = (theta - theta[0]) * h1[0] / SCALE
    dh_off = (h1 - h1[0]) / SCALE
    for un, h in ((1, h1), (2, h2)):
        fh, fq = rng.normal(0, 0.02, N), rng.normal(0, 2.0, N)
        f = rng.uniform(0.2, 0.6, N)
        change = gain * f * (BETA + BETA_U * u + BETA_H * dh_off)  # eq. (9) / (15) right side
        d.update({f"f{un}_h": fh, f"f{un}_theta": fq, f"f{un}": f,
                  f"f{un}_t": change - fh * (axial - h * W) - fq * DTHETA
                  + rng.normal(0, noise, N)})  # fmt: skip
    return d, np.tile(np.arange(N), (N, 1)), np.ones((N, N))


def _solve(d, idx, w, **kw):
    return decoupled_linear_gain(tuple(d[c] for c in DERIVS), (d["f1"], d["f2"]), d["h1"],
                                 d["h2"], d["theta"], idx, w, scale=SCALE,
                                 min_conditioning=0.0, **kw)  # fmt: skip


def test_the_linear_gain_model_recovers_a_flow_breaking_eq14():
    """Exact data: point 0's (dh1, dh2, dtheta) to rounding. Mutation caught: one gain per
    pool (``slopes=False``) misses dh1 by 0.0135 px here (printed)."""
    d, idx, w = _pool()
    a1, a2, b, _ = _solve(d, idx, w)
    assert a1[0] == pytest.approx(U - d["h1"][0] * W, abs=1e-9)
    assert a2[0] == pytest.approx(U - d["h2"][0] * W, abs=1e-9)
    assert b[0] == pytest.approx(DTHETA, abs=1e-12)
    s1, _, _, _ = _solve(d, idx, w, slopes=False)
    print(f"one gain: dh1 error {abs(s1[0] - (U - d['h1'][0] * W)):.4f} px")
    assert abs(s1[0] - (U - d["h1"][0] * W)) > 1e-3


def _brute_force(d, idx, w):
    """The 6-column design of the docstring, numpy, and both fits' F_U."""
    hi = d["h1"][:, None]
    u = ((d["theta"][idx] - d["theta"][:, None] + np.pi) % (2 * np.pi) - np.pi) * hi / SCALE
    dh = (d["h1"][idx] - hi) / SCALE
    X, y = [], []
    for un in (1, 2):
        fh, fq, f, h = (d[f"f{un}_h"][idx], d[f"f{un}_theta"][idx], d[f"f{un}"][idx],
                        d[f"h{un}"][idx])  # fmt: skip
        X.append(np.stack([fh, -fh * h / hi, fq / hi, -f, -f * u, -f * dh], axis=-1))
        y.append(-d[f"f{un}_t"][idx])
    X, y = np.concatenate(X, axis=1), np.concatenate(y, axis=1)
    ww = np.concatenate([w, w], axis=1)
    out = []
    for cols in (slice(0, 6), slice(1, 6)):  # decoupled; coupled (U = 0, eq. 14)
        A = X[..., cols] * np.sqrt(ww)[..., None]
        sol = np.stack([np.linalg.lstsq(a, b, rcond=None)[0] for a, b in
                        zip(A, y * np.sqrt(ww), strict=True)])  # fmt: skip
        res = np.einsum("nkp,np->nk", X[..., cols], sol) - y
        out.append((sol, (ww * res**2).sum(axis=1)))
    (x, rss), (_, rss_c) = out
    n_eff = 2.0 * w.sum(axis=1) ** 2 / (w * w).sum(axis=1)
    return x, (rss_c - rss) / (rss / (n_eff - 6.0))


def test_the_compiled_sums_equal_a_brute_force_design():
    """Noisy pool (so F_U is finite): flow and F_U from the compiled 6 x 6 Gram against
    numpy's least squares on the 6-column design, pools with weights below 1 and a
    neighbour missing (index N). Measured agreement: flow 7e-15, F_U 4e-12 relative.
    Mutation caught: the gain's slopes left out (``slopes=False``) differs from the
    design by 5 % in dh1 and 93 % in F_U."""
    d, idx, w = _pool(seed=3, noise=1e-3)
    rng = np.random.default_rng(0)
    w = w * rng.uniform(0.2, 1.0, w.shape)
    idx = idx.copy()
    idx[:, -1], w[:, -1] = N, 0.0  # no neighbour: the sentinel, weight 0
    a1, a2, b, F = _solve(d, idx, w)
    x, F_ref = _brute_force(d, np.where(idx < N, idx, 0), w)
    np.testing.assert_allclose(a1, x[:, 0] - x[:, 1], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(a2, x[:, 0] - d["h2"] / d["h1"] * x[:, 1], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(b, x[:, 2] / d["h1"], rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(F, F_ref, rtol=1e-8)
    assert np.nanmin(F) > 100.0  # eq. (14) broken by 0.3 px of U: measured 166-256
    F1 = _solve(d, idx, w, slopes=False)[3]
    assert not np.allclose(F1, F_ref, rtol=1e-2)


def _plain_design(d, size):
    """Point 0's (dh1, dh2, dtheta) from numpy's least squares on the decoupled model's
    three columns alone (no gain), unit weights, the first ``size`` points."""
    h0 = d["h1"][0]
    X, y = [], []
    for un in (1, 2):
        fh, fq, h = (d[f"f{un}_h"][:size], d[f"f{un}_theta"][:size], d[f"h{un}"][:size])
        X.append(np.stack([fh, -fh * h / h0, fq / h0], axis=-1))
        y.append(-d[f"f{un}_t"][:size])
    x = np.linalg.lstsq(np.concatenate(X), np.concatenate(y), rcond=None)[0]
    return x[0] - x[1], x[0] - d["h2"][0] / h0 * x[1], x[2] / h0


def test_no_brightness_change_no_gain_in_the_answer(monkeypatch):
    """Pools of 6 points (n_eff 12 for 6 unknowns, as the closed-form synthetic:vertical
    pillar's five switched points), eq. (14) broken (U 0.3 px), no brightness change,
    noise 1e-3 on f_t, 200 seeds: the gain's three columns only add variance, and the
    answer is the decoupled fit without them (numpy's three-column least squares) at 99.0 %
    of the seeds, point 0's mean |dh1 error| 0.0201 px. Mutation caught: the rule off
    (MIN_GAIN_F -inf, every pool answered with its gain): 0 % plain, error 0.0238 px."""

    def run():
        plain, err = [], []
        for seed in range(200):
            d, _, _ = _pool(seed, noise=1e-3, gain=0.0)
            d = {k: v[:6] for k, v in d.items()}
            a1, a2, b, _ = _solve(d, np.tile(np.arange(6), (6, 1)), np.ones((6, 6)))
            ref = _plain_design(d, 6)
            plain.append(np.allclose((a1[0], a2[0], b[0]), ref, rtol=1e-9, atol=1e-12))
            err.append(abs(a1[0] - (U - d["h1"][0] * W)))
        return np.mean(plain), np.mean(err)

    share, err = run()
    print(f"no brightness change: plain answer {share:.3f}, dh1 error {err:.4f} px")
    assert share > 0.95 and err < 0.022  # measured 0.990, 0.0201
    monkeypatch.setattr(gain_mod, "MIN_GAIN_F", -np.inf)
    monkeypatch.setattr(gain_mod, "MIN_GAIN_CHANGE", 0.0)
    share, err = run()
    print(f"rule off: plain answer {share:.3f}, dh1 error {err:.4f} px")
    assert share < 0.05 and err > 0.022  # measured 0.0, 0.0238


def test_a_linear_gain_keeps_the_gain_answer(monkeypatch):
    """The noisy pool with the linear gain of the brute-force test: its gain's F is far
    above MIN_GAIN_F at every point, so every answer is the six-column fit's (checked to
    1e-9 there). Mutation caught: every pool answered without the gain (MIN_GAIN_F and
    MIN_GAIN_CHANGE infinite) misses the six-column dh1 by up to 0.054 px."""
    d, idx, w = _pool(seed=3, noise=1e-3)
    a1 = _solve(d, idx, w)[0]
    x, _ = _brute_force(d, idx, w)
    np.testing.assert_allclose(a1, x[:, 0] - x[:, 1], rtol=1e-9, atol=1e-12)
    monkeypatch.setattr(gain_mod, "MIN_GAIN_F", np.inf)
    monkeypatch.setattr(gain_mod, "MIN_GAIN_CHANGE", np.inf)
    p1 = _solve(d, idx, w)[0]
    print(f"without the gain: dh1 off by {np.abs(p1 - (x[:, 0] - x[:, 1])).max():.3f} px")
    assert np.abs(p1 - (x[:, 0] - x[:, 1])).max() > 0.03  # measured 0.054


RISING = Motion(vz=0.001)  # the wall rising 1 mm per frame: cam1 radial flow 0.18 px
AMP = 0.02  # frame t + 1 times 1 + AMP sin(2 theta)


def _run(wall=RISING, amp=AMP, **knobs):
    """(result, cam1 endpoint error per point) on the wall scene under the gain field."""
    res, err, dh = wall_under_gain_field(wall, amp, **knobs)
    print(f"wall {wall}, amp {amp} {knobs}: {err.size} points, decoupled "
          f"{np.mean(res['coupled'] == 0):.2f}, EPE mean {err.mean():.4f} median "
          f"{np.median(err):.4f}, mean dh {res['dh1_dt'].mean():+.4f} "
          f"of {dh.mean():+.4f}")  # fmt: skip
    return res, err


def test_the_test_with_the_gain_finds_the_rising_wall(monkeypatch):
    """Without it (decouple_gain_tol None; decouple_tol 20, brightness_gate 20): the gain
    field hides the rise from the plain two-model test at most points (29 % decoupled),
    mean dh 0.122 of 0.180 px, EPE mean 0.0896. decouple_gain_tol 20 (the default): every
    point decoupled, mean dh 0.1805, EPE 0.0086 (no gain field: 0.0022 at 20, 0.0017
    without it, both every point decoupled). Mutation caught: one gain per pool in the
    test and the model (``slopes=False``): EPE 0.0340."""
    _, plain = _run(brightness={"decouple_gain_tol": None})
    res, chain = _run(brightness={"decouple_gain_tol": 20.0})
    assert (res["coupled"] == 0).all()
    assert chain.mean() < 0.15 * plain.mean()  # measured 0.096
    assert chain.mean() < 0.015  # measured 0.0086
    single = functools.partial(decoupled_linear_gain, slopes=False)
    monkeypatch.setattr(decoupled_mod, "decoupled_linear_gain", single)
    _, mutated = _run(brightness={"decouple_gain_tol": 20.0})
    assert not mutated.mean() < 0.015  # measured 0.0340


def test_the_rising_wall_without_a_brightness_change(monkeypatch):
    """The wall rising 1 mm/frame, no gain field: the plain two-model test decouples every
    point already; the linear-gain test passes them too, and its answer is the fit without
    the gain (the gain's F at most MIN_GAIN_F, its terms below MIN_GAIN_CHANGE), so every
    flow column equals decouple_gain_tol None's to rounding (measured 3e-14 px), EPE mean
    0.0017. Mutation caught: the rule off (every pool answered with its gain): EPE mean
    0.0022, dh1 and dh2 off by up to 0.013 px (mean 4e-4)."""
    plain, _ = _run(amp=0.0, brightness={"decouple_gain_tol": None})
    res, err20 = _run(amp=0.0, brightness={"decouple_gain_tol": 20.0})
    for name in ("dh1_dt", "dh2_dt", "dtheta_dt", "dx", "dy", "dx2", "dy2", "dr_dt", "coupled"):
        np.testing.assert_allclose(res[name], plain[name], rtol=0, atol=1e-12, err_msg=name)
    assert err20.mean() < 0.002  # measured 0.0017 (None: 0.0017)
    monkeypatch.setattr(gain_mod, "MIN_GAIN_F", -np.inf)
    monkeypatch.setattr(gain_mod, "MIN_GAIN_CHANGE", 0.0)
    _, mutated = _run(amp=0.0, brightness={"decouple_gain_tol": 20.0})
    assert mutated.mean() > 0.002  # measured 0.0022


def test_no_switch_where_eq14_holds(monkeypatch):
    """The wall at rest under the same gain field (eq. 14 holds, the brightness changes):
    no point switches at 20, so every column equals those without it. Even at a gate of 1
    only 0.2 % switch (1 of 419): the coupled fit's residual is never twice the
    decoupled one's (MIN_RESIDUAL_RATIO). Mutations caught: that ratio at 1 (F_U alone)
    lets a gate of 1 switch 12 % of the points (eq. 14 no longer imposed where it holds)."""
    plain, _ = _run(wall=Motion(), brightness={"decouple_gain_tol": None})
    chain, _ = _run(wall=Motion(), brightness={"decouple_gain_tol": 20.0})
    for name, col in plain.columns.items():
        np.testing.assert_array_equal(chain[name], col, err_msg=name)
    loose, _ = _run(wall=Motion(), brightness={"decouple_gain_tol": 1.0})
    assert (loose["coupled"] == 0).mean() < 0.02  # measured 0.0024
    monkeypatch.setattr(gain_mod, "MIN_RESIDUAL_RATIO", 1.0)
    loose, _ = _run(wall=Motion(), brightness={"decouple_gain_tol": 1.0})
    assert (loose["coupled"] == 0).mean() > 0.05  # measured 0.12


def test_the_lower_gate_at_range_edges(monkeypatch):
    """:func:`omniflow.solve.decoupled.chained`: F_U 12 passes on a range-edge pool (gate 10 at
    decouple_gain_tol 20) and not elsewhere; 25 passes both; NaN answers never. Mutation
    caught: EDGE_GATE 1 (no lower gate) rejects the edge pool."""
    one = np.ones(4)
    fit = dict(gain_F=np.array([12.0, 12.0, 25.0, 25.0]), gain_edge=np.array([1, 0, 0, 1], bool),
               gain_a1=one, gain_a2=one, gain_b=np.array([1.0, 1.0, 1.0, np.nan]))  # fmt: skip
    assert decoupled_mod.chained(fit, 20.0).tolist() == [True, False, True, False]
    monkeypatch.setattr(decoupled_mod, "EDGE_GATE", 1.0)
    assert decoupled_mod.chained(fit, 20.0).tolist() == [False, False, True, False]


def _null_f(size, seeds=400):
    """F_U of point 0 in pools of ``size`` points (unit weights, n_eff = 2 size) of
    :func:`_pool` with U = 0 (eq. 14 holds) and noise 0.01 on f_t, one per seed."""
    out = []
    for seed in range(seeds):
        d, _, _ = _pool(seed, noise=0.01, axial=0.0)
        d = {k: v[:size] for k, v in d.items()}
        out.append(_solve(d, np.tile(np.arange(size), (size, 1)), np.ones((size, size)))[3][0])
    return np.array(out)


def test_too_few_residual_degrees_of_freedom_give_no_test(monkeypatch):
    """Eq. (14) holds (U = 0), Gaussian noise: in pools of 4 points (n_eff 8, 2 residual
    degrees of freedom for 6 unknowns) F_U is not computed (MIN_RESIDUAL_DOF 4); pools of 5
    (n_eff 10) are tested, and pass 20 in 0.5 % of 400 seeds (F(1, 4): 1.1 %). Mutation
    caught: MIN_RESIDUAL_DOF 0 lets the pools of 4 pass 20 in 5.25 % of the seeds (F(1, 2):
    4.7 %), the false switches of approach's small static pools. The residual ratio is
    not tested here (MIN_RESIDUAL_RATIO 1: under the null it rejects most pools)."""
    monkeypatch.setattr(gain_mod, "MIN_RESIDUAL_RATIO", 1.0)
    assert np.isnan(_null_f(4)).all()
    five = _null_f(5)
    assert np.isfinite(five).all() and np.mean(five > 20.0) < 0.02  # measured 0.005
    monkeypatch.setattr(gain_mod, "MIN_RESIDUAL_DOF", 0.0)
    assert np.mean(_null_f(4) > 20.0) > 0.02  # measured 0.0525 (binomial sd 0.011)


@pytest.mark.parametrize("tol", [0.0, -1.0, float("nan")])
def test_bad_tol(tol):
    with pytest.raises(ValueError, match="decouple_gain_tol"):
        OmniFlowConfig(brightness={"decouple_gain_tol": tol})


def test_the_default_and_the_presets():
    """20 by default, 60 in the dense preset (its larger pools), None in the paper's
    configuration (eq. 14 as written)."""
    assert OmniFlowConfig().brightness.decouple_gain_tol == 20.0
    assert OmniFlowConfig.dense().brightness.decouple_gain_tol == 60.0
    assert OmniFlowConfig.paper().brightness.decouple_gain_tol is None


def test_nothing_without_the_test_it_extends():
    """decouple_tol None (no test of eq. 14 at all): the rising wall's every point stays
    coupled whatever decouple_gain_tol (20, the default, here)."""
    res, _ = _run(decouple_tol=None)
    assert (res["coupled"] == 1).all()
