"""benchmarks.noise_refusal: the matcher's tables in units of a known image noise.

A closed-form striped wall (tests.helpers.scenes.wall_scene, 256 px, paper rig) is
rendered without noise and with white noise of a known sigma. The fit, polar table and
blur are linear, so the noisy table less the clean one is the noise's own table. Its
variance per column must be what one other, fixed draw of unit white noise passed
through the same steps predicts (``share(j) sigma^2``), for the values and for the
radial derivative the gradient test reads.
"""

from __future__ import annotations

import numpy as np

from benchmarks.noise_refusal import _tables, _white_grid
from omniflow.config import OmniFlowConfig
from omniflow.matching.tables import polar_maps
from omniflow.paper.dct import fit_dct
from omniflow.pipeline import fill_outside_rim
from tests.helpers.scenes import paper_rig, wall_scene


def _grid(image, unit):
    return np.asarray(fit_dct(fill_outside_rim(image, unit), band=0.5).grid(), np.float32)


def test_table_noise_follows_the_pixel_noise():
    """Measured (sigma 0.02, render seeds 1-2, radii 16-110 px): the noise table's
    variance over the predicted, all columns together, 0.965-0.985; in blocks of 10
    columns 0.78-1.14. Bounds: all together within 5 %, each block within 0.7-1.3 (the
    blur across the lines leaves about 90 independent lines per column and draw)."""
    rig = paper_rig()
    unit = rig.cam1
    scene = wall_scene(rig, radius=2.0, seed=3)
    sigma = 0.02
    cfg = OmniFlowConfig()
    maps = polar_maps(unit, 360, 16.0, 1.0, int(unit.r_m - 20))
    blur = cfg.matching.tangential_blur * 360 / (2 * np.pi)
    wt, wd = _tables(_white_grid(unit, cfg), maps, blur, 1.0)
    share_v, share_d = np.mean(wt**2, axis=0), np.mean(wd**2, axis=0)
    clean = _grid(scene.render("cam1", 0, dtype=np.float32), unit)
    for seed in (1, 2):
        noisy = _grid(scene.render("cam1", 0, dtype=np.float32, noise=sigma, seed=seed), unit)
        tv, td = _tables(noisy - clean, maps, blur, 1.0)
        for measured, share in (
            (np.mean(tv**2, axis=0), share_v),
            (np.mean(td**2, axis=0), share_d),
        ):
            m, p = measured[2:-2], (share * sigma**2)[2:-2]
            n = m.size // 10 * 10
            blocks = m[:n].reshape(-1, 10).sum(axis=1) / p[:n].reshape(-1, 10).sum(axis=1)
            assert abs(m.sum() / p.sum() - 1.0) < 0.05
            assert 0.7 < blocks.min() and blocks.max() < 1.3
