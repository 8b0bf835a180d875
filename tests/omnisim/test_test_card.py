"""The rendered test card (scenes/test_card.toml, omnisim): its ground truth and shading.

The card's seen points (gt.r, gt.theta, gt.h, rig frame) lie on its tube, and the
rendered radiance is dark exactly where TestCard.dark says at those points (away from the
checks' edges), for both misaligned units: the card the registration fits is the card
the renderer drew.
"""

from __future__ import annotations

import gc

import numpy as np
import pytest

from omniflow.geometry.test_card import TestCard, card_in_rig


@pytest.fixture(scope="module")
def frame():
    pytest.importorskip("mitsuba")
    from omnisim import render, scene

    sc = scene.load_scene(
        "scenes/test_card.toml",
        {"render.width": 96, "render.height": 96, "render.spp": 4, "frames": 1},
    )
    out = render.render_frame(sc, 0)
    card = card_in_rig(TestCard(), np.linalg.inv(sc.robot.pose(0)), sc.objects[0].pose(0))
    yield sc, out, card
    render.clear_cache()
    gc.collect()


def test_card_truth_lies_on_the_tube_and_shades_as_its_pattern(frame):
    sc, out, card = frame
    for cam in ("cam1", "cam2"):
        ch = out[cam]
        valid = ch["gt.valid"] > 0
        assert valid.sum() > 0.5 * np.pi * sc.rig.cam1.r_m**2  # the card fills the mirror
        unit = getattr(sc.rig, cam)
        x, y = unit.pixel_centres()
        # the sectors are 2 pi h_i / 24 px wide: a pixel nearer the tip's image spans edges
        far = np.hypot(x - unit.x_c, y - unit.y_c)[valid] > 15
        assert np.all(ch["gt.object"][valid] == sc.objects[0].id)
        # measured 1.19e-6 m off the 0.5 m tube (the facets, 1.2 um, in float32 storage)
        np.testing.assert_allclose(ch["gt.r"][valid], card.radius, atol=3e-6)
        theta, h = ch["gt.theta"][valid], ch["gt.h"][valid]
        fj = np.mod((theta - card.azimuth) / (2 * np.pi) * card.sectors, 1)
        fk = np.mod((h - card.center[2] + card.height / 2) / card.ring_spacing, 1)
        inner = (np.abs(fj - 0.5) < 0.3) & (np.abs(fk - 0.5) < 0.3) & far  # off the edges
        grey = (ch["R"] + ch["G"] + ch["B"])[valid][inner] / 3
        dark = card.dark(theta[inner], h[inner])
        assert dark.any() and (~dark).any()
        assert grey[dark].max() < 0.5 * grey[~dark].min()


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("sectors = 5", "objects[0].sectors: got 5, expected an even integer in [4, 360]"),
        ("radius = -1", "objects[0].radius: got -1, expected a number > 0 (m)"),
        ("height = 0.05", "objects[0].height: got 0.05, expected at least 4 rings"),
        ("texture = {type = 'solid'}", "objects[0].texture: unknown key"),
    ],
)
def test_bad_card_keys_are_one_line(tmp_path, line, message):
    from pathlib import Path

    from omnisim.scene import SceneError, load_scene

    key = line.split(" = ")[0]
    lines = Path("scenes/test_card.toml").read_text().splitlines()
    lines = [ln for ln in lines if not ln.startswith(f"{key} = ")]
    lines.insert(lines.index('type = "test_card"') + 1, line)
    path = tmp_path / "card.toml"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(SceneError) as err:
        load_scene(path)
    assert message in str(err.value) and "\n" not in str(err.value), str(err.value)
