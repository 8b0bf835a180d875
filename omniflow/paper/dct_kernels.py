"""Compiled kernels (Numba) of the DCT fit: the cosine bases at points (eq. 18).

:func:`cos_bases` makes the cosine series' bases at points
(:func:`omniflow.paper.dct.DCTFit.evaluate` and its gradients) as the running product
of a complex exponential, numpy's cumprod value for value, in one pass.

:func:`cos_bases_columns` makes the same products with the loop over the points
innermost, so that the points' independent chains (one dependent complex product per
coefficient each) fill the vector units, and stores them transposed, shape (n_coef, M):
contiguous rows for the stores and for the matrix products of
:meth:`omniflow.paper.dct.DCTFit.value_and_gradient` (``single``), which take them as
``coeffs.T @ bases``. Each product is numpy's, (a c - b d, a d + b c), in the same order,
so the values are :func:`omniflow.paper.dct.bases_numpy`'s, value for value (in float32
output, each rounded once as it is stored).

The kernels compile on first use; ``cache=True`` keeps the machine code
between runs where the package folder (or Numba's user cache) is writable.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = [
    "cos_bases",
    "cos_bases_columns",
]


@numba.njit(cache=True, nogil=True)
def cos_bases(e, w, cos, dsin):  # pragma: no cover - compiled
    """cos[i, k] = Re(e[i]^k) and dsin[i, k] = -w[k] Im(e[i]^k) for k < cos.shape[1], the
    powers as the running product z_k = z_{k-1} e[i] (z_0 = 1), each complex product
    as numpy's, (a c - b d, a d + b c): :func:`omniflow.paper.dct.bases_numpy`'s cumprod
    value for value, without its complex table and the copies of its two parts."""
    n, m = cos.shape
    if m == 0:
        return
    for i in range(n):
        er = e[i].real
        ei = e[i].imag
        zr = 1.0
        zi = 0.0
        cos[i, 0] = 1.0
        dsin[i, 0] = -w[0] * 0.0
        for k in range(1, m):
            r = zr * er - zi * ei
            zi = zr * ei + zi * er
            zr = r
            cos[i, k] = zr
            dsin[i, k] = -w[k] * zi


@numba.njit(cache=True, nogil=True)
def cos_bases_columns(e, w, cos, dsin):  # pragma: no cover - compiled
    """cos[k, i] = Re(e[i]^k) and dsin[k, i] = -w[k] Im(e[i]^k) for k < cos.shape[0]:
    e (M,) complex128, w (n_coef,) float64, cos and dsin (n_coef, M), float64 or float32
    (the running product kept in float64 either way)."""
    m, n = cos.shape
    if m == 0:
        return
    zr = np.ones(n)
    zi = np.zeros(n)
    er = np.empty(n)
    ei = np.empty(n)
    for i in range(n):
        er[i] = e[i].real
        ei[i] = e[i].imag
        cos[0, i] = 1.0
        dsin[0, i] = -w[0] * 0.0
    for k in range(1, m):
        wk = w[k]
        for i in range(n):
            r = zr[i] * er[i] - zi[i] * ei[i]
            zi[i] = zr[i] * ei[i] + zi[i] * er[i]
            zr[i] = r
            cos[k, i] = r
            dsin[k, i] = -wk * zi[i]
