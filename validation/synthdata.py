"""Write a closed-form scene (:mod:`omnisim.synthetic`) as an omnisim dataset.

The validation harness reads only the dataset contract, so a dataset made
here without any renderer is scored exactly like a rendered one. Used by the
fast end-to-end test and handy for trying the harness::

    python -m validation.synthdata OUT_DIR --size 128 --frames 3
    omnivalidate OUT_DIR --out REPORT_DIR

Images: the closed-form grey image is written to R = G = B (so the Rec. 709
luminance is the grey level), pixel-area integrated (``supersample``).
Poses: the rig's world-from-rig matrix and each body's world-from-object
matrix per frame, as ``dataset.json`` lists them.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from omniflow.geometry.rig import Rig
from omnisim.synthetic import Cylinder, Motion, SyntheticScene, Texture

__all__ = [
    "SCENES",
    "demo_scene",
    "main",
    "scene_meta",
    "vertical_scene",
    "write_synthetic_dataset",
]


def _pose(x: float, y: float, z: float, yaw: float) -> list[list[float]]:
    c, s = math.cos(yaw), math.sin(yaw)
    return [[c, -s, 0.0, x], [s, c, 0.0, y], [0.0, 0.0, 1.0, z], [0.0, 0.0, 0.0, 1.0]]


def scene_meta(
    scene: SyntheticScene,
    frames: int,
    *,
    name: str,
    frame_interval: float = 0.1,
    supersample: int = 2,
) -> dict[str, Any]:
    """``dataset.json`` content for a closed-form scene (contract layout)."""
    from omniflow.io.dataset import FORMAT_NAME

    robot = []
    for k in range(frames):
        p, yaw = scene.rig_pose(k)
        robot.append(_pose(float(p[0]), float(p[1]), 0.0, float(yaw)))
    objects = []
    for body in scene.bodies:
        poses = []
        for k in range(frames):
            c, yaw, dz = body.pose(k)
            poses.append(_pose(float(c[0]), float(c[1]), float(dz), float(yaw)))
        objects.append({"id": int(body.id), "name": body.name or f"body{body.id}", "poses": poses})
    return {
        "format": FORMAT_NAME,
        # version 1: omnisim.synthetic gives forward flow only, without the occluded /
        # outside split and the backward flow of version 2
        "format_version": 1,
        "scene": {
            "name": name,
            "path": "",
            "source": "omnisim.synthetic closed-form scene",
            "overrides": {},
        },
        **scene.rig.to_dict(),
        "frames": int(frames),
        "frame_interval": float(frame_interval),
        "render": {
            "width": scene.rig.cam1.width,
            "height": scene.rig.cam1.height,
            "generator": "omnisim.synthetic",
            "supersample": int(supersample),
        },
        "seed": 0,
        "objects": objects,
        "robot": {"poses": robot},
        "versions": {"generator": "omnisim.synthetic"},
    }


def write_synthetic_dataset(
    out_dir: str | Path,
    scene: SyntheticScene,
    frames: int = 3,
    *,
    name: str = "synthetic",
    frame_interval: float = 0.1,
    supersample: int = 2,
    noise: float = 0.0,
) -> Path:
    """Render ``frames`` frames of both units with their exact truth into ``out_dir``."""
    from omnisim.dataset import CHANNELS_V1, DatasetWriter

    writer = DatasetWriter(
        out_dir,
        scene_meta(
            scene, frames, name=name, frame_interval=frame_interval, supersample=supersample
        ),
    )
    for k in writer.todo_frames():
        frame: dict[str, dict[str, NDArray]] = {}
        for ci, cam in enumerate(("cam1", "cam2")):
            img = scene.render(
                cam, k, supersample=supersample, noise=noise, seed=1000 * k + ci
            ).astype(np.float32)
            chans = {"R": img, "G": img, "B": img}
            chans.update({key: val.astype(np.float32) for key, val in scene.truth(cam, k).items()})
            frame[cam] = {c: chans[c] for c in CHANNELS_V1}
        writer.write_frame(k, frame)
    return Path(out_dir)


def demo_scene(
    size: int = 128, *, robot_speed: float = 0.01, pillar_speed: float = 0.02, seed: int = 3
) -> SyntheticScene:
    """A textured round room (radius 3 m, ceiling 2.5 m), the robot driving along +X
    and turning slowly, and a textured pillar (id 3) crossing in front of it."""
    rig = Rig.symmetric(d=0.10, R=0.05, s=0.30, size=size)
    pillar = Cylinder(
        centre=(-1.0, -1.6),
        radius=0.35,
        id=3,
        name="pillar",
        motion=Motion(velocity=(pillar_speed, 0.0)),
        texture=Texture.random(seed + 10, wavelengths=(0.04, 0.25), period_u=2 * np.pi * 0.35),
    )
    return SyntheticScene.room(
        rig,
        wall_radius=3.0,
        ceiling=2.5,
        texture_seed=seed,
        robot=Motion(velocity=(robot_speed, 0.0), yaw_rate=0.004),
        bodies=(pillar,),
    )


def vertical_scene(size: int = 128, *, vz: float = 0.002, seed: int = 3) -> SyntheticScene:
    """The robot standing still in the textured room; a textured pillar (id 3, 1.2 m
    from the axis) rising at ``vz`` metres per frame. Eq. (14) assumes dh/dt = 0, so the
    direct solution's cam2 radial flow on the pillar is biased by
    s v dh / ((d + r)(s - h)) (OMNIFLOW_MATH.md); the static wall is the control."""
    rig = Rig.symmetric(d=0.10, R=0.05, s=0.30, size=size)
    pillar = Cylinder(
        centre=(1.2 + 0.3, 0.4), radius=0.3, id=3, name="pillar",
        motion=Motion(vz=vz),
        texture=Texture.random(seed + 10, wavelengths=(0.04, 0.25), period_u=2 * np.pi * 0.3),
    )  # fmt: skip
    return SyntheticScene.room(rig, wall_radius=3.0, ceiling=2.5, texture_seed=seed,
                               bodies=(pillar,))  # fmt: skip


SCENES = {"demo": demo_scene, "vertical": vertical_scene}


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m validation.synthdata",
        description="Write the closed-form demo scene (omnisim.synthetic) as an omnisim dataset.",
    )
    ap.add_argument("out", help="output dataset directory (created)")
    ap.add_argument("--size", type=int, default=128, help="image width = height, px (default 128)")
    ap.add_argument("--frames", type=int, default=3, help="number of frames (default 3)")
    ap.add_argument("--noise", type=float, default=0.0, help="grey-level noise std (default 0)")
    args = ap.parse_args(argv)
    write_synthetic_dataset(
        args.out, demo_scene(args.size), args.frames, name="synthetic-demo", noise=args.noise
    )
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
