"""Flow scoring: a method's flow at its points (or dense) against the truth, per frame."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .metrics import flow_errors, flow_summary, stats
from .sampling import sample_truth

__all__ = ["FLOW_TRUTH", "coverage", "flow_row", "omniflow_points", "score_dense", "score_flow"]


FLOW_TRUTH = (
    "gt.valid",
    "gt.object",
    "gt.flow.valid",
    "gt.flow.dx",
    "gt.flow.dy",
    "gt.flow.dh",
    "gt.flow.hdtheta",
    "gt.r",
)


def score_flow(
    est: dict[str, NDArray], x: NDArray, y: NDArray, truth: dict[str, NDArray]
) -> dict[str, NDArray]:
    tr = sample_truth(truth, x, y, channels=FLOW_TRUTH)
    has = tr["bilinear_ok"] & (tr["gt.valid"] > 0.5)
    for k in ("dx", "dy", "dh", "hdtheta"):
        has &= np.isfinite(est[k])
    err = flow_errors(
        {k: np.asarray(est[k])[has] for k in ("dx", "dy", "dh", "hdtheta")},
        {k: tr[f"gt.flow.{k}"][has] for k in ("dx", "dy", "dh", "hdtheta")},
    )
    err["noc"] = tr["gt.flow.valid"][has] > 0.5
    err["outside"] = _outside(truth, x, y)[has]
    err["range"] = tr["gt.r"][has]
    err["object"] = tr["gt.object"][has]
    err["n_points"] = np.asarray(x).size
    err.update(coverage(truth))
    return err


def _outside(truth: dict[str, NDArray], x: NDArray, y: NDArray) -> NDArray:
    """``gt.flow.outside`` at the pixel holding each point (a flag: nearest, not
    interpolated); all False for a format-1 dataset, which has no such channel."""
    x = np.asarray(x, dtype=np.float64)
    if "gt.flow.outside" not in truth:
        return np.zeros(x.shape, dtype=bool)
    ch = truth["gt.flow.outside"]
    h, w = ch.shape
    ok = np.isfinite(x) & np.isfinite(y)
    j = np.clip(np.floor(np.where(ok, x, 0.0)).astype(np.int64), 0, w - 1)
    i = np.clip(np.floor(np.where(ok, y, 0.0)).astype(np.int64), 0, h - 1)
    return ok & (ch[i, j] > 0.5)


def coverage(truth: dict[str, NDArray]) -> dict[str, Any]:
    """The pixels a method could have scored in this frame: the denominators of density.

    ``n_valid_pixels`` see the scene (``gt.valid``), ``n_stereo_pixels`` also are
    seen by the other camera (``gt.stereo.valid``), ``object_pixels`` maps each
    ``gt.object`` id to its valid pixels.
    """
    valid = truth["gt.valid"] > 0.5
    ids = np.rint(truth["gt.object"][valid]).astype(np.int64)
    counts = np.bincount(ids[ids >= 0]) if ids.size else np.zeros(0, np.int64)
    return {
        "n_valid_pixels": int(np.count_nonzero(valid)),
        "n_stereo_pixels": int(np.count_nonzero(valid & (truth["gt.stereo.valid"] > 0.5))),
        "object_pixels": {int(i): int(c) for i, c in enumerate(counts) if c},
    }


def score_dense(
    flow_at: Callable[..., dict[str, NDArray]], truth: dict[str, NDArray], dense: NDArray | None
) -> dict[str, NDArray]:
    """Score a dense field at every pixel centre that sees the scene."""
    valid = truth["gt.valid"] > 0.5
    ii, jj = np.nonzero(valid)
    x, y = jj + 0.5, ii + 0.5
    if dense is not None:
        est = {"dx": dense[ii, jj, 0].astype(np.float64), "dy": dense[ii, jj, 1].astype(np.float64)}
        from .metrics import polar_components

        unit_c = truth["_centre"]
        est["dh"], est["hdtheta"] = polar_components(x, y, est["dx"], est["dy"], *unit_c)
    else:
        est = flow_at(x, y)
    gt = {
        k: truth[f"gt.flow.{k}"][ii, jj].astype(np.float64) for k in ("dx", "dy", "dh", "hdtheta")
    }
    has = np.all([np.isfinite(v) for v in (*est.values(), *gt.values())], axis=0)
    err = flow_errors({k: v[has] for k, v in est.items()}, {k: v[has] for k, v in gt.items()})
    err["noc"] = truth["gt.flow.valid"][ii, jj][has] > 0.5
    if "gt.flow.outside" in truth:
        err["outside"] = truth["gt.flow.outside"][ii, jj][has] > 0.5
    else:  # a format-1 dataset: no outside split (see metrics.protocol_splits)
        err["outside"] = np.zeros(int(np.count_nonzero(has)), dtype=bool)
    err["range"] = truth["gt.r"][ii, jj][has].astype(np.float64)
    err["object"] = truth["gt.object"][ii, jj][has].astype(np.float64)
    err["n_points"] = x.size
    err.update(coverage(truth))
    return err


def omniflow_points(cols: dict[str, NDArray], cam: str) -> tuple[NDArray, NDArray, dict]:
    """Points and flow of one camera from OmniFlowResult.columns."""
    if cam == "cam1":
        x, y, h = cols["x"], cols["y"], cols["h1"]
        est = {
            "dx": cols["dx"],
            "dy": cols["dy"],
            "dh": cols["dh1_dt"],
            "hdtheta": h * cols["dtheta_dt"],
        }
    else:
        x, y, h = cols["x2"], cols["y2"], cols["h2"]
        est = {
            "dx": cols["dx2"],
            "dy": cols["dy2"],
            "dh": cols["dh2_dt"],
            "hdtheta": h * cols["dtheta_dt"],
        }
    return (
        np.asarray(x, np.float64),
        np.asarray(y, np.float64),
        {k: np.asarray(v, np.float64) for k, v in est.items()},
    )


def flow_row(t: int, method: str, points: str, cam: str, err: dict, seconds: float) -> dict:
    s = flow_summary(err, err["noc"])
    row: dict[str, Any] = {
        "frame": t,
        "method": method,
        "points": points,
        "camera": cam,
        "n_points": int(err["n_points"]),
        "n_with_truth": s["all"]["n"],
        "density_valid": (
            s["all"]["n"] / err["n_valid_pixels"] if err["n_valid_pixels"] else math.nan
        ),
        "density_stereo": (
            s["all"]["n"] / err["n_stereo_pixels"] if err["n_stereo_pixels"] else math.nan
        ),
        "epe_median": s["all"]["epe"]["median"],
        "epe_mean": s["all"]["epe"]["mean"],
        "epe_p90": s["all"]["epe"]["p90"],
        "dh_median": s["all"]["dh"]["median"],
        "hdtheta_median": s["all"]["hdtheta"]["median"],
        "ae_median_deg": s["all"]["ae"]["median"],
        "out1": s["all"]["out1"],
        "out3": s["all"]["out3"],
        "noc_n": s["noc"]["n"],
        "noc_epe_median": s["noc"]["epe"]["median"],
        "occ_n": s["occ"]["n"],
        "occ_epe_median": s["occ"]["epe"]["median"],
        "speed_median_px": stats(err["speed"])["median"],
        "time_s": seconds,
    }
    for comp in ("radial", "tangential"):
        g = s["all"][comp]
        for key in ("gain", "slope", "mean_signed"):
            row[f"{comp}_{key}"] = g[key]
    return row
