"""The cone-mirror unit as an analytic Mitsuba sensor, and its exact ray geometry.

One unit (paper section 2, ``omniflow.geometry.rig.Unit``) is a pinhole camera on the
rig axis at Z = tip_h - d looking up (+Z) at a 90-degree cone mirror whose tip
points down at it. The mirror is traced *analytically* instead of being
tessellated: a film sample at continuous pixel (x, y) is turned straight into
the ray reflected by the cone, so the render saves one bounce and its
geometry is eq. (1) exactly, up to float32.

Derivation (rig frame, meridional plane of the pixel). Let
``theta = atan2(y - y_c, x - x_c)`` and ``h_i = hypot(x - x_c, y - y_c)``.
Image x runs along rig +X and image y along rig +Y (``omniflow.conventions``),
so the camera ray is ``P(t) = (0, 0, tip_h - d) + t (h_i cos theta,
h_i sin theta, v)``: radial coordinate ``rho = t h_i``, height
``Z - tip_h = -d + t v``. The 45-degree cone is ``Z - tip_h = rho``, hence
``t = d / (v - h_i)`` and, with ``k = h_i / v``,

    rho = d k / (1 - k)            (the mirror point, valid while rho <= R,
                                    i.e. h_i <= r_m by eq. 2)

The cone's normal in the meridional (rho, Z) plane is n = (1, -1) / sqrt 2;
reflecting the incoming direction (h_i, v) gives
(h_i, v) - (h_i - v) (1, -1) = (v, h_i): the reflected ray travels outward
along (cos theta, sin theta) with slope dZ/dr = h_i / v = k. A point it meets
at range r has Z - tip_h = rho + (r - rho) k = k (d + r), which is eq. (1),
h_i = v (h - tip_h) / (d + r). ``tests/omnisim/test_sensor.py`` checks this against an
explicit vector reflection off the cone's surface normal.

The mirror is a perfect conductor: reflectance exactly 1 at every wavelength
and angle, so a sample inside the rim (h_i <= r_m) has weight 1 and a sample
outside it weight 0 (black). Neither the mirrors nor the camera bodies are
shapes of the Mitsuba scene: they cannot occlude the scene and the other
unit's mirror can never be hit, because

* cam2's reflected rays leave its cone at rho <= R, Z - 0 = rho <= R, and go
  outward and up with slope k <= R / (d + R) < 1, so while r <= R they stay
  below Z = R < s - d (cam1's camera centre; ``Rig.validate`` requires
  s > d + R): they pass under cam1's whole unit;
* cam1's rays leave at Z >= s and go up (k >= 0), while cam2's mirror lies at
  Z <= R < s.

Neither fan re-enters its own cone either (the rays leave the convex cone
outward).

Numerical departure from eq. (1): the sensor computes the ray in float32
from the continuous film position (exact for the pixel centres of power-of-
two image sizes). Tracing each pixel centre's float32 ray through Mitsuba
and putting the hit's (r, h) through eq. (1) gives h_i within 6.4e-5 px of
the pixel's own (max over a 512 x 512 image, a cylinder wall at 2.5 m around
the axis; ``tests/omnisim/test_sensor.py``) and within 1e-3 px max, 3e-5 px rms on
the default scene's walls, pillar and crate (``benchmarks/bench_render.py``):
far under the 0.02 px target, float32 round-off only.

Rig errors (``Unit.errors``, ``omniflow.geometry.rig_errors``): a tilted or offset
camera or mirror, or a cone of another apex angle, is traced through its actual
geometry instead (``set_errors``: the camera ray, the closed-form ray-cone
intersection and the vector reflection, the float64 ground truth's formulas run in
float32, within 1.4e-4 px of it: ``tests/omnisim/test_rig_errors.py``); a ray that
misses the mirror is black. An ideal unit keeps the rays above, bit for bit.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omniflow.geometry.rig import Unit
from omniflow.geometry.rig_errors import camera_ray, cone_reflect, traced_constants, traced_rays
from omnisim.optics import Optics, thin_lens_cone_ray

__all__ = [
    "DEFAULT_VARIANT",
    "PLUGIN_NAME",
    "MirrorRays",
    "apply_affine",
    "ensure_mitsuba",
    "make_sensor",
    "mirror_rays",
    "pixel_rays_world",
    "transform_rays",
]

#: Mitsuba variant used unless OMNISIM_VARIANT names another RGB JIT variant.
DEFAULT_VARIANT = "llvm_ad_rgb"
#: Name under which the analytic cone-mirror sensor is registered.
PLUGIN_NAME = "omnisim_cone_mirror"

_SENSOR_CLASS = None
_REGISTERED_FOR: str | None = None


# ----------------------------------------------------------------------------
# Exact geometry in float64 numpy (shared by the ground truth and the tests)
# ----------------------------------------------------------------------------
@dataclass(frozen=True)
class MirrorRays:
    """Reflected rays of image points, in the rig frame (float64).

    ``origin`` (..., 3) is the mirror point, ``direction`` (..., 3) the unit
    direction of the reflected ray, ``valid`` where the point lies inside the
    rim (h_i <= r_m), ``h_i`` and ``theta`` the polar image coordinates,
    ``rho`` the radius of the mirror point, metres.
    """

    origin: NDArray
    direction: NDArray
    valid: NDArray
    h_i: NDArray
    dx: NDArray
    dy: NDArray
    rho: NDArray

    @property
    def theta(self) -> NDArray:
        """Polar image angle atan2(y - y_c, x - x_c), radians."""
        return np.arctan2(self.dy, self.dx)


def mirror_rays(unit: Unit, x: ArrayLike, y: ArrayLike) -> MirrorRays:
    """Reflected ray of the continuous pixel (x, y) of ``unit`` (module docstring).

    Points outside the rim get ``valid = False``; their rays are still finite
    (rho is clipped at R) so they can be traced harmlessly. A unit with ``errors``
    is traced through its actual geometry (:func:`omniflow.geometry.rig_errors.traced_rays`;
    ``rho`` is then the hit's distance from the cone's axis, and a ray that misses the
    mirror is invalid).
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    dx = x - unit.x_c
    dy = y - unit.y_c
    h_i = np.hypot(dx, dy)
    if getattr(unit, "errors", None) is not None:
        origin, direction, valid, rho = traced_rays(unit, x, y)
        bad = ~np.all(np.isfinite(origin) & np.isfinite(direction), axis=-1)
        origin[bad], direction[bad] = (0.0, 0.0, unit.tip_h), (1.0, 0.0, 0.0)
        valid = valid & ~bad
        return MirrorRays(origin, direction, valid, h_i, dx, dy, np.where(bad, 0.0, rho))
    v = unit.v
    valid = h_i <= unit.r_m
    k = np.minimum(h_i, unit.r_m) / v  # k <= R / (d + R) < 1
    rho = unit.d * k / (1.0 - k)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(h_i > 0, dx / h_i, 1.0)
        s = np.where(h_i > 0, dy / h_i, 0.0)
    origin = np.stack([rho * c, rho * s, unit.tip_h + rho], axis=-1)
    norm = np.hypot(v, h_i)
    direction = np.stack([v * c / norm, v * s / norm, h_i / norm], axis=-1)
    return MirrorRays(
        origin=origin, direction=direction, valid=valid, h_i=h_i, dx=dx, dy=dy, rho=rho
    )


def transform_rays(pose: ArrayLike, origin: NDArray, direction: NDArray) -> tuple[NDArray, NDArray]:
    """Apply the (4, 4) world-from-rig ``pose`` to ray origins and directions (..., 3)."""
    m = np.asarray(pose, dtype=np.float64)
    return apply_affine(m, origin), apply_affine(m, direction, translate=False)


def apply_affine(m: NDArray, p: NDArray, *, translate: bool = True) -> NDArray:
    """``p @ m[:3, :3].T + m[:3, 3]`` for points (..., 3), column by column (no BLAS)."""
    p = np.asarray(p, dtype=np.float64)
    out = np.empty(p.shape, dtype=np.float64)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    for i in range(3):
        out[..., i] = m[i, 0] * x + m[i, 1] * y + m[i, 2] * z
        if translate:
            out[..., i] += m[i, 3]
    return out


def pixel_rays_world(
    unit: Unit, pose: ArrayLike, x: ArrayLike, y: ArrayLike
) -> tuple[NDArray, NDArray, MirrorRays]:
    """World-frame reflected rays (origin, direction) of pixels (x, y), float64."""
    rays = mirror_rays(unit, x, y)
    o, d = transform_rays(pose, rays.origin, rays.direction)
    return o, d, rays


# ----------------------------------------------------------------------------
# Mitsuba
# ----------------------------------------------------------------------------
def ensure_mitsuba(variant: str | None = None):
    """Import Mitsuba, set the variant, register the sensor; return ``mi``.

    ``variant`` (e.g. a scene's ``render.variant``) is set if given and
    different from the current one; otherwise the first call sets
    ``$OMNISIM_VARIANT`` or ``llvm_ad_rgb`` and later calls keep whatever
    the process uses. Only RGB JIT variants (``llvm_ad_rgb``,
    ``cuda_ad_rgb``) are accepted: the sensor is vectorised Python.
    """
    global _REGISTERED_FOR
    import mitsuba as mi

    current = mi.variant()
    wanted = variant or (None if current else os.environ.get("OMNISIM_VARIANT", DEFAULT_VARIANT))
    if wanted and not _jit_rgb(wanted):
        raise RuntimeError(
            f"Mitsuba variant {wanted!r}: omnisim needs an RGB JIT variant "
            "(llvm_ad_rgb or cuda_ad_rgb)"
        )
    if wanted and wanted != current:
        mi.set_variant(wanted)
        current = mi.variant()
    if not _jit_rgb(current):
        raise RuntimeError(
            f"omnisim needs an RGB JIT variant of Mitsuba (llvm_ad_rgb or cuda_ad_rgb); "
            f"the process already uses {current!r}"
        )
    if _REGISTERED_FOR != current:
        cls = _define_sensor_class(mi)
        mi.register_sensor(PLUGIN_NAME, lambda props: cls(props))
        _REGISTERED_FOR = current
    return mi


def _jit_rgb(variant: str) -> bool:
    return variant.endswith("_rgb") and variant.startswith(("llvm_", "cuda_"))


def _define_sensor_class(mi):
    """Define the sensor class for the current variant (mi.Sensor depends on it): its
    set-up here, its rays from :func:`_ray_methods`."""
    import drjit as dr

    rays = _ray_methods(mi, dr)

    class ConeMirrorSensor(mi.Sensor):
        """Pinhole camera + 90-degree cone mirror, traced analytically.

        Properties: ``d``, ``R``, ``x_c``, ``y_c``, ``r_m``, ``tip_h`` (as in
        ``omniflow.geometry.rig.Unit``), ``pose`` (16 floats, row-major world-from-rig
        matrix), plus the usual ``film`` and ``sampler``. Every number is held
        as an opaque JIT scalar, so changing the pose or the unit between
        renders re-uses the compiled kernels.
        """

        def __init__(self, props):
            super().__init__(props)
            self.set_unit(
                d=props.get("d"),
                R=props.get("R"),
                x_c=props.get("x_c"),
                y_c=props.get("y_c"),
                r_m=props.get("r_m"),
                tip_h=props.get("tip_h", 0.0),
            )
            pose = props.get("pose", None)
            self.set_pose(np.eye(4) if pose is None else np.asarray(list(pose)).reshape(4, 4))
            # A thin lens (omnisim.optics): the aperture sample is sample3.
            self._lens_radius = float(props.get("lens_radius", 0.0))
            self._focus = float(props.get("focus_distance", 1.0))
            self._ops = SimpleNamespace(sqrt=dr.sqrt, select=dr.select, maximum=dr.maximum)
            self._traced = None  # rig errors: the traced model's constants (set_errors)
            self.m_needs_sample_2 = True
            self.m_needs_sample_3 = self._lens_radius > 0.0

        def set_unit(self, *, d, R, x_c, y_c, r_m, tip_h):
            d, R, r_m = float(d), float(R), float(r_m)
            v = (d / R + 1.0) * r_m  # eq. (2)
            self._big_r = dr.opaque(mi.Float, R)
            self._k = [
                dr.opaque(mi.Float, val)
                for val in (v, 1.0 / v, d, float(x_c), float(y_c), r_m, float(tip_h))
            ]

        def set_errors(self, unit):
            """Trace the actual geometry of ``unit.errors`` (None or ideal: eq. 1's rays)."""
            if getattr(unit, "errors", None) is None:
                self._traced = None
                return
            g = traced_constants(unit)

            def op(a):
                return [dr.opaque(mi.Float, float(c)) for c in np.ravel(a)]

            self._traced = SimpleNamespace(
                C=op(g.C),
                Rc=[op(row) for row in g.Rc],
                T=op(g.T),
                a=op(g.a),
                cos2=op(g.cos2)[0],
                R=op(g.R)[0],
                v=op(g.v)[0],
            )

        def set_pose(self, pose):
            pose = np.asarray(pose, dtype=np.float64)
            self._m = [[dr.opaque(mi.Float, float(pose[i, j])) for j in range(4)] for i in range(3)]

        sample_ray = rays.sample_ray
        _traced_ray = rays.traced_ray
        _sample_lens_ray = rays.sample_lens_ray

        def sample_ray_differential(self, time, sample1, sample2, sample3, active=True):
            ray, weight = self.sample_ray(time, sample1, sample2, sample3, active)
            return mi.RayDifferential3f(ray), weight

        def to_string(self):
            return "ConeMirrorSensor[]"

    global _SENSOR_CLASS
    _SENSOR_CLASS = ConeMirrorSensor
    return ConeMirrorSensor


def _ray_methods(mi, dr) -> SimpleNamespace:
    """The sensor's ray methods for the current variant: the ideal pinhole rays of eq. (1)
    (``sample_ray``), through a thin lens (``sample_lens_ray``) and through the actual
    geometry of a unit with rig errors (``traced_ray``)."""

    def to_world(m, o, w, time):
        """The rig-frame ray (origin ``o``, direction ``w``) in the world by the pose ``m``."""
        ow = mi.Point3f(
            *[m[i][0] * o[0] + m[i][1] * o[1] + m[i][2] * o[2] + m[i][3] for i in range(3)]
        )
        dw = mi.Vector3f(*[m[i][0] * w[0] + m[i][1] * w[1] + m[i][2] * w[2] for i in range(3)])
        return mi.Ray3f(ow, dr.normalize(dw), time)

    def traced_ray(self, time, px, py, sample3, active):
        """The ray of film offset (px, py) through the actual geometry (rig errors);
        through an aperture point when there is a lens."""
        g = self._traced
        o, w = camera_ray(px, py, g)
        if self._lens_radius > 0.0:
            disk = mi.warp.square_to_uniform_disk_concentric(sample3) * self._lens_radius
            s = self._focus / g.v
            lens = (disk.x, disk.y, 0.0)
            cam = (px * s - disk.x, py * s - disk.y, self._focus)
            rc = g.Rc
            o = [g.C[i] + rc[i][0] * lens[0] + rc[i][1] * lens[1] for i in range(3)]
            w = [rc[i][0] * cam[0] + rc[i][1] * cam[1] + rc[i][2] * cam[2] for i in range(3)]
        q, r, ok, _ = cone_reflect(self._ops, o, w, g)
        ray = to_world(self._m, q, r, time)
        # Perfect conductor: reflectance 1 on the mirror, black where the ray misses it.
        return ray, mi.Spectrum(dr.select(active & ok, 1.0, 0.0))

    def sample_ray(self, time, sample1, sample2, sample3, active=True):
        v, inv_v, d, x_c, y_c, r_m, tip_h = self._k
        film = self.film()
        size = mi.ScalarVector2f(film.crop_size())
        offset = mi.ScalarVector2f(film.crop_offset())
        px = sample2.x * size.x + offset.x - x_c
        py = sample2.y * size.y + offset.y - y_c
        if self._traced is not None:
            return self._traced_ray(time, px, py, sample3, active)
        if self._lens_radius > 0.0:
            return self._sample_lens_ray(time, px, py, sample3, active)
        h_i = dr.sqrt(dr.fma(px, px, py * py))
        inside = h_i <= r_m
        has_dir = h_i > 0
        inv_h = dr.select(has_dir, dr.rcp(h_i), 0.0)
        c = dr.select(has_dir, px * inv_h, 1.0)
        s = dr.select(has_dir, py * inv_h, 0.0)
        k = dr.minimum(h_i, r_m) * inv_v
        rho = d * k / (1.0 - k)
        o = (rho * c, rho * s, tip_h + rho)  # rig frame
        inv_n = dr.rsqrt(dr.fma(v, v, h_i * h_i))
        w = (v * c * inv_n, v * s * inv_n, h_i * inv_n)
        ray = to_world(self._m, o, w, time)
        # Perfect conductor: reflectance 1 inside the rim, black outside.
        weight = dr.select(active & inside, 1.0, 0.0)
        return ray, mi.Spectrum(weight)

    def sample_lens_ray(self, time, px, py, sample3, active):
        """Thin lens: the film point's ray through an aperture point, off the cone.

        A ray that misses the mirror (beyond its rim) is black, as outside the rim.
        """
        v, _, d, _, _, _, tip_h = self._k
        disk = mi.warp.square_to_uniform_disk_concentric(sample3) * self._lens_radius
        q, w, ok = thin_lens_cone_ray(
            self._ops, px, py, disk.x, disk.y, v=v, d=d, focus=self._focus
        )
        o = (q[0], q[1], q[2] + tip_h)
        ray = to_world(self._m, o, w, time)
        weight = dr.select(active & ok & (q[2] <= self._big_r), 1.0, 0.0)
        return ray, mi.Spectrum(weight)

    return SimpleNamespace(
        sample_ray=sample_ray, traced_ray=traced_ray, sample_lens_ray=sample_lens_ray
    )


def sampler_dict(spp: int, kind: str | None = None) -> dict:
    """Sampler description: stratified when spp is a perfect square, else independent."""
    spp = int(spp)
    if kind is None:
        kind = "stratified" if round(spp**0.5) ** 2 == spp else "independent"
    out = {"type": kind, "sample_count": spp}
    if kind == "stratified":
        out["jitter"] = True
    return out


def make_sensor(
    unit: Unit,
    pose: ArrayLike,
    *,
    spp: int = 16,
    sampler: str | None = None,
    optics: Optics | None = None,
):
    """A Mitsuba sensor for ``unit`` at the world-from-rig ``pose``.

    ``optics`` with a finite f-number renders through a thin lens
    (:mod:`omnisim.optics`); None or a pinhole keeps the exact pinhole rays.

    The film is an RGB ``hdrfilm`` of the unit's size with a box filter
    (each pixel integrates exactly its own square [j, j+1) x [i, i+1)) and no
    sample border, so radiance at a pixel is the mean over its footprint.
    """
    mi = ensure_mitsuba()
    return _make_sensor(mi, unit, np.asarray(pose, dtype=np.float64), spp, sampler, optics)


def sensor_dict(unit: Unit, spp: int, sampler: str | None, optics: Optics | None) -> dict:
    """The Mitsuba description of the sensor of ``unit`` (film, sampler, lens)."""
    out = {
        "type": PLUGIN_NAME,
        "d": float(unit.d),
        "R": float(unit.R),
        "x_c": float(unit.x_c),
        "y_c": float(unit.y_c),
        "r_m": float(unit.r_m),
        "tip_h": float(unit.tip_h),
        "film": {
            "type": "hdrfilm",
            "width": int(unit.width),
            "height": int(unit.height),
            "pixel_format": "rgb",
            "component_format": "float32",
            "rfilter": {"type": "box"},
            "sample_border": False,
        },
        "sampler": sampler_dict(spp, sampler),
    }
    if optics is not None and not optics.pinhole:
        out["lens_radius"] = optics.aperture_radius
        out["focus_distance"] = float(optics.focus_distance)
    return out


def _make_sensor(mi, unit: Unit, pose: NDArray, spp: int, sampler: str | None, optics):
    sensor = mi.load_dict(sensor_dict(unit, spp, sampler, optics))
    sensor.set_pose(pose)
    sensor.set_errors(unit)
    return sensor
