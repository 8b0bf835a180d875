"""Registration of one unit from an image of the test card (paper section 2.1).

The paper leaves registration to "a simple test card registration method": circles
about the axis image as circles and lines coplanar with it as radial lines only when the
unit is aligned. This module fits the traced model of a misaligned unit
(:mod:`omniflow.geometry.rig_errors`) to the card's edges (:mod:`omniflow.geometry.test_card`)
with ``scipy.optimize.least_squares``.

Parameters (:data:`PARAMS`, the keys of ``[rig.errors.camN]``): ``mirror_tilt`` [a, b]
(deg), ``mirror_offset`` [x, y] (m; its z is held at 0) and ``cone_angle`` (deg), and
with ``camera_tilt=True`` the camera's tilt [a, b] (deg). The other keys are held ideal:
what a card at one radius can tell apart is measured in docs/decisions/registration.md
(``python3 -m benchmarks.registration_identifiability``): ``camera_offset`` moves the
card's image like the mirror's offset and tilt (within 5 %), ``camera_tilt`` like them
within 12 % (so it is a seventh parameter when the camera may be tilted), and
``mirror_offset`` z like the cone angle (within 4 %) at one card radius. The camera's
intrinsics (v of eq. 2 and the principal point x_c, y_c) are the rig file's: a camera
tilt moves the image as a principal point does, and a cone angle or axial offset as v.

Features: the card's ring edges, sampled along the image radius, and its sector edges,
sampled across it, each located to a fraction of a pixel on a 1-D profile (cubic
interpolation, derivative of a Gaussian, the extremum of the expected sign, a parabola
through it), away from the checks' corners. Each feature pixel's traced ray is met with
the card's tube; the residual is the hit's height minus the ring's (scaled to pixels by
eq. 1's v / (d + r)) or its azimuth minus the sector edge's (times h_i, pixels). The
features are found again about the fitted model, with a narrower search, ``rounds`` times.
The rim circle (:func:`omniflow.geometry.calibration.find_rim`) can be added: the traced
model's rim (the mirror's edge seen directly) against the circle found; without a card
it is all there is (tilts held at 0, see the decision page for what that recovers).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage, optimize

from omniflow.conventions import wrap_angle
from omniflow.geometry.rig_errors import (
    UnitErrors,
    traced_constants,
    traced_project,
    traced_rays,
)
from omniflow.geometry.test_card import TestCard

__all__ = [
    "PARAMS",
    "CardFeatures",
    "Registration",
    "card_features",
    "check_rim",
    "errors_of_params",
    "predicted_rim",
    "register_unit",
    "rim_points",
    "rim_residual_rms",
]

#: The fitted parameters, in the order of the vector: name, unit of the scaled value.
PARAMS = (
    ("mirror_tilt[0]", "deg"),
    ("mirror_tilt[1]", "deg"),
    ("mirror_offset[0]", "mm"),
    ("mirror_offset[1]", "mm"),
    ("cone_angle - 90", "deg"),
)
#: The two more with ``camera_tilt=True``.
CAMERA_TILT = (("camera_tilt[0]", "deg"), ("camera_tilt[1]", "deg"))
#: Smallest image radius of a feature, px: the sectors are 2 pi h_i / sectors wide.
MIN_FEATURE_H_PX = 25.0
#: Half-width (px) of the band about the fitted model's rim searched for the image's rim
#: (:func:`check_rim`): find_rim's default; the fitted rim lies 0.02-0.06 px from it.
RIM_SEARCH_PX = 3.0
#: Profile sampling step along a search line, px.
PROFILE_STEP = 0.05
#: Gaussian derivative scale of the profile, px.
PROFILE_SIGMA = 0.8


def errors_of_params(p: NDArray) -> UnitErrors:
    """The :class:`UnitErrors` of a parameter vector (deg, deg, mm, mm, deg from 90, and
    with 7 entries the camera tilt, deg, deg: :data:`CAMERA_TILT`)."""
    p = np.asarray(p, dtype=np.float64)
    cam = (float(p[5]), float(p[6])) if len(p) > 5 else (0.0, 0.0)
    return UnitErrors(
        mirror_tilt=(float(p[0]), float(p[1])),
        mirror_offset=(float(p[2]) * 1e-3, float(p[3]) * 1e-3, 0.0),
        cone_angle=90.0 + float(p[4]),
        camera_tilt=cam,
    )


def params_of_errors(e: UnitErrors) -> NDArray:
    """The parameter vector of ``e`` (its held keys dropped)."""
    return np.array(
        [
            e.mirror_tilt[0],
            e.mirror_tilt[1],
            e.mirror_offset[0] * 1e3,
            e.mirror_offset[1] * 1e3,
            e.cone_angle - 90.0,
            *e.camera_tilt,
        ]
    )


@dataclass(frozen=True)
class CardFeatures:
    """Edge pixels of the card: ``x``, ``y`` (px), ``kind`` (0 ring, 1 sector edge) and
    ``target`` (the ring's z in the rig frame, m, or the sector edge's azimuth, rad)."""

    x: NDArray
    y: NDArray
    kind: NDArray
    target: NDArray

    def __len__(self) -> int:
        return len(self.x)


@dataclass(frozen=True)
class Registration:
    """The fit of one unit: its errors, residual rms (px), features used, the rim found."""

    errors: UnitErrors
    rms_px: float
    n_rings: int
    n_lines: int
    rim: tuple[float, float, float] | None = None
    rim_rms_px: float | None = None
    params: NDArray = field(default=None, repr=False)


def _sample(img: NDArray, x: NDArray, y: NDArray) -> NDArray:
    """Cubic interpolation at continuous pixel coordinates (centres at j + 0.5)."""
    return ndimage.map_coordinates(img, [y - 0.5, x - 0.5], order=3, mode="nearest")


def _edges_along(img, x0, y0, ux, uy, sign, half):
    """Sub-pixel edge offsets along (ux, uy) from (x0, y0), within +-half px; NaN if none.

    ``sign`` +1 where the image should brighten along the direction, -1 where it darkens.
    """
    t = np.arange(-half - 3 * PROFILE_SIGMA, half + 3 * PROFILE_SIGMA + 1e-9, PROFILE_STEP)
    xs = x0[:, None] + t[None, :] * ux[:, None]
    ys = y0[:, None] + t[None, :] * uy[:, None]
    prof = _sample(img, xs.ravel(), ys.ravel()).reshape(xs.shape)
    der = ndimage.gaussian_filter1d(prof, PROFILE_SIGMA / PROFILE_STEP, axis=1, order=1)
    der = der * sign[:, None] / PROFILE_STEP  # per px
    inside = np.abs(t) <= half
    der_in = np.where(inside[None, :], der, -np.inf)
    k = np.argmax(der_in, axis=1)
    rows = np.arange(len(k))
    ok = (k > 0) & (k < len(t) - 1) & inside[np.clip(k - 1, 0, None)] & inside[
        np.clip(k + 1, None, len(t) - 1)]  # fmt: skip
    a, b, c = der[rows, k - 1], der[rows, k], der[rows, np.minimum(k + 1, len(t) - 1)]
    den = a - 2 * b + c
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(den < 0, 0.5 * (a - c) / den, 0.0)
    contrast = np.percentile(np.abs(prof), 95, axis=1) - np.percentile(np.abs(prof), 5, axis=1)
    ok &= b > 0.3 * contrast / (2.5 * PROFILE_SIGMA)  # a step's peak: contrast / (2.5 sigma)
    return np.where(ok, t[k] + frac * PROFILE_STEP, np.nan)


def card_features(
    image: NDArray, unit, card: TestCard, errors: UnitErrors, *, half: float = 3.0,
    per_sector: int = 6, per_ring: int = 3,
) -> CardFeatures:  # fmt: skip
    """Edge pixels of ``card`` in ``image`` of ``unit``, searched about the pixels the
    traced model with ``errors`` predicts, within ``half`` px along the search line.

    Ring edges: ``per_sector`` azimuths per sector (its middle 70 %), searched along the
    image radius; sector edges: ``per_ring`` heights per ring (its middle 60 %),
    searched across it. Only edges wholly in the mirror (h_i within 3 px of the rim) and
    outside :data:`MIN_FEATURE_H_PX`.
    """
    img = np.asarray(image, dtype=np.float64)
    r_c = card.radius
    hmax = (unit.d + r_c) * unit.R / (unit.d + unit.R)  # eq. (1): the rim's h at r
    cx, cy = card.center[0], card.center[1]
    out = []
    # ring edges
    zk = card.ring_edges()
    zk = zk[(zk - unit.tip_h > 0) & (zk - unit.tip_h < hmax)]
    f = np.linspace(0.15, 0.85, per_sector)
    th = (card.sector_edges()[:, None] + f[None, :] * 2 * np.pi / card.sectors).ravel()
    z_g, th_g = np.meshgrid(zk, th, indexing="ij")
    out.append(_search(img, unit, card, errors, cx + r_c * np.cos(th_g), cy + r_c * np.sin(th_g),
                       z_g, 0, z_g, th_g, half))  # fmt: skip
    # sector edges
    zc = card.ring_edges()
    mids = np.concatenate([zc[:-1, None] + np.linspace(0.2, 0.8, per_ring)[None, :]
                           * card.ring_spacing]).ravel()  # fmt: skip
    mids = mids[(mids - unit.tip_h > 0) & (mids - unit.tip_h < hmax)]
    z_g, th_g = np.meshgrid(mids, card.sector_edges(), indexing="ij")
    out.append(_search(img, unit, card, errors, cx + r_c * np.cos(th_g), cy + r_c * np.sin(th_g),
                       z_g, 1, th_g, th_g, half))  # fmt: skip
    return CardFeatures(*(np.concatenate([o[i] for o in out]) for i in range(4)))


def _search(img, unit, card, errors, px, py, pz, kind, target, theta, half):
    q = np.stack([px.ravel(), py.ravel(), pz.ravel()], axis=-1)
    x0, y0, seen = traced_project(unit, q, errors)
    th, z = theta.ravel(), pz.ravel()
    dx, dy = x0 - unit.x_c, y0 - unit.y_c
    h_i = np.hypot(dx, dy)
    rim = unit.r_m - 3.0 - half
    keep = seen & (h_i > MIN_FEATURE_H_PX) & (h_i < rim)
    x0, y0, dx, dy, h_i, th, z = (a[keep] for a in (x0, y0, dx, dy, h_i, th, z))
    tgt = target.ravel()[keep]
    eps_z, eps_t = 1e-3 * card.ring_spacing, 1e-3 / card.sectors
    if kind == 0:  # along the radius: brighter outward when the check above is light
        ux, uy = dx / h_i, dy / h_i
        sign = np.where(card.dark(th, z + eps_z), -1.0, 1.0)
    else:  # across: towards larger theta (image angle grows from x to y)
        ux, uy = -dy / h_i, dx / h_i
        sign = np.where(card.dark(th + eps_t, z), -1.0, 1.0)
    # a sector edge's search must not reach the neighbouring edge: keep half under a third
    # of the local spacing (2 pi h_i / sectors across, the rings' image spacing along)
    t = _edges_along(img, x0, y0, ux, uy, sign, half)
    ok = np.isfinite(t)
    xe, ye = x0 + t * ux, y0 + t * uy
    return xe[ok], ye[ok], np.full(int(ok.sum()), kind), tgt[ok]


def _card_hits(unit, errors: UnitErrors, feats: CardFeatures, card: TestCard):
    """Azimuth (rad) and z (rig frame) where each feature pixel's traced ray meets the
    card's tube (NaN where it does not)."""
    o, w, ok, _ = traced_rays(unit, feats.x, feats.y, errors)
    c = np.array(card.center)
    p = o[:, :2] - c[:2]
    a = (w[:, :2] ** 2).sum(-1)
    b = (p * w[:, :2]).sum(-1)
    cc = (p**2).sum(-1) - card.radius**2
    with np.errstate(invalid="ignore"):
        t = (-b + np.sqrt(b * b - a * cc)) / a
    hit = o + t[:, None] * w
    theta = np.arctan2(hit[:, 1] - c[1], hit[:, 0] - c[0])
    return np.where(ok, theta, np.nan), np.where(ok, hit[:, 2], np.nan)


def _card_residuals(unit, errors, feats, card) -> NDArray:
    """Pixels: ring features' (z - z_k) v / (d + r), sector features' (theta - theta_j) h_i."""
    theta, z = _card_hits(unit, errors, feats, card)
    ring = feats.kind == 0
    h_i = np.hypot(feats.x - unit.x_c, feats.y - unit.y_c)
    res = np.where(
        ring,
        (z - feats.target) * unit.v / (unit.d + card.radius),  # eq. (1)
        wrap_angle(theta - feats.target) * h_i,
    )
    return np.nan_to_num(res, nan=10.0)  # a ray off the mirror: a large, finite penalty


def rim_points(unit, errors: UnitErrors, n: int = 90) -> tuple[NDArray, NDArray]:
    """Pixels (x, y) of the mirror's rim seen directly by the camera (the traced model:
    the circle of radius R about the cone's axis, R / tan(half-angle) above its tip)."""
    g = traced_constants(unit, errors)
    a = g.a
    e1 = np.cross(a, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    phi = np.linspace(0, 2 * np.pi, n, endpoint=False)
    half = math.radians(errors.cone_angle) / 2
    p = g.T + a * (g.R / math.tan(half)) + g.R * (np.cos(phi)[:, None] * e1
                                                 + np.sin(phi)[:, None] * e2)  # fmt: skip
    dc = (p - g.C) @ g.Rc  # camera frame: Rc^T (p - C)
    return g.x_c + g.v * dc[:, 0] / dc[:, 2], g.y_c + g.v * dc[:, 1] / dc[:, 2]


def predicted_rim(unit, errors: UnitErrors) -> tuple[float, float, float]:
    """The circle (x_c, y_c, r_m, px) through the traced model's rim (:func:`rim_points`).

    A least-squares (algebraic) circle: a tilted or offset mirror's rim still images as a
    circle, off the nominal centre (0.0005 px from one at a 0.5 deg tilt, 256 px).
    """
    x, y = rim_points(unit, errors, n=360)
    a = np.column_stack([x, y, np.ones_like(x)])
    (cx2, cy2, c), *_ = np.linalg.lstsq(a, x**2 + y**2, rcond=None)
    xc, yc = cx2 / 2, cy2 / 2
    return float(xc), float(yc), float(np.sqrt(c + xc**2 + yc**2))


def check_rim(image: NDArray, unit, errors: UnitErrors, *, search: float = RIM_SEARCH_PX):
    """The rim found in ``image`` within ``search`` px of the model's (:func:`predicted_rim`).

    Returns (x_c, y_c, r_m) of the circle found and the rms distance (px) of the model's
    rim from it. The rim is searched about the fitted model's prediction, not over the
    image: there the card's own ring edges can outscore it (docs/decisions/registration.md,
    "The rim check"). Raises :class:`~omniflow.geometry.calibration.RimError`.
    """
    from omniflow.geometry.calibration import find_rim

    c = find_rim(image, near=predicted_rim(unit, errors), search=search)
    rim = (c.x_c, c.y_c, c.r_m)
    return rim, rim_residual_rms(unit, errors, rim)


def _rim_residuals(unit, errors, rim) -> NDArray:
    x, y = rim_points(unit, errors)
    return np.hypot(x - rim[0], y - rim[1]) - rim[2]


def rim_residual_rms(unit, errors: UnitErrors, rim: tuple[float, float, float]) -> float:
    """Rms distance (px) of the model's rim (:func:`rim_points`) from a circle found."""
    return float(np.sqrt(np.mean(_rim_residuals(unit, errors, rim) ** 2)))


def register_unit(
    image: NDArray, unit, card: TestCard | None, *, rim: tuple[float, float, float] | None = None,
    rounds: int = 3, free: tuple[bool, ...] | None = None, camera_tilt: bool = False,
) -> Registration:  # fmt: skip
    """Fit the errors of ``unit`` (its ideal intrinsics) to ``card`` seen in ``image``.

    ``rim`` (x_c, y_c, r_m of the circle found, px) adds the rim's residuals; with
    ``card`` None only the rim is fitted, and only the parameters it constrains
    (``free``: default mirror_offset x, y and cone_angle, tilts held at 0).
    """
    if card is None and rim is None:
        raise ValueError("nothing to fit: no card and no rim")
    if free is None:
        free = (True,) * 5 if card is not None else (False, False, True, True, True)
        free += (camera_tilt, camera_tilt)
    idx = np.flatnonzero(free)
    p = np.zeros(len(free))
    feats = None
    halves = (4.0, 2.0, 1.5, 1.5, 1.5)
    for k in range(rounds if card is not None else 1):
        if card is not None:
            feats = card_features(image, unit, card, errors_of_params(p), half=halves[min(k, 4)])
            if len(feats) < 20:
                raise ValueError(f"only {len(feats)} card edges found; expected the card in view")

        def fun(q, feats=feats):
            pp = p.copy()
            pp[idx] = q
            e = errors_of_params(pp)
            parts = []
            if feats is not None:
                parts.append(_card_residuals(unit, e, feats, card))
            if rim is not None:
                parts.append(_rim_residuals(unit, e, rim))
            return np.concatenate(parts)

        sol = optimize.least_squares(fun, p[idx], x_scale=1.0, loss="soft_l1", f_scale=0.3,
                                     xtol=1e-10, ftol=1e-12)  # fmt: skip
        p[idx] = sol.x
    e = errors_of_params(p)
    n_r = n_l = 0
    rms = float("nan")
    if feats is not None:
        res = _card_residuals(unit, e, feats, card)
        rms = float(np.sqrt(np.mean(res**2)))
        n_r, n_l = int((feats.kind == 0).sum()), int((feats.kind == 1).sum())
    rim_rms = None if rim is None else float(np.sqrt(np.mean(_rim_residuals(unit, e, rim) ** 2)))
    return Registration(e, rms, n_r, n_l, rim, rim_rms, params=p)
