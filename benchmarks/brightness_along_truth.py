"""Brightness change along the true motion, per object: I_{t+1}(x + flow) - I_t(x).

Brightness constancy (eq. 8) holds where this is zero up to the image noise.
For each camera and frame pair of a dataset, the next frame (formed as
omnivalidate forms it: the dataset's camera model on the radiance) is read at
each valid pixel moved by its true flow (cubic interpolation), the frame is
subtracted, and per object with at least 200 such pixels (5 px inside the valid
area) the mean of that difference relative to the object's mean grey (its
brightness change per frame along the motion) and the spread (noise and
interpolation) are printed, with the mean true displacement. Run::

    python benchmarks/brightness_along_truth.py /work/data/approach
"""

from __future__ import annotations

import sys

import cv2
import numpy as np


def main(directory: str) -> None:
    from omniflow.io.dataset import open_dataset
    from validation.inputs import Inputs, camera_model

    ds = open_dataset(directory)
    camera = camera_model(ds.meta)
    inputs = Inputs(ds, camera, auto_exposure=camera is not None and "camera" not in ds.meta)
    for cam in ("cam1", "cam2"):
        for t in range(ds.frame_count - 1):
            g0, g1 = inputs.grey(t, cam), inputs.grey(t + 1, cam)
            tr = ds.read_frame(t, cam)
            yy, xx = np.mgrid[0 : g0.shape[0], 0 : g0.shape[1]].astype(np.float32)
            dx = np.nan_to_num(tr["gt.flow.dx"]).astype(np.float32)
            dy = np.nan_to_num(tr["gt.flow.dy"]).astype(np.float32)
            moved = cv2.remap(g1.astype(np.float32), xx + dx, yy + dy, cv2.INTER_CUBIC)
            change = moved - g0
            ok = (tr["gt.flow.valid"] > 0.5) & np.isfinite(tr["gt.flow.dx"])
            ok &= cv2.erode(ok.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
            obj = np.rint(tr["gt.object"]).astype(int)
            parts = []
            for o in np.unique(obj[ok]):
                m = ok & (obj == o)
                if m.sum() < 200:
                    continue
                grey = g0[m].mean()
                parts.append(
                    f"{ds.objects.get(int(o), o)} {change[m].mean() / grey:+.4f} "
                    f"(sd {change[m].std() / grey:.4f}, {np.hypot(dx, dy)[m].mean():.2f} px)"
                )
            print(f"{cam} pair {t}: " + "; ".join(parts), flush=True)


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python benchmarks/brightness_along_truth.py DATASET")
    main(sys.argv[1])
