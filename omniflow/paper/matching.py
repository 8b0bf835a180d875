"""The paper's matching rule: the most similar polar gradient vector (section 5.2).

Both rules search the same polar tables (:class:`TableGeometry`, one row per radial
line) and place a match to sub-pixel at the vertex of a parabola (:func:`parabola_offset`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["TableGeometry", "match_paper", "parabola_offset"]


@dataclass(frozen=True)
class TableGeometry:
    """Geometry of the two polar tables (columns include ``pad`` on each side)."""

    maps1: tuple
    maps2: tuple
    pad: int
    n_h: int
    h0: float
    h_step: float
    scale2: float
    n_theta: int
    win: tuple[int, int]  # column offsets j2 - j1 that can hold the match


def parabola_offset(s_m: NDArray, s_0: NDArray, s_p: NDArray) -> NDArray:
    """Vertex offset in [-1, 1] of the parabola through (-1, s_m), (0, s_0), (1, s_p)."""
    den = s_m - 2.0 * s_0 + s_p
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(np.abs(den) > 1e-12, 0.5 * (s_m - s_p) / den, 0.0)
    return np.clip(off, -1.0, 1.0)


def match_paper(tab: TableGeometry, fh1, fh2, ft1, ft2, thr):
    """Section 5.2 as written: most similar polar gradient vector along the line."""
    pad, n_h = tab.pad, tab.n_h
    h1_cols = tab.h0 + tab.h_step * np.arange(fh1.shape[1])
    g1t = ft1 / h1_cols  # (1/h_i) df/dtheta_i, eq. (8)
    g2t = ft2 / (tab.scale2 * h1_cols)
    sig = []
    for f in (fh1, fh2):
        m = np.abs(f) > thr
        m[:, :pad] = False
        m[:, pad + n_h :] = False
        sig.append(m)
    k1, j1 = np.nonzero(sig[0])
    k2, j2 = np.nonzero(sig[1])
    n_sig = int(k1.size)
    if k1.size == 0 or k2.size == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0), np.zeros(0), n_sig
    n_cols = fh1.shape[1]
    key2 = k2 * n_cols + j2
    start = np.searchsorted(key2, k1 * n_cols + j1 + tab.win[0], side="left")
    stop = np.searchsorted(key2, k1 * n_cols + j1 + tab.win[1], side="right")
    count = stop - start
    m = max(int(count.max()), 1)
    ga = np.stack([fh1[k1, j1], g1t[k1, j1]], axis=1)
    gb = np.stack([fh2[k2, j2], g2t[k2, j2]], axis=1)
    best_d = np.full(k1.size, np.inf, np.float32)
    best_i = np.zeros(k1.size, int)
    for s in range(0, k1.size, 8192):  # chunks keep the (n, m, 2) array small
        e = min(s + 8192, k1.size)
        idx = start[s:e, None] + np.arange(m)[None, :]
        ok = np.arange(m)[None, :] < count[s:e, None]
        idx = np.where(ok, idx, 0)
        dist = np.where(ok, np.linalg.norm(ga[s:e, None, :] - gb[idx], axis=2), np.inf)
        bi = np.argmin(dist, axis=1)
        best_d[s:e] = dist[np.arange(e - s), bi]
        best_i[s:e] = idx[np.arange(e - s), bi]
    ok = np.isfinite(best_d)
    k1, j1, ga, best_d = k1[ok], j1[ok], ga[ok], best_d[ok]
    jb = j2[best_i[ok]]

    def dist_at(jj):
        jj = np.clip(jj, 0, n_cols - 1)
        return np.hypot(ga[:, 0] - fh2[k1, jj], ga[:, 1] - g2t[k1, jj])

    off = parabola_offset(-dist_at(jb - 1), -best_d, -dist_at(jb + 1))
    gnorm = np.hypot(ga[:, 0], ga[:, 1]) + np.hypot(fh2[k1, jb], g2t[k1, jb])
    score = np.clip(1.0 - best_d / np.maximum(gnorm, 1e-12), 0.0, 1.0)
    return k1, j1 - pad, jb + off - pad, score, n_sig
