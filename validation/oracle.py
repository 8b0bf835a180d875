"""A perfect "method" built from the ground truth, for testing the harness itself.

:class:`TruthOracle` has the signature of :func:`omniflow.pipeline.estimate`
and returns, at a grid of cam1 pixel centres that both cameras see, exactly
the dataset's truth in omniflow's output columns. Scored by the harness it
must come out with zero error; any other figure means the harness, not the
method, is wrong.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .sampling import sample_truth

__all__ = ["OracleConfig", "OracleResult", "TruthOracle"]


@dataclass(frozen=True)
class OracleConfig:
    """Stand-in for OmniFlowConfig (the runner names rows by these fields)."""

    match_method: str = "truth"
    step: int = 3


@dataclass
class OracleResult:
    columns: dict[str, NDArray]
    timings: dict[str, float] = field(default_factory=dict)
    n_significant: int = 0


class TruthOracle:
    """``estimate(frames1, frames2, rig, config, *, t)`` answering from the truth.

    The runner passes frame windows, not frame numbers, so the oracle counts
    its calls: construct it for one dataset and one variant, and score the
    pairs in order (``run_validation(..., variants=[(name, OracleConfig())])``).
    """

    def __init__(self, dataset_dir: str | Path):
        from omniflow.io.dataset import open_dataset

        self.ds = open_dataset(dataset_dir)
        self.pairs = [t for t in range(self.ds.frame_count - 1)]
        self.calls = 0

    def __call__(
        self, frames1: Any, frames2: Any, rig: Any, config: OracleConfig, *, t: int = 0
    ) -> OracleResult:
        k = self.pairs[self.calls % len(self.pairs)]
        self.calls += 1
        g1, g2 = self.ds.read_frame(k, "cam1"), self.ds.read_frame(k, "cam2")
        ii, jj = np.nonzero(g1["gt.stereo.valid"] > 0.5)
        ii, jj = ii[:: config.step], jj[:: config.step]
        x, y = jj + 0.5, ii + 0.5
        tr = sample_truth(g1, x, y)
        keep = tr["bilinear_ok"]
        x, y = x[keep], y[keep]
        tr = {name: v[keep] for name, v in tr.items()}
        h1, theta = rig.cam1.polar_of_pixel(x, y)
        h2 = tr["gt.stereo.h_other"]
        x2, y2 = rig.cam2.pixel_of_polar(h2, theta)
        t2 = sample_truth(g2, x2, y2)
        dtheta = tr["gt.flow.hdtheta"] / h1
        nan = np.full(x.size, np.nan)
        cols = {
            "x": x, "y": y, "theta": theta, "h1": h1, "h2": h2, "r": tr["gt.r"], "h": tr["gt.h"],
            "dh1_dt": tr["gt.flow.dh"], "dtheta_dt": dtheta, "dr_dt": nan,
            "dx": tr["gt.flow.dx"], "dy": tr["gt.flow.dy"], "x2": x2, "y2": y2,
            "dh2_dt": t2["gt.flow.dh"], "dx2": t2["gt.flow.dx"], "dy2": t2["gt.flow.dy"],
            "confidence": np.ones(x.size), "D": np.ones(x.size),
        }  # fmt: skip
        return OracleResult(columns=cols, timings={"total": 0.0}, n_significant=int(x.size))
