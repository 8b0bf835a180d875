"""Grid pooling (omniflow.solve.gridpool, ``pool_grid``): the pooled solver's sums by filtering.

Checked against closed-form references:

* points on cell centres (no binning error): the grid's sums equal the brute-force
  sums over every pair, with the Gaussian of the pair's offset on the square window,
  u the tangential component of the offset, and the range bins' weights of the
  module's docstring (float32 filters: measured 1.3e-7 relative to the largest entry);
* a flow field that the pooled model holds exactly at every point (dh_1/dt = alpha h_1,
  dtheta/dt = beta) from exact equations at arbitrary positions: pooled_solution with
  the grid returns it (measured 3e-7 relative);
* the closed-form motion boundary of test_pooling.py (true matches at 10 % of the
  pixels): the grid's band ratio and wall EPE no worse than the k-d tree's.

Each check has a mutation that it catches (the tests named ``..._catches_...``).
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from omniflow.config import OmniFlowConfig
from omniflow.pipeline import estimate
from omniflow.solve.decoupled import screen
from omniflow.solve.gain import decoupled_linear_gain, gated
from omniflow.solve.gain_kernels import gain_sums, nested_fits
from omniflow.solve.gridpool import GridPools
from omniflow.solve.pooled import neighbourhoods, pooled_solution
from tests.helpers.scenes import band_scene, frames, paper_rig, sparse_true_matches

RADIUS, CELL, SHAPE = 16.0, 2.0, (128, 160)


def _cell_centre_case(seed: int = 0, n: int = 400, ranges: bool = False):
    """Points on distinct cell centres, random derivatives, tangents and (optionally) ranges."""
    rng = np.random.default_rng(seed)
    gh, gw = SHAPE[0] // int(CELL), SHAPE[1] // int(CELL)
    cells = rng.choice(gh * gw, size=n, replace=False)
    x = (cells % gw + 0.5) * CELL
    y = (cells // gw + 0.5) * CELL
    ang = rng.uniform(-np.pi, np.pi, n)
    tangent = np.column_stack([np.cos(ang), np.sin(ang)])
    derivs = tuple(rng.normal(size=n) for _ in range(6))
    h1 = rng.uniform(40.0, 120.0, n)
    r = np.exp(rng.uniform(0.0, 0.5, n)) if ranges else None
    return x, y, tangent, derivs, h1, r


def _window_weights(x, y, r, tol):
    """(x_j - x_i, y_j - y_i, w_ij) by the definition: the Gaussian of the pool radius
    inside the square window, times the linear share of j's range bin where ``r`` is given."""
    dx, dy = x[None, :] - x[:, None], y[None, :] - y[:, None]  # [i, j]: x_j - x_i
    half = round(RADIUS / CELL) * CELL
    w = np.exp(-0.5 * (dx**2 + dy**2) / (RADIUS / 2.0) ** 2)
    w *= (np.abs(dx) <= half + 1e-9) & (np.abs(dy) <= half + 1e-9)
    if r is not None:
        pos = np.log(r) / math.log1p(tol)
        b = np.floor(pos)
        f = (pos - b)[:, None]
        db = b[None, :] - b[:, None]  # bin of j minus bin of i
        w *= np.where(db == 0, 1.0, np.where(db == -1, 1.0 - f, np.where(db == 1, f, 0.0)))
    return dx, dy, w


def _brute_force(x, y, tangent, derivs, h1, r, tol, scale):
    """sum_j w_ij u_ij^m (pp, pq, qq, pf, qf) by the definition, (N, 3, 5), and sum_j w u^m."""
    f1h, f1th, f1t, kf2h, f2th, f2t = derivs
    dx, dy, w = _window_weights(x, y, r, tol)
    u = (tangent[:, 0:1] * dx + tangent[:, 1:2] * dy) / scale
    hi = h1[:, None]
    rel = h1[None, :] / hi
    p1, p2 = f1h[None, :] * rel, kf2h[None, :] * rel
    q1, q2 = f1th[None, :] / hi, f2th[None, :] / hi
    t1, t2 = f1t[None, :], f2t[None, :]
    terms = [p1 * p1 + p2 * p2, p1 * q1 + p2 * q2, q1 * q1 + q2 * q2, p1 * t1 + p2 * t2,
             q1 * t1 + q2 * t2]  # fmt: skip
    sums = np.stack([np.stack([(w * u**m * t).sum(1) for t in terms], -1) for m in range(3)], 1)
    wsum = np.stack([(w * u**m).sum(1) for m in range(3)], 1)
    return sums, wsum


def _rel_err(a, b):
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


@pytest.mark.parametrize("ranges", [False, True])
def test_grid_sums_equal_the_brute_force_sums(ranges):
    x, y, tangent, derivs, h1, r = _cell_centre_case(ranges=ranges)
    tol, scale = 0.1, RADIUS
    grid = GridPools(x, y, tangent, SHAPE, radius=RADIUS, cell=CELL, r=r, range_tol=tol)
    sums, wsum = grid.sums(derivs, h1, linear=True, scale=scale)
    ref, ref_w = _brute_force(x, y, tangent, derivs, h1, r, tol, scale)
    for m in range(3):  # each power's entries against their own magnitude
        assert _rel_err(sums[:, m], ref[:, m]) < 1e-5  # measured 3e-8 - 1.1e-7 (float32)
        assert _rel_err(wsum[:, m], ref_w[:, m]) < 1e-5  # measured 6e-8 - 1.3e-7


@pytest.mark.parametrize("mutation", ["moment_sign", "range_share", "no_range"])
def test_grid_sums_check_catches_mutations(mutation):
    """The brute-force check fails when the first-moment kernel's sign is flipped, when the
    neighbouring bins' shares are swapped (f for 1 - f), or when the range test is off."""
    x, y, tangent, derivs, h1, r = _cell_centre_case(ranges=True)
    tol, scale = 0.1, RADIUS
    grid = GridPools(x, y, tangent, SHAPE, radius=RADIUS, cell=CELL, r=r,
                     range_tol=None if mutation == "no_range" else tol)  # fmt: skip
    if mutation == "moment_sign":
        grid.kernels[1] = -grid.kernels[1]
    elif mutation == "range_share":
        grid.frac = 1.0 - grid.frac
    sums, _ = grid.sums(derivs, h1, linear=True, scale=scale)
    ref, _ = _brute_force(x, y, tangent, derivs, h1, r, tol, scale)
    # measured: moment sign 2.0 (power 1), shares 0.37-0.50, no range 0.78-1.99
    assert max(_rel_err(sums[:, m], ref[:, m]) for m in range(3)) > 1e-2


def _brute_force_decouple(x, y, derivs, h1, h2, r, tol):
    """The two-model test's sums (omniflow.solve.decouple_kernels.DECOUPLE_SUMS) by the
    definition."""
    f1h, f1th, f1t, f2h, f2th, f2t = derivs
    _, _, w = _window_weights(x, y, r, tol)
    a, bb, q, t = (f1h, f2h), (f1h * h1, f2h * h2), (f1th, f2th), (f1t, f2t)
    pairs = [(a, a), (a, bb), (a, q), (bb, bb), (bb, q), (q, q), (a, t), (bb, t), (q, t), (t, t)]
    cols = [w @ (u[0] * v[0] + u[1] * v[1]) for u, v in pairs]
    return np.column_stack([*cols, w.sum(1), (w * w).sum(1)])


@pytest.mark.parametrize("ranges", [False, True])
def test_grid_decouple_sums_equal_the_brute_force_sums(ranges):
    x, y, _, derivs, h1, r = _cell_centre_case(ranges=ranges)
    h2 = h1 * 1.6
    grid = GridPools(x, y, None, SHAPE, radius=RADIUS, cell=CELL, r=r, range_tol=0.1)
    got = grid.decouple_sums(derivs, h1, h2)
    ref = _brute_force_decouple(x, y, derivs, h1, h2, r, 0.1)
    errs = np.abs(got - ref).max(axis=0) / np.abs(ref).max(axis=0)
    assert errs.max() < 1e-12  # measured 3.9e-16 (float64 filters)


def test_grid_decouple_check_catches_unsquared_shares():
    """Mutation: the squared weights read with the bin shares instead of their squares
    (measured 0.17 relative on the sum of squared weights)."""
    x, y, _, derivs, h1, r = _cell_centre_case(ranges=True)
    grid = GridPools(x, y, None, SHAPE, radius=RADIUS, cell=CELL, r=r, range_tol=0.1)
    ref = _brute_force_decouple(x, y, derivs, h1, 1.6 * h1, r, 0.1)
    g2 = grid.gauss**2
    w2 = grid._filter(np.ones((x.size, 1)), [(g2, g2, 1)])[0][:, 0]
    assert np.abs(w2 - ref[:, 11]).max() / ref[:, 11].max() > 1e-2


def _exact_field(seed: int = 3, n: int = 3000, alpha: float = 0.004, beta: float = -0.003):
    """Exact eq. (9) and (15) of the field dh_1/dt = alpha h_1, dtheta/dt = beta at random
    points of a polar image (centre (128, 128)): the pooled model holds in every pool."""
    rng = np.random.default_rng(seed)
    h1 = rng.uniform(30.0, 120.0, n)
    theta = rng.uniform(-np.pi, np.pi, n)
    h2 = h1 * rng.uniform(1.3, 1.8, n)
    x, y = 128.0 + h1 * np.cos(theta), 128.0 + h1 * np.sin(theta)
    tangent = np.column_stack([-np.sin(theta), np.cos(theta)])
    f1h, f1th, f2h, f2th = (rng.normal(size=n) for _ in range(4))
    f1th, f2th = f1th * h1, f2th * h1  # grey per radian: the tangential gradient times h_1
    a, b = alpha * h1, np.full(n, beta)
    f1t = -(f1h * a + f1th * b)  # eq. (9)
    f2t = -((h2 / h1) * f2h * a + f2th * b)  # eq. (15)
    return (f1h, f1th, f1t, f2h, f2th, f2t, h1, h2), theta, x, y, tangent, a, b


def _field_errors(model: str, mutate=None) -> tuple[float, float, float]:
    """(share solved, max |a error| / max |a|, max |b error| / |beta|) of the exact field."""
    args, theta, x, y, tangent, a, b = _exact_field()
    grid = GridPools(x, y, tangent, (256, 256), radius=16.0, cell=2.0)
    if mutate is not None:
        mutate(grid)
    pa, pb, _ = pooled_solution(*args, None, None, theta=theta, model=model, scale=16.0,
                                grid=grid)  # fmt: skip
    ok = np.isfinite(pa)
    return (float(ok.mean()), float(np.max(np.abs(pa[ok] - a[ok])) / np.max(np.abs(a))),
            float(np.max(np.abs(pb[ok] - b[ok])) / abs(b[0])))  # fmt: skip


@pytest.mark.parametrize("model", ["constant", "linear"])
def test_grid_pooled_solution_recovers_an_exact_field(model):
    share, err_a, err_b = _field_errors(model)
    print(f"{model}: solved {share:.3f}, errors {err_a:.1e} {err_b:.1e}")
    assert share > 0.99  # measured 1.0
    assert err_a < 1e-4  # measured 2.1e-7 (linear), 1.9e-7 (constant): float32 filters
    assert err_b < 1e-4  # measured 2.7e-7, 2.6e-7


def test_exact_field_check_catches_a_wrong_radius_factor(monkeypatch):
    """Mutation: the scattered terms without the relative model's h_1,j (every neighbour's
    h_1 taken as the mean): the field's radial part is missed by far more than the bound."""
    orig = GridPools.sums

    def wrong(self, derivs6, h1, **kw):
        return orig(self, derivs6, np.full_like(h1, h1.mean()), **kw)

    monkeypatch.setattr(GridPools, "sums", wrong)
    _, err_a, _ = _field_errors("linear")
    print(f"mutation: error {err_a:.1e}")
    assert err_a > 1e-4  # measured 7e-2


@pytest.fixture(scope="module")
def boundary():
    rig = paper_rig(256)
    scene = band_scene(rig, yaw=0.01)
    f1, f2 = frames(scene, 2)
    m, gt = sparse_true_matches(scene, 0.1)
    return rig, f1, f2, m, gt


def _band(boundary, **knobs) -> tuple[float, float]:
    """(mean estimated / true h_1 dtheta/dt on the band, mean EPE on the wall)."""
    rig, f1, f2, m, gt = boundary
    res = estimate(f1, f2, rig, OmniFlowConfig(**knobs), matches=m)
    iy, ix = res["y"].astype(int), res["x"].astype(int)
    obj = gt["gt.object"][iy, ix]
    true_dh, true_tan = gt["gt.flow.dh"][iy, ix], gt["gt.flow.hdtheta"][iy, ix]
    est_tan = res["h1"] * res["dtheta_dt"]
    epe = np.hypot(res["dh1_dt"] - true_dh, est_tan - true_tan)
    band, wall = obj == 2, obj == 1
    return float(est_tan[band].mean() / true_tan[band].mean()), float(epe[wall].mean())


def test_grid_pools_at_a_motion_boundary_no_worse_than_the_tree(boundary):
    """Closed-form motion boundary, true matches at 10 % of the pixels: the band keeps 0.758
    of its flow with the grid (0.750 with the tree), the wall's mean EPE 0.0179 px (0.0193)."""
    tree_ratio, tree_wall = _band(boundary)
    ratio, wall = _band(
        boundary, pooling={"pool_grid": 0.125}, brightness={"brightness_model": "gain"}
    )
    print(
        f"grid: band ratio {ratio:.3f} (tree {tree_ratio:.3f}); wall {wall:.4f} ({tree_wall:.4f})"
    )
    assert ratio >= tree_ratio - 0.02  # measured +0.008
    assert wall <= 1.05 * tree_wall  # measured 0.93x


def test_boundary_check_catches_grid_pools_without_the_range_test(boundary):
    """Mutation: the grid without its range bins (pool_range_tol None). The band (1.85 m) and
    the wall (2.0 m) fall in neighbouring bins, which count only by their share of the
    window, so without the bins the band's pools take more of the wall: band ratio 0.659
    and wall EPE 0.0211 px, both outside the check's bounds (the tree's 0.750 - 0.02 and
    1.05 x 0.0193)."""
    tree_ratio, tree_wall = _band(boundary)
    ratio, wall = _band(
        boundary,
        pooling={"pool_grid": 0.125, "pool_range_tol": None},
        brightness={"brightness_model": "gain"},
    )
    assert ratio < tree_ratio - 0.02  # measured 0.659
    assert wall > 1.05 * tree_wall  # measured 1.09x


def test_grid_pools_reject_the_linear_gain():
    """Grid pools fit one gain per pool: ``brightness_model="linear"`` with them is an error
    (main fell back to one gain, silently); without the gain fit there is no conflict."""
    message = re.escape("pooling.pool_grid = 0.125 with brightness.brightness_model = 'linear'")
    with pytest.raises(ValueError, match=message):
        OmniFlowConfig(pooling={"pool_grid": 0.125})
    OmniFlowConfig(brightness_gate=None, pooling={"pool_grid": 0.125})
    OmniFlowConfig(pooling={"pool_grid": 0.125}, brightness={"brightness_model": "gain"})


def _brute_force_gain(x, y, tangent, derivs, f, h1, h2, r, tol, scale):
    """The gain fit's normal equations (omniflow.solve.gain_kernels.gain_sums's layout, linear
    model)
    by the definition: every pair's two rows (p, q, p u, q u, -f) and right side -f_t,
    weighted; and the sums of the weights and their squares."""
    f1h, f1th, f1t, f2h, f2th, f2t = derivs
    _, _, w = _window_weights(x, y, r, tol)
    dx, dy, _ = _window_weights(x, y, None, tol)
    u = (tangent[:, 0:1] * dx + tangent[:, 1:2] * dy) / scale
    hi = h1[:, None]
    rows = []
    for fh, fq, ft, fu in ((f1h, f1th, f1t, f[0]), (f2h * h2 / h1, f2th, f2t, f[1])):
        p = fh[None, :] * h1[None, :] / hi  # eq. (9); eq. (15) with eq. (14)
        q = np.broadcast_to(fq[None, :] / hi, p.shape)
        g = np.broadcast_to(-fu[None, :], p.shape)
        y_ = np.broadcast_to(-ft[None, :], p.shape)
        rows.append((np.stack([p, q, p * u, q * u, g], -1), y_))
    M = sum(np.einsum("ij,ijp,ijq->ipq", w, X, X) for X, _ in rows)
    v = sum(np.einsum("ij,ijp,ij->ip", w, X, y_) for X, y_ in rows)
    yy = sum(np.einsum("ij,ij,ij->i", w, y_, y_) for _, y_ in rows)
    return M, v, yy, np.stack([w.sum(1), (w * u).sum(1), (w * u * u).sum(1)], 1), (w * w).sum(1)


def _sums_case(ranges: bool):
    """_cell_centre_case with cam2's h2 (1.5-1.9 h1) and both images' f at the points."""
    x, y, tangent, derivs, h1, r = _cell_centre_case(ranges=ranges)
    rng = np.random.default_rng(5)
    h2 = h1 * rng.uniform(1.5, 1.9, h1.size)
    f = (rng.uniform(0.2, 0.8, h1.size), rng.uniform(0.2, 0.8, h1.size))
    return x, y, tangent, derivs, h1, r, h2, f


@pytest.mark.parametrize("ranges", [False, True])
def test_grid_gain_sums_equal_the_brute_force_sums(ranges):
    """GridPools.gain_sums (float64 filters) against the definition, points on cell centres:
    measured 2e-16 - 4e-16 relative to each quantity's largest entry."""
    x, y, tangent, derivs, h1, r, h2, f = _sums_case(ranges)
    tol, scale = 0.1, RADIUS
    grid = GridPools(x, y, tangent, SHAPE, radius=RADIUS, cell=CELL, r=r, range_tol=tol)
    got = grid.gain_sums(derivs, f, h1, h2, None, linear=True, scale=scale)
    ref = _brute_force_gain(x, y, tangent, derivs, f, h1, h2, r, tol, scale)
    for name, a, b in zip(("M", "v", "yy", "powers", "w2"), got, ref, strict=True):
        assert _rel_err(a, b) < 1e-10, name


def test_grid_gain_sums_check_catches_a_gain_channel_sign():
    """The mutation: the image's column entered as +f instead of -f (the gain's sign)
    changes the gain's row of M and v far beyond the check's tolerance."""
    x, y, tangent, derivs, h1, _, h2, f = _sums_case(False)
    grid = GridPools(x, y, tangent, SHAPE, radius=RADIUS, cell=CELL)
    got = grid.gain_sums(derivs, (-f[0], -f[1]), h1, h2, None, linear=True, scale=RADIUS)
    ref = _brute_force_gain(x, y, tangent, derivs, f, h1, h2, None, 0.1, RADIUS)
    assert _rel_err(got[0], ref[0]) > 0.05 and _rel_err(got[1], ref[1]) > 0.1  # measured 0.13, 0.45


@pytest.mark.parametrize("ranges", [False, True])
def test_grid_gain_sums_in_float32_equal_the_brute_force_sums(ranges):
    """GridPools.gain_sums(single=True), float32 filters, against the definition: measured
    1.5e-7 relative to each quantity's largest entry at most (tolerance 2e-6)."""
    x, y, tangent, derivs, h1, r, h2, f = _sums_case(ranges)
    tol, scale = 0.1, RADIUS
    grid = GridPools(x, y, tangent, SHAPE, radius=RADIUS, cell=CELL, r=r, range_tol=tol)
    got = grid.gain_sums(derivs, f, h1, h2, None, linear=True, scale=scale, single=True)
    ref = _brute_force_gain(x, y, tangent, derivs, f, h1, h2, r, tol, scale)
    for name, a, b in zip(("M", "v", "yy", "powers", "w2"), got, ref, strict=True):
        assert _rel_err(a, b) < 2e-6, name


def test_grid_gain_sums_in_float32_check_catches_kernels_in_cells():
    """The mutation: the float32 moment kernels with the offset in cells instead of pixels
    (d g(d) off by the cell, 2 px here): the slopes' entries of M fail the check."""
    x, y, tangent, derivs, h1, _, h2, f = _sums_case(False)
    grid = GridPools(x, y, tangent, SHAPE, radius=RADIUS, cell=CELL)
    grid.kernels = [(k / CELL**m).astype(np.float32) for m, k in enumerate(grid.kernels)]
    got = grid.gain_sums(derivs, f, h1, h2, None, linear=True, scale=RADIUS, single=True)
    ref = _brute_force_gain(x, y, tangent, derivs, f, h1, h2, None, 0.1, RADIUS)
    assert _rel_err(got[0], ref[0]) > 0.05  # measured 0.21


def _gain_case(seed=7, n=400):
    """Cell-centre points whose equations hold a flow and, in the left half, a brightness
    gain of 2 % per frame (f_t = -(p a + q c) + beta f + noise)."""
    x, y, tangent, _, h1, _ = _cell_centre_case(seed=seed, n=n)
    rng = np.random.default_rng(seed)
    h2 = h1 * rng.uniform(1.5, 1.9, n)
    f = (rng.uniform(0.2, 0.8, n), rng.uniform(0.2, 0.8, n))
    # gradients per px and per radian (times h_u), a flow the pooled model holds exactly:
    # dh_1/dt = alpha h_1 (the relative model), dtheta/dt = b
    g = [rng.normal(size=n) * 0.02 * s for s in (1.0, h1, 1.0, h2)]
    alpha, b = 0.3 / 80.0, 0.2 / 80.0
    beta = np.where(x < SHAPE[1] / 2, 0.02, 0.0)
    f1t = -(g[0] * alpha * h1 + g[1] * b) + beta * f[0] + rng.normal(size=n) * 1e-3
    f2t = -(g[2] * alpha * h2 + g[3] * b) + beta * f[1] + rng.normal(size=n) * 1e-3
    derivs = (g[0], g[1], f1t, g[2], g[3], f2t)
    return x, y, tangent, derivs, f, h1, h2


def test_gain_f_statistic_from_float32_grid_sums_as_float64(monkeypatch):
    """The gain fit's F statistic and gate decisions from the float32 grid sums against the
    float64 ones, on pools with and without a brightness change: F measured 2.3e-4
    relative at most (tolerance 1e-3; the residual sum, 1e-3 noise under a 2 % gain, is the
    small difference), flow 2.6e-7 px (tolerance 1e-5); the same pools pass gate 20."""
    import omniflow.solve.gain as gain

    x, y, tangent, derivs, f, h1, h2 = _gain_case()
    grid = GridPools(x, y, tangent, SHAPE, radius=RADIUS, cell=CELL)
    theta = np.zeros_like(h1)
    out = {}
    kw = dict(model="linear", scale=RADIUS, min_conditioning=1e-3, grid=grid)
    for single in (False, True):
        monkeypatch.setattr(gain, "GRID_SINGLE", single)
        out[single] = gain.gain_solution(derivs, f, h1, h2, theta, None, None, **kw)
    (a64, b64, _, F64), (a32, b32, _, F32) = out[False], out[True]
    assert np.array_equal(np.isnan(F64), np.isnan(F32))
    ok = np.isfinite(F64)
    assert (F64[ok] > 20).sum() > 50 and (F64[ok] < 20).sum() > 10  # both sides (180, 19)
    assert np.max(np.abs(F32[ok] / F64[ok] - 1)) < 1e-3
    assert np.array_equal(gain.gated(F64, 20.0, a64, b64), gain.gated(F32, 20.0, a32, b32))
    fin = np.isfinite(a64)
    assert np.max(np.abs(a32[fin] - a64[fin])) < 1e-5 and np.nanmax(np.abs(b32 - b64)) < 1e-5


def _brute_force_linear_gain(x, y, derivs, f, h1, h2, r, tol, scale, basis=None):
    """The linear-gain test's Grams (omniflow.solve.gain_kernels.gain_sums's ``decoupled_linear``
    layout) by the definition: every pair's two rows (f_h, -f_h h_u,j / h_1,i,
    f_theta / h_1,i, -f, -f e1 . d / scale, -f e2 . d / scale), d = (x_j - x_i, y_j - y_i),
    right side -f_t, weighted. ``basis`` (N, 2, 2): each point's e1, e2 (default the pixel
    axes)."""
    f1h, f1th, f1t, f2h, f2th, f2t = derivs
    _, _, w = _window_weights(x, y, r, tol)
    dx, dy, _ = _window_weights(x, y, None, tol)
    e = np.broadcast_to(np.eye(2), (x.size, 2, 2)) if basis is None else basis
    o1 = (e[:, 0, 0:1] * dx + e[:, 0, 1:2] * dy) / scale
    o2 = (e[:, 1, 0:1] * dx + e[:, 1, 1:2] * dy) / scale
    hi = h1[:, None]
    rows = []
    for fh, fq, ft, fu, hu in ((f1h, f1th, f1t, f[0], h1), (f2h, f2th, f2t, f[1], h2)):
        j = lambda a: np.broadcast_to(a[None, :], w.shape)  # noqa: E731  (j's own value)
        g = j(-fu)
        X = np.stack([j(fh), -j(fh * hu) / hi, j(fq) / hi, g, g * o1, g * o2], -1)
        rows.append((X, j(-ft)))
    M = sum(np.einsum("ij,ijp,ijq->ipq", w, X, X) for X, _ in rows)
    v = sum(np.einsum("ij,ijp,ij->ip", w, X, y_) for X, y_ in rows)
    yy = sum(np.einsum("ij,ij,ij->i", w, y_, y_) for _, y_ in rows)
    return M, v, yy, w.sum(1), (w * w).sum(1)


@pytest.mark.parametrize("ranges", [False, True])
def test_grid_linear_gain_sums_equal_the_brute_force_sums(ranges):
    """GridPools.linear_gain_sums (float64 filters) against the definition, points on cell
    centres: measured 1.6e-16 - 4.0e-16 relative to each quantity's largest entry."""
    x, y, _, derivs, h1, r, h2, f = _sums_case(ranges)
    tol, scale = 0.1, RADIUS
    grid = GridPools(x, y, None, SHAPE, radius=RADIUS, cell=CELL, r=r, range_tol=tol)
    got = grid.linear_gain_sums(derivs, f, h1, h2, None, scale=scale)
    ref = _brute_force_linear_gain(x, y, derivs, f, h1, h2, r, tol, scale)
    for name, a, b in zip(("M", "v", "yy", "wsum", "w2"), got, ref, strict=True):
        assert _rel_err(a, b) < 1e-10, name


def test_grid_linear_gain_sums_check_catches_offsets_in_cells():
    """The mutation: the moment kernels' offsets in cells instead of pixels (the grid's cell
    set to 1 px after binning at 2 px): the slopes' entries of M fail the check."""
    x, y, _, derivs, h1, _, h2, f = _sums_case(False)
    grid = GridPools(x, y, None, SHAPE, radius=RADIUS, cell=CELL)
    grid.cell = 1.0
    got = grid.linear_gain_sums(derivs, f, h1, h2, None, scale=RADIUS)
    ref = _brute_force_linear_gain(x, y, derivs, f, h1, h2, None, 0.1, RADIUS)
    assert _rel_err(got[0][:, 4:, 4:], ref[0][:, 4:, 4:]) > 0.05  # measured 0.75


def _polar_linear_case(curved: bool = False):
    """_sums_case's points with h_1 and theta linear in the pixel position (so the tree's
    offsets u = (theta_j - theta_i) h_1,i and dh = h_1,j - h_1,i are, at each point, an
    invertible linear map of (dx, dy)), and every pool the grid's window as a k-d tree
    pool over all points (idx, w). ``curved``: theta quadratic in x instead (u then not
    a linear map of the offset)."""
    x, y, _, derivs, _, r, _, f = _sums_case(True)
    h1 = 40.0 + 0.3 * x + 0.2 * y
    theta = (0.004 * x if not curved else 4e-5 * x**2) - 0.006 * y
    h2 = h1 * np.random.default_rng(9).uniform(1.5, 1.9, x.size)
    _, _, w = _window_weights(x, y, r, 0.1)
    idx = np.broadcast_to(np.arange(x.size), w.shape)
    return x, y, derivs, f, h1, h2, theta, r, idx, w


def _test_fits(M, v, yy):
    x, conf, rss, rss_c = nested_fits(M, v, yy, 1e-6, drop=0)
    return x[:, :3], conf, rss, rss_c


def _fit_errs(a_fits, b_fits):
    """Each of the fits' largest relative difference, over the pools both solve (a pool
    solved by one only: inf)."""
    errs = []
    for a, b in zip(a_fits, b_fits, strict=True):
        fa, fb = np.isfinite(a), np.isfinite(b)
        errs.append(_rel_err(a[fa], b[fa]) if (fa == fb).all() else math.inf)
    return errs


def test_grid_linear_gain_test_equals_the_trees_over_the_same_pools():
    """The linear-gain test's fits (omniflow.solve.gain_kernels.nested_fits, as
    omniflow.solve.gain.decoupled_linear_gain makes them) from the grid's Grams, slopes along
    (dx, dy), and from the tree's kernel over the same pools, slopes along (u, dh): the
    same (U, h_1 W, c), confidence and both RSS where the tree's offsets are a linear map
    of the pixel offsets (measured 1.5e-11 relative at most; tolerance 1e-9), at the 99 %
    of the pools both solve."""
    x, y, derivs, f, h1, h2, theta, r, idx, w = _polar_linear_case()
    grid = GridPools(x, y, None, SHAPE, radius=RADIUS, cell=CELL, r=r, range_tol=0.1)
    sums = grid.linear_gain_sums(derivs, f, h1, h2, theta, scale=RADIUS)
    tree = gain_sums(idx, w, np.arange(x.size), derivs, f, h1, h2, theta,
                     model="decoupled_linear", scale=RADIUS)  # fmt: skip
    fits = _test_fits(*sums[:3])
    errs = _fit_errs(fits, _test_fits(*tree[:3]))
    assert max(errs) < 1e-9, errs
    assert np.isfinite(fits[0][:, 0]).mean() > 0.9  # measured 0.99


def test_grid_linear_gain_equivalence_check_catches_a_curved_offset():
    """The mutation: the tree's u no longer a linear map of the offset (theta quadratic in
    x): the two fits differ far beyond the check's tolerance."""
    x, y, derivs, f, h1, h2, theta, r, idx, w = _polar_linear_case(curved=True)
    grid = GridPools(x, y, None, SHAPE, radius=RADIUS, cell=CELL, r=r, range_tol=0.1)
    sums = grid.linear_gain_sums(derivs, f, h1, h2, theta, scale=RADIUS)
    tree = gain_sums(idx, w, np.arange(x.size), derivs, f, h1, h2, theta,
                     model="decoupled_linear", scale=RADIUS)  # fmt: skip
    errs = _fit_errs(_test_fits(*sums[:3]), _test_fits(*tree[:3]))
    assert max(errs) > 1e-3, errs  # measured: confidence 0.039, the others solve other pools


@pytest.mark.parametrize("ranges", [False, True])
def test_grid_linear_gain_sums_in_float32_equal_the_brute_force_sums(ranges):
    """GridPools.linear_gain_sums(single=True), float32 filters, against the definition:
    measured 1.5e-7 relative to each quantity's largest entry at most (tolerance 2e-6)."""
    x, y, _, derivs, h1, r, h2, f = _sums_case(ranges)
    grid = GridPools(x, y, None, SHAPE, radius=RADIUS, cell=CELL, r=r, range_tol=0.1)
    got = grid.linear_gain_sums(derivs, f, h1, h2, None, scale=RADIUS, single=True)
    ref = _brute_force_linear_gain(x, y, derivs, f, h1, h2, r, 0.1, RADIUS)
    for name, a, b in zip(("M", "v", "yy", "wsum", "w2"), got, ref, strict=True):
        assert _rel_err(a, b) < 2e-6, name


def _screen_case(n: int = 1500, seed: int = 11):
    """Points on cell centres whose equations hold a decoupled flow (U 0.5 px/frame, eq. 14
    broken) left of x = 80 and eq. (14) (U = 0) right of it, the same W, dtheta and a gain
    of 2 % per frame everywhere, f_t noise 0.01; and every pool the grid's window as tree
    pools (idx, w)."""
    rng = np.random.default_rng(seed)
    gh, gw = SHAPE[0] // int(CELL), SHAPE[1] // int(CELL)
    cells = rng.choice(gh * gw, size=n, replace=False)
    x, y = (cells % gw + 0.5) * CELL, (cells // gw + 0.5) * CELL
    h1 = 40.0 + 0.3 * x + 0.2 * y
    h2, theta = 1.6 * h1, 0.004 * x - 0.006 * y
    f = (rng.uniform(0.2, 0.8, n), rng.uniform(0.2, 0.8, n))
    U, W, dtheta, beta = np.where(x < 80.0, 0.5, 0.0), 0.002, 0.001, 0.02
    derivs = []
    for hu, fu in ((h1, f[0]), (h2, f[1])):
        fh, fq = rng.normal(size=n), rng.normal(size=n)
        ft = -(fh * (U - hu * W) + fq * dtheta) + beta * fu + rng.normal(0.0, 0.01, n)
        derivs += [fh, fq, ft]
    _, _, w = _window_weights(x, y, None, 0.1)
    idx = np.broadcast_to(np.arange(n), w.shape)
    return x, y, tuple(derivs), f, h1, h2, theta, idx, w


@pytest.mark.parametrize("mutation", [None, "gate"])
def test_screen_keeps_every_pool_the_trees_test_passes(mutation):
    """omniflow.solve.decoupled.screen from the grid's float32 sums keeps every point whose
    linear-gain test (omniflow.solve.gain.decoupled_linear_gain over the same pools) passes the
    gate, and drops most of the others (measured: 636 of 1500 pass, the screen keeps them
    and 251 of the 864 others); the mutation (the screen told a 100 times higher gate)
    loses 23 passing points."""
    x, y, derivs, f, h1, h2, theta, idx, w = _screen_case()
    gate, floor = 30.0, 1e-6
    F = decoupled_linear_gain(derivs, f, h1, h2, theta, idx, w, scale=RADIUS,
                              min_conditioning=floor)[3]  # fmt: skip
    passing = gated(F, gate)
    grid = GridPools(x, y, None, SHAPE, radius=RADIUS, cell=CELL)
    sums = grid.linear_gain_sums(derivs, f, h1, h2, theta, scale=RADIUS, single=True)
    keep = screen(sums, floor, gate * (100.0 if mutation else 1.0))
    if mutation:
        assert (passing & ~keep).any()
    else:
        assert passing.sum() > 100 and not (passing & ~keep).any()
        assert (keep & ~passing).sum() < 0.5 * (~passing).sum()


def test_neighbourhoods_of_queried_points_are_the_full_searchs_rows():
    """omniflow.solve.pooled.neighbourhoods with ``query``: the queried rows the full search's, bit
    for bit (weights made for those rows only), the others index N and weight 0."""
    x, y, _, _, _, r, _, _ = _sums_case(True)
    query = np.random.default_rng(2).random(x.size) < 0.3
    full = neighbourhoods(x, y, k=24, radius=RADIUS, r=r, range_tol=0.1)
    part = neighbourhoods(x, y, k=24, radius=RADIUS, r=r, range_tol=0.1, query=query)
    for a, b in zip(part, full, strict=True):
        np.testing.assert_array_equal(a[query], b[query])
    assert (part[0][~query] == x.size).all() and (part[1][~query] == 0).all()


@pytest.mark.parametrize("mutation", [False, True])
def test_k_window_holds_about_k_points(mutation):
    """GridPools.k_window on uniformly spread points (one in 12 cells of 2 px, 1 / 48 per
    px^2): for k 12 about 0.5 sqrt(12 * 48) = 12 px (measured 11.7 px; its square holds a
    median 11 points away from the borders), for k 48 (24 px) the window's own 16 px. The
    mutation, the density taken per cell instead of per px^2 (the cell set to 1 px after
    binning at 2 px), halves the half-width (measured 5.9 px) and fails the check."""
    rng = np.random.default_rng(4)
    gh, gw = SHAPE[0] // int(CELL), SHAPE[1] // int(CELL)
    cells = rng.choice(gh * gw, size=gh * gw // 12, replace=False)
    x, y = (cells % gw + 0.5) * CELL, (cells // gw + 0.5) * CELL
    grid = GridPools(x, y, None, SHAPE, radius=RADIUS, cell=CELL)
    if mutation:
        grid.cell = 1.0
        assert abs(grid.k_window(12) - 12.0) > 3.0
        return
    half = grid.k_window(12)
    inside = (np.abs(x[:, None] - x[None, :]) <= half) & (np.abs(y[:, None] - y[None, :]) <= half)
    interior = (x > 40) & (x < SHAPE[1] - 40) & (y > 40) & (y < SHAPE[0] - 40)
    assert abs(half - 12.0) < 1.2 and 9 <= np.median(inside[interior].sum(1)) <= 15
    assert grid.k_window(48) == grid.half * grid.cell
