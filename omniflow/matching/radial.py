"""Radial stereo matching of a coaxial pair (paper section 5.2).

Epipolar lines of a coaxial rig are the radial lines: a scene point at
azimuth theta is imaged at (h_1, theta) by cam1 and (h_2, theta) by cam2 with
h_2 / v_2 - h_1 / v_1 = s / (d + r) > 0 (eq. 3-5). Both fitted images are
sampled once into polar tables (one row per theta, one column per radius)
with :func:`cv2.remap`; the search then runs on the tables with numpy, for all
radial lines at once.

The tables use a common normalised radius u = h_i / v_i: column j of cam1's
table is at h_1 = h_min + j * h_step and column j of cam2's at
h_2 = (v_2 / v_1) (h_min + j * h_step). The disparity window of a range
interval [r_min, r_max] is then the same on every line and at every radius:
j_2 - j_1 in [v_1 s / ((d + r_max) h_step), v_1 s / ((d + r_min) h_step)].

Two methods:

``"paper"``
    The paper's rule. Significant points of image 1 are the samples where
    |df1/dh_1| passes a threshold (a percentile of |df1/dh_1| over the
    annulus); the candidates are the significant samples of image 2 on the
    same radial line inside the disparity window (the window's far end is the
    paper's minimum disparity); the best match has the most similar polar
    gradient vector (df/dh_i, (1/h_i) df/dtheta_i); h_2 is refined to
    sub-pixel by a parabola through the gradient distance of the neighbouring
    samples. Ambiguous on real texture; kept to be measured.

``"robust"``
    Both tables of f are first blurred across the lines (``tangential_blur``,
    Gaussian in theta): at one scene point cam1 (at h_1) resolves theta
    h_2 / h_1 times more coarsely than cam2 (at h_2 > h_1), so the same
    point looks different in the two units until both are brought to one
    angular resolution (without it an isotropic texture gave almost no match
    above the NCC floor). Significant points are the local maxima of
    |df/dh_i| along each radial line (edges across the line; central
    differences of the blurred table) above the threshold; candidates are the
    edges of image 2 inside the disparity window. The score is the normalised
    cross-correlation (NCC) of the radial intensity profiles, +-
    ``patch_radius`` px around each edge, on its own line. A
    match must have the same edge polarity, score at least ``min_score``, be
    unique ((1 - NCC) of the best at most ``uniqueness`` times that of the
    second best edge) and pass a left-right check (matching image 2's edge
    back to image 1 finds the same edge). h_2 is refined to sub-pixel by a
    parabola through the NCC at the neighbouring samples, and the match is
    kept only where that peak is sharp enough to place (``flatness``) and
    its image-1 profile does not recur on its own line within the window
    with an alias in image 2 a recurrence away (``alias_score``,
    ``alias_image2``, ``alias_period``, :mod:`omniflow.matching.periodic`:
    on a periodic texture an alias can outscore the truth). Then a disparity
    consistency vote (``consistency``) keeps a match only where enough of its
    neighbours in (theta, h_1) agree with its disparity. The matches then
    grow to the textured samples near them on their lines
    (``dense_percentile``, :mod:`omniflow.matching.dense`), and a second pass
    with shorter profiles (``short_patch``) adds matches where the first has
    none (small objects, inclined surfaces). The profiles
    compare equal radial scales, which is exact for vertical surfaces (both
    units map dh to dh_i = v dh / (d + r)); on inclined surfaces the scales
    differ by up to h_2 / h_1 and the NCC drops.

    Compiled: each pass (:func:`_prepare`) samples its tables and finds its
    edges, then :class:`~omniflow.matching.robust.RobustSearch` scores each
    significant edge only against the image-2 edges inside its disparity
    window, takes the sub-pixel step and the periodic-alias test, one Numba
    loop over the radial lines (:mod:`omniflow.matching.ncc`); the lines of
    both passes are split into ranges over two threads
    (:mod:`omniflow.parallel`), then each pass's vote
    (:mod:`omniflow.matching.vote`, compiled) and densification run on a
    thread of their own. The short pass reads the long pass's tables where
    their radii coincide (no second remap).

Measured on closed-form scenes (``omnisim.synthetic``, see
``tests/omniflow/test_matching.py``): see that file's module docstring for the
figures and the command.

Outliers on rendered frames, and the three changes that cut them:
docs/decisions/matching.md.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from omniflow import parallel
from omniflow.geometry.rig import Rig
from omniflow.matching.dense import densify, grown_from, smooth_profiles
from omniflow.matching.robust import RobustSearch
from omniflow.matching.tables import (
    PolarGrids,
    abs_percentile,
    blur_lines,
    polar_grids,
    polar_maps,
    polar_radii,
    polar_table,
    radial_derivative,
)
from omniflow.matching.vote import consistent
from omniflow.paper.dct import DCTFit
from omniflow.paper.matching import TableGeometry, match_paper

__all__ = ["MATCH_METHODS", "Matches", "match_radial"]

MATCH_METHODS = ("robust", "paper")


_FIELDS = ("x", "y", "theta", "h1", "h2", "score")  # the per-match arrays of Matches

#: The short second pass runs only when its profiles reach at least this many
#: samples either side: shorter ones match noise (a lens-capped 96 px frame,
#: 0.2 % sensor noise: 2.9 px profiles gave 66 matches, none without the pass;
#: at 256 px the 7.9 px profiles measured 0 outliers on the closed-form scenes).
MIN_SHORT_RADIUS = 6


@dataclass(frozen=True)
class Matches:
    """Stereo matches along radial lines; all arrays 1-D of equal length N.

    Attributes
    ----------
    x, y : ndarray, shape (N,)
        Continuous pixel coordinates of the point in cam1's image.
    theta : ndarray, shape (N,)
        Azimuth of the radial line, radians (theta_1 = theta_2).
    h1, h2 : ndarray, shape (N,)
        Image radii in cam1 and cam2, pixels; h2 is sub-pixel.
    score : ndarray, shape (N,)
        Match quality in [0, 1], higher is better (NCC for ``"robust"``;
        1 - |g1 - g2| / (|g1| + |g2|) for ``"paper"``).
    n_significant : int
        Number of significant points of image 1 that were tried (the
        denominator of a match rate): the edges of both passes and the
        samples the densification tried.
    method : str
        ``"robust"`` or ``"paper"``.
    ramp : ndarray of bool, shape (N,), optional
        The matches whose image-1 profile is smooth over its own length
        (``edge_smooth`` with ``edge_smooth_floor``: kept for the flow step
        to judge by its pool's conditioning), and the densified matches grown
        from such a match (placed at its disparity:
        :func:`~omniflow.matching.dense.grown_from`); None: none flagged.
    """

    x: NDArray
    y: NDArray
    theta: NDArray
    h1: NDArray
    h2: NDArray
    score: NDArray
    n_significant: int = 0
    method: str = ""
    ramp: NDArray | None = None

    def __len__(self) -> int:
        return int(self.x.size)

    def subset(self, keep: NDArray) -> Matches:
        """The matches selected by a boolean mask or index array."""
        ramp = None if self.ramp is None else self.ramp[keep]
        return replace(self, **{k: getattr(self, k)[keep] for k in _FIELDS}, ramp=ramp)

    @classmethod
    def from_polar(
        cls, rig: Rig, theta: NDArray, h1: NDArray, h2: NDArray, score: NDArray | None = None, **kw
    ) -> Matches:
        """Matches given by (theta, h1, h2), e.g. the true ones of a synthetic scene."""
        theta = np.asarray(theta, dtype=float).ravel()
        h1 = np.asarray(h1, dtype=float).ravel()
        h2 = np.asarray(h2, dtype=float).ravel()
        x, y = rig.cam1.pixel_of_polar(h1, theta)
        score = np.ones_like(h1) if score is None else np.asarray(score, dtype=float).ravel()
        return cls(x=x, y=y, theta=theta, h1=h1, h2=h2, score=score, **kw)


def match_radial(
    fit1: DCTFit | None,
    fit2: DCTFit | None,
    rig: Rig,
    *,
    method: str = "robust",
    threshold_percentile: float = 80.0,
    min_gradient: float = 1e-4,
    r_min: float | None = None,
    r_max: float = 10.0,
    n_theta: int = 360,
    h_step: float = 1.0,
    h_min: float = 16.0,
    rim_margin: float = 4.0,
    patch_radius: float | None = None,
    profile_step: float | None = None,
    min_score: float = 0.95,
    uniqueness: float | None = 0.5,
    left_right: bool = True,
    candidate_fraction: float = 0.5,
    tangential_blur: float | None = 0.02,
    consistency: float | None = 1.0,
    consistency_support: int = 2,
    flatness: float | None = 0.5,
    alias_score: float | None = 0.9,
    alias_image2: float = 0.9,
    alias_period: float = 0.8,
    dense_percentile: float | None = None,
    dense_reach: float = 1.0,
    dense_smooth: float | None = None,
    edge_smooth: float | None = None,
    edge_smooth_floor: float | None = None,
    short_patch: float | None = 0.5,
    grids: tuple[PolarGrids, PolarGrids] | None = None,
) -> Matches:
    """Match cam1's significant points along radial lines in cam2 (section 5.2).

    Parameters
    ----------
    fit1, fit2 : DCTFit
        The fitted images of cam1 and cam2 (eq. 17). May be None when
        ``grids`` is given.
    rig : Rig
        The coaxial pair (v_1, v_2, s, d, image centres, rims).
    method : {"robust", "paper"}
        See the module docstring.
    threshold_percentile, min_gradient, r_min, r_max, n_theta, h_step, h_min, rim_margin
        The significant points and the search's geometry: the same-named fields of
        :class:`omniflow.config.OmniFlowConfig`. r_min defaults to
        :attr:`Rig.min_common_range`, the nearest range both units can see.
    patch_radius, profile_step, min_score, uniqueness, left_right,\
    candidate_fraction, tangential_blur, consistency, consistency_support,\
    flatness, alias_score, alias_image2, alias_period,\
    dense_percentile, dense_reach, dense_smooth, edge_smooth, edge_smooth_floor,\
    short_patch
        ``robust`` only: the robust matcher's tests, documented once on the
        same-named fields of :class:`omniflow.config.OmniFlowConfig` (the defaults
        here are the function's own: ``edge_smooth`` None switches the smooth-profile
        test off). None switches a test off, as on the config. The short pass is skipped when
        its profile would be shorter than ``MIN_SHORT_RADIUS`` samples either side.
    grids : (PolarGrids, PolarGrids), optional
        Precomputed grids of the two fits (saves re-evaluating them).

    Returns
    -------
    Matches
    """
    kw = {k: v for k, v in locals().items() if k in _PASS_ARGS}
    if short_patch is not None and not (0.0 < short_patch < 1.0):
        raise ValueError(f"short_patch = {short_patch!r}: expected (0, 1) or None")
    kw, short_step = _checked_args(rig, kw)
    if grids is None:
        if fit1 is None or fit2 is None:
            raise ValueError("match_radial needs fit1 and fit2, or grids")
        grids = (
            polar_grids(fit1, rig.cam1, gradient=method == "paper"),
            polar_grids(fit2, rig.cam2, gradient=method == "paper"),
        )
    return _run_passes(grids, rig, kw, short_patch, short_step)


def _checked_args(rig: Rig, kw: dict) -> tuple[dict, float | None]:
    """match_radial's pass arguments checked, with the defaults that depend on the rig
    resolved (patch_radius, profile_step, r_min); also the profile step as given, from
    which the short pass derives its own."""
    o = dict(kw)
    method = o["method"]
    if method not in MATCH_METHODS:
        raise ValueError(f"method = {method!r}: expected one of {MATCH_METHODS}")
    threshold_percentile = o["threshold_percentile"]
    if not (0.0 <= threshold_percentile < 100.0):
        raise ValueError(f"threshold_percentile = {threshold_percentile!r}: expected [0, 100)")
    dense_percentile, dense_reach = o["dense_percentile"], o["dense_reach"]
    if not ((dense_percentile is None or 0.0 <= dense_percentile < 100.0) and dense_reach > 0):
        raise ValueError(
            f"dense_percentile = {dense_percentile!r}, dense_reach = {dense_reach!r}: "
            "expected [0, 100) or None (off), and > 0"
        )
    for name in ("flatness", "tangential_blur", "consistency"):  # None: off
        if o[name] is not None and not o[name] > 0:
            raise ValueError(f"{name} = {o[name]!r}: expected > 0 or None (off)")
    for name in ("dense_smooth", "edge_smooth", "alias_score"):
        if o[name] is not None and not (-1.0 <= o[name] < 1.0):
            raise ValueError(f"{name} = {o[name]!r}: expected an NCC in [-1, 1) or None (off)")
    if o["uniqueness"] is not None and not (0.0 < o["uniqueness"] < 1.0):
        raise ValueError(f"uniqueness = {o['uniqueness']!r}: expected (0, 1) or None (off)")
    short_step = o["profile_step"]  # the short pass's profile step derives from the one given
    if o["patch_radius"] is None:
        o["patch_radius"] = rig.cam1.r_m / 8.0
    if o["profile_step"] is None:
        o["profile_step"] = o["patch_radius"] / 16.0
    if not (o["h_step"] > 0 and o["n_theta"] >= 8 and o["patch_radius"] > 0):
        raise ValueError("expected h_step > 0, n_theta >= 8, patch_radius > 0")
    r_min, r_max = o["r_min"], o["r_max"]
    r_min = o["r_min"] = rig.min_common_range if r_min is None else float(r_min)
    if not (0 <= r_min < r_max):
        raise ValueError(f"r_min = {r_min!r}, r_max = {r_max!r}: expected 0 <= r_min < r_max")
    return o, short_step


def _run_passes(
    grids: tuple[PolarGrids, PolarGrids],
    rig: Rig,
    kw: dict,
    short_patch: float,
    short_step: float | None,
) -> Matches:
    """The long pass, and the short one where its profiles are long enough, searched on
    the threads; their matches united (the short pass's only where the long has none)."""
    method, patch_radius, h_step = kw["method"], kw["patch_radius"], kw["h_step"]
    kw = dict(kw)
    passes = [_prepare(grids, rig, **kw)]
    if (method == "robust" and short_patch is not None
            and short_patch * patch_radius >= MIN_SHORT_RADIUS * h_step):  # fmt: skip
        # the second pass, with short profiles: its matches are added where the
        # first pass has none
        short = kw["patch_radius"] = short_patch * patch_radius
        kw["profile_step"] = short / 16.0 if short_step is None else min(short_step, short / 2)
        passes.append(_prepare(grids, rig, **kw, wider=passes[0]))
    if method == "paper":
        return _finish(passes[0])
    # both passes' lines in one list of ranges on the threads, then the second
    # pass's numpy steps on the pool's thread while this one takes the first's
    parallel.map_tasks(
        _run_range, *[(p.search, k0, k1) for p in passes for k0, k1 in p.search.ranges]
    )
    later = [parallel.submit(_finish, p) for p in passes[1:]]
    try:
        out = _finish(passes[0])
    except BaseException:
        for task in later:
            task.cancel()  # no task outlives the call
        raise
    for task in later:
        out = _union(out, task.result(), kw["n_theta"], h_step)
    return out


#: match_radial's arguments that one pass (:func:`_prepare`) reads
_PASS_ARGS = (
    "method", "threshold_percentile", "min_gradient", "r_min", "r_max", "n_theta", "h_step",
    "h_min", "rim_margin", "patch_radius", "profile_step", "min_score",
    "uniqueness", "left_right", "candidate_fraction", "tangential_blur", "consistency",
    "consistency_support", "flatness", "alias_score", "alias_image2",
    "alias_period", "dense_percentile", "dense_reach", "dense_smooth", "edge_smooth",
    "edge_smooth_floor",
)  # fmt: skip


def _off(value: float | None, off: float) -> float:
    """A knob as the kernels take it: None (off) as their own value for off."""
    return off if value is None else value


def _run_range(search, k0: int, k1: int) -> None:
    search.run(k0, k1)


@dataclass
class _Pass:
    """One matching pass, from its polar tables to its compiled search (:func:`_prepare`);
    :func:`_finish` turns it into Matches once the search has run."""

    rig: Rig
    opts: dict
    tab: TableGeometry
    t1: NDArray | None
    t2: NDArray | None
    fh1: NDArray
    thr: float
    w: int
    stride: int
    search: RobustSearch | None = None
    paper: tuple | None = None
    raw: tuple | None = None  # the tables before the blur


def _sampled_columns(wider: _Pass | None, tab: TableGeometry, n_cols: int) -> tuple | None:
    """The columns of ``wider``'s tables (before the blur) at the radii of a table of
    ``n_cols`` columns from ``tab.h0`` (contiguous copies), or None where they differ:
    equal radii give equal maps (:func:`~omniflow.matching.tables.polar_radii`), and
    cv2.remap samples each column alike."""
    if wider is None or wider.raw is None:
        return None
    wt = wider.tab
    off = wt.pad - tab.pad
    n_wide = wider.raw[0].shape[1]
    if off < 0 or off + n_cols > n_wide or wt.n_theta != tab.n_theta:
        return None
    for scale in (1.0, tab.scale2):  # cam1's radii, cam2's (scaled, as polar_maps is called)
        wide = polar_radii(scale * wt.h0, scale * wt.h_step, n_wide)[off : off + n_cols]
        if not np.array_equal(wide, polar_radii(scale * tab.h0, scale * tab.h_step, n_cols)):
            return None
    return tuple(np.ascontiguousarray(r[:, off : off + n_cols]) for r in wider.raw)


def _prepare(
    grids: tuple[PolarGrids, PolarGrids], rig: Rig, wider: _Pass | None = None, **o
) -> _Pass:
    """The polar tables, edges and significance threshold of one pass (match_radial's
    arguments ``o``, defaults resolved); the robust search is set up, not run.

    ``wider``: a pass whose tables hold this one's columns (the first pass, with
    longer profiles and so wider padding): where its maps hold this pass's maps
    (the same values), this pass's tables before the blur are its columns, not
    sampled again (cv2.remap samples each column alike)."""
    g1, g2 = grids
    cam1, cam2 = rig.cam1, rig.cam2
    method, h_step, h_min, n_theta = o["method"], o["h_step"], o["h_min"], o["n_theta"]
    scale2 = cam2.v / cam1.v  # cam2 table radius per cam1 table radius
    h_top = min(cam1.r_m - o["rim_margin"], (cam2.r_m - o["rim_margin"]) / scale2)
    n_h = int(np.floor((h_top - h_min) / h_step)) + 1
    if n_h < 8:
        raise ValueError("the annulus h_min .. r_m - rim_margin is too narrow to match")
    # disparity window in table columns (the same everywhere, see module doc)
    d_lo = cam1.v * rig.s / ((rig.d + o["r_max"]) * h_step)
    d_hi = cam1.v * rig.s / ((rig.d + o["r_min"]) * h_step)
    win = (int(np.floor(d_lo)) - 1, int(np.ceil(d_hi)) + 1)

    stride = max(1, round(o["profile_step"] / h_step))  # patch profile spacing, in columns
    w = int(np.ceil(o["patch_radius"] / (h_step * stride)))
    pad = w * stride + 2 if method == "robust" else 1
    h0 = h_min - pad * h_step
    n_cols = n_h + 2 * pad
    maps1 = polar_maps(cam1, n_theta, h0, h_step, n_cols)
    maps2 = polar_maps(cam2, n_theta, scale2 * h0, scale2 * h_step, n_cols)
    tab = TableGeometry(maps1, maps2, pad, n_h, h0, h_step, scale2, n_theta, win)
    t1 = t2 = raw = None
    if method == "robust":
        raw = _sampled_columns(wider, tab, n_cols)
        if raw is None:
            raw = polar_table(g1.f, maps1), polar_table(g2.f, maps2)
        t1, t2 = raw
        if o["tangential_blur"] is not None:
            sigma = o["tangential_blur"] * n_theta / (2.0 * np.pi)  # in lines
            t1, t2 = blur_lines(t1, sigma), blur_lines(t2, sigma)
    # df/dh_i along the lines. The paper's rule reads the polar edge finder's
    # grid (eq. 19); the robust matcher finds its edges on the same blurred
    # profiles it compares, by central differences of the table (it needs
    # only where |df/dh_i| peaks and its sign, not its exact value)
    if method == "robust":
        fh1 = radial_derivative(t1, h_step)
        fh2 = radial_derivative(t2, scale2 * h_step)
    else:
        if g1.f_h is None or g2.f_h is None or g1.f_theta is None or g2.f_theta is None:
            raise ValueError("the paper's rule needs f_h and f_theta grids")
        fh1, fh2 = polar_table(g1.f_h, maps1), polar_table(g2.f_h, maps2)
    core = slice(pad, pad + n_h)
    # the percentile of every other line is the same to well within a percent
    thr = abs_percentile(fh1[::2, core], o["threshold_percentile"])
    thr = max(thr, float(o["min_gradient"]))
    p = _Pass(rig, o, tab, t1, t2, fh1, thr, w, stride, raw=raw)
    if method == "paper":
        ft1, ft2 = polar_table(g1.f_theta, maps1), polar_table(g2.f_theta, maps2)
        p.paper = match_paper(tab, fh1, fh2, ft1, ft2, thr)
    else:
        p.search = RobustSearch(
            tab, fh1, fh2, t1, t2, thr, w=w, stride=stride, min_score=o["min_score"],
            uniqueness=_off(o["uniqueness"], 1.0), left_right=o["left_right"],
            candidate_fraction=o["candidate_fraction"],
            # the periodic-alias test (omniflow.matching.periodic.not_periodic) on the
            # matches that passed the sub-pixel step, not on every candidate
            flatness=_off(o["flatness"], 0.0), alias_score=1.0,
            periodic=None if o["alias_score"] is None else dict(
                alias_score=o["alias_score"], image2=o["alias_image2"] > -1.0,
                alias2_score=o["alias_image2"], confirm_score=o["alias_period"],
                columns2=_profile_columns(h0, h_step, cam2.r_m / scale2, w * stride)),
            threads=parallel.THREADS,
        )  # fmt: skip
    return p


def _finish(p: _Pass) -> Matches:
    """One pass's matches once its search has run (which took the sub-pixel step and
    the alias test): the disparity window, the consistency vote and the
    densification."""
    o, rig, tab = p.opts, p.rig, p.tab
    cam1 = rig.cam1
    method, h_step, h_min, n_theta = o["method"], o["h_step"], o["h_min"], o["n_theta"]
    r_min, r_max, scale2 = o["r_min"], o["r_max"], tab.scale2
    pad, n_h, w, stride = tab.pad, tab.n_h, p.w, p.stride
    t1, t2, fh1 = p.t1, p.t2, p.fh1
    k1, j1, c2, score, n_sig = p.paper if method == "paper" else p.search.finish()
    theta = -np.pi + (2.0 * np.pi / n_theta) * (k1 + 0.5)
    h1 = h_min + h_step * j1  # j1, c2: columns from the first core column
    h2 = scale2 * (h_min + h_step * c2)
    lo, hi = rig.disparity_window(h1, r_min, r_max)
    ok = (h2 >= lo) & (h2 <= hi) & np.isfinite(h2)
    flagged = None  # the smooth matches kept for the flow step (edge_smooth_floor)
    if method == "robust" and o["edge_smooth"] is not None and np.any(ok):
        idx = np.nonzero(ok)[0]  # a ramp's match is not placed by its NCC
        ramp = smooth_profiles(t1, k1[idx], j1[idx] + pad, w=w, stride=stride,
                               smooth=o["edge_smooth"])  # fmt: skip
        if o["edge_smooth_floor"] is None:
            ok[idx[ramp]] = False
        else:
            flagged = np.zeros(ok.size, dtype=bool)
            flagged[idx[ramp]] = True
    if method == "robust" and o["consistency"] is not None and np.any(ok):
        idx = np.nonzero(ok)[0]
        agree = consistent(
            theta[idx], h1[idx], h2[idx] - scale2 * h1[idx],
            half_theta=0.05, half_h=cam1.r_m / 16.0, tol=o["consistency"],
            support=o["consistency_support"],
        )  # fmt: skip
        ok[idx[~agree]] = False
    if method == "robust" and o["dense_percentile"] is not None and np.any(ok):
        core = slice(pad, pad + n_h)
        thr_d = abs_percentile(fh1[::2, core], o["dense_percentile"])
        reach = max(1, round(o["dense_reach"] * o["patch_radius"] / h_step))
        dk, dj, dc, ds, n_tried = densify(
            tab, fh1, t1, t2, (k1[ok], j1[ok], c2[ok]), max(thr_d, float(o["min_gradient"])),
            w=w, stride=stride, min_score=o["min_score"],
            reach=reach, flatness=_off(o["flatness"], 0.0), smooth=_off(o["dense_smooth"], 1.0),
        )  # fmt: skip
        n_sig += n_tried
        th_d = -np.pi + (2.0 * np.pi / n_theta) * (dk + 0.5)
        h1_d = h_min + h_step * dj
        h2_d = scale2 * (h_min + h_step * dc)
        lo_d, hi_d = rig.disparity_window(h1_d, r_min, r_max)
        in_d = (h2_d >= lo_d) & (h2_d <= hi_d) & np.isfinite(h2_d)
        theta = np.concatenate([theta[ok], th_d[in_d]])
        h1 = np.concatenate([h1[ok], h1_d[in_d]])
        h2 = np.concatenate([h2[ok], h2_d[in_d]])
        score = np.concatenate([score[ok], ds[in_d]])
        if flagged is not None:
            # a densified match sits at its seeds' disparity: a flagged seed's (a ramp's,
            # placed wherever NCC liked) is no evidence, so its matches carry the flag
            grown = grown_from(dk, dj, k1[ok], j1[ok], flagged[ok], reach)
            flagged = np.concatenate([flagged[ok], grown[in_d]])
        ok = np.ones(theta.size, dtype=bool)
    return Matches.from_polar(
        rig,
        theta[ok],
        h1[ok],
        h2[ok],
        score[ok],
        n_significant=n_sig,
        method=method,
        ramp=None if flagged is None else flagged[ok],
    )


def _profile_columns(h0: float, h_step: float, rim: float, half: int) -> tuple[int, int]:
    """Table columns (h = h0 + col h_step) whose profile of +-``half`` columns
    lies between the image centre (h >= 0) and ``rim`` (in table radius)."""
    return int(np.ceil(-h0 / h_step)) + half, int(np.floor((rim - h0) / h_step)) - half


def _union(a: Matches, b: Matches, n_theta: int, h_step: float) -> Matches:
    """``a`` plus the matches of ``b`` at (line, column) samples ``a`` has none at."""

    def key(m: Matches) -> NDArray:
        k = np.rint((m.theta + np.pi) * n_theta / (2.0 * np.pi) - 0.5).astype(np.int64)
        return k * (1 << 32) + np.rint(m.h1 / h_step).astype(np.int64)

    new = ~np.isin(key(b), key(a))
    cols = {f: np.concatenate([getattr(a, f), getattr(b, f)[new]]) for f in _FIELDS}
    ramp = None
    if a.ramp is not None or b.ramp is not None:
        ra = np.zeros(len(a), bool) if a.ramp is None else a.ramp
        rb = np.zeros(len(b), bool) if b.ramp is None else b.ramp
        ramp = np.concatenate([ra, rb[new]])
    return replace(a, **cols, n_significant=a.n_significant + b.n_significant, ramp=ramp)
