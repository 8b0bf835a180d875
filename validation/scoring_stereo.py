"""Stereo scoring: the matched h_2, r and h of a method's points against the truth."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .metrics import stereo_errors, stereo_summary
from .results import Results
from .sampling import sample_truth

__all__ = ["STEREO_TRUTH", "score_stereo"]


STEREO_TRUTH = (
    "gt.valid",
    "gt.object",
    "gt.stereo.valid",
    "gt.stereo.h_other",
    "gt.r",
    "gt.h",
    "gt.X",
    "gt.Y",
    "gt.Z",
)


def score_stereo(
    results: Results, name: str, cols: dict, res: Any, truth: dict[str, NDArray], t: int
) -> dict[str, Any]:
    x = np.asarray(cols["x"], np.float64)
    y = np.asarray(cols["y"], np.float64)
    tr = sample_truth(truth, x, y, channels=STEREO_TRUTH)
    has = tr["bilinear_ok"] & (tr["gt.stereo.valid"] > 0.5)
    err = stereo_errors(
        {
            "h2": np.asarray(cols["h2"])[has],
            "r": np.asarray(cols["r"])[has],
            "h": np.asarray(cols["h"])[has],
        },
        {"h_other": tr["gt.stereo.h_other"][has], "r": tr["gt.r"][has], "h": tr["gt.h"][has]},
    )
    results.stereo[name].append(err)
    counts = results.stereo_counts[name]
    counts["matched"] += int(x.size)
    counts["valid_pixels"] += int(np.count_nonzero(truth["gt.valid"] > 0.5))
    n_sig = n_significant_valid(res)
    if n_sig is None:
        counts["significant_unknown"] = 1
    else:
        counts["significant_valid"] += n_sig
    s = stereo_summary(
        err,
        n_matched=x.size,
        n_significant_valid=n_sig,
        n_valid_pixels=int(np.count_nonzero(truth["gt.valid"] > 0.5)),
    )
    return {
        "stereo_n": s["all"]["n"],
        "stereo_outliers": s["all"]["outliers"],
        "match_rate": s["match_rate"],
        "density": s["density"],
        "rel_r_median": s["all"]["rel_r"]["median"],
        "err_h_median_m": s["all"]["err_h"]["median"],
    }


def n_significant_valid(result: Any) -> int | None:
    """The number of significant points matching started from (``n_significant``)."""
    n = result.n_significant
    return None if n is None else int(n)
