"""Find the mirror's rim in an omni image and build a Unit from it (eq. 2).

The rim circle (x_c, y_c, r_m) gives the image of the axis and, with the
mirror's d and R, the image distance v = (d / R + 1) r_m (eq. 2).

A real rig's image has a lit, textured surround outside the mirror, so the
rim is not the only edge, and its contrast changes sign around the circle
(the surround is brighter here, darker there). The search therefore looks for
an edge that is *coherent along a circle*: the image is resampled on polar
coordinates about a candidate centre (``cv2.remap``), smoothed along the
circle (``scipy.ndimage.gaussian_filter1d`` in theta, which averages the
surround's texture away but not an edge that follows the circle), and
differentiated along the radius. Steps:

1. coarse centre and radius, coarse to fine: on an image pyramid
   (``cv2.pyrDown``) whose coarsest level is 41-80 px, every candidate
   centre of a 2 px grid over the middle half of the image is scored by how
   far the peak of its angle-averaged radial-edge profile rises above the
   profile's median (a textured surround raises the whole profile, the rim
   adds a peak); all candidates go through one ``cv2.remap``. The best few
   distinct centres are each refined on a +-2 px grid at every finer level,
   and the best score at full resolution wins;
2. sub-pixel edge points: on ``rays`` radial lines about the coarse centre,
   samples every 0.1 px within ``search`` px of the coarse radius (cubic
   ``cv2.remap``), smoothed along the circle by ``arc_sigma`` px of arc, a
   Gaussian derivative along the ray (``sigma``), and the strongest edge
   located to a fraction of a sample (a parabola through the peak);
3. circle fit: ``skimage.measure.ransac`` with ``CircleModel`` rejects the
   rays where the rim has no contrast, then a least-squares circle on the
   inliers; steps 2-3 run again about the refined centre.

Where the rim is known to a few pixels (``near``: a traced model's predicted
rim, :func:`omniflow.geometry.registration.check_rim`), step 1 is skipped. It is
the step that can pick a wrong circle: on a test card whose rim nearly touches
the image border, the coarsest level scores the rim no higher than circles
made of the card's own edges (docs/decisions/registration.md, "The rim check").

Coordinates follow :mod:`omniflow.conventions` (pixel centre at j + 0.5,
i + 0.5); OpenCV and scipy index pixel centres at j, i, converted here.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage
from skimage.measure import CircleModel, ransac

from omniflow.geometry.rig import Unit
from omniflow.io.imageio import to_grey

__all__ = ["RimCircle", "RimError", "calibrate_unit", "find_rim"]


class RimError(ValueError):
    """No mirror rim could be found in the image."""


@dataclass(frozen=True)
class RimCircle:
    """The rim circle in continuous pixel coordinates.

    Attributes
    ----------
    x_c, y_c : float
        Image of the axis (circle centre), pixels.
    r_m : float
        Rim radius, pixels.
    residual_px : float
        RMS distance of the inlier edge points from the circle, pixels.
    inlier_fraction : float
        Fraction of the radial edge points kept by RANSAC.
    """

    x_c: float
    y_c: float
    r_m: float
    residual_px: float
    inlier_fraction: float = 1.0


def _grey(image: ArrayLike) -> NDArray:
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = to_grey(img)
    if img.ndim != 2:
        raise RimError(
            f"image: expected a grey (H, W) or colour (H, W, 3) array, got shape {img.shape}"
        )
    img = img.astype(np.float64)
    if min(img.shape) < 16:
        raise RimError(f"image: {img.shape[1]}x{img.shape[0]} is too small; expected >= 16 px")
    if not np.all(np.isfinite(img)):
        raise RimError("image: contains NaN or inf values")
    if np.ptp(img) <= 0:
        raise RimError("image is blank (constant): there is no rim to find")
    return img


def _polar(img: NDArray, cx: NDArray, cy: NDArray, radii: NDArray, n_theta: int) -> NDArray:
    """Samples of ``img`` on polar grids, shape (centres, n_theta, radii); NaN off the image.

    ``cx``, ``cy`` are continuous centres (pixel centre at j + 0.5), one per grid.
    """
    ang = np.linspace(-np.pi, np.pi, n_theta, endpoint=False)
    ux, uy = np.cos(ang)[:, None], np.sin(ang)[:, None]
    mx = (cx[:, None, None] - 0.5 + radii * ux).astype(np.float32)
    my = (cy[:, None, None] - 0.5 + radii * uy).astype(np.float32)
    shape = mx.shape
    mx, my = mx.reshape(-1, shape[-1]), my.reshape(-1, shape[-1])
    out = np.empty(mx.shape, np.float32)
    for lo in range(0, mx.shape[0], 32000):  # cv2.remap maps are at most 32767 rows
        sl = slice(lo, lo + 32000)
        out[sl] = cv2.remap(
            img, mx[sl], my[sl], cv2.INTER_CUBIC, borderMode=cv2.BORDER_CONSTANT,
            borderValue=float("nan"),
        )  # fmt: skip
    return out.reshape(shape)


def _radial_edges(polar: NDArray, *, arc_samples: float, sigma_samples: float) -> NDArray:
    """|d/dr| of the polar samples smoothed along the circle; 0 where off the image.

    Smoothing along theta (axis -2, periodic) averages texture away but keeps
    an edge that follows the circle. NaN samples (off the image) are left out
    of the average (normalised convolution).
    """
    ok = np.isfinite(polar)
    vals = np.where(ok, polar, 0.0)
    if arc_samples > 0:
        vals = ndimage.gaussian_filter1d(vals, arc_samples, axis=-2, mode="wrap")
        weight = ndimage.gaussian_filter1d(ok.astype(np.float32), arc_samples, axis=-2, mode="wrap")
        vals = vals / np.maximum(weight, 1e-6)
    deriv = np.abs(ndimage.gaussian_filter1d(vals, sigma_samples, axis=-1, order=1))
    # The derivative steps where the samples leave the image: zero it within 3 samples.
    reach = np.ones((1,) * (deriv.ndim - 1) + (7,), bool)
    bad = ndimage.binary_dilation(~ok, structure=reach)
    return np.where(bad, 0.0, deriv)


def _circle_scores(level: NDArray, gx: NDArray, gy: NDArray, radii: NDArray):
    """Per candidate centre: (score, best radius) of the angle-averaged radial-edge profile."""
    n_theta = 128
    arc = 4.0 * n_theta / (2 * np.pi * max(radii[0], 1.0))  # 4 px of arc, in samples
    edges = _radial_edges(_polar(level, gx, gy, radii, n_theta), arc_samples=arc, sigma_samples=2.0)
    profile = edges.mean(axis=1)  # (centres, radii): angle-averaged edge strength
    # A textured surround raises the whole profile; the rim is a peak above it.
    score = profile.max(axis=1) - np.median(profile, axis=1)
    return score, radii[np.argmax(profile, axis=1)]


def _coarse_circle(
    img: NDArray, r_min: float, r_max: float, candidates: int
) -> tuple[float, float, float]:
    """Centre and radius to about a pixel: the circle-coherent edge, coarse to fine (step 1).

    The ``candidates`` best distinct centres of the coarsest level are each
    followed to full resolution, where the best score wins.
    """
    levels = [img.astype(np.float32)]
    while min(levels[-1].shape) > 80:  # the coarsest level is 41-80 px
        levels.append(cv2.pyrDown(levels[-1]))
    h, w = img.shape
    top = len(levels) - 1
    f = 2.0**top
    xs = np.arange(0.25 * w / f, 0.75 * w / f + 1e-9, 2.0)
    ys = np.arange(0.25 * h / f, 0.75 * h / f + 1e-9, 2.0)
    gx, gy = (g.ravel() for g in np.meshgrid(xs, ys))
    score, radius = _circle_scores(levels[top], gx, gy, np.arange(r_min / f, r_max / f + 1.0, 0.5))
    starts: list[tuple[float, float, float]] = []
    for k in np.argsort(score)[::-1]:  # the best, at least 3 px apart
        if all(np.hypot(gx[k] - x, gy[k] - y) >= 3.0 for x, y, _ in starts):
            starts.append((gx[k] * f, gy[k] * f, radius[k] * f))
        if len(starts) == candidates:
            break
    best = None
    for cx, cy, r0 in starts:
        s = -np.inf
        for k in range(top - 1, -1, -1):  # +-2 px, +-6 px radius about it at each finer level
            f = 2.0**k
            xs, ys = cx / f + np.arange(-2.0, 2.5, 1.0), cy / f + np.arange(-2.0, 2.5, 1.0)
            gx, gy = (g.ravel() for g in np.meshgrid(xs, ys))
            radii = r0 / f + np.arange(-6.0, 6.25, 0.5)
            score, radius = _circle_scores(levels[k], gx, gy, radii)
            i = int(np.argmax(score))
            cx, cy, r0, s = gx[i] * f, gy[i] * f, radius[i] * f, score[i]
        if best is None or s > best[3]:
            best = (cx, cy, r0, s)
    return float(best[0]), float(best[1]), float(best[2])


def _edge_points(img, x_c, y_c, r0, *, rays, search, sigma, arc_sigma):
    """Sub-pixel rim points on ``rays`` radial lines about (x_c, y_c) (step 2)."""
    step = 0.1
    radii = np.arange(r0 - search, r0 + search + step / 2, step)
    polar = _polar(img, np.array([x_c]), np.array([y_c]), radii, rays)[0]
    inside = np.all(np.isfinite(polar), axis=1)
    if inside.sum() < 8:
        raise RimError(
            f"the circle found (centre ({x_c:.1f}, {y_c:.1f}), radius {r0:.1f}) "
            "lies outside the image"
        )
    arc = arc_sigma * rays / (2 * np.pi * r0)
    deriv = _radial_edges(polar, arc_samples=arc, sigma_samples=sigma / step)
    k = np.clip(np.argmax(deriv[:, 1:-1], axis=1) + 1, 1, deriv.shape[1] - 2)
    rows = np.arange(rays)
    a, b, c = deriv[rows, k - 1], deriv[rows, k], deriv[rows, k + 1]
    den = a - 2 * b + c
    frac = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, 1.0), 0.0)  # parabola vertex
    r = radii[k] + np.clip(frac, -0.5, 0.5) * step
    ang = np.linspace(-np.pi, np.pi, rays, endpoint=False)
    keep = inside & (b > 0)
    pts = np.column_stack([x_c + r * np.cos(ang), y_c + r * np.sin(ang)])
    return pts[keep]


def _fit_circle(points: NDArray):
    if hasattr(CircleModel, "from_estimate"):  # scikit-image >= 0.26
        model = CircleModel.from_estimate(points)
        return model if model else None
    model = CircleModel()
    return model if model.estimate(points) else None


def _circle_params(model) -> tuple[float, float, float]:
    if hasattr(model, "center"):  # scikit-image >= 0.26
        return float(model.center[0]), float(model.center[1]), float(model.radius)
    x, y, r = model.params
    return float(x), float(y), float(r)


def find_rim(
    image: ArrayLike,
    *,
    r_min: float | None = None,
    r_max: float | None = None,
    rays: int = 720,
    search: float = 3.0,
    sigma: float = 0.7,
    arc_sigma: float = 6.0,
    residual_threshold: float = 0.2,
    min_inliers: float = 0.5,
    candidates: int = 3,
    near: tuple[float, float, float] | None = None,
    seed: int = 0,
) -> RimCircle:
    """Locate the mirror's rim circle to sub-pixel accuracy.

    Parameters
    ----------
    image : array_like, shape (H, W) or (H, W, 3)
        Omni image; colour is reduced to luminance. The surround outside the
        mirror may be lit and textured.
    r_min, r_max : float, optional
        Radius search range, pixels; default 0.25 and 0.55 of min(H, W). The
        centre is searched in the middle half of the image.
    rays : int
        Radial lines sampled for edge points.
    search : float
        Half-width, pixels, of the band about the coarse radius searched for the edge.
    sigma : float
        Gaussian derivative scale along the rays, pixels.
    arc_sigma : float
        Gaussian smoothing along the circle, pixels of arc: averages the
        texture of the surround and the scene away from the rim's edge.
    residual_threshold : float
        RANSAC inlier distance, pixels.
    min_inliers : float
        Smallest fraction of the radial lines whose edge points must agree on
        the circle.
    candidates : int
        Distinct centres of the coarsest level followed to full resolution.
    near : (x_c, y_c, r_m), optional
        A circle the rim lies within ``search`` px of (pixels): the coarse
        search (step 1) is skipped, and a circle fitted more than ``search``
        px from it is refused. ``r_min``, ``r_max`` are then not used.
    seed : int
        RANSAC seed (the result is deterministic).

    Returns
    -------
    RimCircle

    Raises
    ------
    RimError
        Blank image, no circle in the radius range, or too few consistent edge points.
    """
    img = _grey(image).astype(np.float32)
    size = min(img.shape)
    if near is not None:
        x_c, y_c, r_m = (float(v) for v in near)
        if not (np.isfinite([x_c, y_c, r_m]).all() and r_m > search):
            raise RimError(f"near = {near}: expected a finite circle of radius > {search} px")
        r_min, r_max = r_m - search, r_m + search
        start = (x_c, y_c, r_m)
    else:
        r_min = 0.25 * size if r_min is None else float(r_min)
        r_max = 0.55 * size if r_max is None else float(r_max)
        if not (0 < r_min < r_max):
            raise RimError(f"r_min = {r_min}, r_max = {r_max}: expected 0 < r_min < r_max")
        x_c, y_c, r_m = _coarse_circle(img, r_min, r_max, candidates)
    if near is None and not (r_min - 1 <= r_m <= r_max + 1):
        raise RimError(
            f"no rim circle with a radius in [{r_min:.1f}, {r_max:.1f}] px found "
            f"(the strongest circular edge has {r_m:.1f} px): is the mirror's rim in the image?"
        )
    for band in (search, search, 1.0):  # about the refined circle again; last: a narrow band
        pts = _edge_points(
            img, x_c, y_c, r_m, rays=rays, search=band, sigma=sigma, arc_sigma=arc_sigma
        )
        if len(pts) < 8:
            raise RimError(
                f"no rim edge found near radius {r_m:.1f} px about ({x_c:.1f}, {y_c:.1f})"
            )
        model, inl = ransac(
            pts,
            CircleModel,
            min_samples=3,
            residual_threshold=residual_threshold,
            max_trials=100,
            rng=seed,
        )
        if model is None or inl is None or inl.sum() < max(8, min_inliers * len(pts)):
            raise RimError(
                f"no consistent rim circle: only {0 if inl is None else int(inl.sum())} of "
                f"{len(pts)} radial lines agree near radius {r_m:.1f} px about "
                f"({x_c:.1f}, {y_c:.1f})"
            )
        fit = _fit_circle(pts[inl])
        if fit is None:
            raise RimError("circle fit to the rim's edge points failed")
        x_c, y_c, r_m = _circle_params(fit)
    res = np.hypot(pts[inl, 0] - x_c, pts[inl, 1] - y_c) - r_m
    if near is not None and np.hypot(x_c - start[0], y_c - start[1]) + abs(r_m - start[2]) > search:
        raise RimError(
            f"the rim circle found (centre ({x_c:.1f}, {y_c:.1f}), radius {r_m:.1f} px) lies "
            f"more than {search} px from the expected ({start[0]:.1f}, {start[1]:.1f}), "
            f"{start[2]:.1f} px"
        )
    if near is None and not (r_min <= r_m <= r_max):
        raise RimError(
            f"no rim circle with a radius in [{r_min:.1f}, {r_max:.1f}] px found "
            f"(the circle fitted has {r_m:.1f} px): is the mirror's rim in the image?"
        )
    return RimCircle(
        x_c=x_c,
        y_c=y_c,
        r_m=r_m,
        residual_px=float(np.sqrt(np.mean(res**2))),
        inlier_fraction=float(inl.mean()),
    )


def calibrate_unit(
    image: ArrayLike, *, d: float, R: float, tip_h: float = 0.0, name: str = "", **rim_kw
) -> Unit:
    """A :class:`~omniflow.geometry.rig.Unit` from an omni image and the mirror's d and R.

    The rim gives (x_c, y_c, r_m); v follows from eq. (2) through ``Unit.v``.
    Extra keyword arguments go to :func:`find_rim`.
    """
    img = np.asarray(image)
    rim = find_rim(img, **rim_kw)
    unit = Unit(
        d=float(d),
        R=float(R),
        x_c=rim.x_c,
        y_c=rim.y_c,
        r_m=rim.r_m,
        width=int(img.shape[1]),
        height=int(img.shape[0]),
        tip_h=float(tip_h),
        name=name,
    )
    unit.validate(where="calibrate_unit")
    return unit
