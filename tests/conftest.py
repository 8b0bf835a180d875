"""Shared fixtures: a small symmetric rig and closed-form scenes on it."""

from __future__ import annotations

import numpy as np
import pytest

from omniflow.geometry.rig import Rig
from omnisim.synthetic import Cylinder, Motion, SyntheticScene, Texture


@pytest.fixture(scope="session")
def small_rig() -> Rig:
    """d = 0.10 m, R = 0.05 m, s = 0.30 m, 128 x 128 images, r_m = 62 px."""
    return Rig.symmetric(d=0.10, R=0.05, s=0.30, size=128)


@pytest.fixture(scope="session")
def room_scene(small_rig) -> SyntheticScene:
    """A static textured round room (wall radius 3 m, ceiling 2.5 m) around the rig."""
    return SyntheticScene.room(small_rig, wall_radius=3.0, ceiling=2.5, texture_seed=7)


@pytest.fixture(scope="session")
def busy_scene(small_rig) -> SyntheticScene:
    """Room plus a moving pillar; the robot drives and turns slowly."""
    pillar = Cylinder(
        centre=(1.0, 0.4),
        radius=0.25,
        z_min=-1.0,
        z_max=2.0,
        id=3,
        name="pillar",
        motion=Motion(velocity=(-0.01, 0.02), yaw_rate=0.01),
        texture=Texture.random(11, period_u=2 * np.pi * 0.25),
    )
    return SyntheticScene.room(
        small_rig,
        wall_radius=3.0,
        ceiling=2.5,
        texture_seed=7,
        robot=Motion(velocity=(0.02, 0.01), yaw_rate=0.003),
        bodies=[pillar],
    )
