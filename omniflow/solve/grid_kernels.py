"""Compiled kernels (Numba) of the grid pools: scatter into cells, read back at the points.

:func:`grid_scatter` and :func:`grid_read` put the grid pooling's point terms
into a cell image and read filtered images back bilinearly at the points
(:mod:`omniflow.solve.gridpool`), without numpy's (N, C) temporaries per corner.

The kernels compile on first use; ``cache=True`` keeps the machine code
between runs where the package folder (or Numba's user cache) is writable.
"""

from __future__ import annotations

import numba

__all__ = [
    "grid_read",
    "grid_scatter",
]


@numba.njit(cache=True, nogil=True)
def grid_scatter(img, iy, ix, y0, x0, parts, members):  # pragma: no cover - compiled
    """Add ``parts[i]`` (C,) into ``img[iy[i] - y0, ix[i] - x0]`` (img (H, W, C)) for i in
    ``members``."""
    for t in range(members.size):
        i = members[t]
        for c in range(parts.shape[1]):
            img[iy[i] - y0, ix[i] - x0, c] += parts[i, c]


@numba.njit(cache=True, nogil=True)
def grid_read(f, gx, gy, x0, y0, readers, coef, out):  # pragma: no cover - compiled
    """Add ``coef[t]`` times the bilinear sample of ``f`` (H, W, C), H, W >= 2, at cell
    coordinates (gx[i] - x0, gy[i] - y0) (centres at integers, clamped to the grid) to
    ``out[i]`` (C,) for i = ``readers[t]``."""
    h, w, nc = f.shape
    for t in range(readers.size):
        i = readers[t]
        x = min(max(gx[i] - x0, 0.0), w - 1.0)
        y = min(max(gy[i] - y0, 0.0), h - 1.0)
        xi = min(int(x), w - 2)  # x >= 0: truncation is the floor
        yi = min(int(y), h - 2)
        fx = x - xi
        fy = y - yi
        c = coef[t]
        w00 = (1.0 - fx) * (1.0 - fy) * c
        w01 = fx * (1.0 - fy) * c
        w10 = (1.0 - fx) * fy * c
        w11 = fx * fy * c
        for k in range(nc):
            out[i, k] += (w00 * f[yi, xi, k] + w01 * f[yi, xi + 1, k]
                          + w10 * f[yi + 1, xi, k] + w11 * f[yi + 1, xi + 1, k])  # fmt: skip
