"""Which rig errors a test card can tell apart: the singular values of the card's image.

Points of the card (scenes/test_card.toml: r = 0.5 m, 8 heights by 24 azimuths in the
unit's view; or several radii) are projected by the traced model
(:func:`omniflow.geometry.rig_errors.traced_project`); each error key is stepped by
0.01 deg or 0.1 mm and the image displacement (px) is a column of J. Prints J's
singular values with every key and with the fitted five
(:data:`omniflow.geometry.registration.PARAMS`), the near-null combinations, and how
well the five absorb each held key (the rms left after a least-squares fit, px).
``python3 -m benchmarks.registration_identifiability [--radii 0.5] [--size 256]``.
"""

from __future__ import annotations

import argparse

import numpy as np

from omniflow.geometry.rig import Rig
from omniflow.geometry.rig_errors import UnitErrors, traced_project

NAMES = ("mirror_tilt[0]", "mirror_tilt[1]", "mirror_offset[0]", "mirror_offset[1]",
         "mirror_offset[2]", "cone_angle", "camera_tilt[0]", "camera_tilt[1]",
         "camera_offset[0]", "camera_offset[1]")  # fmt: skip
STEPS = (0.01, 0.01, 1e-4, 1e-4, 1e-4, 0.01, 0.01, 0.01, 1e-4, 1e-4)  # deg or m
FITTED = (0, 1, 2, 3, 5)


def _errors(p) -> UnitErrors:
    return UnitErrors(mirror_tilt=(p[0], p[1]), mirror_offset=(p[2], p[3], p[4]),
                      cone_angle=90 + p[5], camera_tilt=(p[6], p[7]),
                      camera_offset=(p[8], p[9]))  # fmt: skip


def jacobian(unit, radii) -> np.ndarray:
    """Image displacement (px) per step of each key, (2 N, 10)."""
    pts = []
    for rc in radii:
        hmax = (unit.d + rc) * unit.R / (unit.d + unit.R)
        for h in np.linspace(0.1 * hmax, 0.97 * hmax, 8):
            for th in np.linspace(0, 2 * np.pi, 24, endpoint=False):
                pts.append([rc * np.cos(th), rc * np.sin(th), unit.tip_h + h])
    q = np.array(pts)
    x0, y0, _ = traced_project(unit, q, UnitErrors())
    cols = []
    for i, s in enumerate(STEPS):
        p = np.zeros(10)
        p[i] = s
        x, y, _ = traced_project(unit, q, _errors(p))
        cols.append(np.concatenate([x - x0, y - y0]))
    return np.array(cols).T


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--radii", type=float, nargs="+", default=[0.5])
    ap.add_argument("--size", type=int, default=256)
    args = ap.parse_args()
    unit = Rig.symmetric(d=0.10, R=0.05, s=0.30, size=args.size).cam2
    J = jacobian(unit, args.radii)
    print(f"{args.size} px, card radii {args.radii} m; steps 0.01 deg / 0.1 mm")
    rms = np.sqrt((J**2).mean(0))
    print("rms px per step: " + ", ".join(f"{n} {r:.3f}" for n, r in zip(NAMES, rms, strict=True)))
    _, S, Vt = np.linalg.svd(J, full_matrices=False)
    print("all ten keys, singular values:", " ".join(f"{s:.3g}" for s in S))
    for k in (1, 2, 3):
        v = Vt[-k]
        top = np.argsort(-np.abs(v))[:4]
        print(
            f"  near-null {k} ({S[-k]:.3g}): " + ", ".join(f"{NAMES[i]} {v[i]:+.2f}" for i in top)
        )
    B = J[:, FITTED]
    print("the fitted five, singular values:",
          " ".join(f"{s:.3g}" for s in np.linalg.svd(B, compute_uv=False)))  # fmt: skip
    for i in (4, 6, 7, 8, 9):
        coef, *_ = np.linalg.lstsq(B, J[:, i], rcond=None)
        left = J[:, i] - B @ coef
        print(
            f"  {NAMES[i]}: {np.sqrt((J[:, i] ** 2).mean()):.4f} px rms per step, "
            f"{np.sqrt((left**2).mean()):.4f} left after the five ({np.abs(left).max():.4f} max)"
        )


if __name__ == "__main__":
    main()
