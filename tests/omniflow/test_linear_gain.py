"""The coupled pools' linear gain (``OmniFlowConfig.brightness_model`` "linear") against truth.

1. One closed-form pool whose flow keeps eq. (14) (dh_2 = (h_2 / h_1) dh_1, the pooled
   model's relative radial column) under a gain varying linearly across it,
   (beta + beta_u u_j + beta_h dh_j) f_j (texture turning through shading that stays
   put: independent_movers' spinner): :func:`omniflow.solve.gain.gain_solution` with
   ``linear_gain`` returns the flow exactly, and its sums and F statistic equal a
   brute-force numpy design's, for both pool models.
2. Its gates: no F where fewer than MIN_RESIDUAL_DOF residual degrees of freedom
   estimate the variance, nor where every fitted term is below MIN_GAIN_CHANGE.
3. End to end through :func:`omniflow.pipeline.estimate`: the striped wall of
   tests/helpers/scenes.py at rest under the gain field 1 + 0.08 sin(2 theta) (the form of
   tests/omniflow/test_decouple_gain.py's field, stronger). Errors are cam1 endpoint
   errors, px per frame; figures measured with these exact scenes (python -m pytest -s prints them).
"""

from __future__ import annotations

import numpy as np
import pytest

import omniflow.solve.gain as gain_mod
from omniflow.config import OmniFlowConfig
from omniflow.solve.gain import gain_solution
from omnisim.synthetic import Motion
from tests.helpers.scenes import wall_under_gain_field

N, SCALE = 30, 8.0
A0, DTHETA = 0.25, 0.002  # point 0's radial flow (px/frame), rad/frame
BETA, BETA_U, BETA_H = 0.003, 0.04, -0.03  # the gain and its slopes: little level, a gradient
DERIVS = ("f1_h", "f1_theta", "f1_t", "f2_h", "f2_theta", "f2_t")


def _pool(seed: int = 7, noise: float = 0.0, gain: float = 1.0, size: int = N,
          terms: tuple[float, float, float] = (BETA, BETA_U, BETA_H)):  # fmt: skip
    """``size`` points pooling all (unit weights); the flow keeps eq. (14) with the radial
    flow scaling with h_1 (dh_u,j = A0 h_u,j / h_1,0); ``gain`` times ``terms`` (beta,
    beta_u, beta_h) the gain across the pool (0: no brightness change), offsets from
    point 0."""
    beta, beta_u, beta_h = terms
    rng = np.random.default_rng(seed)
    h1 = rng.uniform(100.0, 110.0, size)
    h2 = h1 * rng.uniform(2.2, 2.4, size)
    theta = rng.uniform(-0.05, 0.05, size)
    d = dict(h1=h1, h2=h2, theta=theta)
    u = (theta - theta[0]) * h1[0] / SCALE
    dh_off = (h1 - h1[0]) / SCALE
    for un, h in ((1, h1), (2, h2)):
        fh, fq = rng.normal(0, 0.02, size), rng.normal(0, 2.0, size)
        f = rng.uniform(0.2, 0.6, size)
        change = gain * f * (beta + beta_u * u + beta_h * dh_off)  # eq. (9) / (15) right side
        d.update({f"f{un}_h": fh, f"f{un}_theta": fq, f"f{un}": f,
                  f"f{un}_t": change - fh * A0 * h / h1[0] - fq * DTHETA
                  + rng.normal(0, noise, size)})  # fmt: skip
    return d, np.tile(np.arange(size), (size, 1)), np.ones((size, size))


def _solve(d, idx, w, model="linear", **kw):
    return gain_solution(tuple(d[c] for c in DERIVS), (d["f1"], d["f2"]), d["h1"], d["h2"],
                         d["theta"], idx, w, model=model, scale=SCALE, min_conditioning=0.0,
                         **kw)  # fmt: skip


@pytest.mark.parametrize("model", ["linear", "constant"])
def test_the_linear_gain_recovers_the_flow(model):
    """Exact data: every point's (dh1, dtheta) to rounding (point i's pool relative to i:
    the gain is linear in the offsets from any point). Mutation caught: one gain per pool
    (``linear_gain`` False) misses point 0's dh1 by 0.081 px (linear) and 0.045 px
    (constant)."""
    d, idx, w = _pool()
    a, b, _, _ = _solve(d, idx, w, model=model, linear_gain=True)
    np.testing.assert_allclose(a, A0 * d["h1"] / d["h1"][0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(b, DTHETA, rtol=0, atol=1e-12)
    one, _, _, _ = _solve(d, idx, w, model=model)
    print(f"{model}: one gain, dh1 error {abs(one[0] - A0):.4f} px")
    assert abs(one[0] - A0) > 0.01


def _brute_force(d, idx, w, model):
    """numpy's weighted least squares on the design of gain_solution's docstring: the flow's
    columns (p, q[, p u, q u]) then -f, -f u, -f dh; point i's (a, c / h1) and the F of
    the three gain columns against the flow's alone."""
    hi = d["h1"][:, None]
    u = ((d["theta"][idx] - d["theta"][:, None] + np.pi) % (2 * np.pi) - np.pi) * hi / SCALE
    dh = (d["h1"][idx] - hi) / SCALE
    rel = d["h1"][idx] / hi
    X, y = [], []
    for un in (1, 2):
        k = 1.0 if un == 1 else d["h2"][idx] / d["h1"][idx]  # eq. (14)
        p, q, f = k * d[f"f{un}_h"][idx] * rel, d[f"f{un}_theta"][idx] / hi, d[f"f{un}"][idx]
        flow = [p, q] + ([p * u, q * u] if model == "linear" else [])
        X.append(np.stack([*flow, -f, -f * u, -f * dh], axis=-1))
        y.append(-d[f"f{un}_t"][idx])
    X, y = np.concatenate(X, axis=1), np.concatenate(y, axis=1)
    ww = np.concatenate([w, w], axis=1)
    P = X.shape[-1]
    out = []
    for cols in (slice(0, P), slice(0, P - 3)):  # with the gain; the flow alone
        A = X[..., cols] * np.sqrt(ww)[..., None]
        sol = np.stack([np.linalg.lstsq(a, b, rcond=None)[0] for a, b in
                        zip(A, y * np.sqrt(ww), strict=True)])  # fmt: skip
        res = np.einsum("nkp,np->nk", X[..., cols], sol) - y
        out.append((sol, (ww * res**2).sum(axis=1)))
    (x, rss), (_, rss0) = out
    n_eff = 2.0 * w.sum(axis=1) ** 2 / (w * w).sum(axis=1)
    return x[:, 0], x[:, 1] / d["h1"], (rss0 - rss) / 3.0 / (rss / (n_eff - P))


@pytest.mark.parametrize("model", ["linear", "constant"])
def test_the_compiled_sums_equal_a_brute_force_design(model):
    """Noisy pool (so F is finite), weights below 1 and a neighbour missing (index N): flow
    and F against numpy's least squares on the design. Mutations caught: the gain's
    radial slope left out of the sums (column -f dh as -f u) or F not divided by the
    three columns both break the F comparison (the latter by a factor 3)."""
    d, idx, w = _pool(seed=3, noise=1e-3)
    rng = np.random.default_rng(0)
    w = w * rng.uniform(0.2, 1.0, w.shape)
    idx = idx.copy()
    idx[:, -1], w[:, -1] = N, 0.0  # no neighbour: the sentinel, weight 0
    a, b, _, F = _solve(d, idx, w, model=model, linear_gain=True)
    a_ref, b_ref, F_ref = _brute_force(d, np.where(idx < N, idx, 0), w, model)
    np.testing.assert_allclose(a, a_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(b, b_ref, rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(F, F_ref, rtol=1e-8)
    assert np.nanmin(F) > 100.0  # the gain's slopes 3-4 % a radius, noise 1e-3


def test_too_few_residual_degrees_of_freedom_give_no_f(monkeypatch):
    """Pools of 5 points (n_eff 10) for the linear model's 7 unknowns: 3 residual degrees of
    freedom, F NaN (MIN_RESIDUAL_DOF 4: the static points at the spinner's silhouette had
    2.8-2.9); pools of 6 (5 of them) are tested. Mutation caught: MIN_RESIDUAL_DOF 0 gives
    the pools of 5 an F."""
    d, idx, w = _pool(seed=3, noise=1e-3, size=5)
    assert np.isnan(_solve(d, idx, w, linear_gain=True)[3]).all()
    d6, idx6, w6 = _pool(seed=3, noise=1e-3, size=6)
    assert np.isfinite(_solve(d6, idx6, w6, linear_gain=True)[3]).all()
    monkeypatch.setattr(gain_mod, "MIN_RESIDUAL_DOF", 0.0)
    assert np.isfinite(_solve(d, idx, w, linear_gain=True)[3]).all()


def test_no_f_without_a_change(monkeypatch):
    """No brightness change, noise 1e-4 on f_t: every fitted term below MIN_GAIN_CHANGE
    (0.02), so no F (model error, not a change). Mutation caught: MIN_GAIN_CHANGE 0 gives
    every pool an F."""
    d, idx, w = _pool(seed=5, noise=1e-4, gain=0.0)
    assert np.isnan(_solve(d, idx, w, linear_gain=True)[3]).all()
    monkeypatch.setattr(gain_mod, "MIN_GAIN_CHANGE", 0.0)
    assert np.isfinite(_solve(d, idx, w, linear_gain=True)[3]).all()


def test_one_gain_where_the_slopes_add_nothing():
    """With the gate (20, as ``brightness_gate``): a pool whose change is a level (beta 0.02,
    no slopes: approach's face) keeps the one-gain answer at every point, to rounding (the
    sums made in another order; one gain's F passes, the slopes' F against it does not);
    a pool with the slopes and little level (the spinner's) takes the linear gain's (one
    gain's F does not pass).
    The same with the errors-in-variables correction (noise 1e-5; it moves dh1 by up to
    0.012 px). Mutations caught: the linear gain wherever it passes (no preference,
    ``gate`` None) moves the level pool's dh1 by up to 3.2e-4 px (the slopes' two unknowns
    fitting noise); the one-gain pools corrected in the full 7 x 7 Gram instead of their
    own block differ at all 30 points."""
    d, idx, w = _pool(seed=3, noise=1e-3, terms=(0.02, 0.0, 0.0))
    one = _solve(d, idx, w)
    lin = _solve(d, idx, w, linear_gain=True, gate=20.0)
    assert (one[3] > 20.0).all()
    for got, ref in zip(lin, one, strict=True):
        np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-12)
    # with the errors-in-variables correction too (each fit corrected in its own block)
    eiv = dict(noise=(1e-5, 1e-5), gate=20.0)
    np.testing.assert_allclose(_solve(d, idx, w, linear_gain=True, **eiv)[0],
                               _solve(d, idx, w, **eiv)[0], rtol=1e-9, atol=1e-12)  # fmt: skip
    free = _solve(d, idx, w, linear_gain=True)[0]
    print(f"level: linear gain moves dh1 by up to {np.abs(free - one[0]).max():.1e} px")
    assert np.abs(free - one[0]).max() > 1e-4
    d, idx, w = _pool(seed=3, noise=1e-3)
    np.testing.assert_array_equal(_solve(d, idx, w, linear_gain=True, gate=20.0)[0],
                                  _solve(d, idx, w, linear_gain=True)[0])  # fmt: skip
    assert not (_solve(d, idx, w, gate=20.0)[3] > 20.0).any()


def test_config():
    """The default "linear"; "gain" selectable; anything else refused."""
    assert OmniFlowConfig().brightness.brightness_model == "linear"
    assert (
        OmniFlowConfig(brightness={"brightness_model": "gain"}).brightness.brightness_model
        == "gain"
    )
    with pytest.raises(ValueError, match="brightness_model"):
        OmniFlowConfig(brightness={"brightness_model": "offset"})
    with pytest.raises(ValueError, match="k-d tree"):  # the kernel itself refuses the grid
        _solve(*_pool(), linear_gain=True, grid=object())


# frame t + 1 times 1 + AMP sin(2 theta): slopes of 2-4 % over a pool radius, above
# MIN_GAIN_CHANGE (0.02; the spinner's 9-13 %). The field of test_decouple_gain.py, 0.02,
# has slopes of 0.5-1 % a radius, which the default leaves to one gain (0.0280 against
# one gain's 0.0288 mean EPE; 0.0077 with a least term of MIN_CHANGE, 0.002, which on the
# noise-free striped wall of test_brightness_gate.py took model error for a change).
AMP = 0.08
AT_REST = Motion()


def _run(wall=AT_REST, amp=AMP, **knobs):
    """(result, cam1 endpoint error per point) on the wall scene under the gain field."""
    res, err, _ = wall_under_gain_field(wall, amp, **knobs)
    print(f"wall {wall}, amp {amp} {knobs}: {err.size} points, EPE mean {err.mean():.4f} "
          f"median {np.median(err):.4f}")  # fmt: skip
    return res, err


def test_the_wall_at_rest_under_a_gain_field():
    """The wall at rest (true flow 0) under the gain field (419 points): one gain per pool
    leaves EPE mean 0.1366 (median 0.0723), the linear gain (the default) 0.0260 (0.0200).
    Without the field the linear model changes nothing (EPE 0 both: no F, every term below
    MIN_CHANGE). Mutation caught: make_solver not passing ``linear_gain`` (the knob
    ignored) gives the one-gain figure."""
    _, one = _run(brightness={"brightness_model": "gain"})
    _, lin = _run()
    assert lin.mean() < 0.4 * one.mean() and lin.mean() < 0.035  # measured 0.19x, 0.0260
    flat, _ = _run(amp=0.0, brightness={"brightness_model": "gain"})
    flat_lin, _ = _run(amp=0.0)
    for name in ("dh1_dt", "dtheta_dt"):
        np.testing.assert_array_equal(flat_lin[name], flat[name], err_msg=name)
