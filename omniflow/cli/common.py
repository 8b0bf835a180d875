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
import sys
import types
import typing
from collections.abc import Sequence
from typing import Any

from omniflow.geometry.rig import Rig, RigError
from omniflow.io.imageio import ImageError, OutputError

__all__ = [
    "MACHINE_ERRNOS",
    "CLIError",
    "Formatter",
    "Parser",
    "add_config_options",
    "add_expert_options",
    "check_knobs",
    "check_rig_size",
    "column_units",
    "config_from_settings",
    "expand_settings",
    "explain_error",
    "flag",
    "make_config",
    "one_line",
    "setting_flags",
    "shorten_help",
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


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def check_knobs(values: Any) -> None:
    """Raise :class:`CLIError` naming the option if a knob's value is not allowed.

    ``values`` is an OmniFlowConfig or a mapping of dotted knob name to value
    (``pooling.pool_k``); each is checked by its field's metadata
    (:func:`omniflow.config.knob_problem`), the one place that knows the knob's type,
    range and choices.
    """
    from omniflow.config import knob_fields, knob_problem

    known = knob_fields()
    if dataclasses.is_dataclass(values):
        values = values.to_dict()
    for name, value in values.items():
        if name not in known:
            continue
        problem = knob_problem(known[name], value)
        if problem:
            shown = f"{value:g}" if isinstance(value, float) else str(value)
            raise CLIError(f"{flag(name)} {shown}: {problem}")


def _knob_hints() -> dict[str, Any]:
    """Each knob's type by its dotted name (``pooling.pool_k``: int)."""
    from omniflow.config import GROUPS

    cls = _config_class()
    try:
        hints = dict(typing.get_type_hints(cls))
        for group, group_cls in GROUPS.items():
            hints.update({f"{group}.{k}": v for k, v in typing.get_type_hints(group_cls).items()})
    except Exception:  # unresolvable annotations: fall back to the defaults' types
        hints = {}
    return hints


def add_config_options(parser: argparse.ArgumentParser) -> list[str]:
    """One option per OmniFlowConfig knob, its default shown (a group's knobs under
    dotted names, ``--pooling.pool-k``, in one option group per expert group); returns
    the knobs' dotted names."""
    from omniflow.config import GROUPS, knob_fields

    hints = _knob_hints()
    groups = {"": parser.add_argument_group(
        "algorithm options (omniflow.config.OmniFlowConfig; each default shown)")}  # fmt: skip
    for name, cls in GROUPS.items():
        doc = (cls.__doc__ or "").split(":")[0].split("(")[0].strip()
        groups[name] = parser.add_argument_group(f"expert options, {name}: {doc}")
    names = []
    for name, f in knob_fields().items():
        if not f.init or f.name.startswith("_"):
            continue
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            continue
        tp, optional = _unwrap_optional(hints.get(name, type(default)))
        desc = f.metadata.get("help", "")
        kwargs: dict[str, Any] = {"dest": f"cfg_{name}", "default": argparse.SUPPRESS}
        choices = list(f.metadata["choices"]) if f.metadata.get("choices") else None
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
        group = groups[name.partition(".")[0] if "." in name else ""]
        group.add_argument(flag(name), help=help_text.replace("%", "%%"), **kwargs)
        names.append(name)
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
        preset = "paper" if args.paper else "dense" if dense else "default"
        config = cls.preset(preset).with_settings(overrides)
    except (TypeError, ValueError) as exc:
        raise CLIError(f"bad algorithm option: {one_line(exc)}") from exc
    check_knobs(config)
    return config


class _SettingsParser(argparse.ArgumentParser):
    """Parser of NAME=VALUE settings: a usage error is a :class:`CLIError`, not an exit."""

    def error(self, message: str) -> typing.NoReturn:
        raise CLIError(message)


def setting_flags(
    item: str, parser: argparse.ArgumentParser, fields: list[str], *, presets: bool = False
) -> list[str]:
    """The options one ``NAME=VALUE`` setting stands for (``pooling.pool_k=64`` ->
    ``--pooling.pool-k=64``, ``matching.left_right=false`` -> ``--no-matching.left-right``),
    so that the knob's own option parses and checks it; a :class:`CLIError` naming the
    setting where NAME is no knob."""
    name, sep, value = item.partition("=")
    name = name.strip().replace("-", "_")
    if not sep or name not in fields:
        raise CLIError(
            f"{item!r}: expected NAME=VALUE with NAME an OmniFlowConfig knob, e.g. "
            f"band=0.3 or fit.flow_taper=0{_knob_hint(name)} (omniflow pair --help-expert "
            "lists them)" + (", or a preset: paper, dense" if presets else "")
        )
    action = next(a for a in parser._actions if a.dest == f"cfg_{name}")
    if isinstance(action, argparse.BooleanOptionalAction):
        if value.strip().lower() not in ("true", "false", "1", "0", "yes", "no"):
            raise CLIError(f"{item!r}: expected {name}=true or {name}=false")
        on = value.strip().lower() in ("true", "1", "yes")
        return [flag(name) if on else "--no-" + name.replace("_", "-")]
    if action.nargs is None:
        return [f"{flag(name)}={value.strip()}"]
    return [flag(name), *value.split()]


def _knob_hint(name: str) -> str:
    """``; it is pooling.pool_k`` where ``name`` is a group's knob given without its group."""
    from omniflow.config import knob_fields

    dotted = [k for k in knob_fields() if k.endswith("." + name)]
    return f"; it is {dotted[0]}" if dotted else ""


def expand_settings(argv: list[str], parser: argparse.ArgumentParser) -> list[str]:
    """``argv`` with every ``--set NAME=VALUE`` replaced by the option it stands for
    (:func:`setting_flags`); a bad setting is the parser's one-line usage error."""
    fields = parser._config_fields  # type: ignore[attr-defined]
    out: list[str] = []
    i = 0
    while i < len(argv):
        arg = argv[i]
        if arg != "--set" and not arg.startswith("--set="):
            out.append(arg)
            i += 1
            continue
        if arg == "--set" and i + 1 >= len(argv):
            parser.error("--set: expected NAME=VALUE")
        item = argv[i + 1] if arg == "--set" else arg[len("--set=") :]
        i += 2 if arg == "--set" else 1
        try:
            out += setting_flags(item, parser, fields)
        except CLIError as exc:
            parser.error(f"--set {exc}")
    return out


class ExpertHelp(argparse.Action):
    """``--help-expert``: print the parser's help with every option (``full()``) and exit."""

    def __init__(self, option_strings, dest, full=None, **kwargs) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)
        self.full = full

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        self.full().print_help()
        parser.exit()


def add_expert_options(parser: argparse.ArgumentParser, full) -> None:
    """``--set NAME=VALUE`` (any OmniFlowConfig field, checked by its metadata) and
    ``--help-expert`` (``full()``: the parser with every option shown)."""
    group = parser.add_argument_group("expert options")
    group.add_argument(
        "--set", action="append", metavar="NAME=VALUE", dest="set_items", default=[],
        help="set any knob, a group's by its dotted name, repeatable (--set "
        "pooling.pool_k=64; none for None); --help-expert lists them",
    )  # fmt: skip
    group.add_argument("--help-expert", action=ExpertHelp, full=full,
                       help="show every option, with its default, and exit")  # fmt: skip


def shorten_help(parser: argparse.ArgumentParser, keep: set[str]) -> None:
    """Hide from ``--help`` every option whose dest is not in ``keep`` (each is still
    accepted; ``--help-expert`` shows them all)."""
    for action in parser._actions:
        if action.option_strings and action.dest not in keep and action.dest != "help":
            action.help = argparse.SUPPRESS


def config_from_settings(settings: str | Sequence[str], *, paper: bool = False) -> Any:
    """An OmniFlowConfig from ``NAME=VALUE`` settings, checked as the CLI's options are.

    ``settings`` is a comma-separated string (``"fit.flow_taper=0,pooling.eiv=none"``)
    or a list of ``NAME=VALUE`` strings; NAME is an OmniFlowConfig knob's dotted name
    (``-`` or ``_``), VALUE parsed as its option would be (``none`` for None, ``true`` /
    ``false`` for a switch, space-separated numbers for a tuple). The other
    knobs keep their defaults (``paper``: those of ``OmniFlowConfig.paper()``).
    An item ``paper`` or ``dense`` (no ``=``) starts from that preset instead
    (``"dense,pooling.pool_k=64"``). Raises :class:`CLIError` with one line naming the
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
        argv += setting_flags(item, parser, fields, presets=True)
    try:
        args = parser.parse_args(argv)
    except CLIError as exc:
        raise CLIError(f"{', '.join(items)}: {exc}") from None
    args.paper, args.dense = paper, dense
    return make_config(args, fields)


# -- outputs -----------------------------------------------------------------------------


def column_units() -> dict[str, str]:
    from omniflow.pipeline import COLUMNS
    from omniflow.result import SIGMA_COLUMNS

    return {
        **COLUMNS,
        **SIGMA_COLUMNS,
        "time_to_contact": "frames, -r / (dr/dt) where approaching, else inf",
        "odometry_inlier": "1 where the odometry fit used the point, 0 where not (moving or "
        "mismatched), nan without a fit",
        "auto_region": "the --auto-regions group (auto1 = 1, ...), 0 in none",
    }


def one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


#: errno values of a machine that refused to write (a full disk or quota, an I/O error):
#: exit 1 in every command, never 2 (bad input), whatever else a command maps to 2.
MACHINE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO})

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
