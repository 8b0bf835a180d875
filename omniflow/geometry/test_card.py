"""The registration test card (paper section 2.1): a polar checkerboard on a tube.

The paper registers a unit with "a test card of the shooting target type consisting of
cross-hairs and concentric circles, centered on the cone axis": circles about the axis
image as circles and lines coplanar with the axis as radial lines (eq. 1). Here the card
is a tube of radius ``radius`` about the rig's axis, ``height`` tall, carrying a
checkerboard in (azimuth, height): ``sectors`` equal sectors and rings ``ring_spacing``
tall. Every ring edge is a circle about the axis (r = radius, h = const) and every
sector edge a line coplanar with the axis (theta = const), so through eq. (1) the whole
image of an ideal unit is a target of concentric circles and radial lines.

The card's frame is its own: origin at the tube's centre, Z along its axis; ring edges at
z = -height / 2 + k ring_spacing, sector edges at azimuth 2 pi j / sectors, check (j, k)
dark when j + k is even. The scene's ``position`` puts the centre in the world
(``omnisim``); :func:`card_in_rig` gives the card in the rig frame. Lengths in metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["CARD_DEFAULTS", "TestCard", "card_in_rig"]

#: Defaults of the scene keys: a 0.5 m tube 0.8 m tall (both units of the default rig,
#: s = 0.3 m, see it from r = 0.5 m: h up to (d + r) R / (d + R) = 0.2 m above each tip),
#: 24 sectors (15 deg) and 2.5 cm rings (16 px apart at 256 px, v = 378 px: more than
#: twice the largest image shift of the errors' limits near the rim).
CARD_DEFAULTS = {"radius": 0.5, "height": 0.8, "sectors": 24, "ring_spacing": 0.025}


@dataclass(frozen=True)
class TestCard:
    """A card: its pattern and its centre in the rig frame (``center``, m; axis along Z)."""

    __test__ = False  # not a pytest class

    radius: float = CARD_DEFAULTS["radius"]
    height: float = CARD_DEFAULTS["height"]
    sectors: int = CARD_DEFAULTS["sectors"]
    ring_spacing: float = CARD_DEFAULTS["ring_spacing"]
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    azimuth: float = 0.0  # rad, the card's turn about its axis

    @property
    def n_rings(self) -> int:
        """Rings (whole ones) on the tube."""
        return math.floor(self.height / self.ring_spacing + 1e-9)

    def ring_edges(self) -> NDArray:
        """Z (rig frame) of every ring edge, the tube's ends excluded."""
        k = np.arange(1, self.n_rings)
        return self.center[2] - self.height / 2 + k * self.ring_spacing

    def sector_edges(self) -> NDArray:
        """Azimuth (rad, rig frame) of every sector edge."""
        return self.azimuth + 2 * np.pi * np.arange(self.sectors) / self.sectors

    def dark(self, theta: ArrayLike, z: ArrayLike) -> NDArray:
        """True where the check at azimuth theta and height z (rig frame) is dark."""
        j = np.floor((np.asarray(theta) - self.azimuth) / (2 * np.pi) * self.sectors)
        k = np.floor((np.asarray(z) - self.center[2] + self.height / 2) / self.ring_spacing)
        return (j + k) % 2 == 0

    def texture(self, resolution: int = 256) -> NDArray[np.float32]:
        """One tile of the pattern (2 sectors by 2 rings), (res, res) in [0, 1]: 1 light.

        Rows run along z (texel row 0 at the lowest ring), columns along azimuth, the
        texel convention of ``omnisim.textures``; the tube's UVs repeat it.
        """
        c = (np.arange(resolution) + 0.5) / resolution
        j = np.floor(c * 2)
        return ((j[:, None] + j[None, :]) % 2).astype(np.float32)

    def uv(self, theta: ArrayLike, z_card: ArrayLike) -> tuple[NDArray, NDArray]:
        """Texture coordinates (in tiles) of azimuth theta (card frame) and card z."""
        u = np.asarray(theta) / (2 * np.pi) * (self.sectors / 2)
        v = (np.asarray(z_card) + self.height / 2) / (2 * self.ring_spacing)
        return u, v


def card_from_table(tbl: dict[str, Any], fail) -> TestCard:
    """The pattern keys of a ``test_card`` object table (``fail(key, value, expected)``)."""
    out: dict[str, Any] = {}
    for key in ("radius", "height", "ring_spacing"):
        v = tbl.get(key, CARD_DEFAULTS[key])
        if not _number(v) or v <= 0:
            raise fail(key, v, "a number > 0 (m)")
        out[key] = float(v)
    n = tbl.get("sectors", CARD_DEFAULTS["sectors"])
    if not isinstance(n, int) or isinstance(n, bool) or n < 4 or n % 2 or n > 360:
        raise fail("sectors", n, "an even integer in [4, 360]")
    if out["height"] < 4 * out["ring_spacing"]:
        raise fail("height", out["height"], f"at least 4 rings: >= {4 * out['ring_spacing']:g} m")
    return TestCard(sectors=n, **out)


def card_in_rig(card: TestCard, rig_from_world: NDArray, world_from_card: NDArray) -> TestCard:
    """The card placed in the rig frame (4x4 poses); its axis must be the rig's Z.

    Raises ValueError when the card's axis is not along the rig's (within 1e-6 rad).
    """
    m = np.asarray(rig_from_world) @ np.asarray(world_from_card)
    axis = m[:3, 2]
    if axis[2] < math.cos(1e-6):
        raise ValueError(f"the card's axis is {np.round(axis, 6).tolist()} in the rig frame")
    azimuth = math.atan2(m[1, 0], m[0, 0])
    return replace(card, center=tuple(float(c) for c in m[:3, 3]), azimuth=azimuth)


def _number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
