"""The camera model's noise figures and cost (omnisim.camera).

Prints, for a flat patch of constant radiance (256 x 256 x 3 samples), the standard
deviation of the digital numbers measured against the one the parameters predict,
``sqrt(mu + read_noise^2)`` electrons times ``gain (2^bits - 1) / full_well`` (and, at
8 bits, with the quantisation step's ``1/12`` DN^2 added), and the median time of
``CameraModel.apply`` and of the PNG encoding on a 512 x 512 RGB image. Run::

    python3 -m benchmarks.bench_camera
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import numpy as np

from omnisim.camera import CameraModel

#: (parameters, mean charge in electrons) of the noise table.
CASES: list[tuple[dict, float]] = [
    ({"bits": 16, "read_noise": 0.0}, 100.0),
    ({"bits": 16, "read_noise": 0.0}, 1000.0),
    ({"bits": 16, "read_noise": 0.0}, 10000.0),
    ({"bits": 16, "read_noise": 20.0}, 400.0),
    ({"bits": 16, "read_noise": 80.0}, 1000.0),
    ({"bits": 16, "read_noise": 5.0, "gain": 2.0}, 3000.0),
    ({}, 10000.0),  # the default camera at mid grey
    ({"full_well": 80000.0}, 40000.0),  # 8 bits, noise 0.64 DN: quantisation matters
]


def noise_cases(size: int = 256) -> list[dict]:
    """Measured and predicted noise (DN) of a flat patch for each of :data:`CASES`."""
    out = []
    for params, mu in CASES:
        m = CameraModel(**params)
        flat = np.full((size, size, 3), mu / (m.exposure * m.full_well), np.float32)
        dn = m.apply(flat, frame=0, cam="cam1").astype(np.float64)
        sigma = m.noise_electrons(mu) * m.gain * m.max_dn / m.full_well
        if m.bits == 8:
            sigma = math.hypot(sigma, 12**-0.5)
        label = ", ".join(f"{k} {v:g}" for k, v in params.items()) or "defaults"
        out.append({"label": label, "mu": mu, "predicted": sigma, "measured": dn.std()})
    return out


def noise_table(size: int = 256) -> None:
    print("parameters | mu (e-) | predicted DN | measured DN | ratio")
    for c in noise_cases(size):
        print(f"{c['label']} | {c['mu']:g} | {c['predicted']:.4f} | {c['measured']:.4f} | "
              f"{c['measured'] / c['predicted']:.4f}")  # fmt: skip


def timing(size: int = 512, repeats: int = 7) -> None:
    rng = np.random.default_rng(0)
    img = (rng.random((size, size, 3)) * 0.45).astype(np.float32)
    for params in ({}, {"bits": 16}, {"vignetting": 0.3, "defocus": 1.0}):
        m = CameraModel(**params)
        ta, tp = [], []
        for i in range(repeats):
            t = time.perf_counter()
            dn = m.apply(img, frame=i, cam="cam1")
            ta.append(time.perf_counter() - t)
            t = time.perf_counter()
            m.png_bytes(dn)
            tp.append(time.perf_counter() - t)
        print(
            f"{params or 'defaults'}: apply {1e3 * statistics.median(ta):.1f} ms, "
            f"PNG {1e3 * statistics.median(tp):.1f} ms per {size}x{size} camera image "
            f"(median of {repeats})"
        )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=7)
    args = p.parse_args()
    noise_table()
    timing(repeats=args.repeats)


if __name__ == "__main__":
    main()
