"""omniflow.solve.decoupled: where eq. (14) fails, each unit's radial flow on its own.

Closed-form truth: validation.synthdata.vertical_scene at 256 px (a textured
pillar 1.2 m from the axis rising 2 mm per frame in front of the static room;
eq. (14) assumes dh/dt = 0), the flow step run on the true stereo matches at a
seeded 10 % of cam1's pixels (tests.helpers.scenes.sparse_true_matches): 30
points on the pillar, 2,103 on the room. For pure vertical motion at fixed r
both units' radial flows are v dh / (d + r) (eq. 3-4 differentiated), so
cam2's truth is cam1's.

Measured (``python -m pytest tests/omniflow/test_decoupled.py -s``, printed),
mean over the pillar's points, px per frame, and the median dr/dt (truth 0)::

                       switched  dh1_dt  dh2_dt  (true 0.537)  dr_dt m/frame
    decouple_tol None   0 / 30   0.180   0.607                 -7.4e-3
    decouple_tol 20    25 / 30   0.381   0.549                 -2.4e-3
    room points switched at 20: 4 of 2,103; at 10: 50

cam1 stays short on the decoupled points because cam1 sees the pillar at
h_1 = 22-49 px, where its fitted image is coarse: eq. (9) evaluated at the
true flow implies 0.74 of the true radial flow there (cam2's eq. (10): 1.01).
"""

from __future__ import annotations

import numpy as np
import pytest

from omniflow.config import OmniFlowConfig
from omniflow.geometry.rig import Rig
from omniflow.paper.flow import radial_velocity, radial_velocity_stereo
from omniflow.pipeline import COLUMNS, estimate
from omniflow.solve.decoupled import model_fits
from tests.helpers.scenes import frames, sparse_true_matches
from validation.synthdata import vertical_scene

VZ = 0.002  # m per frame: 0.54 px of radial flow on the pillar in both units


@pytest.fixture(scope="module")
def pillar():
    scene = vertical_scene(256, vz=VZ)
    f1, f2 = frames(scene, 2)
    m, gt = sparse_true_matches(scene, 0.1)
    return scene, f1, f2, m, gt


def _pillar_figures(pillar, tol):
    scene, f1, f2, m, gt = pillar
    rig = scene.rig
    res = estimate(f1, f2, rig, OmniFlowConfig(decouple_tol=tol), matches=m)
    iy, ix = res["y"].astype(int), res["x"].astype(int)  # true matches lie on pixel centres
    on = gt["gt.object"][iy, ix] == 3
    true1 = gt["gt.flow.dh"][iy, ix]
    assert on.sum() >= 25 and (~on).sum() > 2000
    return {
        "switched": float(np.mean(res["coupled"][on] == 0)),
        "room_switched": int(np.sum(res["coupled"][~on] == 0)),
        "dh1": float(res["dh1_dt"][on].mean() / true1[on].mean()),
        "dh2": float(res["dh2_dt"][on].mean() / true1[on].mean()),  # cam2's truth = cam1's
        "dr": float(np.median(res["dr_dt"][on])),
        "room_epe": float(np.abs(res["dh1_dt"] - true1)[~on].mean()),
    }


def test_vertical_pillar_is_decoupled_and_its_flow_follows_the_truth(pillar):
    fig = _pillar_figures(pillar, 20.0)
    off = _pillar_figures(pillar, None)
    print("\ndecouple_tol 20:", fig, "\nNone:", off)
    assert fig["switched"] >= 0.7  # measured 25 / 30
    assert fig["room_switched"] <= 10  # measured 4 of 2,103
    assert abs(fig["dh2"] - 1.0) <= 0.05  # measured 1.023 (coupled 1.130)
    assert fig["dh1"] >= 0.6  # measured 0.71 (coupled 0.34); eq. (9) itself caps it near 0.74
    assert abs(fig["dr"]) <= 4e-3  # measured -2.4e-3 (coupled -7.4e-3; truth 0)
    assert fig["room_epe"] <= 1.2 * off["room_epe"] + 1e-4  # the room keeps its flow


def test_the_pillar_checks_fail_with_eq_14_imposed(pillar):
    """The mutation the checks above catch: every point coupled (the knob off)."""
    off = _pillar_figures(pillar, None)
    assert off["switched"] < 0.7
    assert off["dh1"] < 0.6 and abs(off["dh2"] - 1.0) > 0.05 and abs(off["dr"]) > 4e-3


def test_default_columns_and_direct_solver(pillar):
    scene, f1, f2, m, _ = pillar
    assert "coupled" in COLUMNS
    res = estimate(f1, f2, scene.rig, OmniFlowConfig.paper(), matches=m)
    assert np.all(res["coupled"] == 1.0)  # the paper's model: eq. (14)


def _pool_equations(U, W, b, n=40, seed=1, noise=1e-6):
    """Exact eq. (9) and (10) of n points that share (U, W, b) in one pool."""
    rng = np.random.default_rng(seed)
    h1 = rng.uniform(40.0, 50.0, n)
    h2 = h1 * rng.uniform(1.6, 1.7, n)
    f1_h, f1_th, f2_h, f2_th = rng.normal(size=(4, n)) * np.array([[1.0], [40.0], [1.0], [70.0]])
    a1, a2 = U - h1 * W, U - h2 * W  # eq. (3)-(4) differentiated
    f1_t = -(f1_h * a1 + f1_th * b) + noise * rng.normal(size=n)
    f2_t = -(f2_h * a2 + f2_th * b) + noise * rng.normal(size=n)
    idx = np.tile(np.arange(n), (n, 1))
    return (f1_h, f1_th, f1_t, f2_h, f2_th, f2_t), h1, h2, idx, np.ones((n, n))


def test_model_fits_recover_exact_motion_and_test_eq_14():
    derivs, h1, h2, idx, w = _pool_equations(U=0.3, W=0.004, b=0.002)
    fit = model_fits(derivs, h1, h2, idx, w)
    np.testing.assert_allclose(fit["a1"], 0.3 - h1 * 0.004, atol=1e-5)  # measured 4.5e-7
    np.testing.assert_allclose(fit["a2"], 0.3 - h2 * 0.004, atol=1e-5)  # measured 1.2e-7
    np.testing.assert_allclose(fit["b"], 0.002, atol=1e-7)  # measured 1.8e-9
    assert np.all(fit["F"] > 1e6)  # the coupled model cannot fit U = 0.3
    # no axial motion: the extra unknown explains only the noise
    derivs, h1, h2, idx, w = _pool_equations(U=0.0, W=0.004, b=0.002)
    fit = model_fits(derivs, h1, h2, idx, w)
    assert np.all(fit["F"] < 20.0)  # measured max 4.9 over seeds 1-5 (seed 1 here)
    np.testing.assert_allclose(fit["coupled_a"], -h1 * 0.004, atol=1e-5)  # measured 1.2e-7


def test_radial_velocity_stereo_is_the_derivative_of_eq_5():
    """dr/dt from both units' radial flows, against finite differences of eq. (3)-(4)."""
    rig = Rig.symmetric(d=0.10, R=0.05, s=0.30, size=512)
    r, Z, dr, dz, eps = 1.7, 0.9, -0.01, 0.004, 1e-6
    h = [
        (u.image_radius(r, Z), u.image_radius(r + eps * dr, Z + eps * dz))
        for u in (rig.cam1, rig.cam2)
    ]
    (h1, h1e), (h2, h2e) = h
    dh1, dh2 = (h1e - h1) / eps, (h2e - h2) / eps
    got = radial_velocity_stereo(r, h1, h2, dh1, dh2, d=rig.d)
    assert got == pytest.approx(dr, rel=1e-5)  # measured 7.9e-9
    # eq. (14)'s formula is off by the axial motion's share; equal when dz = 0
    assert abs(radial_velocity(r, h1, dh1, d=rig.d) - dr) > 0.01
    h1e0, h2e0 = rig.cam1.image_radius(r + eps * dr, Z), rig.cam2.image_radius(r + eps * dr, Z)
    same = radial_velocity_stereo(r, h1, h2, (h1e0 - h1) / eps, (h2e0 - h2) / eps, d=rig.d)
    assert same == pytest.approx(radial_velocity(r, h1, (h1e0 - h1) / eps, d=rig.d), rel=1e-5)


def test_early_pool_fits_are_used_only_for_the_same_points(monkeypatch):
    """flow_at_matches has the two-model test's pool fits made before it refines the
    flow: they are decouple's own fits of the final columns where the refinement keeps
    every point's flow, and are dropped (decouple fits the kept points itself) where
    it loses one. With ``decouple_gain_tol`` (the dense preset's grid pools, so the
    k-d tree pools are searched there) the early fits carry the linear-gain test's
    columns too (the mutation of not passing the image to the early fits fails here;
    every point keeps its flow in this scene, so the image's subsetting to the kept
    points is not exercised)."""
    from omniflow.pipeline import OmniFlowConfig, estimate
    from omniflow.solve import at_matches as solve_mod
    from omniflow.solve.decoupled import pool_fits
    from omnisim.synthetic import Motion
    from tests.helpers.scenes import frames, paper_rig, wall_scene

    rig = paper_rig(256)
    f1, f2 = frames(wall_scene(rig, robot=Motion(velocity=(0.02, 0.01), yaw_rate=0.004)), 2)
    config = OmniFlowConfig.dense(brightness={"decouple_gain_tol": 60.0})
    seen = []
    real_decouple = solve_mod.decouple

    def spy(cols, rig_, config_, displacement, *, pools=None, fit=None, **kw):
        seen.append((cols, fit, kw))
        return real_decouple(cols, rig_, config_, displacement, pools=pools, fit=fit, **kw)

    monkeypatch.setattr(solve_mod, "decouple", spy)
    estimate(f1, f2, rig, config)
    cols, fit, kw = seen[-1]
    assert fit is not None
    fresh = pool_fits(cols, rig, config, brightness=kw["brightness"])
    assert "gain_F" in fresh
    for k in fresh:
        np.testing.assert_array_equal(fit[k], fresh[k], err_msg=k)

    real_refine = solve_mod._refine

    def lose_one(a, *args):  # the refinement loses the first point's flow
        a, b, conf = real_refine(a, *args)
        a = a.copy()
        a[np.flatnonzero(np.isfinite(a))[0]] = np.nan
        return a, b, conf

    monkeypatch.setattr(solve_mod, "_refine", lose_one)
    estimate(f1, f2, rig, config)
    assert seen[-1][1] is None
