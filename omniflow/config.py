"""The knobs of the stereo omni flow step: :class:`OmniFlowConfig`.

Every choice :func:`omniflow.pipeline.estimate` makes is a field here, checked
when the config is made. Start from a preset (:data:`PRESETS`,
``OmniFlowConfig.preset("dense", pool_k=64)``) and change one or two things; a
combination of knobs that cannot work together is an error naming both.
"""

from __future__ import annotations

import math
from dataclasses import Field, dataclass, field, fields, replace
from typing import Any

from omniflow.matching import MATCH_METHODS

__all__ = ["PRESETS", "PUBLIC_FIELDS", "OmniFlowConfig", "knob", "knob_problem", "range_text"]

INF = math.inf
#: A numeric knob's range: (low, high, low included, high included).
Limits = tuple[float, float, bool, bool]

GRADIENTS = ("first", "average")
TEMPORALS = ("difference", "dct3d")
SOLVERS = ("direct", "pooled")
SAMPLINGS = ("cubic", "linear", "exact")
RIM_FILLS = ("reflect", "none")
POOL_MODELS = ("linear", "constant")
EIVS = ("correct", "residual", "none")
SHADING_WHERE = ("everywhere", "moving")
BRIGHTNESS_MODELS = ("linear", "gain")


def knob(default: Any, help: str, *, limits: Limits | None = None,
         choices: tuple | None = None) -> Any:  # fmt: skip
    """A config field with what its one check (:func:`knob_problem`) and the command
    line need: a one-line ``help``, the range of a numeric knob or the ``choices`` of a
    word. None is allowed exactly where the field's type says ``| None`` (off)."""
    return field(default=default, metadata={"help": help, "limits": limits, "choices": choices})


def range_text(limits: Limits) -> str:
    """``in (0, 1]`` or ``>= 8`` for :data:`Limits`."""
    lo, hi, lo_in, hi_in = limits
    if math.isinf(hi):
        return f"{'>=' if lo_in else '>'} {lo:g}"
    return f"in {'[' if lo_in else '('}{lo:g}, {hi:g}{']' if hi_in else ')'}"


def knob_problem(f: Field, value: Any) -> str | None:
    """What is wrong with ``value`` for the knob ``f`` (``"expected ..."``), or None."""
    limits, choices = f.metadata.get("limits"), f.metadata.get("choices")
    if value is None:
        return None if "None" in str(f.type) else "expected a value (None is not allowed)"
    if choices is not None:
        return None if value in choices else f"expected one of {choices}"
    kind = str(f.type).split("|")[0].strip()
    if kind == "bool":
        return None if isinstance(value, bool) else "expected True or False"
    if kind in ("int", "float"):
        if isinstance(value, bool) or not isinstance(value, int | float):
            return f"expected {'an integer' if kind == 'int' else 'a number'}"
        if kind == "int" and not isinstance(value, int):
            return "expected an integer"
        if not math.isfinite(value):
            return f"expected a finite number {range_text(limits) if limits else ''}".strip()
        if limits is not None:
            lo, hi, lo_in, hi_in = limits
            if not ((lo < value or (lo_in and value == lo))
                    and (value < hi or (hi_in and value == hi))):  # fmt: skip
                return f"expected {'an integer' if kind == 'int' else 'a number'} " + range_text(
                    limits
                )
    return None


#: The fields :meth:`OmniFlowConfig.dense` changes from the defaults. Grid pools fit one
#: gain per pool (``brightness_model="gain"``; the linear gain needs the k-d tree's pools).
DENSE = {
    "dense_percentile": 60.0,
    "dense_smooth": 0.95,
    "pool_grid": 0.125,
    "decouple_tol": 60.0,
    "decouple_gain_tol": 60.0,
    "brightness_model": "gain",
}

#: The fields :meth:`OmniFlowConfig.paper` changes from the defaults: the paper's choices.
PAPER = {
    "band": 0.25,
    "flow_band": 0.25,
    "flow_taper": 0.0,
    "eiv": "none",
    "match_method": "paper",
    "gradients": "first",
    "temporal": "difference",
    "solver": "direct",
    "rim_fill": "none",
    "sampling": "exact",
    "iterations": 0,
    "iterate_min_px": 0.0,
    "brightness_gate": None,
    "decouple_gain_tol": None,
}

#: The presets of :meth:`OmniFlowConfig.preset`: each one's fields changed from the
#: defaults. "default": the robust edges-only step; "dense": more matches and grid
#: pools, about three times the time (docs/decisions/dense_mode.md); "paper": the paper
#: as written (docs/decisions/paper_preset.md).
PRESETS: dict[str, dict] = {"default": {}, "dense": DENSE, "paper": PAPER}

#: The knobs a user sets (``omniflow pair --help`` shows them; the others are expert
#: options, ``--set NAME=VALUE``): the band, the matcher's search range and rule, the
#: density, the solver and its pool, the refinement and the motion tests.
PUBLIC_FIELDS = (
    "band", "flow_band", "match_method", "threshold_percentile", "r_min", "r_max",
    "n_theta", "patch_radius", "dense_percentile", "solver", "pool_radius", "iterations",
    "decouple_tol", "brightness_gate", "monocular_gap",
)  # fmt: skip


@dataclass(frozen=True)
class OmniFlowConfig:
    """Every knob of the stereo omni flow step, checked when the config is made.

    Start from a preset, ``OmniFlowConfig.preset("default" | "dense" | "paper",
    **changes)``, and change one or two of the public knobs (:data:`PUBLIC_FIELDS`:
    the band, the matcher's search range and rule, the density, the solver and its
    pool, the refinement, the motion tests). Each field's metadata (:func:`knob`) holds
    its one-line help, its range or choices: the one check (:func:`knob_problem`) and
    the command line's options and ``--set NAME=VALUE`` read it. None is the one
    spelling of "off". A combination that cannot work is an error naming both knobs
    (:meth:`_check_combinations`).

    Why each default is what it is, with the figures and the command that measured
    them: docs/decisions/flow_band.md (band, flow_band, flow_taper, eiv, rim_fill),
    docs/decisions/matching.md (the robust matcher's tests), docs/decisions/pooling.md
    (pool_k, pool_grid, pool_range_tol and the pool tests), docs/decisions/decoupling.md
    (decouple_tol, decouple_gain_tol), docs/decisions/brightness_model.md
    (brightness_gate, brightness_model), docs/decisions/refinement.md (iterations,
    iterate_min_px), docs/decisions/monocular.md (monocular_gap),
    docs/decisions/dense_mode.md and docs/decisions/paper_preset.md (the presets).
    """

    band: float = knob(
        0.5,
        "DCT band matched on, P = band W (eq. 17)",
        limits=(0.0, 1.0, False, True),
    )
    flow_band: float | None = knob(
        0.5,
        "DCT band of the flow step; None: per pair",
        limits=(0.0, 1.0, False, True),
    )
    flow_taper: float = knob(
        0.5,
        "fraction of the flow band rolled off to 0 (cos^2); 0: the sharp truncation of eq. (18)",
        limits=(0.0, 1.0, True, True),
    )
    eiv: str = knob(
        "residual",
        "errors-in-variables correction of the pooled solver (residual: noise from residuals)",
        choices=EIVS,
    )
    match_method: str = knob(
        "robust",
        "robust NCC matcher, or the paper's rule",
        choices=MATCH_METHODS,
    )
    threshold_percentile: float = knob(
        80.0,
        "edges above this |df1/dh_1| percentile",
        limits=(0.0, 100.0, True, False),
    )
    min_gradient: float = knob(
        1e-4,
        "significant points also need |df1/dh_1| above this, grey levels per pixel",
        limits=(0.0, INF, True, False),
    )
    r_min: float | None = knob(
        None,
        "nearest range, m; None: both units' nearest",
        limits=(0.0, INF, True, False),
    )
    r_max: float = knob(
        10.0,
        "farthest range searched, m",
        limits=(0.0, INF, False, False),
    )
    n_theta: int = knob(360, "radial lines searched", limits=(8, INF, True, False))
    h_step: float = knob(
        1.0, "sample spacing along the radial lines, pixels", limits=(0.0, INF, False, False)
    )
    h_min: float = knob(
        16.0, "smallest image radius searched in cam1, pixels", limits=(0.0, INF, True, False)
    )
    rim_margin: float = knob(
        4.0, "radii within this of the rim are not searched, pixels", limits=(0.0, INF, True, False)
    )
    patch_radius: float | None = knob(
        None,
        "matched profile half-length, px; None: r_m/8",
        limits=(0.0, INF, False, False),
    )
    profile_step: float | None = knob(
        None,
        "robust matcher: spacing of the profile's samples, pixels; None: patch_radius / 16",
        limits=(0.0, INF, False, False),
    )
    min_score: float = knob(
        0.95, "robust matcher: smallest NCC accepted", limits=(-1.0, 1.0, True, True)
    )
    uniqueness: float | None = knob(
        0.5,
        "robust matcher: accept when 1 - NCC_best <= this x (1 - NCC_second); None: off",
        limits=(0.0, 1.0, False, False),
    )
    left_right: bool = knob(True, "robust matcher: require the left-right consistency check")
    candidate_fraction: float = knob(
        0.5,
        "robust matcher: edges are candidates down to this fraction of the threshold",
        limits=(0.0, 1.0, False, True),
    )
    # 1 rad already averages a third of the circle; above ~3 rad the matcher's table is
    # empty (measured: 1.6 runs, 3.2 fails)
    tangential_blur: float | None = knob(
        0.02,
        "robust matcher: Gaussian blur across the radial lines, radians; None: off",
        limits=(0.0, 1.0, False, True),
    )
    consistency: float | None = knob(
        1.0,
        "robust matcher: disparity consistency vote, pixels; None: off",
        limits=(0.0, INF, False, False),
    )
    consistency_support: int = knob(
        2, "robust matcher: agreeing neighbours the vote needs", limits=(1, INF, True, False)
    )
    alias_score: float | None = knob(
        0.9,
        "robust matcher: drop a match whose profile recurs on its line above this NCC; None: off",
        limits=(-1.0, 1.0, True, False),
    )
    alias_image2: float = knob(
        0.9,
        "robust matcher: ... only where image 2 holds the alias above this NCC; -1: any recurrence",
        limits=(-1.0, 1.0, True, True),
    )
    alias_period: float = knob(
        0.8,
        "robust matcher: past image 2's rim, drop only on a second recurrence above this NCC",
        limits=(-1.0, 1.0, True, True),
    )
    flatness: float | None = knob(
        0.5,
        "robust matcher: keep a match whose NCC peak is sharp, 1 - NCC <= this x curvature; "
        "None: off",
        limits=(0.0, INF, False, False),
    )
    dense_percentile: float | None = knob(
        None,
        "also match above this percentile; None: off",
        limits=(0.0, 100.0, True, False),
    )
    dense_reach: float = knob(
        1.0,
        "robust matcher: how far along the line a match's disparity is tried, patch radii",
        limits=(0.0, INF, False, False),
    )
    dense_smooth: float | None = knob(
        None,
        "robust matcher: drop smooth densified matches (self-NCC above this); None: off",
        limits=(-1.0, 1.0, True, False),
    )
    edge_smooth: float | None = knob(
        0.95,
        "robust matcher: the smooth-profile test on the search's own matches; None: off",
        limits=(-1.0, 1.0, True, False),
    )
    edge_smooth_floor: float | None = knob(
        0.015,
        "with edge_smooth: keep smooth matches with pool conditioning >= this; None: drop",
        limits=(0.0, 1.0, True, True),
    )
    short_patch: float | None = knob(
        0.5,
        "robust matcher: a second pass with profiles this fraction long; None: off",
        limits=(0.0, 1.0, False, False),
    )
    gradients: str = knob(
        "average",
        "spatial gradient of frame t (the paper) or the mean of frames t and t + 1",
        choices=GRADIENTS,
    )
    temporal: str = knob(
        "difference",
        "f_t as the frame difference (the paper) or from a 3-D DCT over temporal_frames frames",
        choices=TEMPORALS,
    )
    temporal_frames: int = knob(3, "frames in the 3-D DCT window", limits=(3, INF, True, False))
    solver: str = knob(
        "pooled",
        "eq. (16) per point, or pooled least squares",
        choices=SOLVERS,
    )
    pool_radius: float | None = knob(
        None,
        "pool radius, px; None: r_m / 8",
        limits=(0.0, INF, False, False),
    )
    pool_k: int = knob(
        48,
        "pooled solver: most neighbours, the point itself included",
        limits=(1, INF, True, False),
    )
    pool_grid: float | None = knob(
        None,
        "pooled solver: grid-filter pools, cells this fraction of pool_radius; None: k-d tree",
        limits=(0.0, 1.0, False, True),
    )
    pool_range_tol: float | None = knob(
        0.1,
        "pooled solver: leave out neighbours whose range differs by more than this fraction",
        limits=(0.0, INF, False, False),
    )
    pool_model: str = knob(
        "linear",
        "pooled solver: local flow model, linear in theta or constant",
        choices=POOL_MODELS,
    )
    static_test: float | None = knob(
        None,
        "pooled solver: zero flow where the pool's Wald statistic of motion is below this",
        limits=(0.0, INF, False, False),
    )
    static_max_px: float | None = knob(
        None,
        "with static_test: only where the pool would have seen this much flow, px/frame",
        limits=(0.0, INF, False, False),
    )
    pool_min_conditioning: float = knob(
        1e-3,
        "pooled solver: drop points whose pooled system's confidence is below this",
        limits=(0.0, 1.0, True, True),
    )
    decouple_tol: float | None = knob(
        20.0,
        "F above which the radial flows decouple",
        limits=(0.0, INF, False, False),
    )
    brightness_gate: float | None = knob(
        20.0,
        "F above which a pool fits a brightness gain",
        limits=(0.0, INF, False, False),
    )
    brightness_model: str = knob(
        "linear",
        "with brightness_gate: one gain per pool, or a gain varying linearly across it",
        choices=BRIGHTNESS_MODELS,
    )
    decouple_gain_tol: float | None = knob(
        20.0,
        "with decouple_tol: test eq. (14) again with a linear gain, F above this",
        limits=(0.0, INF, False, False),
    )
    flow_shading: float | None = knob(
        None,
        "flow step on frames divided by their Gaussian local mean of this many pixels",
        limits=(0.0, INF, False, False),
    )
    flow_shading_where: str = knob(
        "everywhere",
        "with flow_shading: the flattened frames' flow everywhere or only on movers",
        choices=SHADING_WHERE,
    )
    sampling: str = knob(
        "cubic", "how the gradients and fitted images are read at the points", choices=SAMPLINGS
    )
    iterations: int = knob(
        1, "Gauss-Newton refinements (the paper: 0)", limits=(0, INF, True, False)
    )
    iterate_min_px: float = knob(
        1.0,
        "with iterations: refine only points whose first flow is at least this, pixels",
        limits=(0.0, INF, True, False),
    )
    monocular_gap: float | None = knob(
        None,
        "cam1-only flow this far from matches, px",
        limits=(0.0, INF, True, False),
    )
    rim_fill: str = knob(
        "reflect",
        "before the DCT fit, reflect the image about the mirror's rim, or keep it (the paper)",
        choices=RIM_FILLS,
    )

    def __post_init__(self) -> None:
        for f in fields(self):  # each knob against its own metadata (knob())
            value = getattr(self, f.name)
            problem = knob_problem(f, value)
            if problem:
                raise ValueError(f"OmniFlowConfig.{f.name} = {value!r}: {problem}")
        self._check_combinations()

    def _check_combinations(self) -> None:
        """Raise naming both knobs where one would silently cancel the other."""
        if self.pool_grid is None:
            return
        if self.brightness_gate is not None and self.brightness_model != "gain":
            raise ValueError(
                f"OmniFlowConfig.pool_grid = {self.pool_grid!r} with brightness_model = "
                f"{self.brightness_model!r}: grid pools fit one gain per pool; set "
                "brightness_model='gain' or pool_grid=None"
            )

    @classmethod
    def preset(cls, name: str, **overrides) -> OmniFlowConfig:
        """The named preset of :data:`PRESETS` ("default", "dense", "paper") with
        ``overrides`` changed."""
        if name not in PRESETS:
            raise ValueError(f"preset {name!r}: expected one of {tuple(PRESETS)}")
        return cls(**{**PRESETS[name], **overrides})

    @classmethod
    def paper(cls, **overrides) -> OmniFlowConfig:
        """The paper's choices, as written.

        Gradient-similarity matching (section 5.2), P = X/4 for the matching
        and the flow step alike, the image as it is (no rim fill), the series
        and its analytic derivatives evaluated exactly at the points (eq.
        18-20), first-frame gradients, the frame difference of the fitted
        images for f_t and the direct solution of eq. (16) at each point, once
        (no Gauss-Newton step); no noise correction, no brightness gain
        (eq. 8 as written) and no test of eq. (14) with a gain. tests/omniflow/test_flow.py
        checks that this reproduces eq. (16), (19) and (20) computed
        independently to rounding.

        Why it fails under noise: eq. (9) and (15) at one point are nearly
        dependent, because both units see nearly the same patch at the same
        scale (f2_h ~ f1_h, f2_theta ~ f1_theta), so D of eq. (16) is
        ~ f_h f_theta (1 - h_2/h_1) and the radial flow rests on the small
        difference f2_t - f1_t divided by it. Noise in the temporal
        derivatives and in the gradients is divided by that small D: the
        2x2 solve is ill-conditioned, and its error grows as its conditioning
        falls (tests/omniflow/test_flow.py measures this on noisy closed-form frames).
        """
        return cls.preset("paper", **overrides)

    @classmethod
    def dense(cls, **overrides) -> OmniFlowConfig:
        """The densified configuration: more matches beyond the edges, grid pools.

        Matches beyond the edges (``dense_percentile`` 60) whose profiles are
        not smooth over their own length (``dense_smooth`` 0.95), the pooled
        solver's sums on a grid (``pool_grid`` 0.125), the decoupling test at
        ``decouple_tol`` 60 (at 20 the larger pools switch static points) and
        its linear-gain test at ``decouple_gain_tol`` 60, with the default's
        Gauss-Newton step where a surface moves at least a pixel, and the
        default's brightness gain (on the grid's windows). About ten times the
        default's points (4 % of the valid pixels of the rendered scenes against
        0.4 %) and a smaller error on every rendered scene, at about three times
        DIS medium's time per pair (docs/decisions/dense_mode.md). Not the default
        because of that time: the default answers within about DIS medium's time.
        """
        return cls.preset("dense", **overrides)

    @property
    def grid_pools(self) -> bool:
        """Whether the pools are grid filters (``pool_grid``, omniflow.solve.gridpool)."""
        return self.pool_grid is not None

    def replace(self, **changes) -> OmniFlowConfig:
        """A copy with some fields changed."""
        return replace(self, **changes)

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}
