"""What a validation run produced: the container the summary and the report read.

Filled by :func:`validation.runner.run_validation`; importing it does not import
the runner, the methods or OpenCV.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

from numpy.typing import NDArray

__all__ = ["FramePair", "MethodInfo", "Results"]


@dataclass
class MethodInfo:
    name: str
    kind: str  # "omniflow" | "baseline"
    config: dict[str, Any] = field(default_factory=dict)
    default: bool = False
    paper: bool = False  # OmniFlowConfig.paper(), on the method's own matches


@dataclass
class FramePair:
    """What the report draws: the inputs and outputs of the first scored pair."""

    t: int
    images: dict[str, NDArray]  # cam -> uint8 (H, W) at t
    truth: dict[str, dict[str, NDArray]]  # cam -> gt channels at t
    dense: dict[str, dict[str, NDArray]]  # baseline -> cam -> (H, W, 2)
    points: dict[str, dict[str, NDArray]]  # cam -> x, y, dx, dy, epe (default omniflow)
    panorama: NDArray | None = None  # uint8 panorama of cam1 at t


@dataclass
class Results:
    """Everything the report needs, filled by :func:`run_validation`."""

    dataset: dict[str, Any]
    methods: list[MethodInfo]
    rows: list[dict[str, Any]] = field(default_factory=list)
    #: (method, points, cam) -> list of per-frame flow error dicts (with "noc", "range")
    flow: dict[tuple[str, str, str], list[dict[str, NDArray]]] = field(
        default_factory=lambda: defaultdict(list)
    )
    #: method -> list of per-frame stereo error dicts, and counts
    stereo: dict[str, list[dict[str, NDArray]]] = field(default_factory=lambda: defaultdict(list))
    stereo_counts: dict[str, dict[str, int]] = field(
        default_factory=lambda: defaultdict(lambda: defaultdict(int))
    )
    #: method -> list of per-frame sigma records (validation.calibration_sigma.sigma_errors:
    #: cam1, cam2, range -> err, sigma), for a method that predicts its sigmas
    sigma: dict[str, list[dict[str, dict[str, NDArray]]]] = field(
        default_factory=lambda: defaultdict(list)
    )
    #: method -> list of per-frame derived-quantity records
    derived: dict[str, list[dict[str, Any]]] = field(default_factory=lambda: defaultdict(list))
    #: method -> list of per-frame records of its eq. (14) flag (validation.scoring_flags)
    flags: dict[str, list[dict[str, Any]]] = field(default_factory=lambda: defaultdict(list))
    #: method -> seconds per frame pair (both cameras)
    times: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    #: method -> per-stage seconds (omniflow), summed over pairs
    stages: dict[str, dict[str, float]] = field(
        default_factory=lambda: defaultdict(lambda: defaultdict(float))
    )
    snapshot: FramePair | None = None
    notes: list[str] = field(default_factory=list)
