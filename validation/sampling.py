"""Ground truth at a method's sub-pixel points.

The dataset stores the truth at pixel centres (``omniflow.conventions``: pixel
(row i, col j) has its centre at x = j + 0.5, y = i + 0.5). A method reports
its results at arbitrary continuous points, so the truth is sampled there:

* discrete channels (``gt.valid``, ``gt.object``, ``gt.flow.valid``,
  ``gt.stereo.valid``) take the value of the nearest pixel centre, i.e. of the
  pixel that contains the point;
* continuous channels (``gt.r``, ``gt.flow.dx``, ...) are interpolated
  bilinearly between the four surrounding pixel centres, but only where all
  four are valid (``gt.valid`` = 1) and see the same object (``gt.object``);
  elsewhere the sample is NaN and the point has no usable truth.

``gt.theta`` is interpolated on the circle (unwrapped about the first
neighbour) so that points near theta = +-pi get a sensible value.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["DISCRETE_CHANNELS", "bilinear", "sample_truth"]

#: Channels that hold labels or flags: sampled at the nearest pixel centre.
DISCRETE_CHANNELS = frozenset({"gt.valid", "gt.object", "gt.flow.valid", "gt.stereo.valid"})
#: Channels that are angles in radians: interpolated on the circle.
ANGLE_CHANNELS = frozenset({"gt.theta"})


def _nearest_index(
    x: NDArray, y: NDArray, width: int, height: int
) -> tuple[NDArray, NDArray, NDArray]:
    finite = np.isfinite(x) & np.isfinite(y)
    j = np.floor(np.where(finite, x, -1.0)).astype(np.int64)
    i = np.floor(np.where(finite, y, -1.0)).astype(np.int64)
    inside = finite & (j >= 0) & (j < width) & (i >= 0) & (i < height)
    return np.clip(i, 0, height - 1), np.clip(j, 0, width - 1), inside


def bilinear(image: NDArray, x: ArrayLike, y: ArrayLike) -> NDArray:
    """Bilinear sample of ``image`` (H, W) at continuous pixel coordinates.

    Points whose four neighbouring pixel centres are not all inside the image
    give NaN. No validity test: see :func:`sample_truth` for that.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    height, width = image.shape
    j0, i0, fx, fy, inside = _corners(x, y, width, height)
    img = np.asarray(image, dtype=np.float64)
    v = (1 - fy) * ((1 - fx) * img[i0, j0] + fx * img[i0, j0 + 1]) + fy * (
        (1 - fx) * img[i0 + 1, j0] + fx * img[i0 + 1, j0 + 1]
    )
    return np.where(inside, v, np.nan)


def _corners(x: NDArray, y: NDArray, width: int, height: int):
    # Pixel centres sit at index + 0.5, so the lower-left neighbour is floor(x - 0.5).
    u = x - 0.5
    w = y - 0.5
    finite = np.isfinite(u) & np.isfinite(w)
    u = np.where(finite, u, 0.0)
    w = np.where(finite, w, 0.0)
    j0 = np.floor(u).astype(np.int64)
    i0 = np.floor(w).astype(np.int64)
    inside = finite & (j0 >= 0) & (j0 + 1 < width) & (i0 >= 0) & (i0 + 1 < height)
    fx = u - j0
    fy = w - i0
    j0 = np.clip(j0, 0, width - 2)
    i0 = np.clip(i0, 0, height - 2)
    return j0, i0, fx, fy, inside


def sample_truth(
    frame: Mapping[str, NDArray],
    x: ArrayLike,
    y: ArrayLike,
    channels: Iterable[str] | None = None,
) -> dict[str, NDArray]:
    """Sample the ground-truth channels of one camera frame at points (x, y).

    Parameters
    ----------
    frame : mapping of str to ndarray, shape (H, W)
        The channels of one camera at one frame, as ``Dataset.read_frame``
        returns them (``gt.valid``, ``gt.object`` and the channels asked for).
    x, y : array_like, shape (N,)
        Continuous pixel coordinates (pixel centres at j + 0.5, i + 0.5).
    channels : iterable of str, optional
        Channels to sample; default every ``gt.*`` channel in ``frame``.

    Returns
    -------
    dict of str to ndarray, shape (N,)
        One float64 array per channel, plus ``"bilinear_ok"`` (bool): True
        where the four neighbours are valid and on one object, i.e. where the
        continuous channels are defined. Discrete channels are 0 outside the
        image; continuous ones are NaN where ``bilinear_ok`` is False.
    """
    x = np.asarray(x, dtype=np.float64).ravel()
    y = np.asarray(y, dtype=np.float64).ravel()
    if x.shape != y.shape:
        raise ValueError(f"x and y must have the same shape, got {x.shape} and {y.shape}")
    if "gt.valid" not in frame or "gt.object" not in frame:
        raise KeyError("the frame must hold the channels 'gt.valid' and 'gt.object'")
    valid = np.asarray(frame["gt.valid"]) > 0.5
    obj = np.rint(np.asarray(frame["gt.object"])).astype(np.int64)
    height, width = valid.shape
    names = [c for c in frame if c.startswith("gt.")] if channels is None else list(channels)

    out: dict[str, NDArray] = {}
    i, j, inside = _nearest_index(x, y, width, height)
    j0, i0, fx, fy, inside4 = _corners(x, y, width, height)
    corners = [(i0, j0), (i0, j0 + 1), (i0 + 1, j0), (i0 + 1, j0 + 1)]
    ok = inside4.copy()
    o00 = obj[i0, j0]
    for ii, jj in corners:
        ok &= valid[ii, jj] & (obj[ii, jj] == o00)
    out["bilinear_ok"] = ok

    weights = [(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy]
    for name in names:
        img = np.asarray(frame[name])
        if img.shape != valid.shape:
            raise ValueError(f"channel {name!r} has shape {img.shape}, expected {valid.shape}")
        if name in DISCRETE_CHANNELS:
            out[name] = np.where(inside, img[i, j].astype(np.float64), 0.0)
            continue
        vals = [img[ii, jj].astype(np.float64) for ii, jj in corners]
        if name in ANGLE_CHANNELS:
            ref = vals[0]
            vals = [ref + np.angle(np.exp(1j * (v - ref))) for v in vals]
        s = sum(w * v for w, v in zip(weights, vals, strict=True))
        if name in ANGLE_CHANNELS:
            s = np.angle(np.exp(1j * s))
        out[name] = np.where(ok, s, np.nan)
    return out
