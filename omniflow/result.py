"""What the stereo omni flow step returns: :class:`OmniFlowResult`.

One row per matched point, the columns and their units in :data:`COLUMNS`;
with no match, every column has length 0 and :class:`NoMatchesWarning` says so.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from omniflow.config import OmniFlowConfig

__all__ = [
    "COLUMNS",
    "MONOCULAR_COLUMNS",
    "SIGMA_COLUMNS",
    "NoMatchesWarning",
    "OmniFlowResult",
    "confident",
    "no_points",
]


#: Output columns and their units, in CSV order.
COLUMNS: dict[str, str] = {
    "x": "px, cam1 column coordinate (pixel centre j + 0.5)",
    "y": "px, cam1 row coordinate",
    "theta": "rad, azimuth (theta_1 = theta_2)",
    "h1": "px, cam1 image radius",
    "h2": "px, matched cam2 image radius",
    "r": "m, range from the axis (eq. 5)",
    "h": "m, height above cam2's tip (eq. 4)",
    "dh1_dt": "px/frame, cam1 radial flow",
    "dtheta_dt": "rad/frame, angular flow",
    "dr_dt": "m/frame, radial velocity -(d + r) dh1_dt / h1 (decoupled: from dh1_dt and dh2_dt)",
    "dx": "px/frame, cam1 flow along x",
    "dy": "px/frame, cam1 flow along y",
    "x2": "px, cam2 column coordinate",
    "y2": "px, cam2 row coordinate",
    "dh2_dt": "px/frame, cam2 radial flow: (h2/h1) dh1_dt (eq. 14) where coupled, else its own",
    "dx2": "px/frame, cam2 flow along x",
    "dy2": "px/frame, cam2 flow along y",
    "score": "1, stereo match score (NCC or gradient similarity)",
    "confidence": "1, lambda_min/lambda_max of the flow system's normal matrix",
    "D": "grey^2/(px rad), determinant of eq. (16)",
    "f1_h": "grey/px, df1/dh_1 used in eq. (9)",
    "f1_theta": "grey/rad, df1/dtheta used in eq. (9)",
    "f1_t": "grey/frame, df1/dt used in eq. (9)",
    "f2_h": "grey/px, df2/dh_2 used in eq. (15)",
    "f2_theta": "grey/rad, df2/dtheta used in eq. (15)",
    "f2_t": "grey/frame, df2/dt used in eq. (15)",
    "coupled": "1/0, eq. (14) ties dh2_dt to dh1_dt (0: flagged, the eq. 14 test failed: "
    "decoupled, omniflow.solve.decoupled, not a confident answer)",
}


#: The predicted standard deviations (:attr:`OmniFlowResult.sigma`,
#: :mod:`omniflow.solve.sigma`) and their units, in CSV order after the columns.
#: Where ``coupled`` = 0 (the eq. 14 test failed) ``sigma_flow2`` and ``sigma_r`` are inf:
#: no confident answer (:func:`confident`).
SIGMA_COLUMNS: dict[str, str] = {
    "sigma_flow1": "px/frame, predicted RMS endpoint error of cam1's (dx, dy)",
    "sigma_flow2": "px/frame, predicted RMS endpoint error of cam2's (dx2, dy2); "
    "inf where coupled = 0 (not a confident answer)",
    "sigma_r": "m, predicted standard deviation of r; inf where coupled = 0 "
    "(not a confident answer)",
}


def confident(columns: Mapping[str, NDArray], sigma: Mapping[str, NDArray]) -> NDArray:
    """The confident answers, one bool per point: eq. (14) kept (``coupled`` = 1) and
    every sigma of :data:`SIGMA_COLUMNS` finite.

    A flagged point (``coupled`` = 0) is never one: its ``sigma_flow2`` and ``sigma_r``
    are inf (:mod:`omniflow.solve.sigma`, docs/decisions/confidence.md). No sigma
    predicted: no point is confident.
    """
    if not sigma or any(k not in sigma for k in SIGMA_COLUMNS):
        return np.zeros(np.size(next(iter(columns.values()), ())), bool)
    ok = np.ones(np.size(sigma["sigma_flow1"]), bool)
    if "coupled" in columns:
        ok &= np.asarray(columns["coupled"], np.float64) > 0.5
    for k in SIGMA_COLUMNS:
        ok &= np.isfinite(np.asarray(sigma[k], np.float64))
    return ok


#: Columns of :attr:`OmniFlowResult.monocular` and their units.
MONOCULAR_COLUMNS: dict[str, str] = {
    "x": "px, cam1 column coordinate (pixel centre j + 0.5)",
    "y": "px, cam1 row coordinate",
    "theta": "rad, azimuth",
    "h1": "px, cam1 image radius",
    "dh1_dt": "px/frame, cam1 radial flow (cam1 alone)",
    "dtheta_dt": "rad/frame, angular flow (cam1 alone)",
    "dx": "px/frame, cam1 flow along x",
    "dy": "px/frame, cam1 flow along y",
    "confidence": "1, lambda_min/lambda_max of the pooled normal matrix",
    "f1_h": "grey/px, df1/dh_1 used in eq. (9)",
    "f1_theta": "grey/rad, df1/dtheta used in eq. (9)",
    "f1_t": "grey/frame, df1/dt used in eq. (9)",
}


@dataclass
class OmniFlowResult:
    """Per-point results of :func:`estimate`.

    Attributes
    ----------
    columns : dict[str, ndarray]
        Equal-length 1-D arrays, keys and units in :data:`COLUMNS`.
    timings : dict[str, float]
        Seconds per stage: ``fit``, ``grids``, ``match``, ``sample``,
        ``solve``, ``total``.
    config : OmniFlowConfig
    n_significant : int
        Significant points of image 1 that the matcher tried.
    diagnostics : dict[str, float]
        ``flow_band`` (the flow step's DCT band, chosen or given),
        ``noise_sigma1``, ``noise_sigma2`` (the image noise used per unit,
        grey levels; 0 when not needed).
    monocular : dict[str, ndarray]
        With ``config.monocular_gap``: cam1's flow alone where no stereo match is
        near (:mod:`omniflow.solve.monocular`, columns in its ``MONOCULAR_COLUMNS``);
        else empty.
    sigma : dict[str, ndarray]
        The predicted standard deviation of each point's flow per unit and of its
        range (keys and units in :data:`SIGMA_COLUMNS`, :mod:`omniflow.solve.sigma`),
        the same length as the columns; empty where not predicted. Made when first
        read (:meth:`defer_sigma`; its seconds then in ``timings["sigma"]``, not in
        ``total``), so a caller that never reads it does not pay for it.
    confident : ndarray of bool
        (property) The confident answers, :func:`confident` of the columns and sigmas.
    """

    columns: dict[str, NDArray]
    timings: dict[str, float] = field(default_factory=dict)
    config: OmniFlowConfig | None = None
    n_significant: int = 0
    diagnostics: dict[str, float] = field(default_factory=dict)
    monocular: dict[str, NDArray] = field(default_factory=dict)
    _sigma: dict[str, NDArray] | Callable[[], dict[str, NDArray]] = field(
        default_factory=dict, repr=False
    )

    @property
    def sigma(self) -> dict[str, NDArray]:
        if callable(self._sigma):  # made on first reading (defer_sigma)
            t0 = time.perf_counter()
            self._sigma = self._sigma()
            self.timings["sigma"] = time.perf_counter() - t0
        return self._sigma

    @sigma.setter
    def sigma(self, value: dict[str, NDArray]) -> None:
        self._sigma = value

    @property
    def confident(self) -> NDArray:
        """:func:`confident` of the columns and :attr:`sigma` (reads the sigmas)."""
        return confident(self.columns, self.sigma)

    def defer_sigma(self, make: Callable[[], dict[str, NDArray]]) -> None:
        """Make :attr:`sigma` with ``make()`` when it is first read."""
        self._sigma = make

    def __len__(self) -> int:
        return int(next(iter(self.columns.values())).size) if self.columns else 0

    def __getitem__(self, key: str) -> NDArray:
        if key not in self.columns and key in self.sigma:
            return self.sigma[key]
        return self.columns[key]

    def to_csv(self, path: str | Path, units: Mapping[str, str] | None = None) -> Path:
        """Write the columns, then :attr:`sigma`'s, to CSV atomically, with a '#' header
        line of units.

        ``units`` names the unit of columns added after :func:`estimate` (the
        CLI's ``odometry_inlier``, ``auto_region``, ...); :data:`COLUMNS` gives
        the rest.
        """
        cols = {**self.columns, **{k: v for k, v in self.sigma.items() if k not in self.columns}}
        known = {**COLUMNS, **SIGMA_COLUMNS, **(units or {})}
        return _write_csv(path, cols, known, "per-point results")

    def monocular_to_csv(self, path: str | Path) -> Path:
        """Write :attr:`monocular` to CSV atomically, like :meth:`to_csv`."""
        cols = self.monocular or {name: np.zeros(0) for name in MONOCULAR_COLUMNS}
        return _write_csv(path, cols, MONOCULAR_COLUMNS, "cam1-only flow (no stereo match near)")


def _write_csv(
    path: str | Path, columns: Mapping[str, NDArray], known: Mapping[str, str], title: str
) -> Path:
    """Columns to CSV atomically: a '#' line naming each column's unit, then the header."""
    from omniflow.io.imageio import atomic_output

    names = list(columns)
    data = (
        np.column_stack([np.asarray(columns[k], dtype=float) for k in names])
        if names
        else np.zeros((0, 0))
    )
    line = "; ".join(f"{k}: {known.get(k, '')}" for k in names)
    path = Path(path)
    with atomic_output(path) as tmp, open(tmp, "w") as fh:
        fh.write(f"# omniflow {title}; {line}\n")
        fh.write(",".join(names) + "\n")
        np.savetxt(fh, data, delimiter=",", fmt="%.9g")
    return path


class NoMatchesWarning(UserWarning):
    """:func:`estimate` found no stereo match, so its result has no points.

    Zero matches is an answer, not an error: a dark or lens-capped frame, a
    constant image, or a rig whose units share no range in the searched window
    leave nothing to measure. The result then has every column, each of length 0.
    """


def no_points(timings: dict, t_start: float, config, n_sig: int) -> OmniFlowResult:
    """The empty result (every column of :data:`COLUMNS`, length 0) with a warning."""
    warnings.warn(
        f"no stereo matches ({n_sig} significant points in cam1 tried): the result is empty "
        "(is the image dark, constant, or outside the units' common view?)",
        NoMatchesWarning,
        stacklevel=3,
    )
    timings.update(sample=0.0, solve=0.0, total=time.perf_counter() - t_start)
    columns = {name: np.zeros(0) for name in COLUMNS}
    sigma = {name: np.zeros(0) for name in SIGMA_COLUMNS}
    return OmniFlowResult(
        columns=columns, timings=timings, config=config, n_significant=n_sig, _sigma=sigma
    )
