"""A shading-free copy of a rendered dataset: each frame's radiance replaced by its albedo.

The albedo of the first hit through the mirror (Mitsuba's ``aov`` integrator, the
same one the denoiser's guides use: omnisim.denoise.guide_integrator_dict) is the
texture alone: no light, no shading, no shadow. Multiplied by one constant per
dataset (the ratio of the radiance's to the albedo's median luminance over frame 0's
valid pixels, so the dataset's camera model exposes it alike), it replaces R, G, B;
every ``gt.*`` channel and dataset.json are copied unchanged, so the ground truth is
the original's. On these images brightness constancy holds exactly for every material
point that stays visible (up to antialiasing), so a flow method's error on them is the
method's, not the lighting's.

Usage::

    python benchmarks/albedo_dataset.py SOURCE_DATASET SCENE_TOML OUT [--spp 64]
        [--size N --frames K --scale S]

``SCENE_TOML`` is the scene SOURCE was rendered from (with SOURCE's overrides applied:
the frame count and size come from its dataset.json). OUT must not exist. With
``--size N`` the dataset is made at N x N pixels and ``--frames K`` instead: the
ground truth is then traced anew (omnisim.groundtruth.ground_truth_frame) and the
albedo is scaled by ``--scale`` (no radiance to compare with at that size).
"""

from __future__ import annotations

import argparse
import copy
import time

import numpy as np

from omniflow.io.dataset import grey_of, open_dataset
from omnisim.dataset import DatasetWriter
from omnisim.denoise import guide_integrator_dict
from omnisim.groundtruth import ground_truth_frame
from omnisim.meta import build_meta
from omnisim.mitsuba_scene import CAMERAS, camera_unit, get_mitsuba_scene
from omnisim.render import frame_seed, outside_rim
from omnisim.scene import load_scene
from omnisim.sensor import ensure_mitsuba


def render_albedo(scene, ms, integrator, frame: int, cam: str, spp: int) -> np.ndarray:
    """Linear albedo (H, W, 3) of camera ``cam`` at ``frame``; 0 outside the rim."""
    mi = ensure_mitsuba()
    fr = ms.frame(frame)
    u = camera_unit(scene, cam)
    img = mi.render(
        fr.scene,
        sensor=ms.sensor(cam, fr.robot_pose),
        integrator=integrator,
        spp=spp,
        seed=frame_seed(int(scene.render.seed), frame, cam),
    )
    img = np.array(img, dtype=np.float32).reshape(u.height, u.width, -1)[..., 0:3]
    img[outside_rim(u)] = 0.0
    return img


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("source")
    ap.add_argument("scene")
    ap.add_argument("out")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--size", type=int, help="make it at N x N px, the truth traced anew")
    ap.add_argument("--frames", type=int, default=2, help="frames (with --size)")
    ap.add_argument("--scale", type=float, default=None, help="albedo factor (with --size)")
    args = ap.parse_args(argv)
    src = open_dataset(args.source)
    overrides = dict(src.meta["scene"].get("overrides") or {})
    if args.size:
        if args.scale is None:
            ap.error("--size needs --scale")
        overrides.update({"render.width": args.size, "render.height": args.size})
        overrides["frames"] = args.frames
    scene = load_scene(args.scene, overrides)
    if args.size:
        meta = build_meta(scene, overrides)
        meta["camera"] = src.meta.get("camera")
        if meta["camera"] is None:
            del meta["camera"]
    else:
        meta = copy.deepcopy(src.meta)
    mi = ensure_mitsuba()
    ms = get_mitsuba_scene(scene)
    integrator = mi.load_dict(guide_integrator_dict())
    meta["scene"]["name"] = f"{meta['scene']['name']}_albedo"
    meta["scene"]["note"] = (
        "R, G, B replaced by the first hit's albedo x a constant "
        "(benchmarks/albedo_dataset.py); gt.* channels copied from the source"
    )
    writer = DatasetWriter(args.out, meta)
    scale = args.scale if args.size else None
    for k in range(args.frames if args.size else src.frame_count):
        t0 = time.perf_counter()
        frame = {}
        truth = ground_truth_frame(scene, k, CAMERAS) if args.size else None
        for cam in CAMERAS:
            chans = dict(truth[cam]) if truth else dict(src.read_frame(k, cam))
            alb = render_albedo(scene, ms, integrator, k, cam, args.spp)
            if scale is None:  # one constant for the dataset, from frame 0 of cam1
                ok = chans["gt.valid"] > 0.5
                lum_alb = grey_of({"R": alb[..., 0], "G": alb[..., 1], "B": alb[..., 2]})
                scale = float(np.median(grey_of(chans)[ok]) / np.median(lum_alb[ok]))
            for i, c in enumerate("RGB"):
                chans[c] = np.ascontiguousarray(alb[..., i] * scale, dtype=np.float32)
            frame[cam] = chans
        writer.write_frame(k, frame)
        print(f"frame {k}: {time.perf_counter() - t0:.1f} s (scale {scale:.4g})", flush=True)
    writer.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
