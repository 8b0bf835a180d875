"""Compiled kernels (Numba) of the densification's short NCC search.

:func:`ncc_offsets` scores a radial profile of table 1 against profiles of table
2 at a few columns (the densification's short search, omniflow.matching.dense):
the normalised cross-correlation of the same profiles as
omniflow.matching.robust.Descriptors, summed straight from the tables instead of
gathering every profile first.

The kernels compile on first use; ``cache=True`` keeps the machine code
between runs where the package folder (or Numba's user cache) is writable.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = [
    "ncc_offsets",
    "profile_stats",
]


@numba.njit(cache=True, nogil=True, inline="always")
def profile_stats(t1, k, j, w, stride):  # pragma: no cover - compiled
    """(mean, 1 / norm of the mean-removed samples) of the profile of ``t1`` at line
    ``k``, column ``j``: the 2 w + 1 samples every ``stride`` columns on line k, summed in
    float64 in this order; the norm is
    floored at 1e-12 (a flat profile)."""
    n_lines = t1.shape[0]
    s1 = 0.0
    s2 = 0.0
    row = k % n_lines
    for q in range(-w, w + 1):
        v = np.float64(t1[row, j + q * stride])  # float64 products
        s1 += v
        s2 += v * v
    mean1 = s1 / (2 * w + 1)
    return mean1, 1.0 / max(math.sqrt(max(s2 - s1 * mean1, 0.0)), 1e-12)


@numba.njit(cache=True, nogil=True)
def ncc_offsets(t1, t2, k, j, cols, w, stride, out):  # pragma: no cover - compiled
    """NCC of the profile of ``t1`` at (k[i], j[i]) with those of ``t2`` at (k[i], cols[i, s]).

    A profile: the 2 w + 1 samples every ``stride`` columns centred on the column, on
    line k; zero-mean, unit-norm (a
    flat profile has norm 1e-12). Columns must keep the profile inside the table.
    Writes out[i, s].
    """
    n_lines = t1.shape[0]
    length = 2 * w + 1
    for i in range(k.size):
        mean1, inv1 = profile_stats(t1, k[i], j[i], w, stride)
        for s in range(cols.shape[1]):
            c = cols[i, s]
            dot = 0.0
            b1 = 0.0
            b2 = 0.0
            row = k[i] % n_lines
            for q in range(-w, w + 1):
                v2 = np.float64(t2[row, c + q * stride])
                dot += (np.float64(t1[row, j[i] + q * stride]) - mean1) * v2
                b1 += v2
                b2 += v2 * v2
            # sum (v1 - mean1)(v2 - mean2) = sum (v1 - mean1) v2: the first is zero-mean
            inv2 = 1.0 / max(math.sqrt(max(b2 - b1 * (b1 / length), 0.0)), 1e-12)
            out[i, s] = dot * inv1 * inv2
