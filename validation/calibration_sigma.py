"""Calibration of predicted standard deviations: does the error stay within k sigma?

A method that gives a sigma per point (omniflow's :attr:`OmniFlowResult.sigma`, or an
external method's optional ``sigma_flow1``, ``sigma_flow2``, ``sigma_r`` columns) is
scored on three quantities, each at the points that have truth:

* ``cam1``: the endpoint error of cam1's flow, hypot(dx - dx_gt, dy - dy_gt), px,
  against ``sigma_flow1`` (the predicted RMS endpoint error);
* ``cam2``: the same for cam2's flow (dx2, dy2 at (x2, y2)) against ``sigma_flow2``;
* ``range``: |r - r_gt|, m, at cam1's point where cam2 sees it too, against ``sigma_r``.

:func:`calibration_block` gives the share of points within 1 and 2 predicted sigma
(``within1``, ``within2``) and a reliability curve: the points binned by predicted
sigma (equal-count bins), each bin's median sigma against its observed 68.3 % and
95.4 % quantiles of the error (for a calibrated Gaussian error in one dimension, 1 and
2 sigma; the targets are the within-k shares, the curve shows where they fail).
Only finite sigmas are scored: a point whose sigma is inf (omniflow's eq. 14-flagged
points, :func:`omniflow.result.confident`) is counted in ``excluded`` instead.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .sampling import sample_truth

__all__ = [
    "QUANTITIES",
    "SIGMA_KEYS",
    "calibration",
    "calibration_block",
    "has_sigma",
    "sigma_errors",
    "within",
]

#: Each calibrated quantity, its sigma column and its unit.
QUANTITIES: dict[str, tuple[str, str]] = {
    "cam1": ("sigma_flow1", "px"),
    "cam2": ("sigma_flow2", "px"),
    "range": ("sigma_r", "m"),
}
SIGMA_KEYS = tuple(k for k, _ in QUANTITIES.values())

_FLOW = ("gt.valid", "gt.object", "gt.flow.dx", "gt.flow.dy")
_STEREO = ("gt.valid", "gt.object", "gt.stereo.valid", "gt.r")


def has_sigma(sigma: Mapping[str, Any] | None) -> bool:
    """Whether a result carries every sigma of :data:`SIGMA_KEYS`."""
    return bool(sigma) and all(k in sigma for k in SIGMA_KEYS)


def sigma_errors(
    cols: Mapping[str, NDArray], sigma: Mapping[str, NDArray], truth: Mapping[str, Mapping]
) -> dict[str, dict[str, NDArray]]:
    """Per quantity: ``err`` and ``sigma`` at the points with truth and a finite sigma,
    and ``excluded``, how many points with truth had none (not a confident answer).

    ``cols``: the method's per-point columns (x, y, dx, dy, x2, y2, dx2, dy2, r);
    ``truth``: each camera's ground-truth frame (``Dataset.read_frame``).
    """
    out = {}
    for cam, (x, y, dx, dy) in (("cam1", ("x", "y", "dx", "dy")),
                                ("cam2", ("x2", "y2", "dx2", "dy2"))):  # fmt: skip
        px, py = (np.asarray(cols[k], np.float64) for k in (x, y))
        tr = sample_truth(truth[cam], px, py, channels=_FLOW)
        err = np.hypot(np.asarray(cols[dx], np.float64) - tr["gt.flow.dx"],
                       np.asarray(cols[dy], np.float64) - tr["gt.flow.dy"])  # fmt: skip
        out[cam] = _kept(tr["bilinear_ok"] & (tr["gt.valid"] > 0.5), err,
                         sigma[QUANTITIES[cam][0]])  # fmt: skip
    px, py = (np.asarray(cols[k], np.float64) for k in ("x", "y"))
    tr = sample_truth(truth["cam1"], px, py, channels=_STEREO)
    err = np.abs(np.asarray(cols["r"], np.float64) - tr["gt.r"])
    ok = tr["bilinear_ok"] & (tr["gt.valid"] > 0.5) & (tr["gt.stereo.valid"] > 0.5)
    out["range"] = _kept(ok, err, sigma["sigma_r"])
    return out


def _kept(ok: NDArray, err: NDArray, sigma: ArrayLike) -> dict[str, Any]:
    """The points with truth and a finite sigma; ``excluded``: those with truth whose
    sigma is not finite (omniflow's flagged points, sigma inf: no confident answer)."""
    s = np.asarray(sigma, np.float64)
    scored = ok & np.isfinite(err)
    finite = np.isfinite(s) & (s >= 0)
    keep = scored & finite
    return {"err": err[keep], "sigma": s[keep], "excluded": int(np.sum(scored & ~finite))}


def within(err: NDArray, sigma: NDArray, k: float) -> float:
    """Share of points whose error is at most k predicted sigma (NaN with no point)."""
    err, sigma = np.asarray(err), np.asarray(sigma)
    return float(np.mean(err <= k * sigma)) if err.size else math.nan


def calibration_block(records: Sequence[Mapping[str, NDArray]], *, bins: int = 8) -> dict[str, Any]:
    """Coverage and reliability of one quantity over frames' :func:`sigma_errors` records.

    Returns ``n``, ``excluded`` (points with truth left out for a sigma that is not
    finite), ``within1``, ``within2``, ``sigma_median`` and ``reliability`` (per
    equal-count bin of predicted sigma: ``n``, ``sigma`` (its median), ``q68``,
    ``q95`` (observed error quantiles 68.3 % and 95.4 %), ``within2``).
    """
    err = np.concatenate([np.asarray(r["err"], np.float64) for r in records] or [np.zeros(0)])
    sig = np.concatenate([np.asarray(r["sigma"], np.float64) for r in records] or [np.zeros(0)])
    out: dict[str, Any] = {
        "n": int(err.size),
        "excluded": int(sum(int(r.get("excluded", 0)) for r in records)),
        "within1": within(err, sig, 1.0),
        "within2": within(err, sig, 2.0),
        "sigma_median": float(np.median(sig)) if sig.size else math.nan,
        "reliability": [],
    }
    if err.size == 0:
        return out
    order = np.argsort(sig, kind="stable")
    for part in np.array_split(order, min(bins, err.size)):
        e, s = err[part], sig[part]
        out["reliability"].append({
            "n": int(part.size),
            "sigma": float(np.median(s)),
            "q68": float(np.quantile(e, 0.683)),
            "q95": float(np.quantile(e, 0.954)),
            "within2": within(e, s, 2.0),
        })  # fmt: skip
    return out


def calibration(frames: Sequence[Mapping[str, Mapping[str, NDArray]]]) -> dict[str, Any]:
    """:func:`calibration_block` of each quantity over a method's per-frame records, with
    its sigma column and unit."""
    out = {}
    for q, (key, unit) in QUANTITIES.items():
        out[q] = {"sigma": key, "unit": unit,
                  **calibration_block([f[q] for f in frames if q in f])}  # fmt: skip
    return out
