"""Write OpenCV DIS (medium preset) flow of a dataset in the ``--method-output`` format.

    python -m validation.examples.dis_method_output DATASET OUT_DIR [--panorama] [--camera K=V]
    omnivalidate DATASET --out REPORT --method-output OUT_DIR --method-name my-DIS

It stands for a method we did not write: it reads each frame pair through the
harness's own image function (:class:`validation.inputs.Inputs`, so it sees the
images every built-in method sees) and writes ``OUT_DIR/frames/NNNNNN/cam1.flo``
and ``cam2.flo``, the image-plane flow from frame NNNNNN to the next, as any
other method would. With ``--panorama`` it runs DIS on the unwarped panoramas
and maps the flow back to the image plane (``DIS-medium-panorama``).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from omniflow.io.imageio import atomic_write_bytes

__all__ = ["main", "write_dis_outputs"]


def write_dis_outputs(
    dataset: str | Path, out: str | Path, *, panorama: bool = False, camera: Sequence[str] = ()
) -> int:
    """Write DIS flow for every complete frame pair of ``dataset`` into ``out``; the count."""
    from omnisim.dataset import flo_bytes, open_dataset
    from validation import baselines as bl
    from validation.inputs import CAMERAS, Inputs, camera_model

    ds = open_dataset(dataset)
    auto = "camera" not in ds.meta and not any(c.startswith("exposure") for c in camera)
    images = Inputs(ds, camera_model(ds.meta, camera), auto_exposure=auto)
    done = set(ds.frames_done())
    pairs = [t for t in range(ds.frame_count - 1) if t in done and t + 1 in done]
    for t in pairs:
        for cam in CAMERAS:
            unit = ds.rig.cam1 if cam == "cam1" else ds.rig.cam2
            a, b = images.u8(t, cam), images.u8(t + 1, cam)
            if panorama:
                field = bl.panorama_flow(a, b, unit)
                h, w = a.shape
                yy, xx = np.mgrid[0:h, 0:w] + 0.5
                est = field.at(xx.ravel(), yy.ravel())
                dx, dy = est["dx"].reshape(h, w), est["dy"].reshape(h, w)
            else:
                flow = bl.dis_flow(a, b)
                dx, dy = flow[..., 0], flow[..., 1]
            path = Path(out) / "frames" / f"{t:06d}" / f"{cam}.flo"
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_bytes(path, flo_bytes(dx, dy))
        images.drop_before(t + 1)
    return len(pairs)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m validation.examples.dis_method_output",
                                 description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("dataset")
    ap.add_argument("out")
    ap.add_argument("--panorama", action="store_true", help="DIS on the unwarped panoramas")
    ap.add_argument("--camera", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args(argv)
    n = write_dis_outputs(args.dataset, args.out, panorama=args.panorama, camera=args.camera)
    print(f"wrote {n} frame pair(s) of DIS flow to {args.out}/frames", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
