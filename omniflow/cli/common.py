"""What the commands share: one-line errors, the parser's look, the config's options.

Every failure of a command is one line naming the path, option or value
(:func:`explain_error` gives its exit status: 2 bad input, 1 the machine refused or an
internal error).
"""

from __future__ import annotations

import argparse
import dataclasses
import errno
import json
import math
import re
import sys
import textwrap
import types
import typing
from collections.abc import Sequence
from typing import Any

from omniflow.geometry.rig import Rig, RigError
from omniflow.io.imageio import ImageError, OutputError

__all__ = [
    "KNOB_LIMITS",
    "CLIError",
    "Formatter",
    "Parser",
    "add_config_options",
    "check_knobs",
    "check_rig_size",
    "column_units",
    "config_from_settings",
    "explain_error",
    "flag",
    "make_config",
    "one_line",
    "size_text",
]


class CLIError(ValueError):
    """Bad command-line input; the message is printed as is."""


class Parser(argparse.ArgumentParser):
    """ArgumentParser whose usage errors are one line, with exit status 2."""

    def error(self, message: str) -> typing.NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


class Formatter(argparse.RawDescriptionHelpFormatter):
    def __init__(self, prog: str) -> None:
        super().__init__(prog, max_help_position=34, width=100)


# -- options from OmniFlowConfig ---------------------------------------------------


def _config_class():
    from omniflow.pipeline import OmniFlowConfig

    return OmniFlowConfig


def _field_docs(cls: type) -> dict[str, tuple[str, str]]:
    """Per-field (type text, description) from a numpydoc ``Attributes`` section.

    Handles ``a, b : float`` (shared entries) and ``a, b : description`` one-liners.
    """
    docs: dict[str, tuple[str, str]] = {}
    doc = textwrap.dedent((cls.__doc__ or "").split("\n", 1)[-1])
    current: list[str] = []
    for line in doc.splitlines():
        m = re.match(r"^(\w+(?:\s*,\s*\w+)*)\s+:\s*(.*)$", line)
        if m:
            current = [n.strip() for n in m.group(1).split(",")]
            for name in current:
                docs[name] = (m.group(2).strip(), "")
        elif current and line.startswith((" ", "\t")) and line.strip():
            for name in current:
                kind, desc = docs[name]
                docs[name] = (kind, (desc + " " + line.strip()).strip())
        elif line.strip():
            current = []
    return docs


_TYPE_WORDS = {
    "float",
    "int",
    "str",
    "bool",
    "tuple",
    "list",
    "dict",
    "none",
    "or",
    "of",
    "optional",
    "ndarray",
    "path",
    "sequence",
    "callable",
    "any",
}


def _is_type(kind: str) -> bool:
    """True if a numpydoc type line holds a type (``float or None``), not prose."""
    if kind.startswith("{"):
        return True
    return all(w.lower() in _TYPE_WORDS for w in re.findall(r"[A-Za-z_]+", kind))


def _doc_choices(kind: str) -> list[str] | None:
    """``{"a", "b"}`` in a numpydoc type line -> ["a", "b"]."""
    m = re.match(r"^\{(.*)\}", kind.strip())
    return re.findall(r"[\"']([^\"']+)[\"']", m.group(1)) if m else None


def _unwrap_optional(tp: Any) -> tuple[Any, bool]:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0], True
    return tp, False


def _none_or(conv):
    def parse(text: str):
        if text.lower() in ("none", "null", ""):
            return None
        return conv(text)

    parse.__name__ = getattr(conv, "__name__", "value")
    return parse


#: Allowed range of every numeric OmniFlowConfig knob: (low, high, low included,
#: high included); None is always allowed where the field's default is None. A new
#: numeric knob needs an entry (tests/omniflow/test_bad_input.py checks the table).
KNOB_LIMITS: dict[str, tuple[float, float, bool, bool]] = {
    "band": (0.0, 1.0, False, True),
    "match_band": (0.0, 1.0, False, True),
    "threshold_percentile": (0.0, 100.0, True, False),
    "min_gradient": (0.0, math.inf, True, False),
    "r_min": (0.0, math.inf, True, False),
    "r_max": (0.0, math.inf, False, False),
    "n_theta": (8, math.inf, True, False),
    "h_step": (0.0, math.inf, False, False),
    "h_min": (0.0, math.inf, True, False),
    "rim_margin": (0.0, math.inf, True, False),
    "patch_radius": (0.0, math.inf, False, False),
    "patch_lines": (0, math.inf, True, False),
    "profile_step": (0.0, math.inf, False, False),
    "min_score": (-1.0, 1.0, True, True),  # a normalised cross-correlation
    "uniqueness": (0.0, 1.0, False, True),
    "candidate_fraction": (0.0, 1.0, False, True),
    # radians of Gaussian blur across the radial lines; 1 rad already averages a third of
    # the circle, and above ~3 rad the matcher's table is empty (measured: 1.6 runs, 3.2 fails)
    "tangential_blur": (0.0, 1.0, True, True),
    "consistency": (0.0, math.inf, True, False),
    "consistency_support": (1, math.inf, True, False),
    "temporal_frames": (3, math.inf, True, False),
    "pool_radius": (0.0, math.inf, False, False),
    "pool_k": (1, math.inf, True, False),
    "pool_grid": (0.0, 1.0, False, True),  # grid cell / pool radius
    "pool_range_tol": (0.0, math.inf, False, False),
    "min_conditioning": (0.0, 1.0, True, True),  # lambda_min / lambda_max
    "pool_min_conditioning": (0.0, 1.0, True, True),  # lambda_min / lambda_max
    "iterations": (0, math.inf, True, False),
    "iterate_min_px": (0.0, math.inf, True, False),  # px of first-step flow
    "monocular_gap": (0.0, math.inf, True, False),  # px from the nearest stereo match
    "flow_band": (0.0, 1.0, False, True),
    "flow_taper": (0.0, 1.0, True, True),  # fraction of the flow band rolled off
    "flow_band_tolerance": (1.0, math.inf, True, False),
    "flow_band_gain": (0.0, 1.0, False, False),
    "noise_sigma": (0.0, math.inf, True, False),  # grey levels of the [0, 1] image
    "self_similarity": (0.0, 1.0, False, True),  # a factor on 1 - NCC; 1 = off
    "alias_score": (-1.0, 1.0, True, True),  # an NCC; 1 = off
    "alias_image2": (-1.0, 1.0, True, True),  # an NCC
    "alias_period": (-1.0, 1.0, True, True),  # an NCC
    "flatness": (0.0, math.inf, True, False),  # (1 - NCC) per unit of peak curvature; 0 = off
    "dense_percentile": (0.0, 100.0, True, True),  # a percentile of |df/dh|; 100 = off
    "dense_reach": (0.0, math.inf, False, False),  # patch radii
    "dense_smooth": (-1.0, 1.0, True, True),  # an NCC; 1 = off
    "edge_smooth": (-1.0, 1.0, True, True),  # an NCC; 1 = off
    "edge_smooth_floor": (0.0, 1.0, True, True),  # lambda_min / lambda_max
    "short_patch": (0.0, 1.0, True, False),  # a fraction of patch_radius; 0 = off
    "pool_flow_tol": (0.0, math.inf, False, False),
    "decouple_tol": (0.0, math.inf, False, False),  # an F statistic (omniflow.solve.decoupled)
    "brightness_gate": (0.0, math.inf, False, False),  # an F statistic (omniflow.solve.gain)
    "decouple_gain_tol": (0.0, math.inf, False, False),  # an F statistic (omniflow.solve.gain)
    "flow_shading": (0.0, math.inf, False, False),  # px, Gaussian sigma (omniflow.solve.shading)
    "pool_edge_tol": (0.0, math.inf, False, False),  # a factor on the median edge at the matches
    "pool_residual_tol": (0.0, math.inf, False, False),  # robust standard deviations
    "pool_min_info": (0.0, math.inf, False, False),  # in typical single points' information
    "static_test": (0.0, math.inf, False, False),  # a Wald statistic (omniflow.paper.flow)
    "static_max_px": (0.0, math.inf, False, False),  # px per frame (cam1)
}


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _range_text(lo: float, hi: float, lo_in: bool, hi_in: bool) -> str:
    if math.isinf(hi):
        return f"{'>=' if lo_in else '>'} {lo:g}"
    return f"in {'[' if lo_in else '('}{lo:g}, {hi:g}{']' if hi_in else ')'}"


def check_knobs(values: Any) -> None:
    """Raise :class:`CLIError` naming the option if a numeric knob is out of its range.

    ``values`` is an OmniFlowConfig or a mapping of field name to value. Each
    float knob must be finite; the ranges are :data:`KNOB_LIMITS`.
    """
    if dataclasses.is_dataclass(values):
        values = {f.name: getattr(values, f.name) for f in dataclasses.fields(values)}
    for name, value in values.items():
        if value is None or isinstance(value, bool) or not isinstance(value, int | float):
            continue
        limits = KNOB_LIMITS.get(name)
        kind = "an integer" if isinstance(value, int) else "a number"
        if not math.isfinite(value):
            expected = _range_text(*limits) if limits else ""
            raise CLIError(f"{flag(name)} {value}: expected a finite number {expected}".strip())
        if limits is None:
            continue
        lo, hi, lo_in, hi_in = limits
        inside = (lo < value or (lo_in and value == lo)) and (value < hi or (hi_in and value == hi))
        if not inside:
            raise CLIError(
                f"{flag(name)} {value:g}: expected {kind} {_range_text(lo, hi, lo_in, hi_in)}"
            )


def add_config_options(parser: argparse.ArgumentParser) -> list[str]:
    """One option per OmniFlowConfig field, its default shown; returns the field names."""
    cls = _config_class()
    group = parser.add_argument_group(
        "algorithm options (omniflow.pipeline.OmniFlowConfig; each default shown)"
    )
    try:
        hints = typing.get_type_hints(cls)
    except Exception:  # unresolvable annotations: fall back to the defaults' types
        hints = {}
    docs = _field_docs(cls)
    names = []
    for f in dataclasses.fields(cls):
        if not f.init or f.name.startswith("_"):
            continue
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            continue
        tp, optional = _unwrap_optional(hints.get(f.name, type(default)))
        flag = "--" + f.name.replace("_", "-")
        kind, desc = docs.get(f.name, ("", ""))
        if kind and not _is_type(kind):
            desc = f"{kind} {desc}".strip()  # a one-line entry: "a, b : what they are"
        desc = re.sub(r":\w+:`~?([^`]+)`", r"\1", desc).replace("``", "").rstrip(".")
        kwargs: dict[str, Any] = {"dest": f"cfg_{f.name}", "default": argparse.SUPPRESS}
        choices = _doc_choices(kind)
        if choices and default not in choices:
            choices = None
        if typing.get_origin(tp) is typing.Literal:
            choices = list(typing.get_args(tp))
            conv = type(choices[0]) if choices else str
        elif tp is bool or isinstance(default, bool):
            kwargs["action"] = argparse.BooleanOptionalAction
            conv = None
        elif tp in (int, float, str):
            conv = tp
        elif isinstance(default, int | float | str) and default is not None:
            conv = type(default)
        elif typing.get_origin(tp) is tuple or isinstance(default, tuple):
            args = typing.get_args(tp)
            elem = args[0] if args else (type(default[0]) if default else float)
            conv = elem if elem in (int, float, str) else float
            kwargs["nargs"] = len(default) if isinstance(default, tuple) and default else "+"
            kwargs["type"] = conv
            kwargs["metavar"] = conv.__name__.upper()
            conv = None
        else:
            conv = json.loads
        if choices and conv is None:
            choices = None  # flags and tuples take no choices
        elif choices:
            conv = type(default)
        if conv is not None:
            kwargs["type"] = _none_or(conv) if optional else conv
            kwargs["metavar"] = (
                "{" + ",".join(map(str, choices)) + "}"
                if choices
                else (getattr(conv, "__name__", "VALUE").upper() + ("|none" if optional else ""))
            )
        if choices:
            kwargs["choices"] = choices + ([None] if optional else [])
        shown = "none" if default is None else default
        if isinstance(default, tuple):
            shown = " ".join(map(str, default))
        help_text = f"{desc} (default: {shown})" if desc else f"(default: {shown})"
        group.add_argument(flag, help=help_text.replace("%", "%%"), **kwargs)
        names.append(f.name)
    return names


def size_text(shape) -> str:
    return f"{shape[1]}x{shape[0]}"


def check_rig_size(rig: Rig, shape: tuple[int, ...], where: str) -> None:
    for unit in (rig.cam1, rig.cam2):
        if (unit.height, unit.width) != tuple(shape):
            raise CLIError(
                f"the images are {size_text(shape)} but {where} says {unit.name} is "
                f"{unit.width}x{unit.height}"
            )


def make_config(args, config_fields: list[str]):
    cls = _config_class()
    overrides = {
        name: getattr(args, f"cfg_{name}") for name in config_fields if hasattr(args, f"cfg_{name}")
    }
    overrides = {k: tuple(v) if isinstance(v, list) else v for k, v in overrides.items()}
    check_knobs(overrides)  # before the config's own checks, so the message names the option
    dense = getattr(args, "dense", False)
    if args.paper and dense:
        raise CLIError("--paper and --dense: expected at most one preset")
    try:
        preset = cls.paper if args.paper else cls.dense if dense else cls
        config = preset(**overrides)
    except (TypeError, ValueError) as exc:
        raise CLIError(f"bad algorithm option: {one_line(exc)}") from exc
    check_knobs(config)
    return config


class _SettingsParser(argparse.ArgumentParser):
    """Parser of NAME=VALUE settings: a usage error is a :class:`CLIError`, not an exit."""

    def error(self, message: str) -> typing.NoReturn:
        raise CLIError(message)


def config_from_settings(settings: str | Sequence[str], *, paper: bool = False) -> Any:
    """An OmniFlowConfig from ``NAME=VALUE`` settings, checked as the CLI's options are.

    ``settings`` is a comma-separated string (``"flow_taper=0,eiv=none"``) or a
    list of ``NAME=VALUE`` strings; NAME is an OmniFlowConfig field (``-`` or
    ``_``), VALUE parsed as its option would be (``none`` for None, ``true`` /
    ``false`` for a switch, space-separated numbers for a tuple). The other
    fields keep their defaults (``paper``: those of ``OmniFlowConfig.paper()``).
    An item ``paper`` or ``dense`` (no ``=``) starts from that preset instead
    (``"dense,pool_k=64"``). Raises :class:`CLIError` with one line naming the
    setting and what was expected.
    """
    items = settings.split(",") if isinstance(settings, str) else list(settings)
    parser = _SettingsParser(prog="settings", add_help=False, allow_abbrev=False)
    fields = add_config_options(parser)
    argv: list[str] = []
    dense = False
    for item in (i.strip() for i in items):
        if not item:
            continue
        if item in ("paper", "dense"):  # a preset, as the CLI's --paper / --dense
            paper, dense = paper or item == "paper", dense or item == "dense"
            continue
        name, sep, value = item.partition("=")
        name = name.strip().replace("-", "_")
        if not sep or name not in fields:
            raise CLIError(
                f"{item!r}: expected NAME=VALUE with NAME an OmniFlowConfig field, e.g. "
                "flow_taper=0 (omniflow --help lists them), or a preset: paper, dense"
            )
        action = next(a for a in parser._actions if a.dest == f"cfg_{name}")
        if isinstance(action, argparse.BooleanOptionalAction):
            if value.strip().lower() not in ("true", "false", "1", "0", "yes", "no"):
                raise CLIError(f"{item!r}: expected {name}=true or {name}=false")
            on = value.strip().lower() in ("true", "1", "yes")
            argv.append(flag(name) if on else "--no-" + name.replace("_", "-"))
        else:
            argv += [f"{flag(name)}={value.strip()}"] if action.nargs is None else [
                flag(name), *value.split()]  # fmt: skip
    try:
        args = parser.parse_args(argv)
    except CLIError as exc:
        raise CLIError(f"{', '.join(items)}: {exc}") from None
    args.paper, args.dense = paper, dense
    return make_config(args, fields)


# -- outputs -----------------------------------------------------------------------------


def column_units() -> dict[str, str]:
    from omniflow.pipeline import COLUMNS

    return {
        **COLUMNS,
        "time_to_contact": "frames, -r / (dr/dt) where approaching, else inf",
        "odometry_inlier": "1 where the odometry fit used the point, 0 where not (moving or "
        "mismatched), nan without a fit",
        "auto_region": "the --auto-regions group (auto1 = 1, ...), 0 in none",
    }


def one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


#: errno values that mean the path given is wrong (exit 2), not that the machine refused.
_BAD_PATH_ERRNOS = {
    errno.ENOENT: "no such file or folder",
    errno.ENOTDIR: "a part of the path is a file, not a folder",
    errno.EISDIR: "is a folder; expected a file",
    errno.EEXIST: "already exists",
    errno.ENAMETOOLONG: "name too long",
    errno.ELOOP: "too many symbolic links",
}


def explain_error(exc: BaseException, out: str | None = None) -> tuple[int, str]:
    """(exit status, one-line message) for an exception that ended a run.

    Bad input (2): the command's own checks, image, rig and dataset errors, a
    file that is not text, a path of the wrong kind. The environment (1):
    permission denied, a read-only or full file system, memory. Anything
    else is a bug in omniflow (1), reported as such.
    """
    # Only modules this run imported can have raised their errors (and importing
    # scikit-image here just to name a class would cost a second).
    if isinstance(exc, OutputError):
        return 2, f"--out {one_line(exc)}"
    known: tuple[type, ...] = (CLIError, ImageError, RigError)
    for module, name in (
        ("omniflow.geometry.calibration", "RimError"),
        ("omniflow.io.dataset", "DatasetError"),
    ):
        if module in sys.modules:
            known += (getattr(sys.modules[module], name),)
    if isinstance(exc, known):
        return 2, one_line(exc)
    if isinstance(exc, UnicodeDecodeError):
        return 2, f"a file that should be text is not UTF-8 ({one_line(exc)})"
    if isinstance(exc, OSError):
        path = exc.filename if exc.filename is not None else "?"
        under_out = out is not None and (
            str(path).startswith(str(out)) or str(out).startswith(str(path))
        )
        need = "; --out needs a folder this command can write" if under_out else ""
        if exc.errno in _BAD_PATH_ERRNOS:
            return 2, f"{path}: {_BAD_PATH_ERRNOS[exc.errno]}{need}"
        reason = exc.strerror or one_line(exc)
        return 1, f"{path}: {reason}{need}"
    if isinstance(exc, MemoryError):
        return 1, "out of memory (try smaller images or fewer --n-theta lines)"
    text = f"{type(exc).__name__}: {one_line(exc)}"
    return 1, f"internal error ({text}); rerun with --debug for the traceback and report it"
