"""The cosine series' bases at points, one coefficient's row at a time (compiled).

:func:`omniflow.kernels.cos_bases` makes, for each point in turn, the running
product z_k = z_{k-1} e (z_0 = 1) of e = exp(i pi c / N), k < n_coef: a chain of
dependent complex products per point, which runs at the latency of one product
per coefficient. :func:`cos_bases_columns` makes the same products with the loop
over the points innermost, so that the points' independent chains fill the
vector units, and stores them transposed, shape (n_coef, M): contiguous rows for
the stores and for the matrix products of :meth:`omniflow.dct.DCTFit.value_and_gradient`
(``single``), which take them as ``coeffs.T @ bases``. Each product is numpy's,
(a c - b d, a d + b c), in the same order, so the values are
:func:`omniflow.dct.bases_numpy`'s, value for value (in float32 output, each
rounded once as it is stored).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["cos_bases_columns"]


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
