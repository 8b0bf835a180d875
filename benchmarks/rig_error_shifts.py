"""How far each rig error moves the image: the traced model against the ideal unit.

For points at azimuth 0 (rig +X) at a few ranges, from just above the tip's horizon to
the rim, prints the smallest and largest image displacement (px) that one error of a
given size causes, through :func:`omniflow.geometry.rig_errors.traced_project`. The
figures of ``docs/decisions/rig_errors.md``:
``python3 -m benchmarks.rig_error_shifts [--size 512] [--ranges 1 2.7 10]``.
"""

from __future__ import annotations

import argparse

import numpy as np

from omniflow.geometry.rig import Rig
from omniflow.geometry.rig_errors import UnitErrors, traced_project

#: One error of each key, of a size a careful lab might leave (label, errors).
CASES = (
    ("cone_angle 90.1 deg", UnitErrors(cone_angle=90.1)),
    ("cone_angle 90.2 deg", UnitErrors(cone_angle=90.2)),
    ("mirror_tilt [0.1, 0] deg", UnitErrors(mirror_tilt=(0.1, 0.0))),
    ("mirror_offset [0.1, 0, 0] mm", UnitErrors(mirror_offset=(1e-4, 0.0, 0.0))),
    ("camera_tilt [0.1, 0] deg", UnitErrors(camera_tilt=(0.1, 0.0))),
    ("camera_offset [0.1, 0] mm", UnitErrors(camera_offset=(1e-4, 0.0))),
)


def shifts(size: int, r: float, errors: UnitErrors) -> tuple[float, float]:
    """(min, max) image displacement, px, of 20 points at range r between the horizon
    and 95 % of the rim height (the default rig: d = 0.10 m, R = 0.05 m)."""
    unit = Rig.symmetric(d=0.1, R=0.05, s=0.3, size=size).cam2
    hs = np.linspace(0.02, (unit.d + r) * unit.R / (unit.d + unit.R) * 0.95, 20)
    q = np.stack([np.full_like(hs, r), np.zeros_like(hs), hs], -1)
    x0, y0, _ = traced_project(unit, q, UnitErrors())
    x1, y1, seen = traced_project(unit, q, errors)
    if not seen.all():
        raise RuntimeError(f"{errors}: a point left the mirror")
    d = np.hypot(x1 - x0, y1 - y0)
    return float(d.min()), float(d.max())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512, help="image size, px (default 512)")
    ap.add_argument("--ranges", type=float, nargs="+", default=[1.0, 2.7, 10.0], help="m")
    args = ap.parse_args(argv)
    print(f"| error | {' | '.join(f'r = {r:g} m' for r in args.ranges)} |")
    print("|---|" + "---|" * len(args.ranges))
    for label, errors in CASES:
        cells = [shifts(args.size, r, errors) for r in args.ranges]
        print(f"| {label} | " + " | ".join(f"{a:.2f}-{b:.2f}" for a, b in cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
