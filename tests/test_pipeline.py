"""omniflow.pipeline: OmniFlowConfig, estimate, OmniFlowResult (closed-form scenes)."""

from __future__ import annotations

import numpy as np
import pytest

from omniflow.pipeline import COLUMNS, OmniFlowConfig, OmniFlowResult, estimate
from omniflow.rig import Rig
from omniflow.synthetic import Cylinder, Motion, SyntheticScene, Texture


def striped_wall(radius: float, seed: int, *, n: int = 16, contrast: float = 0.8) -> Texture:
    """A wall texture the rig resolves: fine detail up the wall, coarse around it.

    Wavelengths 0.03-0.3 m in height; around the wall at least 1 m (whole
    cycles per circumference). Near the image centre cam1 sees h_2/h_1
    times less of the wall per pixel tangentially than cam2, so fine
    tangential detail cannot be matched along radial lines.
    """
    rng = np.random.default_rng(seed)
    fv = np.exp(rng.uniform(np.log(1 / 0.3), np.log(1 / 0.03), n)) * rng.choice([-1, 1], n)
    circ = 2 * np.pi * radius
    kmax = max(1, int(circ / 1.0))
    fu = rng.integers(-kmax, kmax + 1, n) / circ
    amp = rng.uniform(0.5, 1.0, n)
    amp *= contrast / amp.sum()
    return Texture(fu=fu, fv=fv, amp=amp, phase=rng.uniform(0, 2 * np.pi, n), mean=0.5)


def wall_scene(
    rig: Rig, radius: float = 2.0, seed: int = 3, robot: Motion | None = None, **kw
) -> SyntheticScene:
    wall = Cylinder(radius=radius, id=1, name="wall", texture=striped_wall(radius, seed), **kw)
    return SyntheticScene(rig=rig, bodies=(wall,), robot=robot or Motion())


@pytest.fixture(scope="module")
def rig256() -> Rig:
    return Rig.symmetric(d=0.10, R=0.05, s=0.30, size=256)


@pytest.fixture(scope="module")
def moving_frames(rig256):
    scene = wall_scene(rig256, robot=Motion(velocity=(0.01, 0.005), yaw_rate=0.002))
    return (
        scene,
        scene.frames("cam1", 3, dtype=np.float32),
        scene.frames("cam2", 3, dtype=np.float32),
    )


def test_estimate_columns_and_csv(moving_frames, rig256, tmp_path):
    _, f1, f2 = moving_frames
    res = estimate(f1, f2, rig256)
    assert isinstance(res, OmniFlowResult)
    assert set(COLUMNS) <= set(res.columns)
    n = len(res)
    assert n > 100
    assert all(np.asarray(v).shape == (n,) for v in res.columns.values())
    assert {"fit", "grids", "match", "sample", "solve", "total"} <= set(res.timings)
    path = res.to_csv(tmp_path / "out.csv")
    lines = path.read_text().splitlines()
    assert lines[0].startswith("#") and lines[1].split(",") == list(res.columns)
    back = np.loadtxt(path, delimiter=",", skiprows=2)
    assert back.shape == (n, len(res.columns))
    np.testing.assert_allclose(back[:, 0], res["x"], rtol=1e-8)


@pytest.mark.parametrize(
    "config",
    [
        OmniFlowConfig(),
        OmniFlowConfig.paper(),
        OmniFlowConfig(temporal="dct3d"),
        OmniFlowConfig(solver="direct", gradients="first", sampling="exact"),
        OmniFlowConfig(band=0.5, rim_fill="none", sampling="linear"),
    ],
)
def test_every_variant_runs(moving_frames, rig256, config):
    _, f1, f2 = moving_frames
    res = estimate(f1, f2, rig256, config)
    assert len(res) > 50
    c = res.columns
    assert np.all(np.isfinite(c["dx"])) and np.all(np.isfinite(c["dh1_dt"]))
    assert np.all((c["confidence"] >= 0) & (c["confidence"] <= 1))


def test_bad_inputs(moving_frames, rig256):
    _, f1, f2 = moving_frames
    with pytest.raises(ValueError, match="t = 2"):
        estimate(f1, f2, rig256, t=2)
    with pytest.raises(ValueError, match="shape"):
        estimate([f[:, :-1] for f in f1], f2, rig256)
    with pytest.raises(ValueError, match="dct3d"):
        estimate(f1[:2], f2[:2], rig256, OmniFlowConfig(temporal="dct3d"))
    with pytest.raises(ValueError, match="solver"):
        OmniFlowConfig(solver="magic")
