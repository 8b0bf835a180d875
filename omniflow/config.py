"""The knobs of the stereo omni flow step: :class:`OmniFlowConfig`.

Every choice :func:`omniflow.pipeline.estimate` makes is a knob here, checked when the
config is made. A user starts from a preset (:data:`PRESETS`) and changes one or two of
the public knobs (:data:`PUBLIC_FIELDS`); the expert options sit in nested frozen groups
(:data:`GROUPS`: ``fit``, ``search``, ``matching``, ``pooling``, ``brightness``,
``refinement``), named with dots on the command line and in validation rows
(``matching.edge_smooth``)::

    OmniFlowConfig.preset("dense", n_theta=720, pooling={"pool_k": 64})
    OmniFlowConfig().with_settings({"matching.edge_smooth": 0.9})

A combination of knobs that cannot work together is an error naming both.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import Field, dataclass, field, fields, replace
from typing import Any, ClassVar

from omniflow.matching import MATCH_METHODS

__all__ = [
    "GROUPS",
    "PRESETS",
    "PUBLIC_FIELDS",
    "BrightnessOptions",
    "FitOptions",
    "MatchingOptions",
    "OmniFlowConfig",
    "PoolingOptions",
    "RefinementOptions",
    "SearchOptions",
    "knob",
    "knob_fields",
    "knob_problem",
    "nested",
    "range_text",
]

INF = math.inf
#: A numeric knob's range: (low, high, low included, high included).
Limits = tuple[float, float, bool, bool]

GRADIENTS = ("first", "average")
TEMPORALS = ("difference", "dct3d")
SOLVERS = ("direct", "pooled")
SAMPLINGS = ("cubic", "linear", "exact")
RIM_FILLS = ("reflect", "none")
EIVS = ("residual", "none")
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


def _problem_text(name: str, value: Any, problem: str) -> str:
    return f"OmniFlowConfig.{name} = {value!r}: {problem}"


def _check_fields(obj: Any, prefix: str) -> None:
    """Each knob of ``obj`` against its own metadata (:func:`knob`); ``prefix``: the
    group's dotted prefix (``"matching."``) in the message."""
    for f in fields(obj):
        value = getattr(obj, f.name)
        problem = knob_problem(f, value)
        if problem:
            raise ValueError(_problem_text(prefix + f.name, value, problem))


@dataclass(frozen=True)
class _Options:
    """A group of expert options: each field a :func:`knob`, checked when made."""

    GROUP: ClassVar[str] = ""

    def __post_init__(self) -> None:
        _check_fields(self, self.GROUP + ".")

    def as_kwargs(self) -> dict[str, Any]:
        """The group's fields by name (the keywords of the function that reads them)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def changed(self, changes: Mapping[str, Any]) -> _Options:
        """A copy with the fields named in ``changes`` changed; an unknown name is an
        error listing the group's fields."""
        names = [f.name for f in fields(self)]
        unknown = [k for k in changes if k not in names]
        if unknown:
            raise ValueError(
                f"OmniFlowConfig.{self.GROUP}.{unknown[0]}: no such option; expected one of "
                f"{', '.join(names)}"
            )
        return replace(self, **changes)


@dataclass(frozen=True)
class FitOptions(_Options):
    """The DCT fit and the flow step's derivatives (omniflow/fit/): the band's roll-off,
    the rim fill, which frames the gradients and f_t come from, how they are read at the
    points, and the shading-flattened frames."""

    GROUP: ClassVar[str] = "fit"

    flow_taper: float = knob(
        0.5,
        "fraction of the flow band rolled off to 0 (cos^2); 0: the sharp truncation of eq. (18)",
        limits=(0.0, 1.0, True, True),
    )
    rim_fill: str = knob(
        "reflect",
        "before the DCT fit, reflect the image about the mirror's rim, or keep it (the paper)",
        choices=RIM_FILLS,
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
    sampling: str = knob(
        "cubic", "how the gradients and fitted images are read at the points", choices=SAMPLINGS
    )


@dataclass(frozen=True)
class SearchOptions(_Options):
    """Where the matchers search (omniflow/matching/radial.py, omniflow/paper/matching.py):
    the radial lines' sampling, the searched annulus and the significant points' floor
    (the cam1-only flow reads the same annulus and floor)."""

    GROUP: ClassVar[str] = "search"

    min_gradient: float = knob(
        1e-4,
        "significant points also need |df1/dh_1| above this, grey levels per pixel",
        limits=(0.0, INF, True, False),
    )
    h_step: float = knob(
        1.0, "sample spacing along the radial lines, pixels", limits=(0.0, INF, False, False)
    )
    h_min: float = knob(
        16.0, "smallest image radius searched in cam1, pixels", limits=(0.0, INF, True, False)
    )
    rim_margin: float = knob(
        4.0, "radii within this of the rim are not searched, pixels", limits=(0.0, INF, True, False)
    )


@dataclass(frozen=True)
class MatchingOptions(_Options):
    """The robust matcher's tests (omniflow/matching/; docs/decisions/matching.md): the
    profile, the NCC acceptance, the alias and smoothness tests, the disparity vote and
    the densified matches' reach."""

    GROUP: ClassVar[str] = "matching"

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


@dataclass(frozen=True)
class PoolingOptions(_Options):
    """The pooled solver (omniflow/solve/; docs/decisions/pooling.md): which neighbours
    form a pool (its flow is linear across it), its noise correction, its confidence floor and the
    static test."""

    GROUP: ClassVar[str] = "pooling"

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
    eiv: str = knob(
        "residual",
        "errors-in-variables correction of the pooled solver (residual: noise from residuals)",
        choices=EIVS,
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


@dataclass(frozen=True)
class BrightnessOptions(_Options):
    """The brightness model (omniflow/solve/gain.py, shading.py;
    docs/decisions/brightness_model.md): the pools' gain, the decoupling test with a
    gain, the flow step on shading-flattened frames."""

    GROUP: ClassVar[str] = "brightness"

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


@dataclass(frozen=True)
class RefinementOptions(_Options):
    """The Gauss-Newton refinement (omniflow/solve/refine.py;
    docs/decisions/refinement.md): which points it refines."""

    GROUP: ClassVar[str] = "refinement"

    iterate_min_px: float = knob(
        1.0,
        "with iterations: refine only points whose first flow is at least this, pixels",
        limits=(0.0, INF, True, False),
    )


#: The expert groups, by the field name :class:`OmniFlowConfig` holds each under.
GROUPS: dict[str, type[_Options]] = {
    cls.GROUP: cls
    for cls in (
        FitOptions,
        SearchOptions,
        MatchingOptions,
        PoolingOptions,
        BrightnessOptions,
        RefinementOptions,
    )
}

#: The knobs read only while another is on: (knob, the knob it needs, what "on" is, the
#: test of on). Each pair was checked in the code that reads the knob (the module named).
#: Set away from its default while the knob it needs is off, the knob would be silently
#: ignored: :meth:`OmniFlowConfig._check_combinations` makes that an error naming both.
DEPENDENCIES: tuple[tuple[str, str, str, Any], ...] = (
    # omniflow/solve/pooled.py, _zero_where_still: only inside the static test
    ("pooling.static_max_px", "pooling.static_test", "not None", lambda v: v is not None),
    # omniflow/solve/at_matches.py, _refine; omniflow/solve/refine.py: no step at 0
    ("refinement.iterate_min_px", "iterations", "above 0", lambda v: v > 0),
    # omniflow/matching/radial.py, _finish: the vote's support
    ("matching.consistency_support", "matching.consistency", "not None", lambda v: v is not None),
    # omniflow/matching/radial.py, the periodic-alias test's arguments
    ("matching.alias_image2", "matching.alias_score", "not None", lambda v: v is not None),
    ("matching.alias_period", "matching.alias_score", "not None", lambda v: v is not None),
    # omniflow/matching/radial.py, _finish: no flagged matches without the test
    ("matching.edge_smooth_floor", "matching.edge_smooth", "not None", lambda v: v is not None),
    # omniflow/solve/decoupled.py: the linear-gain test runs within eq. (14)'s test
    ("brightness.decouple_gain_tol", "decouple_tol", "not None", lambda v: v is not None),
    # omniflow/pipeline.py: the flattened frames' use
    ("brightness.flow_shading_where", "brightness.flow_shading", "not None",
     lambda v: v is not None),
    # omniflow/solve/at_matches.py: the pools' gain fit
    ("brightness.brightness_model", "brightness_gate", "not None", lambda v: v is not None),
    # omniflow/fit/series.py: the 3-D series' window
    ("fit.temporal_frames", "fit.temporal", "'dct3d'", lambda v: v == "dct3d"),
)  # fmt: skip

#: The knobs :meth:`OmniFlowConfig.dense` changes from the defaults. Grid pools fit one
#: gain per pool (``brightness_model="gain"``; the linear gain needs the k-d tree's pools).
DENSE = {
    "dense_percentile": 60.0,
    "decouple_tol": 60.0,
    "matching": {"dense_smooth": 0.95},
    "pooling": {"pool_grid": 0.125},
    "brightness": {"decouple_gain_tol": 60.0, "brightness_model": "gain"},
}

#: The knobs :meth:`OmniFlowConfig.paper` changes from the defaults: the paper's choices.
PAPER = {
    "band": 0.25,
    "flow_band": 0.25,
    "match_method": "paper",
    "solver": "direct",
    "iterations": 0,
    "brightness_gate": None,
    "fit": {
        "flow_taper": 0.0,
        "gradients": "first",
        "temporal": "difference",
        "rim_fill": "none",
        "sampling": "exact",
    },
    "pooling": {"eiv": "none"},
    "brightness": {"decouple_gain_tol": None},
}

#: The presets of :meth:`OmniFlowConfig.preset`: each one's knobs changed from the
#: defaults (a group's as a mapping of its fields). "default": the robust edges-only
#: step; "dense": more matches and grid pools, about three times the time
#: (docs/decisions/dense_mode.md); "paper": the paper as written
#: (docs/decisions/paper_preset.md).
PRESETS: dict[str, dict] = {"default": {}, "dense": DENSE, "paper": PAPER}

#: The knobs a user sets (``omniflow pair --help`` shows them; the expert groups'
#: options are ``--set GROUP.NAME=VALUE``): the band, the matcher's search range and rule,
#: the density, the solver and its pool, the refinement and the motion tests.
PUBLIC_FIELDS = (
    "band", "flow_band", "match_method", "threshold_percentile", "r_min", "r_max",
    "n_theta", "patch_radius", "dense_percentile", "solver", "pool_radius", "iterations",
    "decouple_tol", "brightness_gate", "monocular_gap",
)  # fmt: skip


@dataclass(frozen=True)
class OmniFlowConfig:
    """Every knob of the stereo omni flow step, checked when the config is made.

    Start from a preset, ``OmniFlowConfig.preset("default" | "dense" | "paper",
    **changes)``, and change one or two of the public knobs (:data:`PUBLIC_FIELDS`: the
    band, the matcher's search range and rule, the density, the solver and its pool, the
    refinement, the motion tests). The expert options are grouped by what the code does
    (:data:`GROUPS`); a group given as a mapping changes those of its fields
    (``pooling={"pool_k": 64}``), a group object replaces it whole. Each knob's metadata
    (:func:`knob`) holds its one-line help, its range or choices: the one check
    (:func:`knob_problem`) and the command line's options and ``--set NAME=VALUE``
    (dotted for a group's: ``pooling.pool_k``) read it. None is the one spelling of
    "off". A combination that cannot work is an error naming both knobs
    (:meth:`_check_combinations`).

    Why each default is what it is, with the figures and the command that measured
    them: docs/decisions/flow_band.md (band, flow_band, fit.flow_taper, pooling.eiv,
    fit.rim_fill), docs/decisions/matching.md (the matching group), docs/decisions/pooling.md
    (the pooling group), docs/decisions/decoupling.md (decouple_tol,
    brightness.decouple_gain_tol), docs/decisions/brightness_model.md (brightness_gate,
    the brightness group), docs/decisions/refinement.md (iterations, the refinement
    group), docs/decisions/monocular.md (monocular_gap), docs/decisions/dense_mode.md and
    docs/decisions/paper_preset.md (the presets).
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
    patch_radius: float | None = knob(
        None,
        "matched profile half-length, px; None: r_m/8",
        limits=(0.0, INF, False, False),
    )
    dense_percentile: float | None = knob(
        None,
        "also match above this percentile; None: off",
        limits=(0.0, 100.0, True, False),
    )
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
    iterations: int = knob(
        1, "Gauss-Newton refinements (the paper: 0)", limits=(0, INF, True, False)
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
    monocular_gap: float | None = knob(
        None,
        "cam1-only flow this far from matches, px",
        limits=(0.0, INF, True, False),
    )
    fit: FitOptions = field(default_factory=FitOptions)
    search: SearchOptions = field(default_factory=SearchOptions)
    matching: MatchingOptions = field(default_factory=MatchingOptions)
    pooling: PoolingOptions = field(default_factory=PoolingOptions)
    brightness: BrightnessOptions = field(default_factory=BrightnessOptions)
    refinement: RefinementOptions = field(default_factory=RefinementOptions)

    def __new__(cls, *args: Any, **knobs: Any) -> OmniFlowConfig:
        """An unknown keyword names the knob, with where a group's field is
        (``pool_k=3``: ``it is pooling.pool_k``), as :meth:`replace` does; the generated
        ``__init__`` would say only "unexpected keyword"."""
        names = {f.name for f in fields(cls)}
        unknown = [k for k in knobs if k not in names]
        if unknown:
            raise TypeError(f"OmniFlowConfig.{unknown[0]}: no such knob{_group_hint(unknown[0])}")
        return super().__new__(cls)

    def __post_init__(self) -> None:
        for name, cls in GROUPS.items():  # a mapping changes the defaults' group
            value = getattr(self, name)
            if isinstance(value, Mapping):
                object.__setattr__(self, name, cls().changed(value))
            elif not isinstance(value, cls):
                raise ValueError(
                    f"OmniFlowConfig.{name} = {value!r}: expected a {cls.__name__} or a "
                    "mapping of its fields"
                )
        for f in fields(self):  # each public knob against its own metadata (knob())
            if f.name not in GROUPS:
                value = getattr(self, f.name)
                problem = knob_problem(f, value)
                if problem:
                    raise ValueError(_problem_text(f.name, value, problem))
        self._check_combinations()

    def _check_combinations(self) -> None:
        """Raise naming both knobs where one would silently cancel the other: a knob of
        :data:`DEPENDENCIES` set while the knob it needs is off, or grid pools with the
        linear gain."""
        for name, needs, on, is_on in DEPENDENCIES:
            value, other = self.knob(name), self.knob(needs)
            if value != _default(name) and not is_on(other):
                raise ValueError(
                    f"OmniFlowConfig.{name} = {value!r} with {needs} = {other!r}: {name} is "
                    f"read only when {needs} is {on}; set {needs} or leave {name} at "
                    f"{_default(name)!r}"
                )
        if self.pooling.pool_grid is None:
            return
        if self.brightness_gate is not None and self.brightness.brightness_model != "gain":
            raise ValueError(
                f"OmniFlowConfig.pooling.pool_grid = {self.pooling.pool_grid!r} with "
                f"brightness.brightness_model = {self.brightness.brightness_model!r}: grid "
                "pools fit one gain per pool; set brightness.brightness_model='gain' or "
                "pooling.pool_grid=None"
            )

    @classmethod
    def preset(cls, name: str, **overrides) -> OmniFlowConfig:
        """The named preset of :data:`PRESETS` ("default", "dense", "paper") with
        ``overrides`` changed as :meth:`replace` changes them: a group's mapping changes
        only those of the preset's group fields (``preset("dense", pooling={"pool_k":
        64})`` keeps the dense preset's ``pooling.pool_grid``)."""
        if name not in PRESETS:
            raise ValueError(f"preset {name!r}: expected one of {tuple(PRESETS)}")
        return cls(**PRESETS[name]).replace(**overrides)

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
        not smooth over their own length (``matching.dense_smooth`` 0.95), the pooled
        solver's sums on a grid (``pooling.pool_grid`` 0.125), the decoupling test at
        ``decouple_tol`` 60 (at 20 the larger pools switch static points) and
        its linear-gain test at ``brightness.decouple_gain_tol`` 60, with the default's
        Gauss-Newton step where a surface moves at least a pixel, and the
        default's brightness gain (on the grid's windows). About ten times the
        default's points (4 % of the valid pixels of the rendered scenes against
        0.4 %) and a smaller error on every rendered scene, at about three times
        DIS medium's time per pair (docs/decisions/dense_mode.md). Not the default
        because of that time: the default answers within about DIS medium's time.
        """
        return cls.preset("dense", **overrides)

    def knob(self, name: str) -> Any:
        """A knob's value by its dotted name (``"pooling.pool_k"``, ``"band"``)."""
        group, dot, rest = name.partition(".")
        return getattr(getattr(self, group), rest) if dot else getattr(self, name)

    @property
    def grid_pools(self) -> bool:
        """Whether the pools are grid filters (``pooling.pool_grid``, omniflow.solve.gridpool)."""
        return self.pooling.pool_grid is not None

    def replace(self, **changes) -> OmniFlowConfig:
        """A copy with some knobs changed: a public knob by name, a group by a mapping of
        the fields to change (``pooling={"pool_k": 64}``) or by a whole group object."""
        for name, value in changes.items():
            if name in GROUPS and isinstance(value, Mapping):
                changes[name] = getattr(self, name).changed(value)
        unknown = [k for k in changes if k not in {f.name for f in fields(self)}]
        if unknown:
            raise ValueError(f"OmniFlowConfig.{unknown[0]}: no such knob{_group_hint(unknown[0])}")
        return replace(self, **changes)

    def with_settings(self, settings: Mapping[str, Any]) -> OmniFlowConfig:
        """A copy with knobs changed by their dotted names (``{"pooling.pool_k": 64,
        "band": 0.3}``), the names of :meth:`to_dict`, ``--set`` and validation rows."""
        return self.replace(**nested(settings))

    def to_dict(self) -> dict[str, Any]:
        """Every knob by its dotted name (``band``, ``matching.edge_smooth``), public first."""
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in GROUPS:
                out.update({f"{f.name}.{g.name}": getattr(value, g.name) for g in fields(value)})
            else:
                out[f.name] = value
        return out


def _group_hint(name: str) -> str:
    """``; it is pooling.pool_k`` where ``name`` is a group's field given at the top."""
    for group, cls in GROUPS.items():
        if name in {f.name for f in fields(cls)}:
            return f"; it is {group}.{name} ({group}={{{name!r}: ...}})"
    return ""


def _default(name: str) -> Any:
    """A knob's default by its dotted name (its field's, before any preset)."""
    f = knob_fields()[name]
    return f.default


def knob_fields() -> dict[str, Field]:
    """Every knob's field by its dotted name (public knobs first, then each group's), the
    table :func:`knob_problem` and the command line read."""
    out: dict[str, Field] = {}
    for f in fields(OmniFlowConfig):
        if f.name in GROUPS:
            out.update({f"{f.name}.{g.name}": g for g in fields(GROUPS[f.name])})
        else:
            out[f.name] = f
    return out


def nested(settings: Mapping[str, Any]) -> dict[str, Any]:
    """Dotted settings as :meth:`OmniFlowConfig.replace`'s keywords: ``{"band": 0.3,
    "pooling.pool_k": 64}`` -> ``{"band": 0.3, "pooling": {"pool_k": 64}}``."""
    out: dict[str, Any] = {}
    for name, value in settings.items():
        group, dot, rest = name.partition(".")
        if dot:
            out.setdefault(group, {})[rest] = value
        else:
            out[name] = value
    return out
