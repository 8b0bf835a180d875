"""The ``omniflow`` command: coaxial omni flow of a stereo frame pair, to CSV and pictures.

See ``docs/omniflow_cli.md`` and ``omniflow --help``. Exit status: 0 on
success (also when no point matched: the outputs are then empty and one
warning line says so), 2 on bad input (a missing or unreadable file, images of
different sizes, a rig file with a missing or impossible field, NaN pixels, an
option out of range, an ``--out`` that is a file), 1 when the machine refuses
(permission denied, read-only or full file system, out of memory) or on an
internal error. Every failure is one line on standard error naming the path,
option or value and what was expected; ``--debug`` shows the traceback
instead. The outputs are staged and moved into ``--out`` as a set
(:class:`omniflow.io.imageio.OutputSet`), so a failed run changes nothing there.
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
import time
import traceback
import types
import typing
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from omniflow.applications.regions import regions_csv_text
from omniflow.geometry.rig import Rig, RigError, Unit, load_rig, unwarp
from omniflow.io.imageio import (
    ImageError,
    OutputError,
    OutputSet,
    atomic_write_text,
    read_image,
    to_grey,
    write_png,
)
from omniflow.io.jsonio import json_text, jsonable

PROG = "omniflow"

#: Every file the command writes in --out; flow.json (the manifest) is moved last.
OUTPUTS = (
    "flow.csv",
    "regions.csv",
    "monocular.csv",
    "flow_arrows.png",
    "flow_color.png",
    "unwarp_cam1.png",
    "flow.json",
)
#: The pictures among OUTPUTS (left out by --no-pictures).
PICTURES = ("flow_arrows.png", "flow_color.png", "unwarp_cam1.png")


class CLIError(ValueError):
    """Bad command-line input; the message is printed as is."""


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose usage errors are one line, with exit status 2."""

    def error(self, message: str) -> typing.NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


class _Formatter(argparse.RawDescriptionHelpFormatter):
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


def _flag(name: str) -> str:
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
            raise CLIError(f"{_flag(name)} {value}: expected a finite number {expected}".strip())
        if limits is None:
            continue
        lo, hi, lo_in, hi_in = limits
        inside = (lo < value or (lo_in and value == lo)) and (value < hi or (hi_in and value == hi))
        if not inside:
            raise CLIError(
                f"{_flag(name)} {value:g}: expected {kind} {_range_text(lo, hi, lo_in, hi_in)}"
            )


def _add_config_options(parser: argparse.ArgumentParser) -> list[str]:
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


def build_parser() -> argparse.ArgumentParser:
    """The ``omniflow`` argument parser (options for every OmniFlowConfig knob included)."""
    parser = _Parser(
        prog=PROG,
        allow_abbrev=False,
        formatter_class=_Formatter,
        description=textwrap.dedent(
            """\
            Omni flow (Spacek) of a coaxial conical-mirror stereo rig: match the two
            cameras along radial lines, solve the direct 2x2 flow equations at every
            match, and write per-point results (CSV + JSON sidecar) and pictures.

            Frames are given as image files in time order, cam1 then cam2 for each
            time step: CAM1_T0 CAM2_T0 CAM1_T1 CAM2_T1 [CAM1_T2 CAM2_T2 ...]
            (PNG 8/16-bit, JPEG, TIFF or OpenEXR; colour is reduced to Rec. 709
            luminance). The flow is from time step --t (default 0) to the next;
            more time steps are used by --temporal dct3d. Or read the frames from an
            omnisim dataset: --dataset DIR --frame K (flow from frame K to K + 1).
            """
        ),
        epilog=textwrap.dedent(
            """\
            outputs (in --out DIR, each written atomically):
              flow.csv         one row per matched point, after a '#' line of units; columns
                               x, y (cam1 px), theta (rad),
                               h1, h2 (px), r, h (m), dh1_dt (px/frame), dtheta_dt (rad/frame),
                               dr_dt (m/frame), dx, dy (cam1 px/frame), cam2 columns x2, y2,
                               dh2_dt, dx2, dy2, confidence, D, coupled (1: eq. 14 holds,
                               0: each camera's radial flow solved on its own),
                               time_to_contact (frames)
              flow.json        units of every column, the config, the rig, the inputs and timings
              regions.csv      with --region / --auto-regions: per region its point count,
                               mean flow, dr/dt, time to contact and steering headings (with
                               --monocular-gap also its cam1-only points' bearing and rate)
              monocular.csv    with --monocular-gap PX: cam1's flow alone at significant points
                               farther than PX from every match (no range): x, y, theta, h1,
                               dh1_dt, dtheta_dt, dx, dy, confidence
              flow_arrows.png  cam1 frame t with the flow drawn as arrows (magnified; see legend)
                               and the regions outlined
              flow_color.png   cam1 frame t with each point in the Middlebury flow colour
              unwarp_cam1.png  cam1 as a panorama (eq. 6-7) with the flow drawn on it
            Velocities are per frame interval: divide by the frame interval for per-second units.

            rig file (TOML or JSON, or an omnisim dataset.json):
              [rig]           d = 0.10  R = 0.05  s = 0.30        (metres)
              [[cameras]]     name = "cam1"  x_c = 256.0  y_c = 256.0  r_m = 250.0
                              width = 512  height = 512           (pixels; pixel centres j + 0.5)
              [[cameras]]     name = "cam2"  ...

            examples:
              omniflow c1_0.png c2_0.png c1_1.png c2_1.png --rig rig.toml --out result
              omniflow --dataset renders/room --frame 3 --out result --solver pooled
              omniflow c1_0.exr c2_0.exr c1_1.exr c2_1.exr --calibrate --d 0.1 --R 0.05 --s 0.3 \\
                  --out result

            exit status: 0 success (no matched point is a success: empty outputs, one warning);
              2 bad input; 1 the machine refused (permission, read-only or full disk) or an
              internal error. One line on stderr names the path, option or value.
            """
        ),
    )
    inputs = parser.add_argument_group("input")
    inputs.add_argument(
        "images",
        nargs="*",
        metavar="IMAGE",
        help="frames in time order, cam1 then cam2 per time step (at least 4 files)",
    )
    inputs.add_argument(
        "--rig", metavar="FILE", help="rig description (.toml or .json, incl. dataset.json)"
    )
    inputs.add_argument(
        "--dataset",
        metavar="DIR",
        help="read frames and rig from an omnisim dataset directory instead of IMAGE files",
    )
    inputs.add_argument(
        "--frame",
        type=int,
        default=0,
        metavar="K",
        help="--dataset only: flow from frame K to K + 1 (default: 0)",
    )
    inputs.add_argument(
        "--t",
        type=int,
        metavar="T",
        help="IMAGE files only: flow from time step T to T + 1 (default: 0)",
    )
    calib = parser.add_argument_group(
        "calibration (find each mirror's rim in the first frames, replacing x_c, y_c, r_m)"
    )
    calib.add_argument(
        "--calibrate",
        action="store_true",
        help="locate the rim circles with omniflow.geometry.calibration "
        "(d, R, s from --rig or below)",
    )
    calib.add_argument("--d", type=float, metavar="M", help="camera centre to cone tip, metres")
    calib.add_argument("--R", type=float, metavar="M", help="mirror base radius, metres")
    calib.add_argument(
        "--s", type=float, metavar="M", help="baseline between the cone tips, metres"
    )
    output = parser.add_argument_group("output")
    output.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    output.add_argument(
        "--no-pictures", action="store_true", help="write only flow.csv and flow.json"
    )
    output.add_argument(
        "--arrow-scale",
        type=float,
        metavar="K",
        help="draw arrows K times their length (default: automatic, shown in the picture)",
    )
    output.add_argument(
        "--debug",
        action="store_true",
        help="on an error, show the Python traceback instead of the one-line message",
    )
    output.add_argument(
        "--odometry",
        action="store_true",
        help="also fit the robot's yaw rate and velocity to the flow "
        "(omniflow.applications.navigation); "
        "flow.csv gets a column odometry_inlier (1: the fit used the point)",
    )
    output.add_argument(
        "--odometry-radial-weight",
        type=float,
        default=1.0,
        metavar="W",
        help="weight of the dr/dt rows against the r dtheta/dt rows in the odometry fit; "
        "0 fits the bearing rates only (default: 1.0)",
    )
    regions = parser.add_argument_group(
        "regions (time to contact, steering and position fix per object; regions.csv)"
    )
    regions.add_argument(
        "--region",
        action="append",
        default=[],
        metavar="SPEC",
        help="a region, repeatable: NAME:box:THETA0,THETA1,H0,H1 (cam1 polar box: theta in "
        "degrees from THETA0 towards increasing theta to THETA1, through 360 if THETA1 < "
        "THETA0; image radius h1 in px, 0 <= H0 < H1 <= r_m), NAME:mask:FILE (an image of "
        "cam1's size, non-zero inside) or NAME:object:ID|NAME (--dataset only: an object of "
        "the ground truth's gt.object at frame K)",
    )
    regions.add_argument(
        "--auto-regions",
        action="store_true",
        help="find the independently moving objects: the points whose flow the odometry fit "
        "does not explain, grouped where they lie together in the image (regions auto1, "
        "auto2, ...; flow.csv gets a column auto_region)",
    )
    regions.add_argument(
        "--auto-min-points",
        type=int,
        default=20,
        metavar="N",
        help="smallest group --auto-regions reports, points (default: 20)",
    )
    regions.add_argument(
        "--auto-link",
        type=float,
        metavar="PX",
        help="largest gap between neighbouring points of one group, cam1 px (default: r_m / 10)",
    )
    regions.add_argument(
        "--auto-residual",
        type=float,
        default=4.0,
        metavar="K",
        help="a point moves on its own when its odometry residual exceeds K times the fit's "
        "inlier threshold (2.5 robust sigma) (default: 4.0)",
    )
    regions.add_argument(
        "--auto-min-speed",
        type=float,
        default=1e-4,
        metavar="M",
        help="a point moves on its own only if its own speed also exceeds M m/frame: the "
        "inlier threshold is relative (2.5 robust sigma), so on near-exact flow it would "
        "call static points moving (default: 1e-4, 0.1 mm per frame)",
    )
    regions.add_argument(
        "--auto-coherence",
        type=float,
        default=0.5,
        metavar="F",
        help="neighbours join one group only when their own velocities (flow minus the "
        "robot's motion) differ by at most F times the larger; inf: position only "
        "(default: 0.5)",
    )
    regions.add_argument(
        "--steer-lead",
        type=float,
        default=1.0,
        metavar="FRAMES",
        help="steering headings aim at the region's centroid this many frames ahead "
        "(omniflow.applications.navigation.steering_heading) (default: 1.0)",
    )
    regions.add_argument(
        "--frame-interval",
        type=float,
        metavar="S",
        help="seconds between frames, for times to contact in seconds (default: the "
        "dataset's; none for IMAGE files)",
    )
    regions.add_argument(
        "--landmark",
        action="append",
        default=[],
        metavar="NAME:X,Y",
        help="the world position (m) of region NAME's centroid, repeatable: with two or more, "
        "flow.json gets the robot's pose (omniflow.applications.navigation.position_fix)",
    )
    algo = parser.add_argument_group("algorithm preset")
    algo.add_argument(
        "--paper",
        action="store_true",
        help="start from the paper's choices (OmniFlowConfig.paper(): gradient-similarity "
        "matching, first-frame gradients, frame differences, the direct 2x2 solution); "
        "options below still override",
    )
    algo.add_argument(
        "--dense",
        action="store_true",
        help="start from the densified configuration (OmniFlowConfig.dense(): matches beyond "
        "the edges, grid pools; about ten times the points and a smaller error, at about "
        "twice the time); options below still override",
    )
    parser._config_fields = _add_config_options(parser)  # type: ignore[attr-defined]
    return parser


# -- inputs ------------------------------------------------------------------------------


def _read_files(paths: list[str]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Grey frames of cam1 and cam2 from files given as CAM1_T0 CAM2_T0 CAM1_T1 CAM2_T1 ..."""
    if len(paths) < 4 or len(paths) % 2:
        raise CLIError(
            f"got {len(paths)} image file(s); expected an even number >= 4: "
            "CAM1_T0 CAM2_T0 CAM1_T1 CAM2_T1 [...]"
        )
    images = [to_grey(read_image(p)) for p in paths]
    for p, img in zip(paths, images, strict=True):
        if img.shape != images[0].shape:
            raise CLIError(
                f"images differ in size: {paths[0]} is {_size(images[0].shape)} "
                f"but {p} is {_size(img.shape)}"
            )
    return images[0::2], images[1::2]


def _size(shape) -> str:
    return f"{shape[1]}x{shape[0]}"


def _read_dataset(directory: str, k: int, window: int):
    """Frames around K of an omnisim dataset: (frames1, frames2, t, rig, info).

    ``window`` time steps are read, placed so that K .. K + 1 sits in the middle
    where the dataset allows; ``t`` is K's index in the returned lists.
    """
    from omniflow.io.dataset import DatasetError, open_dataset

    meta = Path(directory) / "dataset.json"
    try:
        ds = open_dataset(directory)
        n = ds.frame_count
        if not 0 <= k < n - 1:
            raise CLIError(
                f"--frame {k}: the flow needs frames {k} and {k + 1}, but {directory} has "
                f"frames 0..{n - 1}"
            )
        if window > n:
            raise CLIError(f"{directory}: {window} frames needed but the dataset has {n}")
        start = min(max(0, k - (window - 2) // 2), n - window)
        frames = range(start, start + window)
        f1 = [ds.read_grey(j, "cam1") for j in frames]
        f2 = [ds.read_grey(j, "cam2") for j in frames]
    except DatasetError as exc:
        raise CLIError(str(exc)) from exc
    except UnicodeDecodeError as exc:  # omnisim reads dataset.json as UTF-8 text
        raise CLIError(f"{meta}: not UTF-8 text ({_one_line(exc)}); expected JSON") from exc
    for j, a, b in zip(frames, f1, f2, strict=True):
        for cam, img in (("cam1", a), ("cam2", b)):
            bad = ~np.isfinite(img)
            if bad.any():
                raise CLIError(f"{ds.path(j, cam)}: {int(bad.sum())} pixel(s) are NaN or infinite")
    info = {"dataset": str(directory), "frames_read": list(frames), "frame": k,
            "frame_interval_s": ds.frame_interval}  # fmt: skip
    return f1, f2, k - start, ds.rig, info


def _calibrated_rig(args, base: Rig | None, f1: np.ndarray, f2: np.ndarray) -> Rig:
    """The rig with each unit's x_c, y_c, r_m found in its image (omniflow.geometry.calibration)."""
    d = args.d if args.d is not None else (base.d if base else None)
    R = args.R if args.R is not None else (base.R if base else None)
    s = args.s if args.s is not None else (base.s if base else None)
    missing = [n for n, v in (("--d", d), ("--R", R), ("--s", s)) if v is None]
    if missing:
        raise CLIError(f"--calibrate needs {', '.join(missing)} (or a --rig file giving them)")
    from omniflow.geometry.calibration import calibrate_unit

    try:
        u1 = calibrate_unit(f1, d=d, R=R, tip_h=s, name="cam1")
        u2 = calibrate_unit(f2, d=d, R=R, tip_h=0.0, name="cam2")
    except (ValueError, RuntimeError) as exc:
        raise CLIError(f"--calibrate: {_one_line(exc)}") from exc
    rig = Rig(cam1=u1, cam2=u2, s=s)
    rig.validate("--calibrate")
    return rig


def _check_rig_size(rig: Rig, shape: tuple[int, ...], where: str) -> None:
    for unit in (rig.cam1, rig.cam2):
        if (unit.height, unit.width) != tuple(shape):
            raise CLIError(
                f"the images are {_size(shape)} but {where} says {unit.name} is "
                f"{unit.width}x{unit.height}"
            )


def _make_config(args, config_fields: list[str]):
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
        raise CLIError(f"bad algorithm option: {_one_line(exc)}") from exc
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
    fields = _add_config_options(parser)
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
            argv.append(_flag(name) if on else "--no-" + name.replace("_", "-"))
        else:
            argv += [f"{_flag(name)}={value.strip()}"] if action.nargs is None else [
                _flag(name), *value.split()]  # fmt: skip
    try:
        args = parser.parse_args(argv)
    except CLIError as exc:
        raise CLIError(f"{', '.join(items)}: {exc}") from None
    args.paper, args.dense = paper, dense
    return _make_config(args, fields)


def _check_options(args) -> None:
    """Options of the command itself (not of OmniFlowConfig) that argparse cannot range-check."""
    if args.arrow_scale is not None and not (
        math.isfinite(args.arrow_scale) and args.arrow_scale > 0
    ):
        raise CLIError(f"--arrow-scale {args.arrow_scale}: expected a finite number > 0")
    for name in ("d", "R", "s"):
        value = getattr(args, name)
        if value is not None and not (math.isfinite(value) and value > 0):
            raise CLIError(f"--{name} {value}: expected a finite length in metres > 0")
    if args.t is not None and args.t < 0:
        raise CLIError(f"--t {args.t}: expected a time step >= 0")
    if args.frame < 0:
        raise CLIError(f"--frame {args.frame}: expected a frame index >= 0")
    _check_region_options(args)


def _check_region_options(args) -> None:
    """Region, landmark and odometry options: ranges, syntax, names (no file is read here)."""
    from omniflow.applications.regions import RegionError, parse_landmark, parse_region

    w = args.odometry_radial_weight
    if not (math.isfinite(w) and w >= 0):
        raise CLIError(f"--odometry-radial-weight {w}: expected a finite number >= 0")
    if args.auto_min_points < 1:
        raise CLIError(f"--auto-min-points {args.auto_min_points}: expected an integer >= 1")
    if args.auto_link is not None and not (math.isfinite(args.auto_link) and args.auto_link > 0):
        raise CLIError(f"--auto-link {args.auto_link}: expected a finite distance in px > 0")
    if not (math.isfinite(args.auto_residual) and args.auto_residual >= 1):
        raise CLIError(
            f"--auto-residual {args.auto_residual}: expected a finite number >= 1 "
            "(1: every odometry outlier)"
        )
    if not (math.isfinite(args.auto_min_speed) and args.auto_min_speed >= 0):
        raise CLIError(f"--auto-min-speed {args.auto_min_speed}: expected a finite number >= 0")
    if not (args.auto_coherence > 0):  # inf allowed: position only
        raise CLIError(f"--auto-coherence {args.auto_coherence}: expected a number > 0 (or inf)")
    if not (math.isfinite(args.steer_lead) and args.steer_lead >= 0):
        raise CLIError(f"--steer-lead {args.steer_lead}: expected a finite number of frames >= 0")
    fi = args.frame_interval
    if fi is not None and not (math.isfinite(fi) and fi > 0):
        raise CLIError(f"--frame-interval {fi}: expected a finite number of seconds > 0")
    try:
        specs = [parse_region(text) for text in args.region]
        landmarks = [parse_landmark(text) for text in args.landmark]
    except RegionError as exc:
        raise CLIError(str(exc)) from exc
    names = [spec.name for spec in specs]
    for spec in specs:
        if names.count(spec.name) > 1:
            raise CLIError(f"--region {spec.text}: the name {spec.name!r} is given twice")
    for (name, _, _), text in zip(landmarks, args.landmark, strict=True):
        if name not in names:
            known = ", ".join(names) or "none given"
            raise CLIError(f"--landmark {text}: no --region named {name!r} (regions: {known})")
        if [lm[0] for lm in landmarks].count(name) > 1:
            raise CLIError(f"--landmark {text}: region {name!r} has two landmarks")
    if len(landmarks) == 1:
        raise CLIError(
            f"--landmark {args.landmark[0]}: a position fix needs at least 2 landmarks "
            "(one fixes the position only up to a turn about it)"
        )


def _load_inputs(args, config):
    """(frames1, frames2, t, rig, rig_source, info) from the command line."""
    dct3d = getattr(config, "temporal", "difference") == "dct3d"
    window = max(2, int(getattr(config, "temporal_frames", 3))) if dct3d else 2
    if args.dataset:
        if args.images:
            raise CLIError("give either IMAGE files or --dataset, not both")
        if args.t is not None:
            raise CLIError("--t applies to IMAGE files; with --dataset use --frame K")
        f1, f2, t, rig, info = _read_dataset(args.dataset, args.frame, window)
        rig_source = str(Path(args.dataset) / "dataset.json")
        if args.rig:
            rig, rig_source = load_rig(args.rig), args.rig
    else:
        if not args.images:
            raise CLIError("no input: give IMAGE files (CAM1_T0 CAM2_T0 CAM1_T1 ...) or --dataset")
        if args.frame != 0:
            raise CLIError("--frame applies to --dataset; with IMAGE files use --t")
        if args.rig is None and not args.calibrate:
            raise CLIError("--rig FILE is required (or --calibrate with --d, --R, --s)")
        rig = load_rig(args.rig) if args.rig else None
        rig_source = args.rig
        f1, f2 = _read_files(args.images)
        t = args.t or 0
        if not 0 <= t < len(f1) - 1:
            raise CLIError(
                f"--t {t}: the flow needs time steps {t} and {t + 1} of 0..{len(f1) - 1}"
            )
        if dct3d and len(f1) < window:
            raise CLIError(
                f"--temporal dct3d needs {window} time steps (--temporal-frames); got {len(f1)}"
            )
        info = {"images": [str(Path(p)) for p in args.images], "t": t}
    if args.calibrate:
        rig = _calibrated_rig(args, rig, f1[t], f2[t])
        rig_source = f"--calibrate (rims found; d, R, s from {args.rig or 'options'})"
    elif any(v is not None for v in (args.d, args.R, args.s)):
        raise CLIError("--d, --R and --s apply with --calibrate only; edit the rig file instead")
    _check_rig_size(rig, f1[0].shape, rig_source)
    return f1, f2, t, rig, rig_source, info


def _region_masks(args, rig: Rig, shape: tuple[int, int]) -> list[tuple[Any, np.ndarray]]:
    """Each --region as (RegionSpec, cam1 pixel mask (H, W) bool); files read and checked."""
    from omniflow.applications.regions import RegionError, in_box, parse_region

    out = []
    labels = None
    for text in args.region:
        try:
            spec = parse_region(text, r_m=rig.cam1.r_m)
        except RegionError as exc:
            raise CLIError(str(exc)) from exc
        if spec.kind == "box":
            x, y = rig.cam1.pixel_centres()
            h1, theta = rig.cam1.polar_of_pixel(x, y)
            mask = in_box(theta, h1, spec.box) & (h1 <= rig.cam1.r_m)
        elif spec.kind == "mask":
            try:
                image = read_image(spec.path)
            except ImageError as exc:
                raise CLIError(f"--region {text}: {_one_line(exc)}") from exc
            if image.shape[:2] != tuple(shape):
                raise CLIError(
                    f"--region {text}: the mask is {_size(image.shape)}; expected cam1's size "
                    f"{_size(shape)}"
                )
            if not np.isfinite(image).all():
                raise CLIError(f"--region {text}: the mask has NaN or infinite pixels")
            mask = image != 0 if image.ndim == 2 else np.any(image != 0, axis=2)
        else:
            if not args.dataset:
                raise CLIError(
                    f"--region {text}: object regions need --dataset (its ground truth "
                    "gt.object names the objects)"
                )
            if labels is None:
                labels, objects = _object_labels(args.dataset, args.frame)
            ident = _object_id(spec, objects, text)
            mask = labels == ident
        out.append((spec, mask))
    return out


def _object_labels(directory: str, k: int) -> tuple[np.ndarray, dict[int, str]]:
    """gt.object of cam1 at frame K of a dataset, and the dataset's id -> name table."""
    from omniflow.io.dataset import DatasetError, open_dataset

    try:
        ds = open_dataset(directory)
        labels = np.rint(ds.read_frame(k, "cam1")["gt.object"]).astype(int)
    except DatasetError as exc:
        raise CLIError(str(exc)) from exc
    return labels, ds.objects


def _object_id(spec, objects: dict[int, str], text: str) -> int:
    """The gt.object id a --region NAME:object:ID|NAME means (CLIError if none)."""
    if isinstance(spec.object, int) and spec.object in objects:
        return spec.object
    ids = [i for i, name in objects.items() if name == spec.object]
    if len(ids) == 1:
        return ids[0]
    shown = ", ".join(f"{i} {n}" for i, n in sorted(objects.items())) or "none"
    raise CLIError(
        f"--region {text}: no object {spec.object!r} in the dataset; expected an id or "
        f"name of: {shown}"
    )


# -- outputs -----------------------------------------------------------------------------


def _column_units() -> dict[str, str]:
    from omniflow.pipeline import COLUMNS

    return {
        **COLUMNS,
        "time_to_contact": "frames, -r / (dr/dt) where approaching, else inf",
        "odometry_inlier": "1 where the odometry fit used the point, 0 where not (moving or "
        "mismatched), nan without a fit",
        "auto_region": "the --auto-regions group (auto1 = 1, ...), 0 in none",
    }


def _pictures(
    out: Path, image: np.ndarray, unit: Unit, cols, arrow_scale, outlines=()
) -> list[Path]:
    from omniflow.applications.regions import draw_regions
    from omniflow.io.draw import draw_flow_arrows, draw_flow_points

    x, y, dx, dy = (np.asarray(cols[c], float) for c in ("x", "y", "dx", "dy"))
    arrows = draw_flow_arrows(image, x, y, dx, dy, scale=arrow_scale)
    draw_regions(arrows, list(outlines))
    written = [
        write_png(out / "flow_arrows.png", arrows, bits=8),
        write_png(out / "flow_color.png", draw_flow_points(image, x, y, dx, dy), bits=8),
    ]
    # Panorama as omniflow.geometry.rig.unwarp (eq. 6-7): column <- theta, row <- h_1,
    # rim at the top.
    width = int(min(2048, max(256, round(2 * math.pi * unit.r_m))))
    height = max(8, round(unit.r_m))
    pano = unwarp(image, unit, width=width, height=height)
    th = np.mod(np.asarray(cols["theta"], float), 2 * math.pi)
    px = th * width / (2 * math.pi)
    py = height * (1.0 - np.asarray(cols["h1"], float) / unit.r_m)
    pdx = np.asarray(cols["dtheta_dt"], float) * width / (2 * math.pi)
    pdy = -np.asarray(cols["dh1_dt"], float) * height / unit.r_m
    pano_arrows = draw_flow_arrows(pano, px, py, pdx, pdy, scale=arrow_scale)
    written.append(write_png(out / "unwarp_cam1.png", pano_arrows, bits=8))
    return written


def _odometry(cols, radial_weight: float):
    """(OdometryFit or None, its summary for flow.json) on every point's flow."""
    from omniflow.applications.navigation import odometry

    radial = cols["dr_dt"] if radial_weight > 0 else None
    rows = "dtheta/dt, r" + (f" and dr/dt (weight {radial_weight:g})" if radial is not None else "")
    try:
        fit = odometry(cols["theta"], cols["r"], cols["dtheta_dt"], radial,
                       radial_weight=radial_weight)  # fmt: skip
    except ValueError as exc:
        return None, {"error": _one_line(exc)}
    return fit, {
        "fitted_on": f"{rows} of every point (omniflow.applications.navigation.odometry, robust)",
        "yaw_rate_rad_per_frame": fit.w,
        "V_x_m_per_frame": fit.V_x,
        "V_y_m_per_frame": fit.V_y,
        "inlier_fraction": fit.inlier_fraction,
        "residual_scale_m_per_frame": fit.scale,
        "inlier_threshold_m_per_frame": fit.threshold,
        "inliers": "flow.csv column odometry_inlier: 1 where the fit used the point",
    }


def _regions(args, cols, masks, fit, rig: Rig, frame_interval, mono=None):
    """regions.csv rows, pixel outlines for the pictures, and the flow.json block.

    ``mono``: the cam1-only columns (``--monocular-gap``), summarised per given region."""
    from omniflow.applications.regions import auto_groups, in_box, points_in_mask, summarise

    rows, outlines = [], []
    for spec, mask in masks:
        if spec.kind == "box":
            member = in_box(cols["theta"], cols["h1"], spec.box)
            mono_member = None if mono is None else in_box(mono["theta"], mono["h1"], spec.box)
        else:
            member = points_in_mask(mask, cols["x"], cols["y"])
            mono_member = None if mono is None else points_in_mask(mask, mono["x"], mono["y"])
        rows.append(summarise(spec.name, spec.kind, spec.text, cols, member,
                              frame_interval=frame_interval, lead=args.steer_lead,
                              monocular=mono, monocular_member=mono_member))  # fmt: skip
        outlines.append((spec.name, mask))
    block: dict[str, Any] = {}
    if args.auto_regions:
        link = args.auto_link if args.auto_link is not None else rig.cam1.r_m / 10
        block["auto"] = {
            "found_by": "odometry residual > K x its inlier threshold and own speed > "
            "min_speed, grouped by single "
            "linkage in cam1's image (gaps <= link px, own velocities within coherence x the "
            "larger), groups >= min_points",
            "K": args.auto_residual,
            "coherence": args.auto_coherence,
            "link_px": link,
            "min_points": args.auto_min_points,
            "min_speed_m_per_frame": args.auto_min_speed,
        }
        labels = np.zeros(len(cols["x"]), dtype=int)
        if fit is None:
            block["auto"]["error"] = "no odometry fit (see odometry)"
        else:
            with np.errstate(invalid="ignore"):
                moving = np.isfinite(fit.residuals) & (
                    fit.residuals > args.auto_residual * fit.threshold
                )
            own = fit.own_velocity(cols["theta"], cols["r"], cols["dr_dt"], cols["dtheta_dt"])
            with np.errstate(invalid="ignore"):
                moving &= np.hypot(own[:, 0], own[:, 1]) > args.auto_min_speed
            labels = auto_groups(cols["x"], cols["y"], moving, link=link,
                                 min_points=args.auto_min_points, velocity=own,
                                 coherence=args.auto_coherence)  # fmt: skip
            block["auto"]["candidates"] = int(moving.sum())
        cols["auto_region"] = labels.astype(float)
        for k in range(1, int(labels.max(initial=0)) + 1):
            member = labels == k
            v = np.median(own[member], axis=0)
            spec = f"auto: own velocity ({v[0]:.3g}, {v[1]:.3g}) m/frame (rig X, Y, median)"
            rows.append(summarise(f"auto{k}", "auto", spec, cols, member,
                                  frame_interval=frame_interval, lead=args.steer_lead))  # fmt: skip
            outlines.append((f"auto{k}", _hull_mask(cols["x"][member], cols["y"][member], rig)))
    for row in rows:
        if row["points"] == 0 and not row["monocular_points"] > 0:
            warnings.warn(f"region {row['name']} ({row['spec']}) holds no matched point; "
                          "its row in regions.csv is empty", stacklevel=2)  # fmt: skip
    block.update({
        "file": "regions.csv",
        "frame_interval_s": frame_interval,
        "steer_lead_frames": args.steer_lead,
        "rows": rows,
    })  # fmt: skip
    return rows, outlines, block


def _hull_mask(x: np.ndarray, y: np.ndarray, rig: Rig) -> np.ndarray:
    """cam1 pixel mask of the convex hull of points (for the pictures)."""
    import cv2

    mask = np.zeros((rig.cam1.height, rig.cam1.width), np.uint8)
    pts = np.column_stack([np.floor(x), np.floor(y)]).astype(np.int32)
    cv2.fillConvexPoly(mask, cv2.convexHull(pts), 1)
    return mask.astype(bool)


def _position_fix(args, rows) -> dict:
    """The robot's pose from --landmark regions (omniflow.applications.navigation.position_fix)."""
    from omniflow.applications.navigation import position_fix
    from omniflow.applications.regions import parse_landmark

    by_name = {row["name"]: row for row in rows}
    marks = [parse_landmark(text) for text in args.landmark]
    used = [(name, x, y, by_name[name]) for name, x, y in marks]
    empty = [name for name, _, _, row in used if row["points"] == 0]
    block: dict[str, Any] = {"landmarks": {n: [x, y] for n, x, y, _ in used}}
    if empty:
        block["error"] = f"region(s) {', '.join(empty)} hold no matched point"
        return block
    try:
        fix = position_fix(
            [[x, y] for _, x, y, _ in used],
            [row["r"] for *_, row in used],
            [math.radians(row["bearing_deg"]) for *_, row in used],
        )
    except ValueError as exc:
        block["error"] = _one_line(exc)
        return block
    block.update({
        "from": "each region's centroid (r, bearing) against its landmark's world (X, Y)",
        "x_m": fix.x,
        "y_m": fix.y,
        "yaw_deg": math.degrees(fix.yaw),
        "rms_position_m": fix.rms_position,
    })  # fmt: skip
    return block


# -- main ---------------------------------------------------------------------------------


def run(args: argparse.Namespace, config_fields: list[str], argv: list[str]) -> dict:
    """Do the work of one ``omniflow`` invocation; return the summary written to flow.json.

    Inputs and options are checked before anything is computed; the outputs are
    staged and moved into ``--out`` together (:class:`omniflow.io.imageio.OutputSet`).
    """
    from omniflow.applications.navigation import time_to_contact
    from omniflow.pipeline import estimate

    config = _make_config(args, config_fields)
    _check_options(args)
    t0 = time.perf_counter()
    f1, f2, t, rig, rig_source, info = _load_inputs(args, config)
    masks = _region_masks(args, rig, f1[0].shape)
    t_read = time.perf_counter() - t0
    frame_interval = (
        args.frame_interval if args.frame_interval is not None else info.get("frame_interval_s")
    )
    with_regions = bool(masks) or args.auto_regions
    out = Path(args.out)
    written = [
        name
        for name in OUTPUTS
        if not (args.no_pictures and name in PICTURES)
        and not (name == "regions.csv" and not with_regions)
        and not (name == "monocular.csv" and config.monocular_gap is None)
    ]
    with OutputSet(out, owned=OUTPUTS, manifest="flow.json") as stage:
        t1 = time.perf_counter()
        try:
            result = estimate(f1, f2, rig, config, t=t)
        except ValueError as exc:  # inputs and single knobs are checked: a combination is not
            given = ", ".join(
                f"{_flag(name)} {getattr(args, f'cfg_{name}')}"
                for name in config_fields
                if hasattr(args, f"cfg_{name}")
            )
            given = given or "the default options"
            raise CLIError(
                f"the algorithm options do not fit these images ({given}): {_one_line(exc)}"
            ) from exc
        t_estimate = time.perf_counter() - t1

        t2 = time.perf_counter()
        cols = result.columns
        cols["time_to_contact"] = time_to_contact(cols["r"], cols["dr_dt"])
        fit, odometry_block = None, None
        if args.odometry or args.auto_regions:
            fit, odometry_block = _odometry(cols, args.odometry_radial_weight)
            cols["odometry_inlier"] = (
                fit.inliers.astype(float) if fit is not None else np.full(len(cols["x"]), np.nan)
            )
        rows, outlines, regions_block = [], [], None
        if with_regions:
            # estimate() fills every monocular column (possibly empty) when it is configured
            mono = result.monocular if config.monocular_gap is not None else None
            rows, outlines, regions_block = _regions(args, cols, masks, fit, rig, frame_interval,
                                                     mono)  # fmt: skip
            atomic_write_text(stage / "regions.csv", regions_csv_text(rows))
        result.to_csv(stage / "flow.csv", _column_units())
        if config.monocular_gap is not None:
            result.monocular_to_csv(stage / "monocular.csv")
        if not args.no_pictures:
            _pictures(stage, f1[t], rig.cam1, cols, args.arrow_scale, outlines)
        t_write = time.perf_counter() - t2

        n = len(cols["x"])
        units = _column_units()
        summary: dict[str, Any] = {
            "command": [PROG, *argv],
            "inputs": info,
            "rig_source": rig_source,
            "rig": rig.to_dict(),
            "config": jsonable(config),
            "points": n,
            "columns": {c: units.get(c, "") for c in cols},
            "timings_s": {
                "read": t_read,
                "estimate": t_estimate,
                "write": t_write,
                "pipeline_stages": jsonable(result.timings),
            },
            "outputs": list(written),
            "median_flow_px": float(np.median(np.hypot(cols["dx"], cols["dy"]))) if n else None,
        }
        if config.monocular_gap is not None:
            summary["monocular_points"] = len(result.monocular.get("x", ()))
        if odometry_block is not None:
            summary["odometry"] = odometry_block
        if regions_block is not None:
            summary["regions"] = regions_block
        if args.landmark:
            summary["position_fix"] = _position_fix(args, rows)
        atomic_write_text(stage / "flow.json", json_text(summary))
    return summary


def _one_line(exc: BaseException) -> str:
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
        return 2, f"--out {_one_line(exc)}"
    known: tuple[type, ...] = (CLIError, ImageError, RigError)
    for module, name in (
        ("omniflow.geometry.calibration", "RimError"),
        ("omniflow.io.dataset", "DatasetError"),
    ):
        if module in sys.modules:
            known += (getattr(sys.modules[module], name),)
    if isinstance(exc, known):
        return 2, _one_line(exc)
    if isinstance(exc, UnicodeDecodeError):
        return 2, f"a file that should be text is not UTF-8 ({_one_line(exc)})"
    if isinstance(exc, OSError):
        path = exc.filename if exc.filename is not None else "?"
        under_out = out is not None and (
            str(path).startswith(str(out)) or str(out).startswith(str(path))
        )
        need = "; --out needs a folder this command can write" if under_out else ""
        if exc.errno in _BAD_PATH_ERRNOS:
            return 2, f"{path}: {_BAD_PATH_ERRNOS[exc.errno]}{need}"
        reason = exc.strerror or _one_line(exc)
        return 1, f"{path}: {reason}{need}"
    if isinstance(exc, MemoryError):
        return 1, "out of memory (try smaller images or fewer --n-theta lines)"
    text = f"{type(exc).__name__}: {_one_line(exc)}"
    return 1, f"internal error ({text}); rerun with --debug for the traceback and report it"


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """warnings.showwarning for the command: ``omniflow: warning: ...`` on one line."""
    print(f"{PROG}: warning: {_one_line(message)}", file=sys.stderr if file is None else file)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``omniflow`` command; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    with warnings.catch_warnings():
        warnings.simplefilter("default")  # shown, once per place, as one line each
        warnings.showwarning = _one_line_warning
        try:
            summary = run(args, parser._config_fields, argv)  # type: ignore[attr-defined]
        except KeyboardInterrupt:
            print(f"{PROG}: interrupted; nothing was written", file=sys.stderr)
            return 130
        except Exception as exc:  # every failure becomes one line (or, with --debug, a trace)
            if args.debug:
                traceback.print_exc()
            status, message = explain_error(exc, args.out)
            print(f"{PROG}: error: {message}", file=sys.stderr)
            return status
    stages = summary["timings_s"]["pipeline_stages"]
    stage_text = ", ".join(
        f"{k} {1e3 * v:.1f} ms" for k, v in stages.items() if isinstance(v, int | float)
    )
    est_ms = 1e3 * summary["timings_s"]["estimate"]
    print(
        f"{PROG}: {summary['points']} points; estimate {est_ms:.1f} ms"
        + (f" ({stage_text})" if stage_text else "")
    )
    print(f"{PROG}: wrote " + ", ".join(str(Path(args.out) / o) for o in summary["outputs"]))
    return 0


if __name__ == "__main__":  # python -m omniflow.cli.pair
    sys.exit(main())
