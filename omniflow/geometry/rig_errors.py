"""Rig errors of one unit (a mis-made or misaligned mirror and camera) and its traced model.

A real unit is not the ideal one of :class:`omniflow.geometry.rig.Unit` (a pinhole on
the axis of a 90-degree cone). :class:`UnitErrors` holds five departures, the keys of
a scene's ``[rig.errors.cam1]`` / ``[rig.errors.cam2]`` tables and of ``rig.errors`` in
``dataset.json`` and rig files (``docs/scene_format.md``); every key defaults to the
ideal rig:

==================  ==========  ==========================================================
key                 unit        meaning
==================  ==========  ==========================================================
``mirror_tilt``     [deg, deg]  the cone's axis turned about the rig's X axis, then about
                                its Y axis, both through the cone's tip (right-handed)
``mirror_offset``   [m, m, m]   the cone's tip moved, rig frame
``cone_angle``      deg         the cone's full apex angle (90 ideal)
``camera_tilt``     [deg, deg]  the camera turned the same way about its centre
``camera_offset``   [m, m]      the camera centre moved in the rig's X and Y
==================  ==========  ==========================================================

Model (rig frame of :mod:`omniflow.conventions`; ideal camera centre
``C0 = (0, 0, tip_h - d)``, ideal tip ``T0 = (0, 0, tip_h)``). A tilt ``[a, b]`` is the
rotation ``Ry(b) Rx(a)``. The camera keeps its intrinsics (image distance v of eq. 2,
principal point (x_c, y_c)): pixel (x, y) looks from ``C = C0 + (ox, oy, 0)`` along
``Rc (x - x_c, y - y_c, v)``. The mirror is the upper nappe of the cone of tip
``T = T0 + mirror_offset``, axis ``a = Rm (0, 0, 1)`` and half-angle ``alpha =
cone_angle / 2``, out to distance R from its axis (its base circle, the rim).
:func:`cone_reflect` intersects a ray with it in closed form (the quadratic
``((p + t w).a)^2 = cos^2(alpha) |p + t w|^2``, p = origin - T, larger root) and
reflects it off the surface normal ``(q.a) a - cos^2(alpha) q`` (q = hit - T); the
quadratic is solved about the ray's nearest point to the tip, which keeps float32 exact
enough near the tip (the renderer's rays: ``tests/omnisim/test_rig_errors.py``).

:func:`traced_rays` is the forward model (pixel -> reflected ray) and
:func:`traced_project` its inverse (rig point -> pixel), by Gauss-Newton from the
pixel that eq. (1) gives, the Jacobian by finite differences of the forward model.
The ray-cone functions take an ``ops`` namespace (``sqrt``, ``select``, ``maximum``),
so the renderer runs the same formulas in Dr.Jit as the ground truth in numpy.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "ERROR_KEYS",
    "NUMPY_OPS",
    "UnitErrors",
    "cone_reflect",
    "errors_from_dict",
    "tilt_matrix",
    "traced_constants",
    "traced_project",
    "traced_rays",
]

ERROR_KEYS = ("mirror_tilt", "mirror_offset", "cone_angle", "camera_tilt", "camera_offset")
#: Largest tilt, degrees; larger is a different rig, not an alignment error.
MAX_TILT_DEG = 5.0
#: Cone angle range, degrees.
CONE_ANGLE_RANGE = (80.0, 100.0)
#: Largest offset, as a fraction of the rig's d.
MAX_OFFSET_OF_D = 0.1
#: Array operations of the ray-cone functions for numpy.
NUMPY_OPS = SimpleNamespace(sqrt=np.sqrt, select=np.where, maximum=np.maximum)
#: Gauss-Newton of :func:`traced_project`: most steps, the step (px) that ends it, the
#: finite-difference step (px) of the Jacobian.
PROJECT_STEPS = 40
#: Most steps from a retry's start, 1-10 px from the tip's image (measured: those found
#: take under 10; the others are points no pixel sees).
PROJECT_RETRY_STEPS = 15
#: The longest Gauss-Newton step, px (near the axis's image the map bends sharply).
PROJECT_MAX_STEP = 12.0
#: Image radius (px) about the tip's image inside which unseen points are tried again,
#: plus v times the angle by which the errors can turn the rays there (:func:`_near_tip`).
NEAR_TIP_PX = 20.0
PROJECT_STEP_TOL = 1e-7
PROJECT_FD = 1e-3


@dataclass(frozen=True)
class UnitErrors:
    """The five departures of one unit from the ideal (module docstring); degrees, metres."""

    mirror_tilt: tuple[float, float] = (0.0, 0.0)
    mirror_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    cone_angle: float = 90.0
    camera_tilt: tuple[float, float] = (0.0, 0.0)
    camera_offset: tuple[float, float] = (0.0, 0.0)

    @property
    def ideal(self) -> bool:
        """True when every key has its ideal value (the unit is eq. 1's)."""
        return self == UnitErrors()

    def as_dict(self) -> dict[str, Any]:
        """The keys and values as for a rig file or dataset.json (lists, floats)."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self._items()}

    def _items(self):
        return ((k, getattr(self, k)) for k in ERROR_KEYS)


def errors_from_dict(
    tbl: Any, where: str, d: float, fail: Callable[[str, Any, str], Exception]
) -> UnitErrors:
    """Read one ``rig.errors.camN`` table; ``fail(key, value, expected)`` makes the error.

    ``where`` is the table's dotted name (``rig.errors.cam1``), ``d`` the rig's d
    (offsets are limited to :data:`MAX_OFFSET_OF_D` of it).
    """
    if not isinstance(tbl, dict):
        raise fail(where, tbl, f"a table with some of: {', '.join(ERROR_KEYS)}")
    unknown = sorted(set(tbl) - set(ERROR_KEYS))
    if unknown:
        raise fail(f"{where}.{unknown[0]}", tbl[unknown[0]], f"one of: {', '.join(ERROR_KEYS)}")
    lim = MAX_OFFSET_OF_D * d
    specs = {
        "mirror_tilt": (2, MAX_TILT_DEG, "deg"),
        "mirror_offset": (3, lim, f"m (a tenth of rig.d = {d:g} m)"),
        "camera_tilt": (2, MAX_TILT_DEG, "deg"),
        "camera_offset": (2, lim, f"m (a tenth of rig.d = {d:g} m)"),
    }
    out: dict[str, Any] = {}
    for key, (n, hi, unit) in specs.items():
        if key not in tbl:
            continue
        v = tbl[key]
        expected = f"a list of {n} numbers in [{-hi:g}, {hi:g}] {unit}"
        if not isinstance(v, list | tuple) or len(v) != n or not all(_finite(x) for x in v):
            raise fail(f"{where}.{key}", v, expected)
        if any(abs(x) > hi for x in v):
            raise fail(f"{where}.{key}", v, expected)
        out[key] = tuple(float(x) for x in v)
    if "cone_angle" in tbl:
        v = tbl["cone_angle"]
        lo, hi = CONE_ANGLE_RANGE
        if not _finite(v) or not lo <= v <= hi:
            raise fail(f"{where}.cone_angle", v, f"a number in [{lo:g}, {hi:g}] deg (90 ideal)")
        out["cone_angle"] = float(v)
    return UnitErrors(**out)


def _finite(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def tilt_matrix(tilt_deg: ArrayLike) -> NDArray:
    """Ry(b) Rx(a) of a tilt [a, b] in degrees: about X first, then Y (right-handed)."""
    a, b = np.radians(np.asarray(tilt_deg, dtype=np.float64))
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    return ry @ rx


def traced_constants(unit: Any, errors: UnitErrors | None = None) -> SimpleNamespace:
    """The numbers of the traced model of ``unit`` (its ``errors`` unless given), float64.

    ``C`` camera centre, ``Rc`` camera rotation (3, 3), ``T`` cone tip, ``a`` cone axis,
    ``cos2`` = cos^2(cone_angle / 2), ``R`` rim radius, ``v``, ``x_c``, ``y_c``.
    """
    e = errors if errors is not None else (getattr(unit, "errors", None) or UnitErrors())
    ox, oy = e.camera_offset
    rm = tilt_matrix(e.mirror_tilt)
    return SimpleNamespace(
        C=np.array([ox, oy, unit.tip_h - unit.d]),
        Rc=tilt_matrix(e.camera_tilt),
        T=np.array([0.0, 0.0, unit.tip_h]) + np.asarray(e.mirror_offset, dtype=np.float64),
        a=rm[:, 2].copy(),
        cos2=math.cos(math.radians(e.cone_angle) / 2.0) ** 2,
        R=float(unit.R),
        v=float(unit.v),
        x_c=float(unit.x_c),
        y_c=float(unit.y_c),
    )


def cone_reflect(ops, o, w, g):
    """Reflect the rays ``o + t w`` (rig frame, 3-tuples; w need not be unit) off the cone.

    ``g`` holds ``T``, ``a``, ``cos2``, ``R`` (:func:`traced_constants`; numbers or JIT
    scalars). Returns ``(q, r, ok, rho)``: the mirror point (rig frame), the unit
    reflected direction, where the ray meets the upper nappe inside the rim, and the hit's
    distance from the cone's axis (metres).
    """
    T, ax, c2 = g.T, g.a, g.cos2
    p = [o[k] - T[k] for k in range(3)]
    # Well conditioned near the tip (where the two nappes' roots meet), so float32 holds:
    # m = w x p, the ray's line is closest to the tip at q0 = (m x w) / |w|^2, and
    # with q = q0 + s w the quadratic is A s^2 + 2 b s + c = 0, its discriminant
    # b^2 - A c = cos^2 (sin^2 |m|^2 - (a.m)^2) (no difference of near-equal squares).
    m = [w[1] * p[2] - w[2] * p[1], w[2] * p[0] - w[0] * p[2], w[0] * p[1] - w[1] * p[0]]
    ww = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    q0 = [
        (m[(k + 1) % 3] * w[(k + 2) % 3] - m[(k + 2) % 3] * w[(k + 1) % 3]) / ww for k in range(3)
    ]
    wa = w[0] * ax[0] + w[1] * ax[1] + w[2] * ax[2]
    qa0 = q0[0] * ax[0] + q0[1] * ax[1] + q0[2] * ax[2]
    ma = m[0] * ax[0] + m[1] * ax[1] + m[2] * ax[2]
    qa = wa * wa - c2 * ww  # > 0 for a ray closer to the axis than the cone's half-angle
    b = qa0 * wa
    c = qa0 * qa0 - c2 * (q0[0] * q0[0] + q0[1] * q0[1] + q0[2] * q0[2])
    disc = c2 * ((1.0 - c2) * (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]) - ma * ma)
    ok = (disc >= 0.0) & (qa > 0.0)
    h = ops.sqrt(ops.maximum(disc, 0.0))
    # the larger root (the upper nappe), in the form without cancellation
    den = ops.select(b > 0.0, -b - h, ops.select(ok, qa, 1.0))
    num = ops.select(b > 0.0, c, h - b)
    s = num / ops.select(den != 0.0, den, 1.0)
    q = [q0[k] + s * w[k] for k in range(3)]  # tip-relative
    za = q[0] * ax[0] + q[1] * ax[1] + q[2] * ax[2]
    radial = [q[k] - za * ax[k] for k in range(3)]
    rho = ops.sqrt(radial[0] * radial[0] + radial[1] * radial[1] + radial[2] * radial[2])
    ok = ok & (za > 0.0) & (rho <= g.R)
    n = [za * ax[k] - c2 * q[k] for k in range(3)]  # half the gradient of the quadric
    nn = n[0] * n[0] + n[1] * n[1] + n[2] * n[2]
    k2 = 2.0 * (w[0] * n[0] + w[1] * n[1] + w[2] * n[2]) / ops.select(nn > 0.0, nn, 1.0)
    r = [w[k] - k2 * n[k] for k in range(3)]
    inv = 1.0 / ops.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
    return [q[k] + T[k] for k in range(3)], [r[k] * inv for k in range(3)], ok, rho


def camera_ray(px, py, g):
    """Origin and direction (3-tuples, rig frame) of the film offset (px, py) from (x_c, y_c)."""
    rc = g.Rc
    w = [rc[i][0] * px + rc[i][1] * py + rc[i][2] * g.v for i in range(3)]
    return [g.C[0], g.C[1], g.C[2]], w


def traced_rays(
    unit: Any, x: ArrayLike, y: ArrayLike, errors: UnitErrors | None = None
) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Reflected rays of continuous pixels (x, y) through the actual geometry, float64.

    Returns ``(origin, direction, valid, rho)``: the mirror points and unit directions
    (..., 3), rig frame, where the ray meets the mirror inside its rim, and the hit's
    distance from the cone's axis.
    """
    g = traced_constants(unit, errors)
    return _rays(g, np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))


def _rays(g, x: NDArray, y: NDArray):
    o, w = camera_ray(x - g.x_c, y - g.y_c, g)
    o = [np.broadcast_to(c, x.shape) for c in o]
    with np.errstate(invalid="ignore", divide="ignore"):
        q, r, ok, rho = cone_reflect(NUMPY_OPS, o, w, g)
    return np.stack(q, axis=-1), np.stack(r, axis=-1), ok, rho


def traced_project(
    unit: Any, q: ArrayLike, errors: UnitErrors | None = None
) -> tuple[NDArray, NDArray, NDArray]:
    """The pixel (x, y) whose traced reflected ray passes through rig point q (..., 3).

    Gauss-Newton (:func:`_solve`) from eq. (1)'s pixel, placed about the image of the
    cone's tip. Near the tip's image (:func:`_near_tip`) eq. (1) can start on the wrong
    side (the errors turn the nearly level rays there) and the iteration can end on the
    line behind the mirror point; a point not found from there, unless it lies below
    every ray there, is tried again with the robust residual from rings of starts 1, 3
    and 10 px about the tip's image. Returns ``(x, y, seen)``: ``seen`` where
    it converged, the ray meets the mirror inside its rim and q lies ahead of the mirror
    point; x and y are NaN where no pixel's ray runs ahead through q (not converged, or
    only the line behind the mirror point). The image bounds are the caller's.
    """
    g = traced_constants(unit, errors)
    q = np.asarray(q, dtype=np.float64)
    shape = q.shape[:-1]
    q = q.reshape(-1, 3)
    r = np.hypot(q[:, 0], q[:, 1])
    x_t, y_t = _tip_image(g)
    with np.errstate(invalid="ignore", divide="ignore"):
        h_i = g.v * (q[:, 2] - unit.tip_h) / (unit.d + r)  # eq. (1), about the tip's image
        x = x_t + np.where(r > 0, h_i * q[:, 0] / r, 0.0)
        y = y_t + np.where(r > 0, h_i * q[:, 1] / r, 0.0)
    x, y, seen = _solve(g, x, y, q)
    e = errors if errors is not None else (getattr(unit, "errors", None) or UnitErrors())
    near = np.abs(h_i) < _near_tip(g, e)
    retry = np.nonzero(~np.isfinite(x) & near & _above_lowest_ray(g, q))[0]
    for radius in (1.0, 3.0, 10.0):
        for ang in np.arange(8) * (np.pi / 4):
            if len(retry) == 0:
                break
            x0 = np.full(len(retry), x_t + radius * np.cos(ang))
            y0 = np.full(len(retry), y_t + radius * np.sin(ang))
            x1, y1, s1 = _solve(g, x0, y0, q[retry], robust=True)
            got = retry[s1]
            x[got], y[got], seen[got] = x1[s1], y1[s1], True
            off = ~s1 & np.isfinite(x1) & ~np.isfinite(x[retry])  # found, off the mirror
            x[retry[off]], y[retry[off]] = x1[off], y1[off]
            retry = retry[~s1]
    return x.reshape(shape), y.reshape(shape), seen.reshape(shape)


def _solve(g, x: NDArray, y: NDArray, q: NDArray, robust: bool = False):
    """Gauss-Newton from (x, y) to the pixel whose ray runs through q (``seen``, NaN as
    above); returns ``(x, y, seen)``.

    The residual is q's offset across the ray (:func:`_across`: fast, but also zero on
    the line behind the mirror point, which ``found`` rejects), or with ``robust`` the
    direction to q minus the ray's (:func:`_direction`: 2, not 0, behind the mirror
    point; slower where no pixel sees q). The Jacobian comes from the forward model at
    + :data:`PROJECT_FD` px; steps are limited to :data:`PROJECT_MAX_STEP` px; it ends
    when every step is below :data:`PROJECT_STEP_TOL` px (quadratic convergence: the
    last step bounds the error) or after :data:`PROJECT_STEPS` steps
    (:data:`PROJECT_RETRY_STEPS` with ``robust``).
    """
    residual = _direction if robust else _across
    x, y = x.copy(), y.copy()
    step = np.full(len(q), np.inf)
    act = np.arange(len(q))  # the points still moving
    for _ in range(PROJECT_RETRY_STEPS if robust else PROJECT_STEPS):
        xa, ya, qa = x[act], y[act], q[act]
        e0, basis = residual(g, xa, ya, qa, None)
        jx = (residual(g, xa + PROJECT_FD, ya, qa, basis)[0] - e0) / PROJECT_FD
        jy = (residual(g, xa, ya + PROJECT_FD, qa, basis)[0] - e0) / PROJECT_FD
        # the normal equations of [jx jy] s = -e0 (2 or 3 rows)
        a11, a12, a22 = _dot(jx, jx), _dot(jx, jy), _dot(jy, jy)
        b1, b2 = -_dot(jx, e0), -_dot(jy, e0)
        det = a11 * a22 - a12 * a12
        with np.errstate(invalid="ignore", divide="ignore"):
            sx = (a22 * b1 - a12 * b2) / det
            sy = (a11 * b2 - a12 * b1) / det
            st = np.hypot(sx, sy)
            scale = np.minimum(1.0, PROJECT_MAX_STEP / np.where(st > 0, st, 1.0))
        x[act], y[act], step[act] = xa + scale * sx, ya + scale * sy, st
        act = act[st > PROJECT_STEP_TOL]  # NaN (no ray) stops too: it is unseen
        if len(act) == 0:
            break
    o, w, ok, _ = _rays(g, x, y)
    with np.errstate(invalid="ignore"):
        found = (_dot(q - o, w) > 0) & (step <= 1e3 * PROJECT_STEP_TOL)
        found &= np.linalg.norm(_direction(g, x, y, q, None)[0], axis=-1) < 1e-6
    x, y = np.where(found, x, np.nan), np.where(found, y, np.nan)
    return x, y, ok & found


def _dot(a: NDArray, b: NDArray) -> NDArray:
    return np.einsum("ij,ij->i", a, b)


def _above_lowest_ray(g, q: NDArray) -> NDArray:
    """False for points below every ray near the tip (they cannot be seen there): the
    elevation from the tip under the lowest of the rays 0.5 px about the tip's image,
    by more than the parallax of a mirror point within 2 R of the tip."""
    x_t, y_t = _tip_image(g)
    ang = np.linspace(0.0, 2 * np.pi, 64, endpoint=False)
    _, w, _, _ = _rays(g, x_t + 0.5 * np.cos(ang), y_t + 0.5 * np.sin(ang))
    lowest = np.nanmin(np.arcsin(np.clip(w[:, 2], -1.0, 1.0)))
    dq = q - g.T
    dist = np.linalg.norm(dq, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        elev = np.arctan2(dq[:, 2], np.hypot(dq[:, 0], dq[:, 1]))
        parallax = np.arcsin(np.minimum(1.0, 2 * g.R / dist))
    return ~(elev < lowest - parallax)


def _near_tip(g, e: UnitErrors) -> float:
    """The image radius (px) within which eq. (1) can start on the wrong side of the tip:
    :data:`NEAR_TIP_PX` plus v times the turn of the rays there (twice the mirror's
    tilt, the camera's tilt, the change of the cone's full angle, radians) and the
    offsets over the camera's distance to the tip."""
    turn = 2 * math.hypot(*e.mirror_tilt) + math.hypot(*e.camera_tilt) + abs(e.cone_angle - 90)
    shift = math.hypot(*e.camera_offset) + math.hypot(*e.mirror_offset[:2])  # m, at about d
    return NEAR_TIP_PX + g.v * (math.radians(turn) + shift / (g.T[2] - g.C[2]))


def _tip_image(g) -> tuple[float, float]:
    """The pixel that sees the cone's tip (the centre of the image's radial structure)."""
    dc = g.Rc.T @ (g.T - g.C)
    return g.x_c + g.v * dc[0] / dc[2], g.y_c + g.v * dc[1] / dc[2]


def _across(g, x: NDArray, y: NDArray, q: NDArray, basis):
    """q's offset across the ray of (x, y) in the basis (b1, b2), (N, 2) metres, and the
    basis (taken across the ray when None: the Jacobian's neighbours reuse the centre's,
    so their residuals differ only by the ray's change)."""
    o, w, _, _ = _rays(g, x, y)
    if basis is None:
        b1 = np.cross(w, np.array([0.0, 0.0, 1.0]))  # two unit vectors across w
        with np.errstate(invalid="ignore", divide="ignore"):  # NaN rays stay NaN
            b1 /= np.linalg.norm(b1, axis=-1, keepdims=True)
        basis = (b1, np.cross(w, b1))
    dq = q - o
    dq = dq - _dot(dq, w)[:, None] * w  # across this ray
    return np.stack([_dot(dq, basis[0]), _dot(dq, basis[1])], axis=-1), basis


def _direction(g, x: NDArray, y: NDArray, q: NDArray, basis):
    """The unit direction from the mirror point of (x, y) to q minus the ray's, (N, 3)."""
    o, w, _, _ = _rays(g, x, y)
    dq = q - o
    with np.errstate(invalid="ignore", divide="ignore"):
        return dq / np.linalg.norm(dq, axis=-1, keepdims=True) - w, None
