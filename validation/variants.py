"""The omniflow rows: which OmniFlowConfig variants run, their names, and the
flow step on the true stereo matches."""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .inputs import InputError

__all__ = [
    "REGISTRATIONS",
    "VARIANT_CHOICES",
    "Registered",
    "TrueMatches",
    "config_dict",
    "is_paper_config",
    "omniflow_variants",
    "told_rig",
    "true_matches",
    "variant_name",
    "with_registration",
]


#: The selectable choices of OmniFlowConfig that each get a row (by dotted knob name),
#: default first.
VARIANT_CHOICES: dict[str, tuple[str, ...]] = {
    "match_method": ("robust", "paper"),
    "fit.gradients": ("first", "average"),
    "fit.temporal": ("difference", "dct3d"),
    "solver": ("direct", "pooled"),
}


@dataclass(frozen=True)
class TrueMatches:
    """A variant that skips matching: omniflow's flow step on the TRUE stereo matches.

    The points are the cam1 pixels whose radial gradient magnitude is in the
    top ``100 - percentile`` % (the paper's significant points, from the 8-bit
    frame by central differences) and that cam2 sees (``gt.stereo.valid``);
    their match is ``h2 = gt.stereo.h_other``. The row isolates the flow
    solution (section 5.3) from the matching (section 5.2).
    """

    config: Any
    percentile: float = 80.0

    def __getattr__(self, name: str) -> Any:  # temporal, gradients, ... of the inner config
        if name == "config":
            raise AttributeError(name)
        return getattr(self.config, name)


#: What omniflow is told about the rig (docs/validation.md, "Registration"): the
#: dataset's recorded rig (with its true errors, an oracle registration), the ideal rig
#: of eq. (1) (what an unregistered user gets), or a rig file (e.g. ``omniflow
#: calibrate``'s rig.toml: a registration from a test card).
REGISTRATIONS = ("recorded", "none", "card")


@dataclass(frozen=True)
class Registered:
    """An omniflow row told another rig than the dataset's recorded one.

    ``registration`` is ``"none"`` (every unit's errors dropped: eq. (1), no
    rectification) or ``"card"`` (the rig of ``rig_file``, loaded into ``rig``). The
    truth and the baselines still use the recorded rig; only omniflow's input changes.
    The row is named ``omniflow:PRESET+registration=none`` (or ``=card``).
    """

    config: Any
    registration: str
    rig_file: str | None = None
    rig: Any = dataclasses.field(default=None, compare=False, repr=False)

    def __getattr__(self, name: str) -> Any:  # temporal, gradients, ... of the inner config
        if name == "config":
            raise AttributeError(name)
        return getattr(self.config, name)


def told_rig(cfg: Any, recorded: Any) -> Any:
    """The rig omniflow is given for row ``cfg``: ``recorded`` unless ``cfg`` is
    :class:`Registered` (the ideal rig of eq. 1, or the card's rig file)."""
    if not isinstance(cfg, Registered):
        return recorded
    if cfg.registration == "card":
        return cfg.rig
    from omniflow.geometry.rig import Rig

    units = (dataclasses.replace(u, errors=None) for u in (recorded.cam1, recorded.cam2))
    return Rig(*units, s=recorded.s)


def with_registration(rows: list[tuple[str, Any]], text: str | None) -> list[tuple[str, Any]]:
    """The omniflow ``rows`` once per registration of ``text`` (``recorded``, ``none`` or
    a rig file, comma-separated; None or ``recorded``: the rows unchanged). Rows on the
    true matches and other methods' outputs skip matching, so they are kept once, as
    recorded. InputError (one line) for an unknown value or an unreadable rig file."""
    if text is None:
        return rows
    from omniflow.geometry.rig import RigError, load_rig
    from omniflow.pipeline import OmniFlowConfig

    items = [t.strip() for t in str(text).split(",") if t.strip()]
    expected = "expected recorded, none or a rig file (e.g. omniflow calibrate's rig.toml)"
    if not items:
        raise InputError(f"--registration {text!r}: {expected}")
    kinds = [t if t in ("recorded", "none") else "card" for t in items]
    if len(set(kinds)) != len(kinds):
        raise InputError(f"--registration {text!r}: each of recorded, none, card at most once")
    out: list[tuple[str, Any]] = []
    once = "recorded" not in kinds  # the one-off rows go with the first registration
    for i, (item, kind) in enumerate(zip(items, kinds, strict=True)):
        if kind == "card" and not Path(item).is_file():
            raise InputError(f"--registration {item!r}: no such rig file; {expected}")
        try:
            rig = load_rig(item) if kind == "card" else None
        except RigError as exc:
            raise InputError(f"--registration {str(exc).splitlines()[0]}") from None
        path = str(Path(item).resolve()) if kind == "card" else None
        for name, cfg in rows:
            if isinstance(cfg, OmniFlowConfig) and kind != "recorded":
                out.append((f"{name}+registration={kind}", Registered(cfg, kind, path, rig)))
            elif kind == "recorded" or (once and i == 0):
                out.append((name, cfg))
    return out


def variant_name(config: Any) -> str:
    """Short, stable row name of an OmniFlowConfig: ``omniflow:PRESET`` for a preset
    (``omniflow:default``, ``omniflow:dense``, ``omniflow:paper``), else the preset it
    differs from in the fewest knobs (the earlier of :data:`omniflow.config.PRESETS` on a
    tie) and those knobs by their dotted names (``OmniFlowConfig.to_dict``):
    ``omniflow:default+brightness.brightness_model=gain+solver=direct``.
    :class:`TrueMatches` adds ``+matches=truth``. The full config is in summary.json
    (:func:`config_dict`), so a name never needs to list it."""
    inner = config.config if isinstance(config, TrueMatches) else config
    base, changes = _nearest_preset(inner)
    parts = [f"{k}={v!r}".replace("'", "") for k, v in changes]
    if isinstance(config, TrueMatches):
        parts.append("matches=truth")
    return "+".join([f"omniflow:{base}", *parts])


def _settings(config: Any) -> dict[str, Any]:
    """A config's knobs by dotted name (``to_dict``), a stand-in dataclass's fields."""
    if hasattr(config, "to_dict"):
        return config.to_dict()
    return {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}


def _nearest_preset(config: Any) -> tuple[str, list[tuple[str, Any]]]:
    """(preset name, [(knob, value) changed from it]) with the fewest changes; a stand-in
    config (not a dataclass with presets) is compared with its own class's defaults."""
    from omniflow.config import PRESETS

    if not dataclasses.is_dataclass(config):
        return "default", []
    cls = type(config)
    presets = getattr(cls, "preset", None)
    names = list(PRESETS) if presets is not None else ["default"]
    best: tuple[str, list[tuple[str, Any]]] | None = None
    for name in names:
        try:
            base = presets(name) if presets is not None else cls()
        except TypeError:
            return "default", []
        ours, theirs = _settings(config), _settings(base)
        changes = [(k, v) for k, v in ours.items() if v != theirs.get(k)]
        if best is None or len(changes) < len(best[1]):
            best = (name, changes)
    assert best is not None
    return best


def omniflow_variants(mode: str = "all", *, true_matches: bool = True) -> list[tuple[str, Any]]:
    """(name, OmniFlowConfig) for each variant, the default configuration first.

    ``mode``: ``"default"`` (only the default), ``"oat"`` (the default plus each
    choice changed one at a time, plus the paper's configuration), ``"all"``
    (every combination). With
    ``true_matches`` (not for "default") two more rows run the flow step of the
    default and of the paper's configuration on the true matches
    (:class:`TrueMatches`).
    """
    from omniflow.config import knob_fields
    from omniflow.pipeline import OmniFlowConfig

    base = OmniFlowConfig()
    names = knob_fields()
    choices = {k: v for k, v in VARIANT_CHOICES.items() if k in names}
    configs: list[Any] = [base]
    if mode == "oat":
        for key, values in choices.items():
            for val in values:
                if val != base.to_dict()[key]:
                    configs.append(base.with_settings({key: val}))
    elif mode == "all":
        for combo in itertools.product(*choices.values()):
            cfg = base.with_settings(dict(zip(choices, combo, strict=True)))
            if cfg != base:
                configs.append(cfg)
    elif mode != "default":
        raise InputError(f"variants = {mode!r}: expected 'default', 'oat' or 'all'")
    paper = OmniFlowConfig.paper()
    if mode != "default" and paper not in configs:  # the paper's exact configuration
        configs.append(paper)
    if true_matches and mode != "default":
        configs.append(TrueMatches(base))
        if paper != base:
            configs.append(TrueMatches(paper))
    return [(variant_name(c), c) for c in configs]


def true_matches(
    image: NDArray,
    truth: dict[str, NDArray],
    rig: Any,
    percentile: float = 80.0,
    *,
    band: float = 0.25,
) -> Any:
    """The true stereo matches at cam1's significant pixels (see :class:`TrueMatches`).

    ``image`` is cam1's grey float frame; its radial gradient comes from the DCT fit
    (``band`` as the variant's) through :func:`omniflow.paper.edges.polar_gradient_grid`,
    the same eq. (19) the pipeline uses.
    """
    from omniflow.matching import Matches
    from omniflow.paper.dct import fit_dct
    from omniflow.paper.edges import polar_gradient_grid

    unit = rig.cam1
    x, y = unit.pixel_centres()
    h1, theta = unit.polar_of_pixel(x, y)
    f_h = np.abs(polar_gradient_grid(fit_dct(np.asarray(image, np.float32), band=band), unit)[0])
    seen = (truth["gt.valid"] > 0.5) & (truth["gt.stereo.valid"] > 0.5) & (h1 >= 6.0)
    seen &= h1 <= unit.r_m - 4.0
    seen &= np.isfinite(truth["gt.stereo.h_other"]) & np.isfinite(f_h)
    if not seen.any():
        z = np.zeros(0)
        return Matches(x=z, y=z, theta=z, h1=z, h2=z, score=z, n_significant=0, method="truth")
    sig = seen & (f_h >= np.percentile(f_h[seen], percentile))
    ii, jj = np.nonzero(sig)
    return Matches(
        x=x[ii, jj],
        y=y[ii, jj],
        theta=theta[ii, jj],
        h1=h1[ii, jj],
        h2=truth["gt.stereo.h_other"][ii, jj].astype(np.float64),
        score=np.ones(ii.size),
        n_significant=int(ii.size),
        method="truth",
    )


def is_paper_config(cfg: Any) -> bool:
    """Whether ``cfg`` is ``OmniFlowConfig.paper()`` (a stand-in config never is), told
    whichever rig."""
    from omniflow.pipeline import OmniFlowConfig

    cfg = cfg.config if isinstance(cfg, Registered) else cfg

    return bool(cfg == OmniFlowConfig.paper())


def config_dict(cfg: Any) -> dict[str, Any]:
    """The row's settings for summary.json: every knob by its dotted name (the names of
    its row name), and ``registration`` (:data:`REGISTRATIONS`; with ``registration_rig``,
    the card's rig file)."""
    if isinstance(cfg, Registered):
        out = config_dict(cfg.config)
        out["registration"] = cfg.registration
        if cfg.rig_file is not None:
            out["registration_rig"] = cfg.rig_file
        return out
    if isinstance(cfg, TrueMatches):
        out = config_dict(cfg.config)
        out["match_method"] = "truth"
        out["true_matches_percentile"] = cfg.percentile
        return out
    out = {k: v if isinstance(v, int | float | str | bool) or v is None else repr(v)
           for k, v in _settings(cfg).items()}  # fmt: skip
    out["registration"] = "recorded"
    return out
