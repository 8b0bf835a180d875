"""Accuracy metrics for stereo matches, image flow and derived quantities.

All functions are pure and work on 1-D arrays of per-point values. Error
statistics are summarised by :func:`stats` as the point count, median, mean
and 90th percentile; a set with no points gives ``n = 0`` and NaN statistics
(never a warning).

Flow metrics follow the optical-flow benchmarks (Middlebury, KITTI, Sintel):

* EPE: endpoint error, ``hypot(dx - dx_gt, dy - dy_gt)`` in pixels;
* polar components: errors of the radial displacement ``dh`` and of the
  tangential displacement ``h dtheta`` (pixels), reported separately because
  the coaxial direct solution is ill-conditioned radially;
* AE: angular error (Barron et al. 1994) between the space-time vectors
  ``(dx, dy, 1)`` and ``(dx_gt, dy_gt, 1)``, degrees;
* 1 px and 3 px outlier rates: the fraction of points with EPE above 1 and 3 px;
* each split into non-occluded (``gt.flow.valid`` = 1), occluded, and by the
  true speed ``hypot(dx_gt, dy_gt)`` in bins;
* bias (:func:`gain`): the estimated radial (``dh``) and tangential
  (``h dtheta``) components against the true ones, as the least-squares gain
  through the origin, the slope and intercept of a straight-line fit, and the
  mean and median signed error. A method that shrinks its answers towards zero
  has a small median EPE at sub-pixel motion but a gain well below 1.

The benchmark protocol (:func:`protocol_metrics`, :func:`protocol_splits`), the
same four figures for every method on every scene of a suite:

* ``epe``: mean endpoint error (px);
* ``1px``: the 1 px outlier rate, the fraction of points with EPE > 1 px, the
  primary metric (Spring, Mehl et al., CVPR 2023); lower is better;
* ``fl``: the fraction of points whose EPE is > 3 px *and* > 5 % of the true
  flow magnitude (KITTI 2015 Fl, Menze and Geiger, CVPR 2015);
* ``wauc``: the weighted area under the accuracy curve (VIPER, Richter et al.,
  "Playing for Benchmarks", ICCV 2017, used by Spring): with thresholds
  delta_i = 0.05 i px and weights w_i = 1 - (i - 1) / 100 for i = 1..100,
  ``sum_i w_i a_i / sum_i w_i`` where a_i is the fraction of points with
  EPE <= delta_i; 1 = every point within 0.05 px, higher is better;

split by region (``matched``: ``gt.flow.valid`` = 1; ``occluded``; ``outside``:
the point leaves the mirror, ``gt.flow.outside``), by rigidity (``static``
scene vs ``moving`` objects), by true speed (:data:`PROTOCOL_SPEED_BINS`) and by
true range (:data:`PROTOCOL_RANGE_BINS`).

Stereo metrics: matched ``h_2`` more than 1 px from ``gt.stereo.h_other`` is an
outlier; relative error of ``r`` (``|r - r_gt| / r_gt``) and absolute error of
``h`` (metres), split by true range.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence

import numpy as np
import scipy.stats
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "PROTOCOL_METRICS",
    "PROTOCOL_RANGE_BINS",
    "PROTOCOL_SPEED_BINS",
    "RANGE_BINS",
    "SPEED_BINS",
    "bin_label",
    "fl_rate",
    "flow_errors",
    "flow_summary",
    "gain",
    "outlier_rate",
    "polar_components",
    "protocol_metrics",
    "protocol_splits",
    "rate",
    "stats",
    "stereo_errors",
    "stereo_summary",
    "wauc",
]

#: Speed bins in pixels per frame (true displacement magnitude).
SPEED_BINS: tuple[float, ...] = (0.0, 0.25, 0.5, 1.0, 3.0, math.inf)
#: Range bins in metres (true distance from the axis).
RANGE_BINS: tuple[float, ...] = (0.0, 1.0, 2.0, 4.0, math.inf)

#: The protocol's metric names, in the leaderboard's column order.
PROTOCOL_METRICS: tuple[str, ...] = ("1px", "epe", "fl", "wauc")
#: Speed bins of the protocol (px per frame, true displacement magnitude): this rig's
#: motions run from sub-pixel (a slow robot, far surfaces) to several pixels per frame
#: (fast yaw, near movers); octaves from 0.5 px split where the gradient-based flow
#: is first order (< 1 px), where it needs its pyramid (1-4 px), and beyond (>= 8 px).
PROTOCOL_SPEED_BINS: tuple[float, ...] = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0, math.inf)
#: Range bins of the protocol (m): the library's rooms (< 4 m) and the far surfaces of
#: halls and open ground (8-30 m), where the stereo baseline gives little disparity.
PROTOCOL_RANGE_BINS: tuple[float, ...] = (0.0, 1.0, 2.0, 4.0, 8.0, 16.0, math.inf)
#: WAUC's thresholds delta_i = 0.05 i px and weights w_i = 1 - (i - 1) / 100, i = 1..100.
WAUC_THRESHOLDS: NDArray = 0.05 * np.arange(1, 101)
WAUC_WEIGHTS: NDArray = 1.0 - np.arange(100) / 100.0


def stats(values: ArrayLike) -> dict[str, float]:
    """Count, median, mean and 90th percentile of the finite values."""
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"n": 0, "median": math.nan, "mean": math.nan, "p90": math.nan}
    return {
        "n": int(v.size),
        "median": float(np.median(v)),
        "mean": float(np.mean(v)),
        "p90": float(np.percentile(v, 90)),
    }


def rate(flags: ArrayLike) -> float:
    """Fraction of True among the given flags (NaN for none)."""
    f = np.asarray(flags, dtype=bool).ravel()
    return float(f.mean()) if f.size else math.nan


def outlier_rate(epe: ArrayLike, threshold: float = 1.0) -> float:
    """Fraction of the finite EPEs above ``threshold`` px (``1px`` at 1 px; NaN for none)."""
    e = np.asarray(epe, dtype=np.float64).ravel()
    e = e[np.isfinite(e)]
    return float(np.mean(e > threshold)) if e.size else math.nan


def fl_rate(epe: ArrayLike, speed: ArrayLike) -> float:
    """KITTI's Fl: the fraction of points with EPE > 3 px and EPE > 0.05 x true speed.

    Parameters
    ----------
    epe, speed : array_like, shape (N,)
        Endpoint error and true flow magnitude of each point (px); pairs with a
        non-finite value are left out. NaN for no points.
    """
    e = np.asarray(epe, dtype=np.float64).ravel()
    v = np.asarray(speed, dtype=np.float64).ravel()
    ok = np.isfinite(e) & np.isfinite(v)
    if not ok.any():
        return math.nan
    e, v = e[ok], v[ok]
    return float(np.mean((e > 3.0) & (e > 0.05 * v)))


def wauc(epe: ArrayLike) -> float:
    """Weighted area under the accuracy curve (VIPER; Spring), in [0, 1], higher is better.

    ``sum_i w_i a_i / sum_i w_i`` over :data:`WAUC_THRESHOLDS` (0.05, 0.10, ..., 5 px)
    with :data:`WAUC_WEIGHTS` (1, 0.99, ..., 0.01), a_i the fraction of the finite
    EPEs <= delta_i (Richter, Hayder and Koltun, "Playing for Benchmarks", ICCV 2017).
    NaN for no points.
    """
    e = np.sort(np.asarray(epe, dtype=np.float64).ravel())
    e = e[np.isfinite(e)]
    if not e.size:
        return math.nan
    acc = np.searchsorted(e, WAUC_THRESHOLDS, side="right") / e.size
    return float(np.dot(WAUC_WEIGHTS, acc) / WAUC_WEIGHTS.sum())


def protocol_metrics(epe: ArrayLike, speed: ArrayLike) -> dict[str, float]:
    """The protocol's four figures over one set of points: ``n``, ``epe`` (mean),
    ``1px``, ``fl``, ``wauc`` (see the module docstring); NaN figures for no points."""
    e = np.asarray(epe, dtype=np.float64).ravel()
    v = np.asarray(speed, dtype=np.float64).ravel()
    ok = np.isfinite(e) & np.isfinite(v)
    e, v = e[ok], v[ok]
    return {
        "n": int(e.size),
        "epe": float(e.mean()) if e.size else math.nan,
        "1px": outlier_rate(e, 1.0),
        "fl": fl_rate(e, v),
        "wauc": wauc(e),
    }


def protocol_splits(
    err: Mapping[str, ArrayLike],
    *,
    moving: Sequence[int] = (),
    speed_bins: Sequence[float] = PROTOCOL_SPEED_BINS,
    range_bins: Sequence[float] = PROTOCOL_RANGE_BINS,
) -> dict:
    """:func:`protocol_metrics` over all points and each named split.

    Parameters
    ----------
    err : mapping with ``epe``, ``speed`` (px), ``noc`` (bool: ``gt.flow.valid``),
        ``range`` (m), ``object`` (``gt.object`` id) and optionally ``outside``
        (bool: ``gt.flow.outside``; absent in format-1 datasets, then none is
        outside), each shape (N,)
    moving : ids of the objects that move; every other id is the static scene.

    Returns
    -------
    dict with ``all``; ``region``: ``matched``, ``occluded``, ``outside``;
    ``rigid``: ``static``, ``moving``; ``speed`` and ``range``: one block per bin
    (labels from :func:`bin_label`), each a :func:`protocol_metrics` dict.
    """
    e = np.asarray(err["epe"], dtype=np.float64)
    v = np.asarray(err["speed"], dtype=np.float64)
    noc = np.asarray(err["noc"], dtype=bool)
    out_flag = np.asarray(err.get("outside", np.zeros(e.size)), dtype=bool)
    ids = np.rint(np.nan_to_num(np.asarray(err["object"], dtype=np.float64))).astype(np.int64)
    rng = np.asarray(err["range"], dtype=np.float64)
    is_moving = np.isin(ids, np.asarray(list(moving), dtype=np.int64))

    def block(sel: NDArray) -> dict[str, float]:
        return protocol_metrics(e[sel], v[sel])

    everything = np.ones(e.size, dtype=bool)
    out: dict = {
        "all": block(everything),
        "region": {
            "matched": block(noc),
            "occluded": block(~noc & ~out_flag),
            "outside": block(~noc & out_flag),
        },
        "rigid": {"static": block(~is_moving), "moving": block(is_moving)},
        "speed": {},
        "range": {},
    }
    for lo, hi in itertools.pairwise(speed_bins):
        out["speed"][bin_label(lo, hi, "px")] = block((v >= lo) & (v < hi))
    for lo, hi in itertools.pairwise(range_bins):
        out["range"][bin_label(lo, hi, "m")] = block((rng >= lo) & (rng < hi))
    return out


def bin_label(lo: float, hi: float, unit: str = "") -> str:
    """Label of the bin [lo, hi), e.g. ``"0.5-1px"`` or ``">=3px"``."""

    def fmt(v: float) -> str:
        return f"{v:g}"

    if math.isinf(hi):
        return f">={fmt(lo)}{unit}"
    return f"{fmt(lo)}-{fmt(hi)}{unit}"


def polar_components(
    x: ArrayLike, y: ArrayLike, dx: ArrayLike, dy: ArrayLike, x_c: float, y_c: float
) -> tuple[NDArray, NDArray]:
    """Polar displacement (dh, h dtheta) of the move (x, y) -> (x + dx, y + dy).

    Same definition as the dataset's ``gt.flow.dh`` and ``gt.flow.hdtheta``
    (``omniflow.conventions``): dh is the change of image radius, h dtheta the
    change of angle (wrapped to [-pi, pi)) times the radius at the start.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    u0, w0 = x - x_c, y - y_c
    u1, w1 = u0 + np.asarray(dx, dtype=np.float64), w0 + np.asarray(dy, dtype=np.float64)
    h0 = np.hypot(u0, w0)
    dh = np.hypot(u1, w1) - h0
    dth = np.arctan2(w1, u1) - np.arctan2(w0, u0)
    dth = (dth + np.pi) % (2 * np.pi) - np.pi
    return dh, h0 * dth


#: Below this rms of the true component (px) the gain and slope are not defined (NaN):
#: over points that do not move in that direction (a pure rotation radially, a static
#: scene) the ratio is noise over nothing and reaches 1e12.
MIN_TRUE_RMS = 0.01


def gain(est: ArrayLike, true: ArrayLike) -> dict[str, float]:
    """How much of the true component a method recovers, and its signed error.

    Parameters
    ----------
    est, true : array_like, shape (N,)
        Estimated and true values of one flow component (px per frame);
        non-finite pairs are left out.

    Returns
    -------
    dict with ``n``; ``gain`` = sum(est * true) / sum(true**2), the
    least-squares slope through the origin (1 = unbiased, 0 = predicts no
    motion); ``slope`` and ``intercept`` of the straight-line fit of est
    against true (NaN with fewer than 3 points or no spread of the truth);
    ``mean_signed`` and ``median_signed`` of ``est - true``; ``mean_est``
    and ``mean_true`` (the region's mean motion, e.g. an object's);
    ``true_rms``, the root mean square of the truth; ``gain_se``, the standard
    error of ``gain`` from the points' own scatter about it (heteroscedasticity-
    consistent, White's HC0: sqrt(sum true**2 r**2) / sum(true**2) with
    r = est - gain * true), large where a few points far off the line at large
    true motion set the gain (a mean over few points of small true motion is
    not a measurement of a shrink). ``gain``, ``gain_se``, ``slope`` and
    ``intercept`` are NaN where ``true_rms`` is below :data:`MIN_TRUE_RMS`.
    """
    e = np.asarray(est, dtype=np.float64).ravel()
    g = np.asarray(true, dtype=np.float64).ravel()
    ok = np.isfinite(e) & np.isfinite(g)
    e, g = e[ok], g[ok]
    nan = math.nan
    out = {"n": int(e.size), "gain": nan, "gain_se": nan, "slope": nan, "intercept": nan,
           "mean_signed": nan, "median_signed": nan, "mean_est": nan, "mean_true": nan,
           "true_rms": nan}  # fmt: skip
    if e.size == 0:
        return out
    d = e - g
    out.update(mean_signed=float(d.mean()), median_signed=float(np.median(d)),
               mean_est=float(e.mean()), mean_true=float(g.mean()),
               true_rms=float(np.sqrt(np.mean(g * g))))  # fmt: skip
    if out["true_rms"] < MIN_TRUE_RMS:
        return out
    gg = float(np.dot(g, g))
    if gg > 0:
        out["gain"] = k = float(np.dot(e, g) / gg)
        r = e - k * g
        out["gain_se"] = float(np.sqrt(np.dot(g * g, r * r)) / gg)
    if e.size >= 3 and np.ptp(g) > 0:
        fit = scipy.stats.linregress(g, e)
        out["slope"], out["intercept"] = float(fit.slope), float(fit.intercept)
    return out


def flow_errors(est: Mapping[str, ArrayLike], gt: Mapping[str, ArrayLike]) -> dict[str, NDArray]:
    """Per-point flow errors.

    Parameters
    ----------
    est : mapping with ``dx, dy, dh, hdtheta``, each shape (N,)
        The method's displacement per frame, pixels.
    gt : mapping with ``dx, dy, dh, hdtheta``, each shape (N,)
        The true displacement of the same points, pixels.

    Returns
    -------
    dict with ``epe``, ``err_dh``, ``err_hdtheta`` (absolute errors, px),
    ``ae`` (degrees), ``speed`` (true displacement magnitude, px), and for
    :func:`gain` the true components ``gt_dh``, ``gt_hdtheta`` and the
    estimated ones ``est_dh``, ``est_hdtheta`` (px).
    """
    edx, edy = (np.asarray(est[k], dtype=np.float64) for k in ("dx", "dy"))
    gdx, gdy = (np.asarray(gt[k], dtype=np.float64) for k in ("dx", "dy"))
    num = edx * gdx + edy * gdy + 1.0
    den = np.sqrt((edx**2 + edy**2 + 1.0) * (gdx**2 + gdy**2 + 1.0))
    with np.errstate(invalid="ignore"):
        ae = np.degrees(np.arccos(np.clip(num / den, -1.0, 1.0)))
    return {
        "epe": np.hypot(edx - gdx, edy - gdy),
        "err_dh": np.abs(np.asarray(est["dh"], dtype=np.float64) - np.asarray(gt["dh"])),
        "err_hdtheta": np.abs(
            np.asarray(est["hdtheta"], dtype=np.float64) - np.asarray(gt["hdtheta"])
        ),
        "ae": ae,
        "speed": np.hypot(gdx, gdy),
        "gt_dh": np.asarray(gt["dh"], dtype=np.float64),
        "gt_hdtheta": np.asarray(gt["hdtheta"], dtype=np.float64),
        "est_dh": np.asarray(est["dh"], dtype=np.float64),
        "est_hdtheta": np.asarray(est["hdtheta"], dtype=np.float64),
    }


def _flow_block(err: Mapping[str, NDArray], sel: NDArray) -> dict:
    epe = err["epe"][sel]
    return {
        "n": int(np.count_nonzero(sel)),
        "epe": stats(epe),
        "dh": stats(err["err_dh"][sel]),
        "hdtheta": stats(err["err_hdtheta"][sel]),
        "ae": stats(err["ae"][sel]),
        "out1": rate(epe > 1.0),
        "out3": rate(epe > 3.0),
        "radial": gain(err["est_dh"][sel], err["gt_dh"][sel]),
        "tangential": gain(err["est_hdtheta"][sel], err["gt_hdtheta"][sel]),
    }


def flow_summary(
    err: Mapping[str, NDArray],
    noc: ArrayLike,
    *,
    speed_bins: Sequence[float] = SPEED_BINS,
) -> dict:
    """Flow error statistics: all points, non-occluded, occluded, by speed.

    ``err`` is :func:`flow_errors`' output restricted to points with truth;
    ``noc`` (bool, same length) marks the points whose ``gt.flow.valid`` is 1.
    Speed bins are split on non-occluded points, as the benchmarks do.
    """
    noc = np.asarray(noc, dtype=bool)
    finite = np.isfinite(err["epe"])
    out = {
        "all": _flow_block(err, finite),
        "noc": _flow_block(err, finite & noc),
        "occ": _flow_block(err, finite & ~noc),
        "speed": {},
    }
    speed = err["speed"]
    for lo, hi in itertools.pairwise(speed_bins):
        sel = finite & noc & (speed >= lo) & (speed < hi)
        out["speed"][bin_label(lo, hi, "px")] = _flow_block(err, sel)
    return out


def stereo_errors(est: Mapping[str, ArrayLike], gt: Mapping[str, ArrayLike]) -> dict[str, NDArray]:
    """Per-match stereo errors.

    ``est`` holds the method's ``h2`` (px), ``r`` and ``h`` (m); ``gt`` the
    true ``h_other`` (px), ``r`` and ``h`` (m) at the same cam1 points. Gives
    ``err_h2`` (|h2 - h_other|, px), ``rel_r`` (|r - r_gt| / r_gt), ``err_h``
    (|h - h_gt|, m) and ``range`` (r_gt).
    """
    r_gt = np.asarray(gt["r"], dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel_r = np.abs(np.asarray(est["r"], dtype=np.float64) - r_gt) / r_gt
    return {
        "err_h2": np.abs(np.asarray(est["h2"], dtype=np.float64) - np.asarray(gt["h_other"])),
        "rel_r": rel_r,
        "err_h": np.abs(np.asarray(est["h"], dtype=np.float64) - np.asarray(gt["h"])),
        "range": r_gt,
    }


def _stereo_block(err: Mapping[str, NDArray], sel: NDArray) -> dict:
    return {
        "n": int(np.count_nonzero(sel)),
        "outliers": rate(err["err_h2"][sel] > 1.0),
        "err_h2": stats(err["err_h2"][sel]),
        "rel_r": stats(err["rel_r"][sel]),
        "err_h": stats(err["err_h"][sel]),
    }


def stereo_summary(
    err: Mapping[str, NDArray],
    *,
    n_matched: int,
    n_significant_valid: int | None,
    n_valid_pixels: int,
    range_bins: Sequence[float] = RANGE_BINS,
) -> dict:
    """Stereo statistics: match rate, density, outliers and r, h errors by range.

    Parameters
    ----------
    err : :func:`stereo_errors` output for the matches that have truth.
    n_matched : number of matches the method reported.
    n_significant_valid : significant points (the method's own selection) that
        the other camera really sees (``gt.stereo.valid``); None if unknown.
    n_valid_pixels : pixels of cam1 that see the scene (``gt.valid``).

    ``match_rate`` = matched / valid significant points; ``density`` =
    matched / valid pixels (matches per scene pixel).
    """
    has = np.isfinite(err["err_h2"]) & np.isfinite(err["rel_r"])
    out = {
        "n_matched": int(n_matched),
        "n_with_truth": int(np.count_nonzero(has)),
        "n_significant_valid": None if n_significant_valid is None else int(n_significant_valid),
        "match_rate": (n_matched / n_significant_valid if n_significant_valid else math.nan),
        "density": n_matched / n_valid_pixels if n_valid_pixels else math.nan,
        "all": _stereo_block(err, has),
        "range": {},
    }
    for lo, hi in itertools.pairwise(range_bins):
        sel = has & (err["range"] >= lo) & (err["range"] < hi)
        out["range"][bin_label(lo, hi, "m")] = _stereo_block(err, sel)
    return out
