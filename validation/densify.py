"""A dense field from a sparse method's flow: OpenCV contrib's edge-aware interpolation.

Every method of the suite is also scored at every valid pixel. A dense method gives
that field itself; a sparse one (omniflow, a per-point external output) gets it from
:func:`interpolate_flow`, the EpicFlow interpolator of ``cv2.ximgproc``
(``createEdgeAwareInterpolator``: a locally weighted affine fit over the K nearest
matches by edge-aware geodesic distance on the first image; Revaud et al., "EpicFlow",
CVPR 2015). Its Fast Global Smoother post-pass is off: it moves even an exact affine
field by 0.04 px on average, so the dense score would measure the smoother, not the
method (docs/decisions/dense_interpolation.md gives the figures).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["MIN_POINTS", "interpolate_flow"]

#: Fewer points than this give no dense field (NaN everywhere): the affine fit needs
#: neighbours, and below this the interpolation is a guess over the whole image.
MIN_POINTS = 8
#: Nearest matches per affine fit (OpenCV's default); at most half the points.
NEIGHBOURS = 128


def interpolate_flow(
    image: NDArray,
    x: ArrayLike,
    y: ArrayLike,
    dx: ArrayLike,
    dy: ArrayLike,
) -> NDArray:
    """Dense flow at every pixel centre from flow known at scattered points.

    Parameters
    ----------
    image : ndarray, shape (H, W), uint8
        The first frame (its edges stop the interpolation crossing object borders).
    x, y : array_like, shape (N,)
        The points, in the project's pixel coordinates (``omniflow.conventions``:
        pixel (i, j) has its centre at x = j + 0.5, y = i + 0.5).
    dx, dy : array_like, shape (N,)
        The flow at the points, pixels; points with a non-finite value or outside
        the image are left out.

    Returns
    -------
    ndarray, shape (H, W, 2), float32
        (dx, dy) at every pixel centre; NaN everywhere with fewer than
        :data:`MIN_POINTS` usable points.
    """
    import cv2

    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 2:
        raise ValueError(f"image: expected a uint8 (H, W) array, got {img.dtype} {img.shape}")
    h, w = img.shape
    x, y, dx, dy = (np.asarray(v, dtype=np.float64).ravel() for v in (x, y, dx, dy))
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(dx) & np.isfinite(dy)
    ok &= (x >= 0) & (x < w) & (y >= 0) & (y < h)
    n = int(np.count_nonzero(ok))
    if n < MIN_POINTS:
        return np.full((h, w, 2), np.nan, dtype=np.float32)
    # OpenCV puts pixel centres at integer coordinates: shift by half a pixel.
    p1 = np.stack([x[ok] - 0.5, y[ok] - 0.5], axis=1).astype(np.float32)
    p2 = (p1 + np.stack([dx[ok], dy[ok]], axis=1)).astype(np.float32)
    interp = cv2.ximgproc.createEdgeAwareInterpolator()
    interp.setK(min(NEIGHBOURS, n // 2))
    interp.setUsePostProcessing(False)
    flow = interp.interpolate(img, p1, img, p2)
    return np.asarray(flow, dtype=np.float32)
