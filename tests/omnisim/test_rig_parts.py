"""Struts and mount flanges (omnisim.rig_parts): occluders where the geometry puts them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from omnisim.scene import SceneError, load_scene
from omnisim.sensor import mirror_rays

DEFAULT = Path(__file__).resolve().parents[2] / "scenes" / "default.toml"
STRUTS = {"count": 3, "radius": 0.065, "width": 0.006, "azimuth": 10.0}
MOUNT = 0.06  # m, wider than R = 0.05: clips the outer field
OV = {"render.width": 128, "render.height": 128, "render.spp": 16, "render.denoise": "none"}


def _predicted(rig, unit, x, y):
    """Strut / flange hit of each pixel centre's reflected ray, from the geometry alone.

    The ray runs outward along its azimuth theta from the mirror point (rho, tip + rho)
    with slope h_i / v. It meets the flange (the plane tip + R) at radius rho + (R - rho)
    v / h_i; a rod of radius w/2 centred at (Rs, a) at range Rs when Rs |sin(theta - a)|
    <= w/2 and cos(theta - a) > 0, and while the ray is below the rod's top (h = s + R)
    there. ``margin`` is the distance (m) of the ray from the nearest rod edge or top.
    """
    rays = mirror_rays(unit, x, y)
    theta = rays.theta
    with np.errstate(divide="ignore"):
        r_flange = rays.rho + (unit.R - rays.rho) * unit.v / rays.h_i
    mount = rays.valid & (r_flange <= MOUNT)
    a = np.radians(STRUTS["azimuth"] + 120.0 * np.arange(3))[:, None]
    off = STRUTS["radius"] * np.sin(theta[None] - a)
    half = STRUTS["width"] / 2
    # range where the ray meets the rod's front face
    along = STRUTS["radius"] * np.cos(theta[None] - a) - np.sqrt(np.maximum(half**2 - off**2, 0))
    z = unit.tip_h + rays.rho + (along - rays.rho) * rays.h_i / unit.v
    below = rig.s + rig.R - z
    margin = np.minimum(np.abs(np.abs(off) - STRUTS["width"] / 2), np.abs(below)).min(axis=0)
    hits = (np.abs(off) <= STRUTS["width"] / 2) & (along > 0) & (below > 0)
    strut = rays.valid & ~mount & hits.any(0)
    return strut, mount, margin, rays


@pytest.mark.render
def test_struts_and_flange_are_where_the_geometry_puts_them():
    """gt.object is the strut / flange id, and gt.valid 0, exactly at the predicted pixels
    (but within 1e-4 m of a rod's edge); the render is dark there: the spokes' mean
    radiance is under 0.15 of the rest's (measured 0.011, cam2, 128 px, 16 spp;
    the parts' albedo is 0.04)."""
    from omnisim.groundtruth import ground_truth
    from omnisim.render import render_camera

    sc = load_scene(DEFAULT, {**OV, "rig.struts": [STRUTS], "rig.mount_radius": MOUNT})
    ids = {o.kind: o.id for o in sc.objects if o.kind in ("strut", "mount")}
    for cam in ("cam1", "cam2"):
        unit = getattr(sc.rig, cam)
        gt = ground_truth(sc, 0, cam)
        xs, ys = unit.pixel_centres()
        strut, mount, margin, rays = _predicted(sc.rig, unit, xs.ravel(), ys.ravel())
        valid, h_i = rays.valid, rays.h_i
        strut, mount, margin, valid, h_i = (
            a.reshape(xs.shape) for a in (strut, mount, margin, valid, h_i)
        )
        sure = margin > 1e-4
        obj = gt["gt.object"]
        assert (obj[strut & sure] == ids["strut"]).all(), cam
        assert (obj[mount] == ids["mount"]).all(), cam
        other = valid & ~strut & ~mount & sure
        assert not np.isin(obj[other], list(ids.values())).any(), cam
        assert (gt["gt.valid"][strut | mount] == 0).all(), cam
        assert strut.sum() > 300 and mount.sum() > 300  # both are really seen
        if cam == "cam2":
            img = render_camera(sc, 0, cam).mean(axis=2)
            # pixels whose whole square is inside a spoke: the rod's edge over 0.75 px
            # away (margin metres at range Rs subtends margin h_i / Rs px)
            deep = strut & (margin * h_i / STRUTS["radius"] > 0.75)
            clear = other & (h_i < unit.r_m - 2)
            ratio = img[deep].mean() / img[clear].mean()
            assert deep.sum() > 100 and ratio < 0.15, ratio


def test_strut_errors_name_the_key():
    bad = {**STRUTS, "radius": 0.05}
    with pytest.raises(SceneError) as err:
        load_scene(DEFAULT, {**OV, "rig.struts": [bad]})
    assert "rig.struts[0].radius" in str(err.value) and "outside the mirror" in str(err.value)
    with pytest.raises(SceneError) as err:
        load_scene(DEFAULT, {**OV, "rig.mount_radius": 0.01})
    assert "rig.mount_radius (set by an override): got 0.01" in str(err.value)
    with pytest.raises(SceneError) as err:
        load_scene(DEFAULT, {**OV, "rig.struts": [{**STRUTS, "colour": 1}]})
    assert "rig.struts[0].colour: unknown key" in str(err.value)
