"""Regenerate the library's asset files (deterministic; no downloads).

    python scenes/assets/make_assets.py

torus.obj   a torus (major radius 0.25 m, minor 0.08 m), no texture coordinates:
            the scene loader gives it UVs by box projection.
poster.png  a 256 x 256 sRGB image: band-limited noise in two colours with a
            smooth diagonal grating, used as an image texture.
"""

from pathlib import Path

import cv2
import numpy as np
import trimesh

from omnisim import textures

HERE = Path(__file__).resolve().parent


def main() -> None:
    torus = trimesh.creation.torus(
        major_radius=0.25, minor_radius=0.08, major_sections=48, minor_sections=16
    )
    (HERE / "torus.obj").write_text(trimesh.exchange.obj.export_obj(torus, include_normals=False))

    noise = textures.noise_texture(
        tile=1.0, wavelength=(0.03, 0.3), resolution=256, seed=7,
        colors=((0.05, 0.10, 0.30), (0.90, 0.70, 0.20)),
    )  # fmt: skip
    grating = textures.grating_texture(tile=1.0, wavelength=0.125, angle=45.0, resolution=256)
    linear = np.clip(0.7 * noise + 0.3 * grating, 0.0, 1.0)
    srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)
    cv2.imwrite(str(HERE / "poster.png"), np.round(srgb[..., ::-1] * 255).astype(np.uint8))


if __name__ == "__main__":
    main()
