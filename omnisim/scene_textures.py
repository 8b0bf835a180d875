"""Texture tables of a scene file (``[objects.texture]``), read into texel arrays.

Moved out of :mod:`omnisim.scene` unchanged: :func:`texture_from_table` checks a texture
table (each failure a ``SceneError`` naming the key) and builds it with
:mod:`omnisim.textures`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from omnisim import textures
from omnisim.scene_checker import Checker

__all__ = ["IMAGE_SUFFIXES", "TEXTURE_KEYS", "TEXTURE_TYPES", "texture_from_table", "tile_of"]

TEXTURE_TYPES = ("noise", "grating", "checker", "solid", "image")
_TEX_COMMON = {"type", "tile", "resolution", "seed"}
TEXTURE_KEYS = {
    "noise": frozenset(_TEX_COMMON | {"wavelength", "colors", "contrast", "exponent"}),
    "grating": frozenset(_TEX_COMMON | {"wavelength", "angle", "phase", "colors", "contrast"}),
    "checker": frozenset(_TEX_COMMON | {"size", "colors"}),
    "solid": frozenset(_TEX_COMMON | {"color"}),
    "image": frozenset(_TEX_COMMON | {"path", "srgb"}),
}
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".hdr", ".tif", ".tiff", ".bmp")


def texture_from_table(
    chk: Checker, tbl: Any, where: str, seed: int, base: Path
) -> NDArray[np.float32]:
    """The texture of an ``[objects.texture]`` table (``seed``: the default noise seed)."""
    tbl = {} if tbl is None else tbl
    if not isinstance(tbl, dict):
        raise chk.bad(where, tbl, "a table")
    kind = chk.string(tbl, "type", where, "noise", choices=TEXTURE_TYPES)
    chk.table(tbl, where, TEXTURE_KEYS[kind])
    tile = chk.number(tbl, "tile", where, 1.0, lo=0, lo_open=True)
    res = chk.integer(tbl, "resolution", where, 512, lo=8, hi=8192)
    seed = chk.integer(tbl, "seed", where, seed, lo=0)
    colors = None
    if kind in ("noise", "grating", "checker"):
        colors = tbl.get("colors", textures.DEFAULT_COLORS)
        if not isinstance(colors, list | tuple) or len(colors) != 2:
            raise chk.bad(f"{where}.colors", colors, "two [r, g, b] colours with values in [0, 1]")
        colors = [chk.vector({"c": c}, "c", "", n=3, lo=0.0, hi=1.0) for c in colors]
    if kind == "noise":
        wl = chk.vector(tbl, "wavelength", where, [0.05, 0.5], n=2, lo=0.0, lo_open=True)
        if wl[0] > wl[1]:
            raise chk.bad(f"{where}.wavelength", wl.tolist(), "[shortest, longest] in metres")
        if tile / wl[0] > res / 2:
            raise chk.bad(
                f"{where}.wavelength",
                wl.tolist(),
                f"a shortest wavelength of at least 2 texels = {2 * tile / res:.4g} m "
                f"(tile {tile:g} m over {res} texels); 4 or more texels is better",
            )
        if tile / wl[1] < 1:
            raise chk.bad(
                f"{where}.wavelength", wl.tolist(), f"a longest wavelength <= tile ({tile:g} m)"
            )
        return textures.noise_texture(
            tile=tile,
            wavelength=(wl[0], wl[1]),
            resolution=res,
            colors=colors,
            contrast=chk.number(tbl, "contrast", where, 1.0, lo=0.0, hi=1.0),
            exponent=chk.number(tbl, "exponent", where, 1.0),
            seed=seed,
        )
    if kind == "grating":
        wl = chk.number(tbl, "wavelength", where, 0.1, lo=0.0, lo_open=True)
        try:
            return textures.grating_texture(
                tile=tile,
                wavelength=wl,
                angle=chk.number(tbl, "angle", where, 0.0),
                phase=chk.number(tbl, "phase", where, 0.0),
                resolution=res,
                colors=colors,
                contrast=chk.number(tbl, "contrast", where, 1.0, lo=0.0, hi=1.0),
            )
        except ValueError as exc:
            raise chk.bad(f"{where}.wavelength", wl, f"a usable wavelength ({exc})") from exc
    if kind == "checker":
        size = chk.number(tbl, "size", where, 0.25, lo=0.0, lo_open=True)
        if tile / size > res / 2:
            raise chk.bad(f"{where}.size", size, f"at least 2 texels ({2 * tile / res:.4g} m)")
        return textures.checker_texture(tile=tile, size=size, resolution=res, colors=colors)
    if kind == "solid":
        return textures.solid_texture(chk.vector(tbl, "color", where, [0.5, 0.5, 0.5], lo=0, hi=1))
    img_path = chk.file(tbl, "path", where, base, IMAGE_SUFFIXES)
    try:
        return textures.load_image_texture(img_path, srgb=chk.boolean(tbl, "srgb", where, True))
    except ValueError as exc:
        raise chk.error(f"{where}.path", f"{exc}; expected a readable image") from exc


def tile_of(tex_tbl: Any) -> float:
    """The texture table's ``tile`` (m), 1 when not given (for the meshes' UVs)."""
    if isinstance(tex_tbl, dict) and isinstance(tex_tbl.get("tile"), int | float):
        return float(tex_tbl["tile"])
    return 1.0
