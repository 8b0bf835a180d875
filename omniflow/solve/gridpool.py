"""Pooling by filtering on a grid: the pooled solver's sums without a neighbour search.

:func:`omniflow.solve.pooled.pooled_solution` needs, for every matched point i, the
Gaussian-weighted sums over its neighbours j of the products of their
derivatives (pp, pq, qq, pf, qf) times 1, u and u^2, u the tangential offset.
With the ``relative`` model every product factors into a part of j alone and a
power of h_1,i (p_j = f_h,j h_1,j / h_1,i, q_j = f_theta,j / h_1,i), and the
offset u_ij is, to first order in the pool's size, the tangential component of
the pixel offset, u_ij = t_i . (x_j - x_i) / scale with t_i the unit's
d(x, y)/dtheta / h_1 at point i. So every sum is a correlation of an image
holding j's part at j's pixel with the kernel g(d), d_x g(d), d_y g(d),
d_x^2 g(d), d_x d_y g(d) or d_y^2 g(d) (g the pool's Gaussian, d the offset
from the point), read back at the point: a few separable OpenCV filters on a
coarse grid (cells of ``cell`` px), O(pixels) whatever the number of points
or the size of the pools. A pool then holds every point within its radius
(the k-d tree's keeps the ``pool_k`` nearest), so denser matches pool more
equations on the same area.

The range test of :func:`omniflow.solve.pooled.neighbourhoods` (neighbours whose range
differs from the point's by more than ``range_tol``, another surface, left out)
becomes a third axis of the grid, as in a bilateral grid: the points are
binned by log r in bins of delta = log(1 + range_tol), each bin's image is
filtered on its own, and point i at log r_i = (b + f) delta reads
(1 - f) F[b - 1] + F[b] + f F[b + 1]: each bin weighted by the share of it
inside the window |log r_j - log r_i| <= delta, so the expected weight over
neighbours spread evenly in their bins is the tree's test; a neighbour in the
point's own bin always counts, one more than 2 delta away (about twice
``range_tol``) never does. Points without a finite range get the k-d tree's pools.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from omniflow.parallel import map_tasks
from omniflow.solve.decouple_kernels import DECOUPLE_SUMS, decouple_sums
from omniflow.solve.gain_kernels import gain_sums
from omniflow.solve.grid_kernels import grid_read, grid_scatter

__all__ = ["GridPools"]

#: the strict lower triangle of a 6 x 6 (rows, columns)
_LOWER = np.tril_indices(6, -1)


class GridPools:
    """The pools of every matched point as grid filters (plus k-d tree pools where ranges mix).

    Parameters
    ----------
    x, y : ndarray, shape (N,)
        cam1 pixel coordinates of the matches (centres at j + 1/2).
    tangent : ndarray, shape (N, 2), or None
        d(x, y)/dtheta / h_1 at each point (a unit vector for a polar image);
        needed by the linear model's sums only.
    shape : (H, W)
        cam1's image size, pixels.
    radius : float
        Pool radius, pixels; weights Gaussian with sigma = radius / 2, cut at
        ``radius`` (on a square: the filters are separable).
    cell : float
        Grid cell, pixels (positions are binned to it: a neighbour's offset
        is off by at most cell / 2).
    r : ndarray, shape (N,), optional
        Triangulated range; with ``range_tol``, points whose window mixes
        ranges go to the tree (``tree_pools``).
    range_tol : float, optional
    tree_pools : callable, optional
        ``tree_pools(mask) -> (idx, w)``: the k-d tree pools of the masked
        points (rows of the others unused), for the points that leave the grid.
    window : float, optional
        Half-width of the square window, pixels (default ``radius``): the same
        Gaussian cut nearer (:meth:`k_window`).
    """

    def __init__(
        self,
        x: NDArray,
        y: NDArray,
        tangent: NDArray | None,
        shape: tuple[int, int],
        *,
        radius: float,
        cell: float,
        r: NDArray | None = None,
        range_tol: float | None = None,
        tree_pools=None,
        window: float | None = None,
    ) -> None:
        self.n = n = np.size(x)
        self.cell = float(cell)
        self.gh = max(math.ceil(shape[0] / cell), 2)
        self.gw = max(math.ceil(shape[1] / cell), 2)
        x = np.asarray(x, dtype=np.float64).ravel()
        y = np.asarray(y, dtype=np.float64).ravel()
        ix = np.clip(np.floor(x / cell).astype(np.intp), 0, self.gw - 1)
        iy = np.clip(np.floor(y / cell).astype(np.intp), 0, self.gh - 1)
        self.flat = iy * self.gw + ix
        self.gx, self.gy = x / cell - 0.5, y / cell - 0.5  # cell coordinates, centres at integers
        self.tangent = None if tangent is None else np.asarray(tangent, np.float64).reshape(n, 2)
        half = max(round((radius if window is None else window) / cell), 1)
        d = np.arange(-half, half + 1) * cell  # offsets, pixels
        g = np.exp(-0.5 * (d / (radius / 2.0)) ** 2)
        self.kernels = [(g * d**m).astype(np.float32) for m in range(3)]  # g, d g, d^2 g
        self.gauss = g  # float64, for the sums in float64
        self.half = half
        self.on_grid = np.ones(n, dtype=bool)
        self.idx = self.w = None
        self.bins = np.zeros(n, dtype=np.intp)
        self.frac = np.zeros(n)
        if r is not None and range_tol is not None and n:
            r = np.asarray(r, dtype=np.float64).ravel()
            self.on_grid = np.isfinite(r) & (r > 0)
            pos = np.log(np.where(self.on_grid, r, 1.0)) / math.log1p(range_tol)
            self.bins = np.floor(pos).astype(np.intp)
            self.frac = pos - self.bins
            if tree_pools is not None and not self.on_grid.all():
                self.idx, self.w = tree_pools(~self.on_grid)
                self.w = np.where(self.on_grid[:, None], 0.0, self.w)

    def sums(
        self, derivs6: tuple[NDArray, ...], h1: NDArray, *, linear: bool, scale: float
    ) -> tuple[NDArray, NDArray]:
        """Pooled sums of :func:`omniflow.solve.pooled.pooled_solution` (``relative`` model).

        ``derivs6``: f1_h, f1_theta, f1_t, (h2/h1) f2_h, f2_theta, f2_t and ``h1``,
        shape (N,) (no sentinel). Returns sums (N, 1 or 3, 5) of
        w u^m (pp, pq, qq, pf, qf) and wsum (N, 1 or 3) of w u^m, the grid's
        where the point is on it, zero elsewhere (the caller adds the tree's).
        """
        f1h, f1th, f1t, f2h, f2th, f2t = (np.asarray(v, np.float64).ravel() for v in derivs6)
        h1 = np.asarray(h1, np.float64).ravel()
        n = self.n
        m_pow = 3 if linear else 1
        sums = np.zeros((n, m_pow, 5))
        wsum = np.zeros((n, m_pow))
        on = self.on_grid
        if not on.any():
            return sums, wsum
        a1, a2 = f1h * h1, f2h * h1  # p_j h_1,i: the relative model's rel h_1,i
        parts = np.stack(
            [
                np.ones(n),
                a1 * a1 + a2 * a2,  # pp h_1,i^2
                a1 * f1th + a2 * f2th,  # pq h_1,i^2
                f1th * f1th + f2th * f2th,  # qq h_1,i^2
                a1 * f1t + a2 * f2t,  # pf h_1,i
                f1th * f1t + f2th * f2t,  # qf h_1,i
            ],
            axis=1,
        )
        # per-channel scale so that float32 holds every channel near 1
        norm = np.maximum(np.abs(parts[on]).max(axis=0), 1e-300)
        parts = (parts / norm).astype(np.float32)
        g0, g1, g2 = self.kernels
        pairs = [(g0, g0)]
        if linear:
            pairs += [(g1, g0), (g0, g1), (g2, g0), (g1, g1), (g0, g2)]
        read = self._filter(parts, [(kx, ky, 1) for kx, ky in pairs])
        sel = slice(None) if on.all() else on
        read = [r_m[sel] * norm for r_m in read]
        if linear:
            if self.tangent is None:
                raise ValueError("GridPools: the linear model's sums need the tangents")
            tx, ty = self.tangent[sel, 0:1], self.tangent[sel, 1:2]
            m0, mx, my, mxx, mxy, myy = read
            mom = [m0, (tx * mx + ty * my) / scale,
                   (tx * tx * mxx + 2.0 * tx * ty * mxy + ty * ty * myy) / scale**2]  # fmt: skip
        else:
            mom = read
        hi = h1[sel, None]
        fac = np.concatenate([1.0 / hi**2] * 3 + [1.0 / hi] * 2, axis=1)  # (M, 5)
        for m in range(m_pow):
            wsum[sel, m] = mom[m][:, 0]
            sums[sel, m, :] = mom[m][:, 1:] * fac
        return sums, wsum

    def _filter(
        self, parts: NDArray, jobs: list[tuple[NDArray, NDArray, int]], bins: list | None = None
    ) -> NDArray:
        """Every on-grid point's filtered sums of ``parts`` (N, C) over its window.

        One job (kx, ky, power): the points' parts scattered into the cells of their
        range bin, filtered by the separable kernel kx (along x) times ky (along y),
        read back bilinearly at each point of bins c - 1, c, c + 1 with that bin's
        share of its window (the module's docstring) raised to ``power`` (2 for sums
        of squared weights). Filters in the dtype of ``parts`` (float32 or float64).
        Returns (len(jobs), N, C); rows of off-grid points zero. ``bins``: the bins'
        images of ``parts`` made already (:meth:`_bin_images`).

        The bins' images are made once; the jobs are then shared between the two
        threads of :mod:`omniflow.parallel` (the filters and reads, most of the
        time, release the GIL). Each job fills only its own slice of the result,
        bin after bin in the same order whichever thread runs it, so the sums are
        the same, bit for bit, as on one thread.
        """
        n, nc = parts.shape
        read = np.zeros((len(jobs), n, nc))
        bins = self._bin_images(parts) if bins is None else bins
        depth = cv2.CV_64F if parts.dtype == np.float64 else cv2.CV_32F

        def run(j0: int, j1: int) -> None:
            for img, x0, y0, readers, coef in bins:
                # a reader outside the crop reads its border, which is 0 (margin > half)
                for m in range(j0, j1):
                    kx, ky, power = jobs[m]
                    f = cv2.sepFilter2D(img, depth, kx, ky, borderType=cv2.BORDER_CONSTANT)
                    f = f.reshape(img.shape)  # OpenCV drops a single channel's axis
                    grid_read(f, self.gx, self.gy, float(x0), float(y0), readers,
                              coef if power == 1 else coef**power, read[m])  # fmt: skip

        half = (len(jobs) + 1) // 2
        map_tasks(run, *[(j0, j1) for j0, j1 in ((0, half), (half, len(jobs))) if j1 > j0])
        return read

    def _bin_images(self, parts: NDArray) -> list[tuple]:
        """Per range bin c of the on-grid points: (img, x0, y0, readers, coef), img the
        bin's members' ``parts`` summed into the cells of its crop (whose corner is
        cell (x0, y0)), readers the points of bins c - 1, c, c + 1 and coef the share
        of bin c inside each reader's window (1 - f, 1, f for the bins c + 1, c, c - 1;
        see the module's docstring)."""
        ix, iy = self.flat % self.gw, self.flat // self.gw
        margin = self.half + 1
        # the on-grid points by bin: a bin's members, and the readers of its filtered
        # image (the points of bins c - 1, c, c + 1), are runs of this order
        pts = np.flatnonzero(self.on_grid)
        pts = pts[np.argsort(self.bins[pts], kind="stable")]
        ub, first = np.unique(self.bins[pts], return_index=True)
        last = np.append(first[1:], pts.size)
        out = []
        for t, c in enumerate(ub):
            members = pts[first[t] : last[t]]
            lo = first[t - 1] if t > 0 and ub[t - 1] == c - 1 else first[t]
            hi = last[t + 1] if t + 1 < ub.size and ub[t + 1] == c + 1 else last[t]
            readers = pts[lo:hi]
            db = self.bins[readers] - c
            frac = self.frac[readers]
            coef = np.where(db == 0, 1.0, np.where(db == 1, 1.0 - frac, frac))
            x0 = max(int(ix[members].min()) - margin, 0)
            y0 = max(int(iy[members].min()) - margin, 0)
            x1 = min(int(ix[members].max()) + margin + 1, self.gw)
            y1 = min(int(iy[members].max()) + margin + 1, self.gh)
            cw, ch = max(x1 - x0, 2), max(y1 - y0, 2)
            img = np.zeros((ch, cw, parts.shape[1]), parts.dtype)
            grid_scatter(img, iy, ix, y0, x0, parts, members)
            out.append((img, x0, y0, readers, coef))
        return out

    def decouple_sums(self, derivs: tuple[NDArray, ...], h1: NDArray, h2: NDArray) -> NDArray:
        """The two-model test's pool sums (:func:`omniflow.solve.decouple_kernels.decouple_sums`)
        on the grid.

        ``derivs``: f1_h, f1_theta, f1_t, f2_h, f2_theta, f2_t, shape (N,). Every
        sum of :data:`omniflow.solve.decouple_kernels.DECOUPLE_SUMS` is over the neighbours' own
        terms (the point's h_1 enters afterwards), so each is one channel filtered
        with the pool's Gaussian; the sum of squared weights (for the pool's
        effective size) filters the point count with the squared Gaussian and reads
        it with the squared bin shares. In float64: the 3x3 solves of
        :func:`omniflow.solve.decouple_kernels.decouple_fits` test the condition number against
        1e8, beyond float32. Off-grid points get their k-d tree pools' sums.
        Returns (N, 12).
        """
        f1h, f1th, f1t, f2h, f2th, f2t = (np.asarray(v, np.float64).ravel() for v in derivs)
        h1, h2 = (np.asarray(v, np.float64).ravel() for v in (h1, h2))
        n = self.n
        out = np.zeros((n, len(DECOUPLE_SUMS)))
        if self.on_grid.any():
            b1, b2 = f1h * h1, f2h * h2  # f_h h_u,j
            cross = lambda x1, x2, y1, y2: x1 * y1 + x2 * y2  # noqa: E731  (both units)
            terms = [(f1h, f2h), (b1, b2), (f1th, f2th), (f1t, f2t)]  # a, b, q, t
            parts = [cross(*terms[p], *terms[q]) for p, q in
                     ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2), (0, 3), (1, 3), (2, 3),
                      (3, 3))]  # fmt: skip
            g, g2 = self.gauss, self.gauss**2
            # the count first: the squared weights' filter takes it from the same bins
            parts = np.stack([np.ones(n), *parts], axis=1)
            bins = self._bin_images(parts)
            read = self._filter(parts, [(g, g, 1)], bins)[0]
            read2 = self._filter(parts[:, :1], [(g2, g2, 2)], _channels(bins, 1))[0]
            out[:, :10], out[:, 10] = read[:, 1:], read[:, 0]
            out[:, 11] = read2[:, 0]
            out[~self.on_grid] = 0.0
        if self.idx is not None:  # the points whose window mixes ranges: their tree pools
            out += decouple_sums(self.idx, self.w, (f1h, f1th, f1t, f2h, f2th, f2t), h1, h2)
        return out

    def gain_sums(
        self,
        derivs: tuple[NDArray, ...],
        f: tuple[NDArray, NDArray],
        h1: NDArray,
        h2: NDArray,
        theta: NDArray | None,
        *,
        linear: bool,
        scale: float,
        single: bool = False,
    ) -> tuple[NDArray, ...]:
        """The gain fit's normal equations (:func:`omniflow.solve.gain_kernels.gain_sums`) on the
        grid.

        ``derivs``: f1_h, f1_theta, f1_t, f2_h, f2_theta, f2_t; ``f``: each unit's image at
        the points; all shape (N,). The relative model, unknowns (a, h_1,i b[, u a,
        u h_1,i b], beta) (``linear``). Every entry is a pool sum of j's own products
        times a power of the point's h_1,i, so each is a channel filtered as in
        :meth:`sums`; the sum of squared weights as in :meth:`decouple_sums`. Off-grid
        points get their k-d tree pools' sums. ``single``: the filters in float32, each
        channel scaled to a largest |value| of 1 first (as :meth:`sums`), else float64;
        the gain's F statistic from float32 sums is within float32's rounding of the
        float64 one's (its residual sum, y^T W y less the explained part, the least
        precise term; omniflow.solve.gain.GRID_SINGLE says which the solver uses).

        Returns
        -------
        M, v, yy, powers
            As :func:`omniflow.solve.gain_kernels.gain_sums`.
        w2 : ndarray, shape (N,)
            Each pool's sum of squared weights.
        """
        f1h, f1th, f1t, f2h, f2th, f2t = (np.asarray(v, np.float64).ravel() for v in derivs)
        g1, g2 = (np.asarray(v, np.float64).ravel() for v in f)
        h1, h2 = (np.asarray(v, np.float64).ravel() for v in (h1, h2))
        n, p = self.n, 5 if linear else 3
        M, v = np.zeros((n, p, p)), np.zeros((n, p))
        yy, powers, w2 = np.zeros(n), np.zeros((n, 3)), np.zeros(n)
        on = self.on_grid
        if on.any():
            a1, a2 = f1h * h1, f2h * h2  # p_j h_1,i (eq. 9; eq. 15 with eq. 14)
            cross = lambda x1, x2, y1, y2: x1 * y1 + x2 * y2  # noqa: E731  (both units)
            terms = [(a1, a2), (f1th, f2th), (-f1t, -f2t), (-g1, -g2)]  # p, q, y, g (-f)
            pairs = ((0, 0), (0, 1), (1, 1), (0, 2), (1, 2), (0, 3), (1, 3), (3, 3), (3, 2),
                     (2, 2))  # fmt: skip
            parts = np.stack([np.ones(n)] + [cross(*terms[i], *terms[j]) for i, j in pairs], 1)
            sel = slice(None) if on.all() else np.flatnonzero(on)
            if single:  # per-channel scale so that float32 holds every channel near 1
                norm = np.maximum(np.abs(parts[sel]).max(axis=0), 1e-300)
                parts = (parts / norm).astype(np.float32)
                g0, gd, gdd = self.kernels
                gg = (self.gauss**2).astype(np.float32)
            else:
                norm = np.ones(parts.shape[1])
                g0, gd, gdd = (self.gauss * np.arange(-self.half, self.half + 1) ** m
                               * self.cell**m for m in range(3))  # fmt: skip
                gg = self.gauss**2
            # channels: 0 w, 1 pp, 2 pq, 3 qq, 4 py, 5 qy, 6 pg, 7 qg, 8 gg, 9 gy, 10 yy; the
            # first moment of u needs the first 8, the second the first 4 (the linear model)
            # the points binned once; each filter takes the channels it needs (a channel's
            # cells are the same sums whichever others are scattered with it)
            bins = self._bin_images(parts)
            mom = [self._filter(parts, [(g0, g0, 1)], bins)[0][sel] * norm]
            if linear:
                if self.tangent is None:
                    raise ValueError("GridPools: the linear model's sums need the tangents")
                tx, ty = self.tangent[sel, 0:1], self.tangent[sel, 1:2]
                first = [(gd, g0, 1), (g0, gd, 1)]
                mx, my = self._filter(parts[:, :8], first, _channels(bins, 8))[:, sel] * norm[:8]
                second = [(gdd, g0, 1), (gd, gd, 1), (g0, gdd, 1)]
                mxx, mxy, myy = (self._filter(parts[:, :4], second, _channels(bins, 4))[:, sel]
                                 * norm[:4])  # fmt: skip
                u2 = (tx * tx * mxx + 2.0 * tx * ty * mxy + ty * ty * myy) / scale**2
                mom += [(tx * mx + ty * my) / scale, u2]
            # the squared weights: channel 0 (the count) with the squared kernel and shares
            sq = self._filter(parts[:, :1], [(gg, gg, 2)], _channels(bins, 1))[0][:, 0]
            hi = h1[sel]
            i2, i1 = 1.0 / hi**2, 1.0 / hi
            c0 = mom[0]
            last = p - 1
            ent = {(0, 0): c0[:, 1] * i2, (0, 1): c0[:, 2] * i2, (1, 1): c0[:, 3] * i2,
                   (0, last): c0[:, 6] * i1, (1, last): c0[:, 7] * i1,
                   (last, last): c0[:, 8]}  # fmt: skip
            rhs = {0: c0[:, 4] * i1, 1: c0[:, 5] * i1, last: c0[:, 9]}
            if linear:
                c1, c2 = mom[1], mom[2]
                ent.update({(0, 2): c1[:, 1] * i2, (0, 3): c1[:, 2] * i2, (1, 2): c1[:, 2] * i2,
                            (1, 3): c1[:, 3] * i2, (2, 2): c2[:, 1] * i2, (2, 3): c2[:, 2] * i2,
                            (3, 3): c2[:, 3] * i2, (2, last): c1[:, 6] * i1,
                            (3, last): c1[:, 7] * i1})  # fmt: skip
                rhs.update({2: c1[:, 4] * i1, 3: c1[:, 5] * i1})
                powers[sel, 1], powers[sel, 2] = c1[:, 0], c2[:, 0]
            for (r, c), val in ent.items():
                M[sel, r, c] = M[sel, c, r] = val
            for r, val in rhs.items():
                v[sel, r] = val
            yy[sel], powers[sel, 0], w2[sel] = c0[:, 10], c0[:, 0], sq[sel]
        if self.idx is not None:  # the points whose window mixes ranges: their tree pools
            model = "linear" if linear else "constant"
            tree = gain_sums(self.idx, self.w, np.arange(n), derivs, f, h1, h2, theta,
                             model=model, scale=scale)  # fmt: skip
            M, v, yy, powers = M + tree[0], v + tree[1], yy + tree[2], powers + tree[3]
            w2 = w2 + (self.w * self.w).sum(axis=1)
        return M, v, yy, powers, w2

    def linear_gain_sums(
        self,
        derivs: tuple[NDArray, ...],
        f: tuple[NDArray, NDArray],
        h1: NDArray,
        h2: NDArray,
        theta: NDArray | None,
        *,
        scale: float,
        single: bool = False,
    ) -> tuple[NDArray, ...]:
        """The linear-gain test's 6 x 6 Grams (``decoupled_linear``) on the grid windows.

        The rows of :func:`omniflow.solve.gain_kernels.gain_sums` (``decoupled_linear``): unit u's
        row of neighbour j (f_h, -f_h h_u,j / h_1,i, f_theta / h_1,i, -f, -f u_j, -f dh_j),
        right side -f_t, with the gain's slopes taken along the pixel offsets instead,
        -f dx_j / scale and -f dy_j / scale (dx, dy = x_j - x_i, y_j - y_i). To first
        order in the pool's size (u, dh) is a rotation of (dx, dy) (the tangential and
        radial unit vectors at the point), and a fit's residual, and the unknowns of the
        other columns, do not change when two of its columns are replaced by an invertible
        mix of them: the test's RSS, its F_U and the flow are the tree's but for the
        pools' contents. So every entry is a pool sum of j's own products times a power
        of the point's h_1,i (columns 1 and 2) or a first or second moment of the offset
        (columns 4 and 5), filtered as :meth:`gain_sums`' linear model. Off-grid points
        get their k-d tree pools' sums (the tree's u, dh columns). ``single``: the filters
        in float32, each channel scaled to a largest |value| of 1 first (as :meth:`sums`),
        else float64.

        Returns
        -------
        M, v, yy
            As :func:`omniflow.solve.gain_kernels.gain_sums` (``decoupled_linear``), shapes
            (N, 6, 6), (N, 6), (N,).
        wsum, w2 : ndarray, shape (N,)
            Each pool's sums of weights and squared weights.
        """
        f1h, f1th, f1t, f2h, f2th, f2t = (np.asarray(v, np.float64).ravel() for v in derivs)
        g1, g2 = (np.asarray(v, np.float64).ravel() for v in f)
        h1, h2 = (np.asarray(v, np.float64).ravel() for v in (h1, h2))
        n = self.n
        M, v = np.zeros((n, 6, 6)), np.zeros((n, 6))
        yy, wsum, w2 = np.zeros(n), np.zeros(n), np.zeros(n)
        on = self.on_grid
        if on.any():
            cross = lambda x1, x2, y1, y2: x1 * y1 + x2 * y2  # noqa: E731  (both units)
            # the columns' parts of j (0 f_h, 1 -f_h h_u, 2 f_theta, 3 -f) and y = -f_t
            cols = [(f1h, f2h), (-f1h * h1, -f2h * h2), (f1th, f2th), (-g1, -g2), (-f1t, -f2t)]
            # channels: 0 the count; 1-5 column 3 (-f) times columns 3, 0, 1, 2 and y, the
            # ones with moments (channel 1 the second too); then the rest of the block 0-2,
            # its right side and yy
            pairs = [(3, 3), (0, 3), (1, 3), (2, 3), (4, 3), (0, 0), (0, 1), (0, 2), (1, 1),
                     (1, 2), (2, 2), (0, 4), (1, 4), (2, 4), (4, 4)]  # fmt: skip
            parts = np.stack([np.ones(n)] + [cross(*cols[a], *cols[b]) for a, b in pairs], 1)
            sel = slice(None) if on.all() else np.flatnonzero(on)
            d = np.arange(-self.half, self.half + 1) * self.cell  # offsets, pixels
            g0, gd, gdd, gg = (*(self.gauss * d**m for m in range(3)), self.gauss**2)
            norm = np.ones(parts.shape[1])
            if single:  # per-channel scale so that float32 holds every channel near 1
                norm = np.maximum(np.abs(parts[sel]).max(axis=0), 1e-300)
                parts = (parts / norm).astype(np.float32)
                g0, gd, gdd, gg = (k.astype(np.float32) for k in (g0, gd, gdd, gg))
            bins = self._bin_images(parts)
            c0 = self._filter(parts, [(g0, g0, 1)], bins)[0][sel] * norm
            mx, my = (self._filter(parts[:, :6], [(gd, g0, 1), (g0, gd, 1)], _channels(bins, 6))
                      [:, sel, 1:] * (norm[1:6] / scale))  # fmt: skip
            mxx, mxy, myy = (self._filter(parts[:, :2], [(gdd, g0, 1), (gd, gd, 1), (g0, gdd, 1)],
                             _channels(bins, 2))[:, sel, 1] * (norm[1] / scale**2))  # fmt: skip
            sq = self._filter(parts[:, :1], [(gg, gg, 2)], _channels(bins, 1))[0][sel, 0]
            G = np.zeros((c0.shape[0], 6, 6))
            G[:, 3, 3], G[:, 4, 4], G[:, 4, 5], G[:, 5, 5] = c0[:, 1], mxx, mxy, myy
            for t, c in enumerate((3, 0, 1, 2)):  # column c times -f, and its moments
                if c != 3:
                    G[:, c, 3] = c0[:, 1 + t]
                G[:, c, 4], G[:, c, 5] = mx[:, t], my[:, t]
            for t, (a, b) in enumerate(pairs[5:11]):
                G[:, a, b] = c0[:, 6 + t]
            rhs = np.column_stack([c0[:, 12], c0[:, 13], c0[:, 14], c0[:, 5], mx[:, 4], my[:, 4]])
            # the lower triangle from the upper, filled above (np.triu(G) + its strict upper
            # triangle transposed made the same entries through two (N, 6, 6) temporaries)
            G[:, _LOWER[0], _LOWER[1]] = G[:, _LOWER[1], _LOWER[0]]
            hi = h1[sel]
            s = np.ones((hi.size, 6))
            s[:, 1] = s[:, 2] = 1.0 / hi  # the columns -f_h h_u / h_1,i and f_theta / h_1,i
            G *= s[:, :, None]  # in place: (G s_i) s_j as before, without two (N, 6, 6)
            G *= s[:, None, :]  # temporaries (fresh pages are dear on a sandboxed host)
            if on.all():
                M = G
            else:
                M[sel] = G
            v[sel] = rhs * s
            yy[sel], wsum[sel], w2[sel] = c0[:, 15], c0[:, 0], sq
        if self.idx is not None:  # the points whose window mixes ranges: their tree pools
            rows = np.flatnonzero(~on)
            idx, w = self.idx[rows], self.w[rows]
            tree = gain_sums(idx, w, rows, derivs, f, h1, h2, theta, model="decoupled_linear",
                             scale=scale)  # fmt: skip
            M[rows], v[rows], yy[rows] = tree[0], tree[1], tree[2]
            wsum[rows], w2[rows] = w.sum(axis=1), (w * w).sum(axis=1)
        return M, v, yy, wsum, w2

    def k_window(self, k: int) -> float:
        """The half-width of the square that holds ``k`` points at the median density of
        the on-grid points, pixels (at most the window's own): the density is each
        window's Gaussian-weighted count of points (any range) over the Gaussian's sum
        on the cells, so that a window of this half-width holds about the ``k`` nearest
        neighbours of :func:`omniflow.solve.pooled.neighbourhoods` (its pools cut at ``k``,
        the grid's at the window)."""
        if not self.on_grid.any():
            return self.half * self.cell
        count = self._unbinned_count()[self.on_grid]
        density = float(np.median(count)) / (self.cell * self.gauss.sum()) ** 2  # per px^2
        return min(0.5 * math.sqrt(k / density), self.half * self.cell)

    def _unbinned_count(self) -> NDArray:
        """sum_j g(x_j - x_i) over the window's on-grid points whatever their range, read at
        every point (off-grid rows too)."""
        img = np.zeros((self.gh, self.gw, 1))
        pts = np.flatnonzero(self.on_grid)
        grid_scatter(img, self.flat // self.gw, self.flat % self.gw, 0, 0, np.ones((self.n, 1)),
                     pts)  # fmt: skip
        g = self.gauss
        filt = cv2.sepFilter2D(img, cv2.CV_64F, g, g, borderType=cv2.BORDER_CONSTANT)
        out = np.zeros((self.n, 1))
        grid_read(filt.reshape(self.gh, self.gw, 1), self.gx, self.gy, 0.0, 0.0,
                  np.arange(self.n), np.ones(self.n), out)  # fmt: skip
        return out[:, 0]


def _channels(bins: list[tuple], c: int) -> list[tuple]:
    """:meth:`GridPools._bin_images`'s bins with their images' first ``c`` channels only."""
    return [(np.ascontiguousarray(img[..., :c]), *rest) for img, *rest in bins]
