"""Closed-form scenes for the coaxial conical-mirror rig: images and exact truth.

No renderer: every pixel's ray is intersected analytically with vertical
cylinders and horizontal discs, and the seen point's texture is a smooth
band-limited function of the surface's own coordinates. Used by the tests and
the validation suite as exact ground truth (same channel names as the
``omnisim`` dataset contract).

Geometry (:mod:`omniflow.geometry.rig`, :mod:`omniflow.conventions`). The ray of a
pixel at image radius h_i and angle theta leaves the cone at radius
rho = d h_i / (v - h_i) and runs outward in the meridional plane of azimuth
theta, horizontally along (cos theta, sin theta), with every point obeying
eq. (1): h - tip_h = h_i (d + r) / v for r >= rho. So

* a vertical cylinder (centre c, radius R_c) is hit where |r u - c| = R_c,
  a quadratic in r (u the horizontal direction);
* a horizontal disc at height z is hit at r = v (z - tip_h) / h_i - d.

The nearest hit along the ray wins (occlusion).

Sampling. ``render`` samples pixel centres (or an n x n grid per pixel with
``supersample``). Textures are band-limited on the surface, not in the image:
tangentially a wall at range r spans r / h_i metres per pixel, so near the
image centre point sampling aliases. ``blur=sigma`` applies a Gaussian pixel
footprint to every sinusoid analytically (from the Jacobian of the surface
coordinates), which band-limits the image at the cost of brightness constancy
holding only to the footprint's change between frames (tests/omnisim/test_synthetic.py
measures both).

World and rig frames. World Z equals rig h (the rig moves only in the plane);
the rig at frame t sits at world (x, y) = position(t) with yaw psi(t): a rig
point q maps to world p(t) + Rot(psi(t)) q. Bodies move rigidly per frame:
centre c0 + t v, yaw about their own vertical axis yaw0 + t w, and an
optional vertical velocity v_z (which breaks eq. 14). Textures are attached to
the body, so flow is the motion of material points.

Truth channels (:meth:`SyntheticScene.truth`), each (H, W) float64, at pixel
centres: ``gt.valid``, ``gt.r``, ``gt.theta``, ``gt.h``, ``gt.X``, ``gt.Y``,
``gt.Z``, ``gt.object``, ``gt.flow.dx``, ``gt.flow.dy``, ``gt.flow.dh``,
``gt.flow.hdtheta``, ``gt.flow.valid``, ``gt.stereo.h_other``,
``gt.stereo.valid``. Where ``gt.valid`` is 0 the geometric and flow channels
are NaN and ``gt.object`` is 0. Flow and stereo values are given for every
valid pixel; their ``valid`` flags say whether the point is actually seen
(unoccluded and on the mirror) at t + 1, or by the other unit.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omniflow.conventions import wrap_angle
from omniflow.geometry.rig import Rig, Unit

__all__ = [
    "TRUTH_KEYS",
    "Cylinder",
    "Disc",
    "Hit",
    "Motion",
    "SyntheticScene",
    "Texture",
    "rim_coverage",
]

TRUTH_KEYS = (
    "gt.valid", "gt.r", "gt.theta", "gt.h", "gt.X", "gt.Y", "gt.Z", "gt.object",
    "gt.flow.dx", "gt.flow.dy", "gt.flow.dh", "gt.flow.hdtheta", "gt.flow.valid",
    "gt.stereo.h_other", "gt.stereo.valid",
)  # fmt: skip

#: Relative tolerance (on r) for "the same point is the nearest hit of its ray".
_SAME_POINT_RTOL = 1e-7


@dataclass(frozen=True, eq=False)
class Texture:
    """Smooth band-limited texture: mean + sum_k amp_k sin(2 pi (fu_k u + fv_k v) + phase_k).

    u, v are the surface's own coordinates in metres (arc length and height on
    a cylinder, planar coordinates on a disc). Build one with :meth:`random`.
    """

    fu: NDArray
    fv: NDArray
    amp: NDArray
    phase: NDArray
    mean: float = 0.5

    @classmethod
    def random(
        cls,
        seed: int,
        *,
        n: int = 24,
        wavelengths: tuple[float, float] = (0.05, 0.4),
        contrast: float = 0.4,
        mean: float = 0.5,
        period_u: float | None = None,
    ) -> Texture:
        """A seeded random sum of ``n`` sinusoids.

        Parameters
        ----------
        seed : int
            Seed of ``numpy.random.default_rng``.
        n : int
            Number of sinusoids.
        wavelengths : (float, float)
            Shortest and longest wavelength, metres (log-uniform).
        contrast : float
            Sum of the amplitudes: values stay within mean +- contrast.
        period_u : float, optional
            If given, u-frequencies are rounded to whole cycles per period
            (seamless around a cylinder of circumference ``period_u``).
        """
        lo, hi = wavelengths
        if not (0 < lo <= hi):
            raise ValueError(f"wavelengths = {wavelengths!r}: expected 0 < shortest <= longest")
        rng = np.random.default_rng(seed)
        lam = np.exp(rng.uniform(np.log(lo), np.log(hi), n))
        ang = rng.uniform(0, np.pi, n)
        fu, fv = np.cos(ang) / lam, np.sin(ang) / lam
        if period_u is not None:
            fu = np.round(fu * period_u) / period_u
        amp = rng.uniform(0.5, 1.0, n)
        amp *= contrast / amp.sum()
        phase = rng.uniform(0, 2 * np.pi, n)
        return cls(fu=fu, fv=fv, amp=amp, phase=phase, mean=mean)

    @classmethod
    def periodic(
        cls,
        seed: int,
        *,
        period: float = 0.1,
        contrast: float = 0.3,
        detail: float = 0.1,
        mean: float = 0.5,
        period_u: float | None = None,
    ) -> Texture:
        """A strongly periodic texture: horizontal stripes plus weak random detail.

        A sinusoid of ``period`` metres up the surface (along v: the radial
        lines of a vertical wall) of amplitude ``contrast``, and
        :meth:`random` detail (wavelengths 0.05-0.4 m) of total amplitude
        ``detail``. Along a radial line the stripes repeat every
        v period / (d + r) pixels, so a stereo matcher that compares short
        profiles finds an equally good match one or more periods away: the
        case that periodic-alias rejection must handle.
        """
        rest = cls.random(seed, contrast=detail, mean=mean, period_u=period_u)
        return cls(
            fu=np.append(0.0, rest.fu),
            fv=np.append(1.0 / period, rest.fv),
            amp=np.append(contrast, rest.amp),
            phase=np.append(0.0, rest.phase),
            mean=mean,
        )

    @classmethod
    def constant(cls, value: float) -> Texture:
        """A uniform (textureless) surface."""
        z = np.zeros(0)
        return cls(fu=z, fv=z, amp=z, phase=z, mean=value)

    def __call__(
        self, u: NDArray, v: NDArray, *, jacobian: tuple | None = None, blur: float = 0.0
    ) -> NDArray:
        """Texture values at surface coordinates (u, v), any equal shapes.

        With ``jacobian`` = (du/dx, du/dy, dv/dx, dv/dy) (metres per pixel, the
        shape of u) and ``blur`` = sigma > 0 (pixels), each sinusoid is seen
        through a Gaussian pixel footprint of that sigma: its local image
        frequency g = (f_u, f_v) J (cycles per pixel) scales its amplitude by
        exp(-2 pi^2 sigma^2 |g|^2). This band-limits the image analytically
        (locally linear map), where point sampling would alias.
        """
        u = np.asarray(u, dtype=float)
        v = np.asarray(v, dtype=float)
        out = np.full(np.broadcast(u, v).shape, float(self.mean))
        for fu, fv, amp, phase in zip(self.fu, self.fv, self.amp, self.phase, strict=True):
            wave = amp * np.sin(2 * np.pi * (fu * u + fv * v) + phase)
            if jacobian is not None and blur > 0:
                ux, uy, vx, vy = jacobian
                gx, gy = fu * ux + fv * vx, fu * uy + fv * vy
                wave *= np.exp(-2 * np.pi**2 * blur**2 * (gx * gx + gy * gy))
            out += wave
        return out


@dataclass(frozen=True)
class Motion:
    """Constant planar rigid motion per frame (world frame).

    Attributes
    ----------
    velocity : (float, float)
        Translation of the centre per frame, metres, world X and Y.
    yaw_rate : float
        Rotation about the body's own vertical axis, radians per frame
        (counter-clockwise seen from above).
    vz : float
        Vertical velocity, metres per frame (bodies only; breaks eq. 14).
    """

    velocity: tuple[float, float] = (0.0, 0.0)
    yaw_rate: float = 0.0
    vz: float = 0.0


@dataclass(frozen=True)
class _Body:
    centre: tuple[float, float] = (0.0, 0.0)
    yaw: float = 0.0
    motion: Motion = field(default_factory=Motion)
    texture: Texture = field(default_factory=lambda: Texture.constant(0.5))
    id: int = 1
    name: str = ""

    def pose(self, t: float) -> tuple[NDArray, float, float]:
        """World centre (2,), yaw and vertical offset of the body at frame t."""
        c = np.asarray(self.centre, float) + t * np.asarray(self.motion.velocity, float)
        return c, self.yaw + t * self.motion.yaw_rate, t * self.motion.vz

    def to_local(self, t: float, X: NDArray, Y: NDArray, Z: NDArray):
        """World points -> body coordinates (x_b, y_b, z_b) at frame t."""
        c, yaw, dz = self.pose(t)
        ca, sa = np.cos(yaw), np.sin(yaw)
        px, py = X - c[0], Y - c[1]
        return ca * px + sa * py, -sa * px + ca * py, Z - dz

    def to_world(self, t: float, xb: NDArray, yb: NDArray, zb: NDArray):
        """Body coordinates -> world points (X, Y, Z) at frame t."""
        c, yaw, dz = self.pose(t)
        ca, sa = np.cos(yaw), np.sin(yaw)
        return c[0] + ca * xb - sa * yb, c[1] + sa * xb + ca * yb, zb + dz


@dataclass(frozen=True)
class Cylinder(_Body):
    """A vertical textured cylinder (wall or pillar), open at both ends.

    ``radius`` in metres; it spans z_min <= Z <= z_max in its own frame (world
    Z plus its vertical motion). Texture coordinates: u = radius * phi (arc
    length, phi the body-frame angle), v = height. Seen from inside or outside.
    """

    radius: float = 1.0
    z_min: float = -np.inf
    z_max: float = np.inf

    def __post_init__(self):
        if not (self.radius > 0 and self.z_min < self.z_max):
            raise ValueError(
                f"Cylinder {self.name or self.id}: radius = {self.radius}, z_min = "
                f"{self.z_min}, z_max = {self.z_max}: expected radius > 0 and z_min < z_max"
            )

    def intersect(self, t, ox, oy, dx, dy, z_of_r, rho):
        """Range r of the nearest hit beyond the mirror point rho (inf: none), per ray.

        Rays run horizontally from (ox, oy) along (dx, dy); z_of_r gives their
        height at range r (eq. 1). |o + r d - c| = radius is a quadratic in r.
        """
        c, _, dz = self.pose(t)
        wx, wy = ox - c[0], oy - c[1]
        b = wx * dx + wy * dy
        disc = b * b - (wx * wx + wy * wy - self.radius**2)
        root = np.sqrt(np.where(disc >= 0, disc, np.nan))
        best = np.full(np.shape(b), np.inf)
        for r in (-b + root, -b - root):  # the smallest valid root wins
            z = z_of_r(r) - dz
            ok = (r >= rho) & (z >= self.z_min) & (z <= self.z_max)
            best = np.where(ok & (r < best), r, best)
        return best

    def surface_uv(self, xb, yb, zb):
        return self.radius * np.arctan2(yb, xb), zb


@dataclass(frozen=True)
class Disc(_Body):
    """A horizontal textured disc or annulus at height ``z`` (ceiling, table top).

    Radii ``inner`` <= distance from its centre <= ``outer`` (inf for an
    unbounded plane). Texture coordinates: the body-frame (x, y). Only discs
    above a unit's tip can be seen by it.
    """

    z: float = 1.0
    inner: float = 0.0
    outer: float = np.inf

    def __post_init__(self):
        if not (0 <= self.inner < self.outer):
            raise ValueError(
                f"Disc {self.name or self.id}: inner = {self.inner}, outer = {self.outer}: "
                "expected 0 <= inner < outer"
            )

    def intersect(self, t, ox, oy, dx, dy, k, tip_h, d, rho):
        """Range r where rays of slope k meet the disc's plane (eq. 1), inf where they miss."""
        c, _, dz = self.pose(t)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = (self.z + dz - tip_h) / k - d
        ok = np.isfinite(r) & (r >= rho)
        rr = np.hypot(ox + r * dx - c[0], oy + r * dy - c[1])
        ok &= (rr >= self.inner) & (rr <= self.outer)
        return np.where(ok, r, np.inf)

    def surface_uv(self, xb, yb, zb):
        return xb, yb


@dataclass(frozen=True)
class Hit:
    """Nearest hits of a batch of rays (flat arrays of one length N).

    ``index`` is the body's position in the scene (-1: no hit), ``r`` the
    range (inf: no hit), X, Y, Z world coordinates.
    """

    index: NDArray
    r: NDArray
    X: NDArray
    Y: NDArray
    Z: NDArray


def _unit(rig: Rig, cam: str | Unit) -> tuple[Unit, Unit]:
    """(unit, other unit) for a camera name or Unit of the rig."""
    if isinstance(cam, Unit):
        cam = cam.name
    if cam == "cam1":
        return rig.cam1, rig.cam2
    if cam == "cam2":
        return rig.cam2, rig.cam1
    raise ValueError(f"cam = {cam!r}: expected 'cam1' or 'cam2'")


def rim_coverage(unit: Unit, *, samples: int = 32, radius: float | None = None) -> NDArray:
    """Fraction of each pixel's area inside the rim circle, shape (H, W).

    0 or 1 away from the rim. For pixels the circle crosses, the covered
    length of each line across the pixel is exact (the circle's chord clipped
    to the pixel) and is integrated with ``samples``-point Gauss-Legendre
    quadrature, across x or y, whichever the boundary is a smooth graph of
    (per-pixel area error < 2e-4 at the default: measured against 512 points).
    """
    r_m = unit.r_m if radius is None else radius
    x, y = unit.pixel_centres()
    dist = np.hypot(x - unit.x_c, y - unit.y_c)
    cov = (dist <= r_m).astype(float)
    edge = np.abs(dist - r_m) < 0.75  # half a pixel diagonal is 0.707
    nodes, weights = np.polynomial.legendre.leggauss(samples)
    # Integrate along the axis in which the circle's boundary is a smooth graph:
    # across x where the boundary runs more horizontally, across y elsewhere.
    ex, ey = x[edge] - unit.x_c, y[edge] - unit.y_c
    along_x = np.abs(ey) >= np.abs(ex)
    a = np.where(along_x, ex, ey)[:, None] + 0.5 * nodes  # integration variable
    b0 = np.where(along_x, ey, ex)[:, None] - 0.5  # the other axis: [b0, b0 + 1)
    half = np.sqrt(np.clip(r_m * r_m - a * a, 0.0, None))  # half chord at each a
    covered = np.clip(np.minimum(b0 + 1.0, half) - np.maximum(b0, -half), 0.0, 1.0)
    cov[edge] = 0.5 * covered @ weights  # the pixel is 1 wide: the weights sum to 2
    return cov


@dataclass(frozen=True)
class SyntheticScene:
    """A rig, its planar motion, and textured moving bodies; renders images and truth.

    Attributes
    ----------
    rig : Rig
    bodies : tuple of Cylinder | Disc
        Ids must be unique and >= 1 (0 means "nothing hit").
    robot : Motion
        The rig's motion: world translation per frame and yaw rate (vz must be 0).
    start : (float, float, float)
        The rig's world (x, y, yaw) at frame 0.
    background : float
        Grey level of rays that hit nothing.
    outside : float
        Grey level beyond the mirror's rim.
    """

    rig: Rig
    bodies: tuple = ()
    robot: Motion = field(default_factory=Motion)
    start: tuple[float, float, float] = (0.0, 0.0, 0.0)
    background: float = 0.0
    outside: float = 0.0

    def __post_init__(self):
        ids = [b.id for b in self.bodies]
        if any(int(i) != i or i < 1 for i in ids) or len(set(ids)) != len(ids):
            raise ValueError(f"body ids {ids}: expected unique integers >= 1")
        if self.robot.vz != 0:
            raise ValueError(f"robot.vz = {self.robot.vz}: the rig moves only in the plane")

    # -- construction -------------------------------------------------------
    @classmethod
    def room(
        cls,
        rig: Rig,
        *,
        wall_radius: float = 3.0,
        ceiling: float | None = 2.5,
        texture_seed: int = 0,
        wavelengths: tuple[float, float] = (0.05, 0.4),
        contrast: float = 0.4,
        robot: Motion | None = None,
        bodies: Sequence = (),
    ) -> SyntheticScene:
        """A round room centred on the rig's start: a textured wall (id 1) and ceiling (id 2).

        Parameters
        ----------
        wall_radius : float
            Wall radius, metres; the wall spans floor to ceiling (or is unbounded
            when ``ceiling`` is None).
        ceiling : float or None
            Ceiling height (world Z = rig h), metres; must lie above cam1's tip to
            be seen by both units. None: no ceiling, an infinitely tall wall.
        texture_seed : int
            Seed of the wall texture; the ceiling uses ``texture_seed + 1``.
        robot : Motion, optional
            The rig's motion (default: static).
        bodies : sequence of Cylinder | Disc
            More bodies (ids >= 3).
        """
        wall = Cylinder(
            radius=wall_radius,
            id=1,
            name="wall",
            z_max=np.inf if ceiling is None else ceiling,
            texture=Texture.random(
                texture_seed,
                wavelengths=wavelengths,
                contrast=contrast,
                period_u=2 * np.pi * wall_radius,
            ),
        )
        parts = [wall]
        if ceiling is not None:
            parts.append(
                Disc(
                    z=ceiling,
                    outer=wall_radius * (1 + 1e-9),
                    id=2,
                    name="ceiling",
                    texture=Texture.random(
                        texture_seed + 1, wavelengths=wavelengths, contrast=contrast
                    ),
                )
            )
        return cls(rig=rig, bodies=(*parts, *bodies), robot=robot or Motion())

    def with_bodies(self, *bodies) -> SyntheticScene:
        """This scene with more bodies."""
        return replace(self, bodies=(*self.bodies, *bodies))

    # -- geometry -------------------------------------------------------------
    def rig_pose(self, t: float) -> tuple[NDArray, float]:
        """World position (2,) and yaw of the rig at frame t."""
        p = np.asarray(self.start[:2], float) + t * np.asarray(self.robot.velocity, float)
        return p, self.start[2] + t * self.robot.yaw_rate

    def rig_to_world(self, t: float, r: NDArray, theta: NDArray, h: NDArray):
        """Rig cylindrical (r, theta, h) -> world (X, Y, Z) at frame t."""
        p, yaw = self.rig_pose(t)
        return p[0] + r * np.cos(theta + yaw), p[1] + r * np.sin(theta + yaw), np.asarray(h)

    def world_to_rig(self, t: float, X: NDArray, Y: NDArray, Z: NDArray):
        """World (X, Y, Z) -> rig cylindrical (r, theta, h) at frame t, theta in [-pi, pi)."""
        p, yaw = self.rig_pose(t)
        px, py = X - p[0], Y - p[1]
        ca, sa = np.cos(yaw), np.sin(yaw)
        qx, qy = ca * px + sa * py, -sa * px + ca * py
        return np.hypot(qx, qy), wrap_angle(np.arctan2(qy, qx)), np.asarray(Z, float)

    def _rays(self, unit: Unit, t: float, h_i: NDArray, theta: NDArray):
        """World ray geometry of polar image points: origin, direction, slope, mirror point."""
        k = h_i / unit.v  # slope dh/dr, eq. (1)
        ok = (h_i > 0) & (k < 1)
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = np.where(ok, unit.d * k / (1 - k), np.inf)  # mirror point
        p, yaw = self.rig_pose(t)
        return p, np.cos(theta + yaw), np.sin(theta + yaw), k, rho

    @staticmethod
    def _intersect(body, unit: Unit, t: float, rays) -> NDArray:
        """Range of each ray's hit on one body (inf: none), ignoring other bodies."""
        p, dx, dy, k, rho = rays
        if isinstance(body, Cylinder):
            return body.intersect(
                t, p[0], p[1], dx, dy, lambda r: unit.tip_h + k * (unit.d + r), rho
            )
        return body.intersect(t, p[0], p[1], dx, dy, k, unit.tip_h, unit.d, rho)

    def trace(self, unit: Unit, t: float, h_i: ArrayLike, theta: ArrayLike) -> Hit:
        """Nearest hits of the rays at polar image points (h_i, theta) at frame t.

        Rays with h_i <= 0 or h_i >= v hit nothing. The rim is NOT applied here.
        """
        h_i = np.asarray(h_i, float).ravel()
        theta = np.asarray(theta, float).ravel()
        rays = self._rays(unit, t, h_i, theta)
        p, dx, dy, k, _ = rays
        best = np.full(h_i.shape, np.inf)
        index = np.full(h_i.shape, -1)
        for i, body in enumerate(self.bodies):
            r = self._intersect(body, unit, t, rays)
            closer = r < best
            best = np.where(closer, r, best)
            index = np.where(closer, i, index)
        hit = np.isfinite(best)
        r = np.where(hit, best, np.nan)
        return Hit(
            index=index,
            r=np.where(hit, r, np.inf),
            X=p[0] + r * dx,
            Y=p[1] + r * dy,
            Z=unit.tip_h + k * (unit.d + r),  # eq. (1)
        )

    def _surface_uv(self, body, unit: Unit, t: float, x: NDArray, y: NDArray) -> tuple:
        """Texture coordinates where the rays of pixel points (x, y) meet ``body`` (NaN: miss)."""
        h_i, theta = unit.polar_of_pixel(x, y)
        rays = self._rays(unit, t, h_i, theta)
        p, dx, dy, k, _ = rays
        r = self._intersect(body, unit, t, rays)
        r = np.where(np.isfinite(r), r, np.nan)
        local = body.to_local(t, p[0] + r * dx, p[1] + r * dy, unit.tip_h + k * (unit.d + r))
        return body.surface_uv(*local)

    def _jacobian(self, body, unit: Unit, t: float, x: NDArray, y: NDArray) -> tuple:
        """(du/dx, du/dy, dv/dx, dv/dy) of ``body``'s texture coordinates, central differences."""
        eps = 1e-3  # px; the map is smooth on the scale of a pixel
        u_px, v_px = self._surface_uv(body, unit, t, x + eps, y)
        u_mx, v_mx = self._surface_uv(body, unit, t, x - eps, y)
        u_py, v_py = self._surface_uv(body, unit, t, x, y + eps)
        u_my, v_my = self._surface_uv(body, unit, t, x, y - eps)
        period = 2 * np.pi * body.radius if isinstance(body, Cylinder) else np.inf
        du_x, du_y = u_px - u_mx, u_py - u_my
        if np.isfinite(period):  # arc length jumps by the circumference at phi = +-pi
            du_x = (du_x + period / 2) % period - period / 2
            du_y = (du_y + period / 2) % period - period / 2
        jac = (du_x, du_y, v_px - v_mx, v_py - v_my)
        # Grazing rays that miss at an offset: no attenuation information, treat as flat.
        return tuple(np.nan_to_num(j / (2 * eps), nan=0.0) for j in jac)

    def shade(
        self,
        hit: Hit,
        t: float,
        *,
        blur: float = 0.0,
        unit: Unit | None = None,
        x: NDArray | None = None,
        y: NDArray | None = None,
    ) -> NDArray:
        """Texture values of hits (``background`` where nothing is hit).

        With ``blur`` > 0 (Gaussian pixel footprint, sigma in pixels) also give
        the ``unit`` and the hits' pixel coordinates ``x``, ``y`` (flat arrays):
        each body's texture is then band-limited analytically (:class:`Texture`).
        """
        out = np.full(hit.r.shape, float(self.background))
        for i, body in enumerate(self.bodies):
            sel = hit.index == i
            if np.any(sel):
                xb, yb, zb = body.to_local(t, hit.X[sel], hit.Y[sel], hit.Z[sel])
                jac = None
                if blur > 0:
                    if unit is None or x is None or y is None:
                        raise ValueError("shade(blur > 0) needs unit, x and y")
                    jac = self._jacobian(body, unit, t, x[sel], y[sel])
                out[sel] = body.texture(*body.surface_uv(xb, yb, zb), jacobian=jac, blur=blur)
        return out

    # -- images ---------------------------------------------------------------
    def render(
        self,
        cam: str | Unit,
        t: float = 0,
        *,
        supersample: int = 1,
        blur: float = 0.0,
        antialias_rim: bool = True,
        noise: float = 0.0,
        seed: int = 0,
        dtype=np.float64,
    ) -> NDArray:
        """Grey image of one unit at frame t, shape (H, W).

        Parameters
        ----------
        cam : "cam1" | "cam2" | Unit
        t : float
            Frame (time in frame intervals; fractional frames allowed).
        supersample : int
            n: average an n x n grid of sub-pixel rays per pixel (pixel-area
            integration). 1: sample at pixel centres.
        blur : float
            Sigma, pixels, of a Gaussian footprint applied to every texture
            sinusoid analytically (its local image frequency from the Jacobian
            of the surface coordinates). 0: none. Point sampling aliases where a
            surface is seen obliquely or far away: tangentially a wall at range
            r spans r / h_i metres per pixel, so a texture wavelength lambda is
            under-sampled for h_i < 2 r / lambda. ``blur=0.5`` band-limits the
            image (attenuation 0.29 at 0.5 cycle/px, 0.007 at 1 cycle/px); brightness
            constancy then holds to the change of the footprint between frames.
        antialias_rim : bool
            Weight pixels the rim crosses by their area inside it (the texture
            continued just beyond the rim), else a hard cut at pixel centres.
        noise : float
            Standard deviation of additive Gaussian noise (grey levels).
        seed : int
            Noise seed.
        dtype : float32 or float64
        """
        unit, _ = _unit(self.rig, cam)
        n = int(supersample)
        if n < 1:
            raise ValueError(f"supersample = {supersample!r}: expected an integer >= 1")
        x, y = unit.pixel_centres()
        offs = (np.arange(n) + 0.5) / n - 0.5
        ox, oy = np.meshgrid(offs, offs)
        sx = x[..., None] + ox.ravel()
        sy = y[..., None] + oy.ravel()
        if blur < 0:
            raise ValueError(f"blur = {blur!r}: expected a sigma >= 0 in pixels")
        h_i, theta = unit.polar_of_pixel(sx, sy)
        hit = self.trace(unit, t, h_i, theta)
        vals = self.shade(hit, t, blur=blur, unit=unit, x=sx.ravel(), y=sy.ravel())
        vals = vals.reshape(sx.shape)
        if antialias_rim:
            img = vals.mean(axis=-1)
            cov = rim_coverage(unit)
            img = cov * img + (1 - cov) * self.outside
        else:
            vals = np.where(h_i <= unit.r_m, vals, self.outside)
            img = vals.mean(axis=-1)
        if noise > 0:
            img = img + np.random.default_rng(seed).normal(0.0, noise, img.shape)
        return img.astype(dtype)

    def frames(self, cam: str | Unit, count: int, *, start: int = 0, **render_kw) -> NDArray:
        """Frames start .. start + count - 1 of one unit, shape (count, H, W)."""
        return np.stack([self.render(cam, start + k, **render_kw) for k in range(count)])

    # -- truth ------------------------------------------------------------------
    def _sees(self, unit: Unit, t: float, r, theta, h, index) -> NDArray:
        """True where ``unit`` sees the point (r, theta, h) of body ``index`` at frame t.

        On the mirror (inside the rim, above the tip, beyond the mirror point)
        and the nearest hit of its own ray.
        """
        seen = unit.visible(r, h) & np.isfinite(r)
        h_i = unit.image_radius(r, h)
        hit = self.trace(unit, t, np.where(seen, h_i, 0.0), theta)
        same = (hit.index == index) & (np.abs(hit.r - r) <= _SAME_POINT_RTOL * (1 + r))
        return seen & same

    def truth(self, cam: str | Unit, t: int = 0) -> dict[str, NDArray]:
        """Exact per-pixel truth of one unit at frame t (pixel centres), dataset channel names.

        Returns
        -------
        dict of str to ndarray, shape (H, W), float64
            Exactly the keys of :data:`TRUTH_KEYS`. See the module docstring for
            NaN/0 conventions. Flow is from frame t to t + 1.
        """
        unit, other = _unit(self.rig, cam)
        x, y = unit.pixel_centres()
        h_i, theta = unit.polar_of_pixel(x, y)
        h_i, theta, shape = h_i.ravel(), theta.ravel(), x.shape
        hit = self.trace(unit, t, h_i, theta)
        valid = (h_i <= unit.r_m) & (hit.index >= 0)
        r = np.where(valid, hit.r, np.nan)
        h = np.where(valid, hit.Z, np.nan)
        X, Y = np.where(valid, hit.X, np.nan), np.where(valid, hit.Y, np.nan)
        obj = np.zeros(h_i.shape)
        idx = np.where(valid, hit.index, -1)
        ids = np.array([b.id for b in self.bodies] + [0], float)
        obj = ids[idx]  # index -1 picks the trailing 0

        # Move each material point with its body to t + 1, then see it from the rig at t + 1.
        X1, Y1, Z1 = (np.full(h_i.shape, np.nan) for _ in range(3))
        for i, body in enumerate(self.bodies):
            sel = idx == i
            if np.any(sel):
                X1[sel], Y1[sel], Z1[sel] = body.to_world(
                    t + 1, *body.to_local(t, X[sel], Y[sel], h[sel])
                )
        r1, th1, h1 = self.world_to_rig(t + 1, X1, Y1, Z1)
        hi1 = unit.image_radius(r1, h1)  # eq. (1)
        x1, y1 = unit.pixel_of_polar(hi1, th1)
        flow_valid = valid & self._sees(unit, t + 1, r1, th1, h1, idx)

        h_other = other.image_radius(r, h)  # eq. (3) / (4)
        stereo_valid = valid & self._sees(other, t, r, theta, h, idx)

        nan = np.nan
        out = {
            "gt.valid": valid.astype(float),
            "gt.r": r,
            "gt.theta": np.where(valid, theta, nan),
            "gt.h": h,
            "gt.X": X,
            "gt.Y": Y,
            "gt.Z": h,
            "gt.object": obj,
            "gt.flow.dx": x1 - x.ravel(),
            "gt.flow.dy": y1 - y.ravel(),
            "gt.flow.dh": hi1 - h_i,
            "gt.flow.hdtheta": h_i * wrap_angle(th1 - theta),
            "gt.flow.valid": flow_valid.astype(float),
            "gt.stereo.h_other": h_other,
            "gt.stereo.valid": stereo_valid.astype(float),
        }
        return {key: np.asarray(val, float).reshape(shape) for key, val in out.items()}
