"""How far the rectification of :mod:`omniflow.registration` is off at other depths.

The rectification is exact for points at ``DEFAULT_DEPTH`` from the axis. For a unit
with errors, every ideal pixel inside the rim (h_i from 0.1 r_m to r_m) and points at
range r on its eq. (1) ray: the real pixel of the point (traced model) minus the pixel
the rectification sampled. Prints the median, 95th percentile and largest distance, px.
``python3 -m benchmarks.registration_residual [--size 256] [--depth 2]``.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from omniflow.geometry.rig import Rig
from omniflow.geometry.rig_errors import UnitErrors, traced_project
from omniflow.registration import DEFAULT_DEPTH, ideal_points, rectify_map

#: The test card scene's cam1 errors and single errors of the sensitivity sweep's size.
CASES = (
    ("scenes/test_card.toml cam1", UnitErrors(mirror_tilt=(0.15, -0.1),
                                              mirror_offset=(4e-4, -3e-4, 0.0), cone_angle=90.1)),
    ("mirror_tilt [0.5, 0] deg", UnitErrors(mirror_tilt=(0.5, 0.0))),
    ("mirror_offset [1, 0, 0] mm", UnitErrors(mirror_offset=(1e-3, 0.0, 0.0))),
    ("mirror_offset [0, 0, 1] mm", UnitErrors(mirror_offset=(0.0, 0.0, 1e-3))),
    ("cone_angle 90.2 deg", UnitErrors(cone_angle=90.2)),
    ("camera_tilt [0.5, 0] deg", UnitErrors(camera_tilt=(0.5, 0.0))),
    ("camera_offset [1, 0] mm", UnitErrors(camera_offset=(1e-3, 0.0))),
)  # fmt: skip


def residual(unit, depth: float, r: float, step: int = 4) -> NDArray:
    """Distances (px) for points at range r, over every ``step``-th ideal pixel."""
    xr, yr = rectify_map(unit, depth)
    x, y = unit.pixel_centres()
    x, y, xr, yr = (a[::step, ::step] for a in (x, y, xr, yr))
    h = np.hypot(x - unit.x_c, y - unit.y_c)
    keep = (h > 0.1 * unit.r_m) & (h < unit.r_m) & np.isfinite(xr)
    xt, yt, seen = traced_project(unit, ideal_points(unit, x[keep], y[keep], r))
    d = np.hypot(xt - xr[keep], yt - yr[keep])
    return d[seen]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--depth", type=float, default=DEFAULT_DEPTH)
    ap.add_argument("--ranges", type=float, nargs="+", default=[0.5, 1.0, 2.0, 3.3, 10.0])
    args = ap.parse_args()
    unit0 = Rig.symmetric(d=0.10, R=0.05, s=0.30, size=args.size).cam2
    print(f"{args.size} px, rectified at {args.depth:g} m; px: median / p95 / max")
    print("| errors | " + " | ".join(f"r = {r:g} m" for r in args.ranges) + " |")
    print("|---|" + "---|" * len(args.ranges))
    for label, e in CASES:
        unit = replace(unit0, errors=e)
        cells = []
        for r in args.ranges:
            d = residual(unit, args.depth, r)
            cells.append(f"{np.median(d):.3f} / {np.percentile(d, 95):.3f} / {d.max():.3f}")
        print(f"| {label} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
