"""The robust matching rule: NCC of radial profiles (section 5.2, robust).

See :mod:`omniflow.matching.radial` for the rule; :func:`match_robust` runs
it on the polar tables of both units, all radial lines at once.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from omniflow import parallel
from omniflow.matching.ncc import LineSearch, profiles
from omniflow.paper.matching import TableGeometry

__all__ = ["Descriptors", "RobustSearch", "match_robust"]


class Descriptors:
    """Zero-mean, unit-norm polar patches of one table (the robust rule's profiles).

    A patch at (line k, column j) holds the radial profile at columns
    j - w stride .. j + w stride, every ``stride``-th, on line k: L = 2 w + 1
    values (one line: more lost the movers their points,
    docs/decisions/retired_knobs.md). Each is made when asked for, by the compiled
    :func:`omniflow.matching.ncc.profiles` (the same values as the whole-table
    form :class:`TableDescriptors`, bit for bit); indices whose window leaves
    the table go to that form.
    """

    def __init__(self, table: NDArray, w: int, stride: int):
        self.w, self.stride = w, stride
        self.table = np.ascontiguousarray(table, dtype=np.float32)
        self.n_lines, self.n_cols = self.table.shape
        self.length = 2 * w + 1
        self._whole: TableDescriptors | None = None

    def __call__(self, k: NDArray, j: NDArray) -> NDArray:
        """Patches at (k, j) of any equal shapes S; returns S + (L,), float32."""
        k = np.asarray(k, dtype=np.int64)
        j = np.asarray(j, dtype=np.int64)
        reach = self.w * self.stride
        if k.size and (
            k.min() < 0 or k.max() >= self.n_lines or j.min() < reach
            or j.max() >= self.n_cols - reach
        ):  # fmt: skip
            if self._whole is None:
                self._whole = TableDescriptors(self.table, self.w, self.stride)
            return self._whole(k, j)
        out = np.empty((*k.shape, self.length), dtype=np.float32)
        profiles(self.table, k.ravel(), j.ravel(), self.w, self.stride,
                 out.reshape(-1, self.length))  # fmt: skip
        return out


class TableDescriptors:
    """Zero-mean, unit-norm polar patches of one table, every window's mean and norm
    made at once (box filters): :class:`Descriptors`' reference form.

    A patch at (line k, column j) holds the radial profile at columns
    j - w stride .. j + w stride, every ``stride``-th, on line k: L = 2 w + 1
    values. The table is split by column parity into ``stride`` decimated
    copies so each profile is a contiguous run, and each window's mean and
    norm come from cumulative sums.
    """

    def __init__(self, table: NDArray, w: int, stride: int):
        self.w, self.stride = w, stride
        self.n_lines, n_cols = table.shape
        m = 2 * w + 1
        width = -(-n_cols // stride)
        dec = np.zeros((stride, self.n_lines, width), dtype=np.float32)
        for par in range(stride):
            part = table[:, par::stride]
            dec[par, :, : part.shape[1]] = part
        self.view = sliding_window_view(dec, m, axis=2)  # (stride, lines, width - m + 1, m)
        # the same windows by the flat index of their first sample (one
        # index array gathers faster than three; windows never cross a row)
        self.width = width
        self.flat = sliding_window_view(dec.reshape(-1), m)

        # per window: sum and sum of squares over its m samples
        # (box filters anchored at the window's first sample)
        def window_sum(a):
            out = []
            for par in range(stride):
                y = cv2.boxFilter(a[par], -1, (m, 1), anchor=(0, 0), normalize=False,
                                  borderType=cv2.BORDER_CONSTANT)  # fmt: skip
                out.append(y[: self.n_lines])
            return np.stack(out)

        s1 = window_sum(dec)
        s2 = window_sum(dec * dec)
        length = m
        self.length = length
        self.mean = s1 / np.float32(length)
        var = np.maximum(s2 - s1 * self.mean, np.float32(0.0))
        self.inv_norm = np.float32(1.0) / np.maximum(np.sqrt(var), np.float32(1e-12))

    def __call__(self, k: NDArray, j: NDArray) -> NDArray:
        """Patches at (k, j) of any equal shapes S; returns S + (L,), float32."""
        start = j - self.w * self.stride
        par, col = start % self.stride, start // self.stride
        n = self.n_lines
        # flat index of (par, k, col) in the (stride, lines, width) arrays
        fi = (par * n + k) * self.width + col
        p = self.flat[fi]  # a copy: fancy indexing
        p -= self.mean.reshape(-1)[fi][..., None]
        p *= self.inv_norm.reshape(-1)[fi][..., None]
        return p


class RobustSearch:
    """:func:`match_robust` in three steps a caller can schedule: made (the edges),
    :meth:`run` on every range of :attr:`ranges` (any order, any thread: the
    compiled :class:`~omniflow.matching.ncc.LineSearch`, which also takes each
    line's sub-pixel step and, with ``periodic`` given, the periodic-alias test
    of :func:`~omniflow.matching.ncc.alias_lines`), then :meth:`finish`.
    Arguments as :func:`match_robust`.
    """

    def __init__(
        self, tab: TableGeometry, fh1, fh2, t1, t2, thr, *, w, stride, min_score, uniqueness,
        left_right, candidate_fraction, flatness=0.0, alias_score=1.0,
        periodic: dict | None = None, threads: int = 1,
    ):  # fmt: skip
        # the NCC at whole columns can sit below its peak between them by up to
        # ~(1 - peak) (h_step / correlation length)^2; take a looser floor here
        # and apply min_score to the interpolated peak (the sub-pixel step)
        floor = min_score - 0.5 * (1.0 - min_score)
        self.search = LineSearch(
            t1, t2, fh1, fh2, low=candidate_fraction * thr, thr=thr, pad=tab.pad, n_h=tab.n_h,
            win=tab.win, w=w, stride=stride, floor=floor,
            uniqueness=uniqueness, alias_score=alias_score,
            left_right=left_right, min_score=min_score, flatness=flatness, periodic=periodic,
        )  # fmt: skip
        self.ranges = self.search.ranges(threads)
        self.run = self.search.run

    def finish(self):
        """(k, j1, c2, score, n_sig) of :func:`match_robust`, once every range has run.

        The sub-pixel step (taken in the kernel, line by line): a parabola
        through the NCC at the neighbouring columns, after moving one column
        if a neighbour scores higher
        (:func:`~omniflow.paper.matching.parabola_offset`); kept where the
        vertex's NCC is at least min_score and the peak sharp enough
        (:func:`~omniflow.matching.tables.sharp_peak`, ``flatness``).
        """
        return self.search.refined()


def match_robust(
    tab: TableGeometry,
    fh1,
    fh2,
    t1,
    t2,
    thr,
    *,
    w,
    stride,
    min_score,
    uniqueness,
    left_right,
    candidate_fraction,
    flatness=0.0,
    alias_score=1.0,
):
    """NCC of radial profiles between the edges of both images, line by line.

    The edges are the local maxima of |f_h| along a line above
    candidate_fraction * thr; each significant edge of image 1 (above thr)
    is scored against the edges of image 2 inside its disparity window, and
    the best kept when it passes the polarity, uniqueness,
    periodic-alias (:func:`~omniflow.matching.ncc.robust_lines`, a compiled
    loop over the lines that scores nothing outside the windows) and
    left-right tests. Last, h_2 is refined to sub-pixel and the match kept
    when the refined NCC is at least min_score and its peak sharp enough for
    that (:func:`~omniflow.matching.tables.sharp_peak`, ``flatness``).
    The lines are split over :data:`omniflow.parallel.THREADS` threads
    (:class:`RobustSearch` is the same in steps).
    """
    search = RobustSearch(
        tab, fh1, fh2, t1, t2, thr, w=w, stride=stride, min_score=min_score,
        uniqueness=uniqueness, left_right=left_right, candidate_fraction=candidate_fraction,
        flatness=flatness, alias_score=alias_score, threads=parallel.THREADS,
    )  # fmt: skip
    if len(search.ranges) > 1:
        parallel.map_tasks(search.run, *search.ranges)
    else:
        search.run(*search.ranges[0])
    return search.finish()
