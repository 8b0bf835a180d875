"""The lights of a scene file (``[[lights]]``, docs/scene_format.md): their model and reader.

Area lights are shapes a camera ray can hit; they are not objects and have no object id.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from omnisim import textures
from omnisim.scene_checker import REQUIRED, Checker
from omnisim.scene_textures import IMAGE_SUFFIXES

__all__ = [
    "LIGHT_KEYS",
    "LIGHT_TYPES",
    "AreaLight",
    "DirectionalLight",
    "EnvironmentLight",
    "Light",
    "PointLight",
    "lights_from_tables",
]

LIGHT_TYPES = ("point", "area", "environment", "directional")
LIGHT_KEYS = {
    "point": frozenset({"type", "position", "intensity"}),
    "area": frozenset({"type", "position", "size", "normal", "radiance"}),
    "environment": frozenset({"type", "radiance", "path", "scale"}),
    "directional": frozenset({"type", "direction", "irradiance"}),
}


@dataclass(frozen=True)
class PointLight:
    """An isotropic point light: ``intensity`` (W/sr, linear RGB) at ``position`` (world, m)."""

    position: NDArray[np.float64]
    intensity: NDArray[np.float64]
    type: str = "point"


@dataclass(frozen=True)
class AreaLight:
    """A one-sided emitting rectangle: centre ``position``, ``size`` (m), facing ``normal``.

    ``radiance`` is the emitted radiance (W/(m^2 sr), linear RGB).
    """

    position: NDArray[np.float64]
    size: NDArray[np.float64]
    normal: NDArray[np.float64]
    radiance: NDArray[np.float64]
    type: str = "area"

    def to_world(self) -> NDArray[np.float64]:
        """(4, 4) map of the square [-1, 1]^2 in z = 0 (normal +Z) onto the light.

        The rectangle's local X axis is kept as horizontal as possible.
        """
        n = self.normal / np.linalg.norm(self.normal)
        ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        ex = ref - n * (ref @ n)
        ex /= np.linalg.norm(ex)
        ey = np.cross(n, ex)
        m = np.eye(4)
        m[:3, 0] = ex * self.size[0] / 2
        m[:3, 1] = ey * self.size[1] / 2
        m[:3, 2] = n
        m[:3, 3] = self.position
        return m


@dataclass(frozen=True)
class EnvironmentLight:
    """Light from every direction: constant ``radiance`` or an environment map image (linear)."""

    radiance: NDArray[np.float64]
    image: NDArray[np.float32] | None = None
    path: str | None = None
    scale: float = 1.0
    type: str = "environment"


@dataclass(frozen=True)
class DirectionalLight:
    """A distant light travelling along ``direction`` with ``irradiance`` (W/m^2)."""

    direction: NDArray[np.float64]
    irradiance: NDArray[np.float64]
    type: str = "directional"


Light = PointLight | AreaLight | EnvironmentLight | DirectionalLight


def lights_from_tables(chk: Checker, items: Any, base: Path) -> list[Light]:
    """The scene's ``[[lights]]`` tables as light objects, each key checked by ``chk``."""
    if items is REQUIRED or not isinstance(items, list) or not items:
        raise chk.bad(
            "lights", None if items is REQUIRED else items, "at least one [[lights]] table"
        )
    out: list[Light] = []
    for i, tbl in enumerate(items):
        where = f"lights[{i}]"
        if not isinstance(tbl, dict):
            raise chk.bad(where, tbl, "a table")
        kind = chk.string(tbl, "type", where, choices=LIGHT_TYPES)
        chk.table(tbl, where, LIGHT_KEYS[kind])
        col = dict(lo=0.0, scalar_ok=True)
        if kind == "point":
            out.append(
                PointLight(
                    chk.vector(tbl, "position", where), chk.vector(tbl, "intensity", where, **col)
                )
            )
        elif kind == "area":
            normal = chk.vector(tbl, "normal", where, [0.0, 0.0, -1.0])
            if np.linalg.norm(normal) < 1e-9:
                raise chk.bad(f"{where}.normal", normal.tolist(), "a non-zero direction")
            out.append(
                AreaLight(
                    chk.vector(tbl, "position", where),
                    chk.vector(tbl, "size", where, n=2, lo=0.0, lo_open=True),
                    normal / np.linalg.norm(normal),
                    chk.vector(tbl, "radiance", where, **col),
                )
            )
        elif kind == "environment":
            image, img_path = None, None
            if "path" in tbl:
                p = chk.file(tbl, "path", where, base, IMAGE_SUFFIXES)
                try:
                    image = textures.load_image_texture(p, srgb=False)
                except ValueError as exc:
                    raise chk.error(f"{where}.path", f"{exc}; expected an image") from exc
                img_path = str(p)
            out.append(
                EnvironmentLight(
                    chk.vector(tbl, "radiance", where, [1.0, 1.0, 1.0], **col),
                    image,
                    img_path,
                    chk.number(tbl, "scale", where, 1.0, lo=0.0),
                )
            )
        else:
            direction = chk.vector(tbl, "direction", where, [0.0, 0.0, -1.0])
            if np.linalg.norm(direction) < 1e-9:
                raise chk.bad(f"{where}.direction", direction.tolist(), "a non-zero direction")
            out.append(
                DirectionalLight(
                    direction / np.linalg.norm(direction),
                    chk.vector(tbl, "irradiance", where, **col),
                )
            )
    return out
