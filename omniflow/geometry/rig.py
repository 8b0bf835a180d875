"""Rig model: one conical-mirror unit and the coaxial pair (paper sections 2-4).

Conventions (axes, angle sense, pixel centres, units) are in
:mod:`omniflow.conventions`. Symbols follow the paper:

===========  ====================================================  =========
symbol       meaning                                               unit
===========  ====================================================  =========
d            camera centre to cone tip                             m
R            mirror base radius (rim at r = R, h = R)              m
s            baseline between the two cone tips                    m
v            image distance, focal length (eq. 2)                  px
x_c, y_c     image of the axis                                     px
r_m          rim radius in the image                               px
h_i          image radius of a point                               px
===========  ====================================================  =========

The rig file (TOML or JSON) uses the same keys as ``dataset.json`` written by
``omnisim``::

    [rig]
    d = 0.10
    R = 0.05
    s = 0.30

    [rig.errors.cam1]    # optional, per unit: omniflow.geometry.rig_errors
    cone_angle = 90.1    # (dataset.json: rig.errors.cam1); the ideal unit if absent

    [[cameras]]
    name = "cam1"        # tip at h = s
    x_c = 256.0
    y_c = 256.0
    r_m = 250.0
    width = 512
    height = 512
    # v = ...            # optional; if given it must agree with eq. (2)

    [[cameras]]
    name = "cam2"        # tip at h = 0
    ...
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omniflow.conventions import wrap_angle
from omniflow.geometry.rig_errors import UnitErrors, errors_from_dict
from omniflow.input_files import InputFileError, parse_text, read_input

__all__ = [
    "Rig",
    "RigError",
    "Unit",
    "load_rig",
    "rig_from_dict",
    "unwarp",
]


class RigError(ValueError):
    """A rig description is missing a field or describes an impossible rig."""


@dataclass(frozen=True)
class Unit:
    """One catadioptric unit: a pinhole camera on the axis of a 90-degree cone.

    Parameters
    ----------
    d : float
        Distance from the camera centre to the cone tip, metres.
    R : float
        Base radius of the mirror, metres.
    x_c, y_c : float
        Image of the axis, pixels (pixel centres at j + 0.5, i + 0.5).
    r_m : float
        Radius of the mirror's rim in the image, pixels.
    width, height : int
        Image size, pixels.
    tip_h : float
        h of this unit's cone tip in the rig frame (cam2: 0, cam1: s).
    name : str
        ``"cam1"`` or ``"cam2"`` in a rig.
    errors : UnitErrors or None
        The unit's departures from the ideal (:mod:`omniflow.geometry.rig_errors`);
        None for the ideal unit. The methods here are the ideal model, eq. (1)-(7),
        whatever ``errors`` holds; the traced model is in ``rig_errors``.
    """

    d: float
    R: float
    x_c: float
    y_c: float
    r_m: float
    width: int
    height: int
    tip_h: float = 0.0
    name: str = ""
    errors: UnitErrors | None = None

    @property
    def v(self) -> float:
        """Image distance in pixels, eq. (2): v = (d / R + 1) r_m."""
        return (self.d / self.R + 1.0) * self.r_m

    # -- image <-> polar -------------------------------------------------
    def polar_of_pixel(self, x: ArrayLike, y: ArrayLike) -> tuple[NDArray, NDArray]:
        """Polar image coordinates (h_i, theta_i) of continuous pixel coordinates."""
        dx = np.asarray(x, dtype=float) - self.x_c
        dy = np.asarray(y, dtype=float) - self.y_c
        return np.hypot(dx, dy), wrap_angle(np.arctan2(dy, dx))

    def pixel_of_polar(self, h_i: ArrayLike, theta: ArrayLike) -> tuple[NDArray, NDArray]:
        """Continuous pixel coordinates of polar image coordinates, eq. (6)-(7)."""
        h_i = np.asarray(h_i, dtype=float)
        theta = np.asarray(theta, dtype=float)
        return self.x_c + h_i * np.cos(theta), self.y_c + h_i * np.sin(theta)

    def pixel_centres(self) -> tuple[NDArray, NDArray]:
        """Continuous coordinates (x, y) of every pixel centre, each shape (H, W)."""
        x = np.arange(self.width) + 0.5
        y = np.arange(self.height) + 0.5
        return np.meshgrid(x, y)

    # -- scene <-> image (eq. 1) -------------------------------------------
    def image_radius(self, r: ArrayLike, h: ArrayLike) -> NDArray:
        """Eq. (1) with h in the rig frame: h_i = v (h - tip_h) / (d + r)."""
        r = np.asarray(r, dtype=float)
        return self.v * (np.asarray(h, dtype=float) - self.tip_h) / (self.d + r)

    def height_of(self, r: ArrayLike, h_i: ArrayLike) -> NDArray:
        """Inverse of eq. (1): rig-frame h of the point at range r seen at h_i."""
        r = np.asarray(r, dtype=float)
        return self.tip_h + np.asarray(h_i, dtype=float) * (self.d + r) / self.v

    def range_of(self, h: ArrayLike, h_i: ArrayLike) -> NDArray:
        """Inverse of eq. (1) for r: range of the point at height h seen at h_i."""
        return self.v * (np.asarray(h, dtype=float) - self.tip_h) / np.asarray(h_i) - self.d

    def visible(self, r: ArrayLike, h: ArrayLike) -> NDArray:
        """True where the mirror sees (r, h): 0 < h - tip_h <= (d + r) R / (d + R).

        Also requires the point to lie beyond the mirror point its ray leaves
        from (radius rho = d k / (1 - k), k = (h - tip_h) / (d + r)).
        Occlusion by scene objects is not considered.
        """
        r = np.asarray(r, dtype=float)
        rel = np.asarray(h, dtype=float) - self.tip_h
        k = rel / (self.d + r)
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = self.d * k / (1.0 - k)
        return (rel > 0) & (rel <= (self.d + r) * self.R / (self.d + self.R)) & (r >= rho)

    def project(self, r: ArrayLike, theta: ArrayLike, h: ArrayLike) -> tuple[NDArray, NDArray]:
        """Pixel (x, y) of the scene point (r, theta, h), eq. (1), (6), (7)."""
        return self.pixel_of_polar(self.image_radius(r, h), theta)

    def ray_slope(self, h_i: ArrayLike) -> NDArray:
        """dh/dr of the reflected ray leaving the mirror at image radius h_i: h_i / v."""
        return np.asarray(h_i, dtype=float) / self.v

    def validate(self, where: str = "rig") -> None:
        """Raise :class:`RigError` naming the field if this unit is impossible."""
        for key in ("d", "R", "r_m"):
            val = getattr(self, key)
            if not (math.isfinite(val) and val > 0):
                raise RigError(f"{where}: {self.name or 'camera'}.{key} = {val!r}: expected > 0")
        for key in ("width", "height"):
            val = getattr(self, key)
            if int(val) != val or val < 8:
                raise RigError(f"{where}: {self.name}.{key} = {val!r}: expected integer >= 8")
        for key in ("x_c", "y_c", "tip_h"):
            val = getattr(self, key)
            if not math.isfinite(val):
                raise RigError(f"{where}: {self.name}.{key} = {val!r}: expected a finite number")
        if not (0 <= self.x_c <= self.width and 0 <= self.y_c <= self.height):
            raise RigError(
                f"{where}: {self.name} centre ({self.x_c}, {self.y_c}) lies outside the "
                f"{self.width}x{self.height} image"
            )


@dataclass(frozen=True)
class Rig:
    """Two coaxial units: cam1 (tip at h = s, upper) and cam2 (tip at h = 0, lower).

    Both units share d and R (paper section 3); their image centres, rim radii
    and hence v may differ.
    """

    cam1: Unit
    cam2: Unit
    s: float

    @property
    def d(self) -> float:
        return self.cam2.d

    @property
    def R(self) -> float:
        return self.cam2.R

    @classmethod
    def symmetric(
        cls,
        *,
        d: float,
        R: float,
        s: float,
        size: int | tuple[int, int],
        r_m: float | None = None,
    ) -> Rig:
        """A rig of two identical units centred in (width, height) images."""
        width, height = (size, size) if isinstance(size, int) else size
        r_m = (min(width, height) / 2.0 - 2.0) if r_m is None else r_m
        common = dict(
            d=d, R=R, x_c=width / 2.0, y_c=height / 2.0, r_m=r_m, width=width, height=height
        )
        rig = cls(
            cam1=Unit(**common, tip_h=s, name="cam1"),
            cam2=Unit(**common, tip_h=0.0, name="cam2"),
            s=s,
        )
        rig.validate()
        return rig

    # -- stereo (eq. 3-5) ---------------------------------------------------
    def stereo_radii(self, r: ArrayLike, h: ArrayLike) -> tuple[NDArray, NDArray]:
        """Image radii (h_1, h_2) of the point (r, h), eq. (3) and (4)."""
        return self.cam1.image_radius(r, h), self.cam2.image_radius(r, h)

    def triangulate(self, h_1: ArrayLike, h_2: ArrayLike) -> tuple[NDArray, NDArray]:
        """Range r and height h from matched image radii, eq. (5).

        With u_i = h_i / v_i, eq. (3)-(4) give u_2 - u_1 = s / (d + r), so
        r = s / (u_2 - u_1) - d, which is eq. (5) when v_1 = v_2 = v, and
        h = u_2 (d + r). Non-positive disparity gives r = inf, h = nan.
        """
        u1 = np.asarray(h_1, dtype=float) / self.cam1.v
        u2 = np.asarray(h_2, dtype=float) / self.cam2.v
        disp = u2 - u1
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.where(disp > 0, self.s / disp - self.d, np.inf)  # eq. (5)
            h = np.where(disp > 0, u2 * (self.d + r), np.nan)  # eq. (4)
        return r, h

    def disparity_window(
        self, h_1: ArrayLike, r_min: float, r_max: float
    ) -> tuple[NDArray, NDArray]:
        """Range of h_2 at which the match of h_1 can lie for r in [r_min, r_max].

        From eq. (3)-(4): h_2 = v_2 (h_1 / v_1 + s / (d + r)).
        """
        u1 = np.asarray(h_1, dtype=float) / self.cam1.v
        lo = self.cam2.v * (u1 + self.s / (self.d + r_max))
        hi = self.cam2.v * (u1 + self.s / (self.d + r_min))
        return lo, hi

    def common_region(self, r: ArrayLike, h: ArrayLike) -> NDArray:
        """True where both units see (r, h)."""
        return self.cam1.visible(r, h) & self.cam2.visible(r, h)

    def validate(self, where: str = "rig") -> None:
        """Raise :class:`RigError` naming the field if the rig is impossible."""
        self.cam1.validate(where)
        self.cam2.validate(where)
        if not (math.isfinite(self.s) and self.s > 0):
            raise RigError(f"{where}: rig.s = {self.s!r}: expected > 0 (cam1's tip above cam2's)")
        if self.cam1.d != self.cam2.d or self.cam1.R != self.cam2.R:
            raise RigError(f"{where}: cam1 and cam2 must share d and R (paper section 3)")
        if abs(self.cam1.tip_h - self.s) > 1e-12 or self.cam2.tip_h != 0.0:
            raise RigError(f"{where}: cam1.tip_h must equal s and cam2.tip_h must be 0")
        # cam1's camera body must sit above cam2's mirror, or cam2 sees cam1 through itself.
        if self.s - self.d <= self.R:
            raise RigError(
                f"{where}: rig.s = {self.s} too small: cam1's camera (at h = s - d = "
                f"{self.s - self.d:.4g}) would sit inside cam2's mirror (top at h = R = {self.R}); "
                "expected s > d + R"
            )

    @property
    def min_common_range(self) -> float:
        """Smallest range r at which a point can be seen by both units, metres.

        cam2 sees h <= (d + r) R / (d + R) and cam1 sees h > s, so the common
        region needs r > s (d + R) / R - d.
        """
        return self.s * (self.d + self.R) / self.R - self.d

    def to_dict(self) -> dict[str, Any]:
        """The rig in the ``dataset.json`` layout (``rig`` and ``cameras`` keys)."""
        cams = []
        for cam in (self.cam1, self.cam2):
            c = asdict(cam)
            del c["d"], c["R"], c["errors"]
            c["v"] = cam.v
            cams.append(c)
        rig: dict[str, Any] = {"d": self.d, "R": self.R, "s": self.s}
        errors = {c.name: c.errors.as_dict() for c in (self.cam1, self.cam2) if c.errors}
        if errors:  # an ideal rig's layout is what it was before rig errors existed
            rig["errors"] = errors
        return {"rig": rig, "cameras": cams}


_CAM_KEYS = {"name", "x_c", "y_c", "r_m", "width", "height", "v", "tip_h"}


def rig_from_dict(data: dict[str, Any], where: str = "rig") -> Rig:
    """Build and validate a :class:`Rig` from the ``dataset.json`` layout.

    ``where`` names the source (a file path) in error messages.
    """
    if not isinstance(data, dict) or "rig" not in data or "cameras" not in data:
        raise RigError(f"{where}: expected a table 'rig' (d, R, s) and a list 'cameras'")
    rig = data["rig"]
    if not isinstance(rig, dict):
        raise RigError(f"{where}: rig = {rig!r}: expected a table with d, R, s")
    unknown = set(rig) - {"d", "R", "s", "errors"}
    if unknown:  # a typo ('baseline' for 's') would otherwise be silently ignored
        raise RigError(
            f"{where}: rig: unknown key(s) {sorted(unknown)}; expected ['R', 'd', 'errors', 's']"
        )
    vals = {}
    for key in ("d", "R", "s"):
        if key not in rig:
            raise RigError(f"{where}: rig.{key} is missing: expected a number in metres")
        vals[key] = _number(rig[key], f"{where}: rig.{key}")
    cams = data["cameras"]
    if not isinstance(cams, list) or len(cams) != 2:
        raise RigError(f"{where}: 'cameras' must list exactly two cameras, cam1 and cam2")
    units = {}
    for i, cam in enumerate(cams):
        label = f"{where}: cameras[{i}]"
        if not isinstance(cam, dict):
            raise RigError(f"{label}: expected a table")
        unknown = set(cam) - _CAM_KEYS
        if unknown:
            raise RigError(
                f"{label}: unknown key(s) {sorted(unknown)}; expected {sorted(_CAM_KEYS)}"
            )
        name = cam.get("name", f"cam{i + 1}")
        if name not in ("cam1", "cam2") or name in units:
            raise RigError(f"{label}.name = {name!r}: expected 'cam1' and 'cam2' once each")
        fields = {}
        for key in ("x_c", "y_c", "r_m", "width", "height"):
            if key not in cam:
                raise RigError(f"{label} ({name}).{key} is missing: expected a number in pixels")
            fields[key] = _number(cam[key], f"{label} ({name}).{key}")
        for key in ("width", "height"):
            if fields[key] != int(fields[key]) or fields[key] < 8:
                raise RigError(f"{label} ({name}).{key} = {cam[key]!r}: expected integer >= 8")
        tip = vals["s"] if name == "cam1" else 0.0
        if "tip_h" in cam and abs(_number(cam["tip_h"], f"{label}.tip_h") - tip) > 1e-9:
            raise RigError(f"{label} ({name}).tip_h = {cam['tip_h']}: expected {tip}")
        unit = Unit(
            d=vals["d"],
            R=vals["R"],
            x_c=fields["x_c"],
            y_c=fields["y_c"],
            r_m=fields["r_m"],
            width=int(fields["width"]),
            height=int(fields["height"]),
            tip_h=tip,
            name=name,
        )
        unit.validate(where)  # an impossible d, R or r_m is named before v is compared
        corner = math.hypot(
            max(unit.x_c, unit.width - unit.x_c), max(unit.y_c, unit.height - unit.y_c)
        )
        if unit.r_m > corner:  # the whole image lies inside the mirror: no rim to see
            raise RigError(
                f"{label} ({name}).r_m = {unit.r_m:g}: the rim circle lies outside the "
                f"{unit.width}x{unit.height} image; expected r_m <= {corner:.1f} px (the "
                "distance from the centre to the farthest image corner)"
            )
        if "v" in cam:
            v = _number(cam["v"], f"{label}.v")
            if abs(v - unit.v) > 1e-6 * unit.v:
                raise RigError(
                    f"{label} ({name}).v = {v}: disagrees with eq. (2) (d/R + 1) r_m = {unit.v:.6g}"
                )
        units[name] = unit
    errors = _errors(rig.get("errors", {}), vals["d"], where)
    for name, err in errors.items():
        units[name] = replace(units[name], errors=err)
    out = Rig(cam1=units["cam1"], cam2=units["cam2"], s=vals["s"])
    out.validate(where)
    return out


def _errors(tbl: Any, d: float, where: str) -> dict[str, UnitErrors]:
    """``rig.errors``: a table per unit (``cam1``, ``cam2``); ideal ones are left out."""

    def fail(key: str, value: Any, expected: str) -> RigError:
        return RigError(f"{where}: {key} = {value!r}: expected {expected}")

    if not isinstance(tbl, dict):
        raise fail("rig.errors", tbl, "a table with cam1 and/or cam2")
    unknown = sorted(set(tbl) - {"cam1", "cam2"})
    if unknown:
        raise fail(f"rig.errors.{unknown[0]}", tbl[unknown[0]], "only cam1 and cam2 tables")
    out = {}
    for name, sub in tbl.items():
        err = errors_from_dict(sub, f"rig.errors.{name}", d, fail)
        if not err.ideal:
            out[name] = err
    return out


def load_rig(path: str | Path) -> Rig:
    """Read a rig file (``.toml`` or ``.json``, including an omnisim ``dataset.json``)."""
    path = Path(path)
    if not path.exists():
        raise RigError(f"{path}: rig file not found")
    if not path.is_file():
        raise RigError(f"{path}: not a file; expected a rig file (.toml or .json)")
    try:
        text = read_input(path, "TOML or JSON rig file")
        data = parse_text(text, path, "json" if path.suffix.lower() == ".json" else "toml")
    except InputFileError as exc:
        raise RigError(str(exc)) from None
    return rig_from_dict(data, where=str(path))


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise RigError(f"{where} = {value!r}: expected a finite number")
    return float(value)


def unwarp(image: NDArray, unit: Unit, *, width: int = 1024, height: int | None = None) -> NDArray:
    """Panorama of an omni image for people to look at, eq. (6)-(7).

    Column x maps to theta_i = 2 pi (x + 0.5) / width and row y to
    h_i = r_m (height - (y + 0.5)) / height (the rim at the top row), sampled
    bilinearly with OpenCV. Shape (height, width) plus any channel axis.
    """
    height = height or max(8, round(unit.r_m))
    cols = (np.arange(width) + 0.5) * (2 * np.pi / width)
    rows = unit.r_m * (height - (np.arange(height) + 0.5)) / height
    theta, h_i = np.meshgrid(cols, rows)
    x, y = unit.pixel_of_polar(h_i, theta)  # eq. (6), (7)
    import cv2

    # cv2 samples at integer pixel indices; pixel centres are at index + 0.5.
    return cv2.remap(
        np.ascontiguousarray(image, dtype=np.float32),
        (x - 0.5).astype(np.float32),
        (y - 0.5).astype(np.float32),
        interpolation=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
