"""The image-noise estimators against the camera model's known noise.

Closed-form textures (sums of sinusoids, tests/helpers/noise_frames.py) moved by a known
shift between frames t and t + 1, taken by :class:`omnisim.camera.CameraModel` at several
settings and read as omniflow reads a camera image. For each texture, motion and camera:
the single-frame estimate (:func:`omniflow.fit.noise.immerkaer_sigma`, frame t) and the
temporal one (:func:`omniflow.fit.noise.temporal_noise`, at its median tile brightness),
each over the true noise at that brightness (:func:`omnisim.camera_noise.grey_noise_variance`),
as the mean and range over seeds. Then the brightness dependence on a shot-noise-limited
camera, and the cost of both on a 512 x 512 pair. Run (about 40 s)::

    python3 -m benchmarks.noise_estimate [--seeds 3]

The figures are in docs/decisions/noise_estimate.md.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from omniflow.fit.noise import immerkaer_sigma, temporal_noise
from omnisim.camera import CameraModel
from omnisim.camera_noise import grey_noise_level, grey_noise_variance
from tests.helpers.noise_frames import COARSE, FINE, VERY_FINE, moving_pair

#: Camera settings of the table (changes from the defaults: 8 bits, full well 20000 e-,
#: read noise 5 e-, exposure 2).
CAMERAS: dict[str, dict] = {
    "default": {},
    "read 20 e-": {"read_noise": 20.0},
    "exposure 0.5": {"exposure": 0.5},
    "well 5000 e-": {"full_well": 5000.0},
    "12 bits": {"bits": 12},
}
TEXTURES = {"fine 2.5-4 px": FINE, "very fine 2-3 px": VERY_FINE, "coarse 12-40 px": COARSE}
MOTIONS = ((0.0, 0.0), (0.3, 0.2), (0.7, -0.4), (1.6, 0.9))


def ratios(model: CameraModel, shift, wavelengths, seeds: int) -> tuple[list, list]:
    """Temporal and Immerkaer estimates over the true sigma, one per seed."""
    tem, imm = [], []
    for seed in range(seeds):
        f0, f1 = moving_pair(model, shift, seed, wavelengths)
        level = temporal_noise(f0, f1)
        true = float(np.sqrt(grey_noise_variance(model, level.reference)))
        tem.append(level.sigma / true)
        imm.append(immerkaer_sigma(f0) / true)
    return tem, imm


def _cell(values: list) -> str:
    return f"{np.mean(values):.3f} ({min(values):.3f}-{max(values):.3f})"


def table(seeds: int) -> None:
    print("texture | motion (px) | camera | temporal / true | Immerkaer / true")
    print("---|---|---|---|---")
    for tname, wl in TEXTURES.items():
        for shift in MOTIONS:
            for cname, params in CAMERAS.items():
                tem, imm = ratios(CameraModel(**params), shift, wl, seeds)
                print(f"{tname} | {shift[0]:g}, {shift[1]:g} | {cname} | {_cell(tem)} | "
                      f"{_cell(imm)}")  # fmt: skip


def brightness(seeds: int) -> None:
    """Fitted sigma(I) against the truth on a wide-contrast texture, 12 bits, 5000 e-."""
    model = CameraModel(full_well=5000.0, bits=12)
    true = grey_noise_level(model)
    levels = (0.15, 0.4, 0.65)
    rows = []
    for seed in range(seeds):
        f0, f1 = moving_pair(model, (0.7, -0.4), seed, COARSE, mean=0.2, contrast=0.17)
        lev = temporal_noise(f0, f1)
        rows.append([lev.sigma_at(i) / true.sigma_at(i) for i in levels] + [lev.a / true.a])
    print(f"\nbrightness dependence (12 bits, well 5000 e-, coarse texture 0.06-0.74): "
          f"true a = {true.a:.3g}, b = {true.b:.3g}")  # fmt: skip
    cols = [f"sigma({i:g}) / true" for i in levels] + ["a / true a"]
    for j, name in enumerate(cols):
        print(f"{name}: {_cell([r[j] for r in rows])}")


def cost(repeats: int = 5) -> None:
    f0, f1 = moving_pair(CameraModel(), (0.7, -0.4), 0, FINE, size=512)
    for name, fn in (
        ("immerkaer_sigma", lambda: immerkaer_sigma(f0)),
        ("temporal_noise", lambda: temporal_noise(f0, f1)),
    ):
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t)
        print(f"{name}: {1e3 * statistics.median(times):.0f} ms per 512 x 512 "
              f"(median of {repeats})")  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=3)
    args = p.parse_args()
    if args.seeds < 1:
        p.error(f"--seeds = {args.seeds}: expected an integer >= 1")
    table(args.seeds)
    brightness(args.seeds)
    print()
    cost()


if __name__ == "__main__":
    main()
