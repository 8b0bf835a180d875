"""Test doubles for omnisim's job, CLI, Dask and check tests (no Mitsuba needed).

* :func:`render_frame` - a stand-in for ``omnisim.render.render_frame`` (renderer spec
  ``"tests.helpers.fakes:render_frame"``): deterministic arrays with every contract channel,
  a function of the scene's rig, seed and the frame only. ``OMNISIM_FAKE_DELAY`` (s)
  slows each frame down so a test can interrupt a render.
* :func:`write_synthetic_dataset` - a dataset built from :mod:`omnisim.synthetic`'s
  closed-form room (exact truth), with dataset.json poses that match it, for the checks.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from omniflow.geometry.rig import Rig
from omnisim.dataset import CHANNELS, CHANNELS_V1, FORMAT_NAME, DatasetWriter


def render_frame(scene, frame: int) -> dict[str, dict[str, np.ndarray]]:
    delay = float(os.environ.get("OMNISIM_FAKE_DELAY", "0") or 0)
    if delay:
        time.sleep(delay)
    seed = int(getattr(scene.render, "seed", 0) or 0)
    out = {}
    for ci, unit in enumerate((scene.rig.cam1, scene.rig.cam2)):
        rng = np.random.default_rng([seed, int(frame), ci])
        shape = (unit.height, unit.width)
        ch = {name: rng.random(shape, dtype=np.float32) for name in CHANNELS}
        for name in ("gt.valid", "gt.flow.valid", "gt.bflow.valid", "gt.stereo.valid"):
            ch[name] = (ch[name] > 0.2).astype(np.float32)
        for name in ("occluded", "outside"):  # 0/1 like the real masks (not disjoint here)
            for key in ("gt.flow", "gt.bflow"):
                ch[f"{key}.{name}"] = (ch[f"{key}.{name}"] > 0.9).astype(np.float32)
        out[unit.name] = ch
    return out


def _pose(x: float, y: float, yaw: float, z: float = 0.0) -> list:
    c, s = np.cos(yaw), np.sin(yaw)
    m = np.array([[c, -s, 0, x], [s, c, 0, y], [0, 0, 1, z], [0, 0, 0, 1]], float)
    return m.tolist()


def synthetic_scene(size: int = 64, *, moving_pillar: bool = True):
    from omnisim.synthetic import Cylinder, Motion, SyntheticScene, Texture

    rig = Rig.symmetric(d=0.1, R=0.05, s=0.3, size=size)
    bodies = []
    if moving_pillar:
        bodies.append(
            Cylinder(
                centre=(1.6, 0.4),
                radius=0.3,
                id=3,
                name="pillar",
                motion=Motion(velocity=(-0.03, 0.02)),
                texture=Texture.random(7, wavelengths=(0.3, 1.0), period_u=2 * np.pi * 0.3),
            )
        )
    return SyntheticScene.room(
        rig,
        wall_radius=3.0,
        ceiling=2.5,
        texture_seed=3,
        wavelengths=(0.6, 2.0),
        robot=Motion(velocity=(0.04, 0.015), yaw_rate=0.01),
        bodies=bodies,
    )


def write_synthetic_dataset(
    out: str | Path,
    *,
    frames: int = 3,
    size: int = 64,
    noise: float = 0.01,
    supersample: int = 1,
    moving_pillar: bool = True,
) -> Path:
    """A complete dataset from omnisim.synthetic: exact truth, images with Gaussian noise.

    Format version 1 (omnisim.synthetic gives forward flow without the occlusion /
    outside split): the tests' version 1 fixture.
    """
    sc = synthetic_scene(size, moving_pillar=moving_pillar)
    robot = []
    for k in range(frames):
        p, yaw = sc.rig_pose(k)
        robot.append(_pose(p[0], p[1], yaw))
    objects = []
    for b in sc.bodies:
        poses = []
        for k in range(frames):
            c, yaw, dz = b.pose(k)
            poses.append(_pose(c[0], c[1], yaw, dz))
        objects.append({"id": b.id, "name": b.name, "material": "diffuse", "poses": poses})
    meta = {
        "format": FORMAT_NAME,
        "format_version": 1,
        "scene": {"name": "synthetic", "path": "synthetic", "source": "", "overrides": {}},
        **sc.rig.to_dict(),
        "frames": frames,
        "frame_interval": 0.1,
        "render": {"width": size, "height": size, "spp": 1, "seed": 0},
        "seed": 0,
        "robot": {"poses": robot},
        "objects": objects,
        "versions": {},
    }
    w = DatasetWriter(out, meta)
    for k in range(frames):
        fr = {}
        for cam in ("cam1", "cam2"):
            img = sc.render(cam, k, supersample=supersample, noise=noise, seed=10 * k + len(cam))
            ch = {key: v.astype(np.float32) for key, v in sc.truth(cam, k).items()}
            for c in ("R", "G", "B"):
                ch[c] = img.astype(np.float32)
            fr[cam] = {name: ch[name] for name in CHANNELS_V1}
        w.write_frame(k, fr)
    return Path(out)
