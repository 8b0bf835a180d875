"""Motion blur (omnisim.exposure): sub-frame averaging over the open shutter."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from omnisim.exposure import average_subframes, subframe_offsets, subframe_spp

LARGE_MOTION = Path(__file__).resolve().parents[2] / "scenes" / "large_motion.toml"


def test_subframes_are_centred_on_the_instant():
    np.testing.assert_allclose(subframe_offsets(1.0, 4), [-0.375, -0.125, 0.125, 0.375])
    np.testing.assert_allclose(subframe_offsets(0.5, 2), [-0.125, 0.125])
    assert subframe_offsets(0.0, 8).tolist() == [0.0]  # an instant, whatever time_samples
    assert subframe_spp(64, 8) == 9 and subframe_spp(10, 4) == 3 and subframe_spp(1, 8) == 1
    imgs = {0: np.ones((2, 2)), 1: 3 * np.ones((2, 2))}
    np.testing.assert_allclose(average_subframes(lambda off, j: imgs[j], [-0.1, 0.1]), 2.0)


@pytest.mark.render
def test_blur_is_the_mean_of_subframes_and_its_length_is_the_flow():
    """large_motion at 128 px, frame interval 0.15 s (median flow 3.6 px), shutter 1.

    The blurred image is exactly the mean of the eight sub-frame renders (their times
    and seeds, omnisim.exposure). It is compared with the instant image (256 spp)
    warped along the ground-truth flow scaled by L at the same eight offsets and
    averaged: the residual is smallest at L = 1 (measured RMS 0.0035 at L = 1; 0.0071
    at 0.5, 0.0063 at 1.5, 0.014 unblurred), so the blur has the flow's length and is
    centred on the instant. Threshold: L = 1 under 0.7 x its neighbours (measured 0.56).
    """
    import cv2

    from omnisim.groundtruth import ground_truth
    from omnisim.render import frame_seed, render_camera, render_exposure
    from omnisim.scene import load_scene

    ov = {"render.width": 128, "render.height": 128, "render.spp": 256, "frames": 3}
    ov.update({"render.denoise": "none", "frame_interval": 0.15})
    inst = load_scene(LARGE_MOTION, ov)
    blur = load_scene(LARGE_MOTION, {**ov, "camera.shutter": 1.0, "render.time_samples": 8})
    k, cam = 1, "cam2"
    b = render_exposure(blur, k, cam)
    offsets = subframe_offsets(1.0, 8)
    subs = [
        render_camera(blur, k + off, cam, spp=36, seed=frame_seed(0, j, "subframe"))
        for j, off in enumerate(offsets)
    ]
    # the same renders; only the float32 rounding of the mean may differ (1 ulp)
    np.testing.assert_allclose(b, np.mean(np.asarray(subs, dtype=np.float64), 0), rtol=2e-7)

    i0 = render_camera(inst, k, cam)
    gt = ground_truth(inst, k, cam)
    fx, fy = gt["gt.flow.dx"], gt["gt.flow.dy"]
    yy, xx = np.mgrid[0:128, 0:128].astype(np.float32)
    inner = np.hypot(xx + 0.5 - 64, yy + 0.5 - 64) < 55  # away from the rim
    mask = (gt["gt.flow.valid"] > 0) & inner
    res = {}
    for length in (0.0, 0.5, 1.0, 1.5, 2.0):
        warped = [
            cv2.remap(
                i0,
                (xx - s * length * fx).astype(np.float32),
                (yy - s * length * fy).astype(np.float32),
                cv2.INTER_LINEAR,
            )
            for s in offsets
        ]
        res[length] = float(np.sqrt(np.mean((np.mean(warped, 0) - b)[mask] ** 2)))
    assert min(res, key=res.get) == 1.0, res
    assert res[1.0] < 0.7 * min(res[0.5], res[1.5]), res
