"""The camera's lens: a thin lens with a finite aperture, and its image through the cone.

The ``[optics]`` table of a scene (``docs/scene_format.md``) describes the lens of both
units: ``f_number`` N (infinity, the default, is today's pinhole), ``focal_length`` f
and ``focus_distance`` D (metres, along the optical axis from the lens), optional
``pixel_pitch`` p. The image distance in pixels stays the rig's v (eq. 2), so every
ground-truth quantity is unchanged: it is defined by the chief ray of each pixel centre,
the ray through the lens centre, which is the pinhole's ray. The lens only adds blur.

Thin-lens model (rig frame, the unit's camera at the origin of its lens plane, the
cone's tip a distance d above it). A film point at image offset (px, py) from the image
centre has its chief ray along (px, py, v); the lens focuses it on the plane at axial
depth D, at ``F = (D / v) (px, py, v)``. A ray of that film point leaves the lens at a
point L of the aperture disc (radius ``f / (2 N)``) towards F, and is reflected off the
cone where it meets it (:func:`thin_lens_cone_ray`: ray-cone intersection and vector
reflection off the surface normal). So the cone's astigmatism (flat along its
generators, curved around the axis) arises from the geometry, not from a kernel.

:func:`cone_blur_sigma` is the first-order closed form of that blur (Coddington's
equations for the cone's two principal sections, then the thin-lens blur disc); the
tests compare rendered point sources against it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omnisim.scene_checker import Checker

__all__ = [
    "NUMPY_OPS",
    "OPTICS_KEYS",
    "PITCH_TOLERANCE",
    "Optics",
    "cone_blur_sigma",
    "image_distance",
    "optics_from_table",
    "thin_lens_cone_ray",
]

OPTICS_KEYS = frozenset({"f_number", "focal_length", "focus_distance", "pixel_pitch"})
#: A given ``pixel_pitch`` may differ from image distance / v by at most this fraction.
PITCH_TOLERANCE = 0.05

#: Array operations of :func:`thin_lens_cone_ray` for numpy (the sensor passes Dr.Jit's).
NUMPY_OPS = SimpleNamespace(sqrt=np.sqrt, select=np.where, maximum=np.maximum)


@dataclass(frozen=True)
class Optics:
    """The lens of both units (module docstring). ``f_number = inf`` is a pinhole."""

    f_number: float = math.inf
    focal_length: float | None = None
    focus_distance: float | None = None
    pixel_pitch: float | None = None

    @property
    def pinhole(self) -> bool:
        """True for an infinitely small aperture (no blur)."""
        return not math.isfinite(self.f_number)

    @property
    def aperture_radius(self) -> float:
        """Radius of the aperture disc, metres: f / (2 N); 0 for a pinhole."""
        if self.pinhole:
            return 0.0
        return float(self.focal_length) / (2.0 * self.f_number)

    def as_dict(self) -> dict[str, Any]:
        """The table's values for dataset.json (None for what is not set; inf as a string)."""
        return {
            "f_number": "inf" if self.pinhole else self.f_number,
            "focal_length": self.focal_length,
            "focus_distance": self.focus_distance,
            "pixel_pitch": self.pixel_pitch,
        }


def image_distance(focal_length: float, focus_distance: float) -> float:
    """Thin-lens image distance (m) of a lens of ``focal_length`` focused at ``focus_distance``."""
    return focal_length * focus_distance / (focus_distance - focal_length)


def optics_from_table(chk: Checker, tbl: Any, v: float) -> Optics:
    """Read the ``[optics]`` table (``v``: the rig's image distance in pixels, eq. 2).

    ``focal_length`` and ``focus_distance`` are required with a finite ``f_number``.
    ``pixel_pitch`` defaults to image distance / v; a given pitch more than
    :data:`PITCH_TOLERANCE` away from that is an error naming both.
    """
    if not isinstance(tbl, dict):
        raise chk.bad("optics", tbl, "a table of lens parameters ([optics])")
    chk.table(tbl, "optics", OPTICS_KEYS)
    n = tbl.get("f_number", math.inf)
    if not (isinstance(n, int | float) and not isinstance(n, bool) and n > 0 and n == n):
        raise chk.bad("optics.f_number", n, "a number > 0, or inf for a pinhole")
    n = float(n)
    lens = math.isfinite(n)
    f = _positive(chk, tbl, "focal_length", required=lens)
    focus = _positive(chk, tbl, "focus_distance", required=lens)
    if f is not None and focus is not None and focus <= f:
        raise chk.bad(
            "optics.focus_distance", focus, f"more than focal_length ({f:g} m): a real image"
        )
    pitch = _positive(chk, tbl, "pixel_pitch", required=False)
    if f is not None and focus is not None:
        derived = image_distance(f, focus) / v
        if pitch is None:
            pitch = derived
        elif abs(pitch / derived - 1.0) > PITCH_TOLERANCE:
            raise chk.error(
                "optics.pixel_pitch",
                f"got {pitch:g} m, but the lens's image distance at focus "
                f"({image_distance(f, focus):g} m) over the rig's v ({v:g} px) gives "
                f"{derived:g} m; expected them within {PITCH_TOLERANCE:.0%}",
            )
    return Optics(f_number=n, focal_length=f, focus_distance=focus, pixel_pitch=pitch)


def _positive(chk: Checker, tbl: dict, key: str, *, required: bool) -> float | None:
    """A number > 0 (metres) read from ``[optics]``; None where optional and absent."""
    if key not in tbl and not required:
        return None
    return chk.number(tbl, key, "optics", lo=0, lo_open=True)


def thin_lens_cone_ray(ops, px, py, lx, ly, *, v, d: float, focus):
    """The ray of film offset (px, py) through lens point (lx, ly), reflected by the cone.

    Coordinates are the unit's rig frame shifted to the cone's tip (the camera centre,
    the lens centre, at (0, 0, -d)); the 90-degree cone is x^2 + y^2 = z^2, z > 0.
    ``ops`` supplies ``sqrt``, ``select`` and ``maximum`` (:data:`NUMPY_OPS`, or Dr.Jit's
    in the sensor), so the render and the tests run the same formulas.

    Returns ``(q, w, ok)``: the mirror point q (3-tuple, tip-relative, its radius from
    the axis is q[2]), the unit reflected direction w (3-tuple) and ``ok`` where the
    ray meets the cone's upper nappe (the caller tests q[2] <= R, the rim).
    """
    s = focus / v
    ox, oy, oz = lx, ly, -d
    wx, wy, wz = px * s - lx, py * s - ly, focus  # towards F = (D / v)(px, py, v)
    inv = 1.0 / ops.sqrt(wx * wx + wy * wy + wz * wz)
    wx, wy, wz = wx * inv, wy * inv, wz * inv
    # |q_xy|^2 - q_z^2 = 0 along o + t w: a t^2 + b t + c = 0, with a < 0 and c < 0
    # (the lens lies inside the lower nappe); the upper nappe is the larger root.
    a = wx * wx + wy * wy - wz * wz
    b = 2.0 * (ox * wx + oy * wy - oz * wz)
    c = ox * ox + oy * oy - oz * oz
    disc = b * b - 4.0 * a * c
    t = (-b - ops.sqrt(ops.maximum(disc, 0.0))) / (2.0 * a)  # no cancellation: b > 0
    qx, qy, qz = ox + t * wx, oy + t * wy, oz + t * wz
    # outward unit normal of the upper nappe: gradient of x^2 + y^2 - z^2
    inv_n = 1.0 / ops.sqrt(qx * qx + qy * qy + qz * qz)
    nx, ny, nz = qx * inv_n, qy * inv_n, -qz * inv_n
    dot2 = 2.0 * (wx * nx + wy * ny + wz * nz)
    w = (wx - dot2 * nx, wy - dot2 * ny, wz - dot2 * nz)
    ok = (disc >= 0.0) & (qz > 0.0)
    return (qx, qy, qz), w, ok


def cone_blur_sigma(
    *, v: float, d: float, optics: Optics, h_i: ArrayLike, r: ArrayLike
) -> tuple[NDArray, NDArray]:
    """First-order blur (sigma, px) of a point at range ``r`` (m) seen at image radius h_i.

    Returns ``(radial, tangential)``: the standard deviation along h_i and across it of
    the thin-lens blur disc (a uniform disc of diameter ``A v |1/z - 1/D|`` px, sigma a
    quarter of it; A the aperture diameter, z the axial depth of the image the lens
    sees). The cone is flat along its generators, so the radial image lies at the
    unfolded path length ``l1 + l2``; around the axis it is a convex mirror of radius
    ``sqrt(2) rho`` at incidence i, so Coddington's sagittal equation
    ``1/s' = 1/l2 + 2 cos(i) / (sqrt(2) rho)`` puts the tangential image at ``l1 + s'``.
    Both are converted to axial depth by cos(phi), phi the chief ray's angle.
    """
    h_i = np.asarray(h_i, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    k = h_i / v
    rho = d * k / (1.0 - k)  # mirror point (sensor module docstring)
    l1 = np.hypot(rho, d + rho)
    l2 = (r - rho) * np.hypot(1.0, k)
    cos_i = (v - h_i) / (np.sqrt(2.0) * np.hypot(v, h_i))
    s_t = 1.0 / (1.0 / l2 + 2.0 * cos_i / (np.sqrt(2.0) * rho))
    cos_phi = v / np.hypot(v, h_i)
    scale = 2.0 * optics.aperture_radius * v / 4.0
    inv_focus = 1.0 / float(optics.focus_distance)
    radial = scale * np.abs(1.0 / ((l1 + l2) * cos_phi) - inv_focus)
    tangential = scale * np.abs(1.0 / ((l1 + s_t) * cos_phi) - inv_focus)
    return radial, tangential
