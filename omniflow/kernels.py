"""Compiled kernels (Numba) for loops that numpy runs only through large temporaries.

:func:`pooled_sums` forms the weighted sums of the pooled flow solver
(:func:`omniflow.flow.pooled_solution`): for every point, over its K
neighbours, sum_j w_ij u_ij^m (pp, pq, qq, pf, qf)_j. In numpy that is a
dozen (N, K) gathers and products and an (N, K, 5) stack before one batched
product; here it is one pass over the neighbours with nothing stored but
the sums. The arithmetic of each term is numpy's, term by term; only the
order of the additions over the K neighbours differs (a batched matrix
product there, a running sum here), so the sums agree to rounding.

:func:`ncc_offsets` scores a radial profile of table 1 against profiles of table
2 at a few columns (the densification's short search, omniflow.matching.dense):
the normalised cross-correlation of the same profiles as
omniflow.matching.robust.Descriptors, summed straight from the tables instead of
gathering every profile first.

:func:`grid_scatter` and :func:`grid_read` put the grid pooling's point terms
into a cell image and read filtered images back bilinearly at the points
(:mod:`omniflow.gridpool`), without numpy's (N, C) temporaries per corner.

The kernels compile on first use; ``cache=True`` keeps the machine code
between runs where the package folder (or Numba's user cache) is writable.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

__all__ = ["grid_read", "grid_scatter", "ncc_offsets", "pooled_sums"]


@numba.njit(cache=True, nogil=True)
def _pooled_sums(idx, w, f1_h, f1_theta, f1_t, kf2_h, f2_theta, f2_t, h1, th, relative,
                 n_powers, scale):  # pragma: no cover - compiled  # fmt: skip
    n, kk = idx.shape
    sums = np.zeros((n, n_powers, 5))
    wsum = np.zeros((n, n_powers))
    two_pi = 2.0 * math.pi
    for i in range(n):
        hi = h1[i]
        for s in range(kk):
            j = idx[i, s]
            ww = w[i, s]
            rel = h1[j] / hi if relative else 1.0
            p1 = f1_h[j] * rel
            p2 = kf2_h[j] * rel
            q1 = f1_theta[j] / hi
            q2 = f2_theta[j] / hi
            t1 = f1_t[j]
            t2 = f2_t[j]
            pp = p1 * p1 + p2 * p2
            pq = p1 * q1 + p2 * q2
            qq = q1 * q1 + q2 * q2
            pf = p1 * t1 + p2 * t2
            qf = q1 * t1 + q2 * t2
            power = ww
            for m in range(n_powers):
                if m == 1:  # the tangential offset u, as numpy's floor-mod wrap
                    u = (((th[j] - th[i]) + math.pi) % two_pi - math.pi) * hi / scale
                    power = ww * u
                elif m == 2:
                    power = ww * u * u
                sums[i, m, 0] += power * pp
                sums[i, m, 1] += power * pq
                sums[i, m, 2] += power * qq
                sums[i, m, 3] += power * pf
                sums[i, m, 4] += power * qf
                wsum[i, m] += power
    return sums, wsum


def pooled_sums(
    idx: NDArray,
    w: NDArray,
    derivs: tuple[NDArray, ...],
    h1: NDArray,
    theta: NDArray | None,
    *,
    relative: bool,
    linear: bool,
    scale: float,
) -> tuple[NDArray, NDArray]:
    """Weighted sums of the pooled normal equations, and of the weights.

    Parameters
    ----------
    idx, w : ndarray, shape (N, K)
        Neighbour indices (N + 1 entries below: index N is the sentinel) and weights.
    derivs : six ndarrays, shape (N + 1,)
        f1_h, f1_theta, f1_t, (h2/h1) f2_h, f2_theta, f2_t, each with a zero
        sentinel at index N.
    h1 : ndarray, shape (N + 1,)
        cam1 image radius, sentinel 1.
    theta : ndarray, shape (N + 1,), optional
        Azimuth (``linear`` only).
    relative, linear : bool
        The local model of :func:`omniflow.flow.pooled_solution`.
    scale : float
        Tangential length that scales u, pixels.

    Returns
    -------
    sums : ndarray, shape (N, 1 or 3, 5)
        sum_j w u^m (pp, pq, qq, pf, qf), m = 0 (and 1, 2 for ``linear``).
    wsum : ndarray, shape (N, 1 or 3)
        sum_j w u^m.
    """
    f = [np.ascontiguousarray(v, dtype=np.float64) for v in derivs]
    th = np.zeros_like(f[0]) if theta is None else np.ascontiguousarray(theta, dtype=np.float64)
    return _pooled_sums(
        np.ascontiguousarray(idx, dtype=np.int64), np.ascontiguousarray(w, dtype=np.float64),
        *f, np.ascontiguousarray(h1, dtype=np.float64), th, bool(relative),
        3 if linear else 1, float(scale),
    )  # fmt: skip


@numba.njit(cache=True, nogil=True)
def grid_scatter(img, iy, ix, parts, members):  # pragma: no cover - compiled
    """Add ``parts[i]`` (C,) into ``img[iy[i], ix[i]]`` (img (H, W, C)) for i in ``members``."""
    for t in range(members.size):
        i = members[t]
        for c in range(parts.shape[1]):
            img[iy[i], ix[i], c] += parts[i, c]


@numba.njit(cache=True, nogil=True)
def grid_read(f, gx, gy, readers, coef, out):  # pragma: no cover - compiled
    """Add ``coef[i]`` times the bilinear sample of ``f`` (H, W, C), H, W >= 2, at cell
    coordinates (gx[i], gy[i]) (centres at integers, clamped to the grid) to ``out[i]``
    (C,) for i in ``readers``."""
    h, w, nc = f.shape
    for t in range(readers.size):
        i = readers[t]
        x = min(max(gx[i], 0.0), w - 1.0)
        y = min(max(gy[i], 0.0), h - 1.0)
        x0 = min(int(x), w - 2)  # x >= 0: truncation is the floor
        y0 = min(int(y), h - 2)
        fx = x - x0
        fy = y - y0
        c = coef[i]
        w00 = (1.0 - fx) * (1.0 - fy) * c
        w01 = fx * (1.0 - fy) * c
        w10 = (1.0 - fx) * fy * c
        w11 = fx * fy * c
        for k in range(nc):
            out[i, k] += (w00 * f[y0, x0, k] + w01 * f[y0, x0 + 1, k]
                          + w10 * f[y0 + 1, x0, k] + w11 * f[y0 + 1, x0 + 1, k])  # fmt: skip


@numba.njit(cache=True, nogil=True)
def ncc_offsets(t1, t2, k, j, cols, w, stride, lines, out):  # pragma: no cover - compiled
    """NCC of the profile of ``t1`` at (k[i], j[i]) with those of ``t2`` at (k[i], cols[i, s]).

    A profile: the 2 w + 1 samples every ``stride`` columns centred on the column, on
    the 2 ``lines`` + 1 lines around k (wrapping in theta); zero-mean, unit-norm (a
    flat profile has norm 1e-12). Columns must keep the profile inside the table.
    Writes out[i, s].
    """
    n_lines = t1.shape[0]
    length = (2 * w + 1) * (2 * lines + 1)
    for i in range(k.size):
        s1 = 0.0
        s2 = 0.0
        for dk in range(-lines, lines + 1):
            row = (k[i] + dk) % n_lines
            for q in range(-w, w + 1):
                v = np.float64(t1[row, j[i] + q * stride])  # float64 products
                s1 += v
                s2 += v * v
        mean1 = s1 / length
        inv1 = 1.0 / max(math.sqrt(max(s2 - s1 * mean1, 0.0)), 1e-12)
        for s in range(cols.shape[1]):
            c = cols[i, s]
            dot = 0.0
            b1 = 0.0
            b2 = 0.0
            for dk in range(-lines, lines + 1):
                row = (k[i] + dk) % n_lines
                for q in range(-w, w + 1):
                    v2 = np.float64(t2[row, c + q * stride])
                    dot += (np.float64(t1[row, j[i] + q * stride]) - mean1) * v2
                    b1 += v2
                    b2 += v2 * v2
            # sum (v1 - mean1)(v2 - mean2) = sum (v1 - mean1) v2: the first is zero-mean
            inv2 = 1.0 / max(math.sqrt(max(b2 - b1 * (b1 / length), 0.0)), 1e-12)
            out[i, s] = dot * inv1 * inv2
