"""The warp test of benchmarks/mover_warp.py on one object, in bins of image radius h_i.

Per bin of h_i (edges 0, 30, 50, 70, 90, 110, 130, 160, 200, 260 px at 512 px, scaled
with the image size): the object's pixels (as mover_warp.object_pixels), their mean true
radial flow, DIS's (on the noise-free images), and the radial offset from the truth that
minimises the warp residual of the noise-free images (mover_warp.parabola_min; its
curvature near 0 means the radial flow is not determined there). Shows where on an
object brightness constancy and the truth part, and whether that changes with the
image's resolution. Usage::

    python benchmarks/warp_bins.py DATASET CAM OBJECT

e.g. ``python benchmarks/warp_bins.py /work/data/independent_movers cam1 ball``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from mover_warp import (
    OFFSETS,
    clean_grey,
    object_pixels,
    parabola_min,
    polar,
    residual,
    rms,
)

from omniflow.io.dataset import open_dataset
from validation.baselines import dis_flow

EDGES_512 = np.array([0, 30, 50, 70, 90, 110, 130, 160, 200, 260], dtype=float)


def main(directory: str, cam: str, name: str) -> None:
    ds = open_dataset(directory)
    oid = {v: k for k, v in ds.objects.items()}[name]
    unit = getattr(ds.rig, cam)
    c0 = (unit.x_c, unit.y_c)
    edges = EDGES_512 * unit.width / 512
    acc: dict[int, dict] = {}
    for t in range(min(3, ds.frame_count - 1)):
        i0, i1 = clean_grey(ds, t, cam), clean_grey(ds, t + 1, cam)
        dis = dis_flow(*(np.rint(255 * i).astype(np.uint8) for i in (i0, i1)))
        ii, jj = object_pixels(ds.read_frame(t, cam), ds.read_frame(t + 1, cam), oid)
        x, y = jj + 0.5, ii + 0.5
        tr = ds.read_frame(t, cam)
        tdx = tr["gt.flow.dx"][ii, jj].astype(float)
        tdy = tr["gt.flow.dy"][ii, jj].astype(float)
        dh, _, ex, ey = polar(x, y, tdx, tdy, c0)
        ddh, _, _, _ = polar(x, y, dis[ii, jj, 0].astype(float), dis[ii, jj, 1].astype(float), c0)
        b = np.digitize(np.hypot(x - c0[0], y - c0[1]), edges)
        for k in np.unique(b):
            s = b == k
            a = acc.setdefault(int(k), {"dh": [], "dis": [], **{o: [] for o in OFFSETS}})
            a["dh"].append(dh[s])
            a["dis"].append(ddh[s])
            for o in OFFSETS:
                a[o].append(residual(i0, i1, x[s], y[s], tdx[s] + o * ex[s], tdy[s] + o * ey[s]))
    print(f"{directory} {cam} {name}: h_i bin (px), pixels, mean true dh, DIS dh, BC offset, curv")
    for k, a in sorted(acc.items()):
        curve = np.array([rms(np.concatenate(a[o])) for o in OFFSETS])
        off, curv = parabola_min(OFFSETS, curve)
        lo = edges[k - 1] if k >= 1 else 0.0
        hi = edges[k] if k < len(edges) else np.inf
        n = np.concatenate(a["dh"]).size
        print(f"  {lo:5.0f}-{hi:5.0f}  {n:6d}  {np.mean(np.concatenate(a['dh'])):+.3f}"
              f"  {np.mean(np.concatenate(a['dis'])):+.3f}  {off:+.2f}  {curv:.2f}")  # fmt: skip


if __name__ == "__main__":
    main(*sys.argv[1:4])
