"""Find the mirror's rim in an omni image and build a Unit from it (eq. 2).

The rim circle (x_c, y_c, r_m) gives the image of the axis and, with the
mirror's d and R, the image distance v = (d / R + 1) r_m (eq. 2). Steps:

1. coarse circles: OpenCV's gradient Hough transform (``cv2.HoughCircles``)
   on an 8-bit copy, the few strongest circles with a radius in [r_min, r_max];
2. sub-pixel edge points: along ``rays`` radial lines through the coarse
   centre, the image is sampled every 0.1 px (``scipy.ndimage.map_coordinates``,
   cubic spline), differentiated with a Gaussian derivative
   (``scipy.ndimage.gaussian_filter1d``) and the strongest edge within
   ``search`` px of the coarse radius is located to a fraction of a sample
   (a parabola through the peak and its neighbours);
3. circle fit: ``skimage.measure.ransac`` with ``CircleModel`` rejects edge
   points disturbed by texture, then a least-squares circle on the inliers;
   steps 2-3 are repeated once about the refined centre. Of the candidates,
   the circle with the most edge evidence wins (a rim cut by the image border
   can get fewer Hough votes than a circle in the texture).

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

from omniflow.rig import Unit

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
        from omniflow.conventions import LUMA_WEIGHTS

        img = img[..., :3].astype(np.float64) @ np.asarray(LUMA_WEIGHTS)
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


def _coarse_circles(
    img: NDArray, r_min: float, r_max: float, count: int
) -> list[tuple[float, float, float]]:
    lo, hi = np.percentile(img, [0.5, 99.5])
    if hi <= lo:
        lo, hi = img.min(), img.max()
    img8 = np.clip((img - lo) / (hi - lo) * 255.0, 0, 255).astype(np.uint8)
    img8 = cv2.GaussianBlur(img8, (5, 5), 1.0)
    size = min(img.shape)
    circles = cv2.HoughCircles(
        img8,
        cv2.HOUGH_GRADIENT,
        dp=1,
        minDist=max(2.0, size / 16),
        param1=100,
        param2=30,
        minRadius=int(np.floor(r_min)),
        maxRadius=int(np.ceil(r_max)),
    )
    if circles is None or len(circles) == 0:
        return []
    # Strongest first; OpenCV pixel centres are at integers, ours at + 0.5.
    return [(float(x) + 0.5, float(y) + 0.5, float(r)) for x, y, r in circles[0, :count]]


def _contour_circle(img: NDArray, r_min: float, r_max: float, seed: int):
    """Coarse circle from the outline of the largest Otsu region (robust to a cut rim).

    The mirror's disc differs in brightness from its surround; its outline, less
    the points on the image border, is fitted with a RANSAC circle. None if that
    does not give a circle in [r_min, r_max].
    """
    lo, hi = img.min(), img.max()
    img8 = cv2.GaussianBlur(((img - lo) / (hi - lo) * 255.0).astype(np.uint8), (0, 0), 2.0)
    _, mask = cv2.threshold(img8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7))
    best = None
    for m in (mask, 255 - mask):  # the disc may be the brighter or the darker side
        m = cv2.morphologyEx(cv2.morphologyEx(m, cv2.MORPH_OPEN, kernel), cv2.MORPH_CLOSE, kernel)
        contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        if not contours:
            continue
        pts = max(contours, key=cv2.contourArea)[:, 0, :].astype(np.float64)
        h, w = img.shape
        keep = (pts[:, 0] > 1) & (pts[:, 0] < w - 2) & (pts[:, 1] > 1) & (pts[:, 1] < h - 2)
        pts = pts[keep] + 0.5
        if len(pts) < 20:
            continue
        model, inl = ransac(
            pts, CircleModel, min_samples=3, residual_threshold=2.0, max_trials=200, rng=seed
        )
        if model is None or inl is None:
            continue
        x, y, r = _circle_params(model)
        if r_min <= r <= r_max and (best is None or inl.sum() > best[1]):
            best = ((x, y, r), inl.sum())
    return None if best is None else best[0]


def _edge_points(img, x_c, y_c, r0, *, rays, search, sigma):
    step = 0.1
    radii = np.arange(r0 - search, r0 + search + step / 2, step)
    ang = np.linspace(-np.pi, np.pi, rays, endpoint=False)
    cx, cy = np.cos(ang)[:, None], np.sin(ang)[:, None]
    px, py = x_c + radii * cx, y_c + radii * cy  # (rays, samples), continuous coordinates
    prof = ndimage.map_coordinates(
        img, [py.ravel() - 0.5, px.ravel() - 0.5], order=3, mode="constant", cval=np.nan
    ).reshape(px.shape)
    inside = np.all(np.isfinite(prof), axis=1)
    if inside.sum() < 8:
        raise RimError(
            f"the circle found (centre ({x_c:.1f}, {y_c:.1f}), radius {r0:.1f}) "
            "lies outside the image"
        )
    prof, cx, cy = prof[inside], cx[inside, 0], cy[inside, 0]
    deriv = np.abs(ndimage.gaussian_filter1d(prof, sigma / step, axis=1, order=1))
    k = np.clip(np.argmax(deriv[:, 1:-1], axis=1) + 1, 1, deriv.shape[1] - 2)
    rows = np.arange(len(k))
    a, b, c = deriv[rows, k - 1], deriv[rows, k], deriv[rows, k + 1]
    den = a - 2 * b + c
    frac = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, 1.0), 0.0)  # parabola vertex
    r = radii[k] + np.clip(frac, -0.5, 0.5) * step
    strength = deriv[rows, k]
    return np.column_stack([x_c + r * cx, y_c + r * cy]), strength


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
    search: float = 4.0,
    sigma: float = 0.7,
    residual_threshold: float = 0.5,
    min_inliers: float = 0.5,
    candidates: int = 5,
    seed: int = 0,
) -> RimCircle:
    """Locate the mirror's rim circle to sub-pixel accuracy.

    Parameters
    ----------
    image : array_like, shape (H, W) or (H, W, 3)
        Omni image; colour is reduced to luminance.
    r_min, r_max : float, optional
        Radius search range, pixels; default 0.25 and 0.55 of min(H, W).
    rays : int
        Radial lines sampled for edge points.
    search : float
        Half-width, pixels, of the band about the coarse radius searched for the edge.
    sigma : float
        Gaussian derivative scale along the rays, pixels.
    residual_threshold : float
        RANSAC inlier distance, pixels.
    min_inliers : float
        Smallest fraction of edge points that must agree on the circle (pure
        noise gives ~0.18 with the defaults; a textured omni image > 0.9).
    candidates : int
        Coarse circles (strongest Hough votes first) refined; the one with the
        most edge evidence (summed edge strength of its inlier points) wins.
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
    img = _grey(image)
    size = min(img.shape)
    r_min = 0.25 * size if r_min is None else float(r_min)
    r_max = 0.55 * size if r_max is None else float(r_max)
    if not (0 < r_min < r_max):
        raise RimError(f"r_min = {r_min}, r_max = {r_max}: expected 0 < r_min < r_max")
    coarse = _coarse_circles(img, r_min, r_max, candidates)
    outline = _contour_circle(img, r_min, r_max, seed)
    if outline is not None:
        coarse.append(outline)
    if not coarse:
        raise RimError(
            f"no circle with a radius in [{r_min:.1f}, {r_max:.1f}] px found "
            "(cv2.HoughCircles, Otsu outline): is the mirror's rim in the image?"
        )
    best, first_error = None, None
    for x_c, y_c, r_m in coarse:
        try:
            rim, score = _refine(
                img,
                x_c,
                y_c,
                r_m,
                rays=rays,
                search=search,
                sigma=sigma,
                residual_threshold=residual_threshold,
                min_inliers=min_inliers,
                seed=seed,
            )
        except RimError as exc:
            first_error = first_error or exc
            continue
        if best is None or score > best[1]:
            best = (rim, score)
    if best is None:
        raise first_error
    return best[0]


def _refine(img, x_c, y_c, r_m, *, rays, search, sigma, residual_threshold, min_inliers, seed):
    """Sub-pixel circle from a coarse one (steps 2-3, twice); also the edge evidence score."""
    for _ in range(2):
        pts, strength = _edge_points(img, x_c, y_c, r_m, rays=rays, search=search, sigma=sigma)
        model, inl = ransac(
            pts,
            CircleModel,
            min_samples=3,
            residual_threshold=residual_threshold,
            max_trials=200,
            rng=seed,
        )
        if model is None or inl is None or inl.sum() < max(8, min_inliers * len(pts)):
            raise RimError(
                f"no consistent rim circle: only {0 if inl is None else int(inl.sum())} of "
                f"{len(pts)} edge points agree near radius {r_m:.1f} px about "
                f"({x_c:.1f}, {y_c:.1f})"
            )
        fit = _fit_circle(pts[inl])
        if fit is None:
            raise RimError("circle fit to the rim's edge points failed")
        x_c, y_c, r_m = _circle_params(fit)
    res = np.hypot(pts[inl, 0] - x_c, pts[inl, 1] - y_c) - r_m
    rim = RimCircle(
        x_c=x_c,
        y_c=y_c,
        r_m=r_m,
        residual_px=float(np.sqrt(np.mean(res**2))),
        inlier_fraction=float(inl.mean()),
    )
    return rim, float(np.sum(strength[inl]))


def calibrate_unit(
    image: ArrayLike, *, d: float, R: float, tip_h: float = 0.0, name: str = "", **rim_kw
) -> Unit:
    """A :class:`~omniflow.rig.Unit` from an omni image and the mirror's d and R.

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
