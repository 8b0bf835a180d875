"""Score a method we did not write: its outputs, read from a directory laid out like the dataset.

``omnivalidate DATASET --method-output DIR [--method-name NAME]`` reads, for every
scored frame pair t -> t + 1, one of two formats (the first found decides):

* **dense flow**: ``DIR/frames/NNNNNN/cam1.flo`` and ``cam2.flo`` (Middlebury
  ``.flo``, the image-plane displacement (dx, dy) in pixels from frame t to
  t + 1 at every pixel, ``NNNNNN`` = t, the dataset's own layout; unknown
  values as Middlebury's 1e10 or NaN). Scored like a baseline: at every valid
  pixel and at the default omniflow variant's points.
* **per-point CSV**: ``DIR/frames/NNNNNN/flow.csv`` with omniflow's columns
  (``omniflow.pipeline.COLUMNS``; lines starting with ``#`` are skipped, then a
  header row). Required: ``x, y, dx, dy`` (cam1 pixel and its flow). Optional:
  ``x2, y2, dx2, dy2`` (cam2), ``h1, dh1_dt, dtheta_dt`` (else the polar
  components come from dx, dy), ``h2, r, h`` (stereo is scored), ``theta,
  dr_dt`` (dr/dt, time to contact and odometry are scored), ``sigma_flow1,
  sigma_flow2, sigma_r`` (the predicted RMS endpoint error of each camera's flow, px,
  and the standard deviation of r, m: their calibration is scored,
  :mod:`validation.calibration_sigma`; any one may be given alone). Scored like an
  omniflow variant, at its own points.

Missing files for a scored pair are an error naming them (score fewer pairs
with ``--frames``). Times are not known for external outputs (shown as -).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .baselines import DenseFlow
from .calibration_sigma import SIGMA_KEYS
from .inputs import InputError
from .metrics import polar_components

__all__ = ["ExternalOutput", "PointsResult"]

#: Columns the harness reads from a per-point result (missing ones are NaN).
POINT_COLUMNS = ("x", "y", "theta", "h1", "h2", "r", "h", "dh1_dt", "dtheta_dt", "dr_dt", "dx",
                 "dy", "x2", "y2", "dh2_dt", "dx2", "dy2")  # fmt: skip


class PointsResult:
    """A per-point result in the shape of ``OmniFlowResult`` (columns, timings)."""

    def __init__(self, columns: dict[str, NDArray], sigma: dict[str, NDArray] | None = None):
        self.columns = columns
        self.sigma = sigma or {}
        self.timings: dict[str, float] = {}
        self.n_significant = None


class ExternalOutput:
    """The outputs of one external method in ``directory`` (see the module docstring)."""

    def __init__(self, directory: str | Path, name: str | None = None):
        self.dir = Path(directory)
        if not self.dir.is_dir():
            raise InputError(f"--method-output {self.dir}: no such directory")
        frames = self.dir / "frames"
        if any(frames.glob("*/cam1.flo")):
            self.kind = "dense"
        elif any(frames.glob("*/flow.csv")):
            self.kind = "points"
        else:
            raise InputError(
                f"--method-output {self.dir}: found neither frames/NNNNNN/cam1.flo nor "
                "frames/NNNNNN/flow.csv; expected one of the layouts of docs/validation.md"
            )
        self.name = name or self.dir.name

    def _path(self, t: int, file: str) -> Path:
        return self.dir / "frames" / f"{t:06d}" / file

    def check(self, pairs: list[int]) -> None:
        """Raise InputError naming the missing files of the pairs to score."""
        files = ("cam1.flo", "cam2.flo") if self.kind == "dense" else ("flow.csv",)
        missing = [str(self._path(t, f)) for t in pairs for f in files
                   if not self._path(t, f).is_file()]  # fmt: skip
        if missing:
            more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
            raise InputError(
                f"--method-output {self.dir}: missing {', '.join(missing[:3])}{more} "
                f"({len(missing)} of {len(pairs) * len(files)} files); score fewer pairs "
                "with --frames"
            )

    def dense(self, t: int, cam: str, unit: Any, shape: tuple[int, int]) -> DenseFlow:
        """The method's flow of camera ``cam`` from frame t to t + 1, NaN where unknown."""
        from omniflow.io.dataset import DatasetError, read_flo

        path = self._path(t, f"{cam}.flo")
        try:
            flow, valid = read_flo(path)
        except DatasetError as exc:
            raise InputError(str(exc).splitlines()[0]) from exc
        if flow.shape[:2] != tuple(shape):
            raise InputError(
                f"{path}: flow is {flow.shape[1]}x{flow.shape[0]}, expected the dataset's "
                f"{shape[1]}x{shape[0]}"
            )
        flow = np.where(valid[..., None], flow, np.float32(np.nan)).astype(np.float32)
        return DenseFlow(flow=flow, unit=unit, seconds=math.nan)

    def points(self, t: int, rig: Any) -> PointsResult:
        """The method's per-point result for the pair t -> t + 1."""
        path = self._path(t, "flow.csv")
        try:
            with path.open(newline="") as fh:
                rows = list(csv.reader(line for line in fh if not line.startswith("#")))
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"{path}: cannot read: {exc}") from exc
        if not rows:
            raise InputError(f"{path}: empty; expected a header row with x, y, dx, dy")
        header = [h.strip() for h in rows[0]]
        need = [c for c in ("x", "y", "dx", "dy") if c not in header]
        if need:
            raise InputError(f"{path}: no column(s) {need}; expected omniflow's columns")
        try:
            data = np.array([[float(v) for v in r] for r in rows[1:] if r], dtype=np.float64)
        except ValueError as exc:
            raise InputError(f"{path}: {exc}; expected numbers") from exc
        data = data.reshape(-1, len(header))
        cols = {h: data[:, i] for i, h in enumerate(header)}
        n = data.shape[0]
        out = {c: cols.get(c, np.full(n, np.nan)) for c in POINT_COLUMNS}
        for cam, (xs, ys, dxs, dys, hs, dhs) in {
            "cam1": ("x", "y", "dx", "dy", "h1", "dh1_dt"),
            "cam2": ("x2", "y2", "dx2", "dy2", "h2", "dh2_dt"),
        }.items():
            unit = rig.cam1 if cam == "cam1" else rig.cam2
            h, theta = unit.polar_of_pixel(out[xs], out[ys])
            if hs not in cols:
                out[hs] = h
            if cam == "cam1" and "theta" not in cols:
                out["theta"] = theta
            dh, hdth = polar_components(out[xs], out[ys], out[dxs], out[dys], unit.x_c, unit.y_c)
            if dhs not in cols:
                out[dhs] = dh
            if cam == "cam1" and "dtheta_dt" not in cols:
                with np.errstate(invalid="ignore", divide="ignore"):
                    out["dtheta_dt"] = hdth / out["h1"]
        given = [k for k in SIGMA_KEYS if k in cols]  # optional predicted sigmas
        sigma = {k: cols.get(k, np.full(n, np.nan)) for k in SIGMA_KEYS} if given else None
        return PointsResult(out, sigma)
