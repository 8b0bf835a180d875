"""The disparity consistency vote of the robust matcher."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

__all__ = ["consistent"]


def consistent(
    theta: NDArray, h1: NDArray, disparity: NDArray, *, half_theta: float, half_h: float,
    tol: float, support: int,
) -> NDArray:  # fmt: skip
    """Matches whose disparity agrees (within ``tol``) with at least ``support``
    of their neighbours (|d theta| <= half_theta, wrapping; |d h1| <= half_h),
    and with at least half of them; bool (N,)."""
    n = theta.size
    scale = half_h / half_theta  # theta in pixels, so the window is a square
    t = np.mod(theta, 2.0 * np.pi) * scale
    box = (2.0 * np.pi * scale, 4.0 * (float(h1.max()) + half_h) + 1.0)
    pts = np.column_stack([np.minimum(t, np.nextafter(box[0], 0)), h1 - h1.min()])
    pairs = cKDTree(pts, boxsize=box).query_pairs(half_h, p=np.inf, output_type="ndarray")
    i = np.concatenate([pairs[:, 0], pairs[:, 1]])
    j = np.concatenate([pairs[:, 1], pairs[:, 0]])
    near = np.bincount(i, minlength=n)
    agree = np.bincount(i, weights=np.abs(disparity[i] - disparity[j]) <= tol, minlength=n)
    return (agree >= support) & (agree >= 0.5 * near)
