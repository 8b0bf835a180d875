"""The ``omniflow`` command: coaxial omni flow of a stereo frame pair, to CSV and pictures.

See ``docs/omniflow_cli.md`` and ``omniflow --help``. Exit status: 0 on
success (also when no point matched: the outputs are then empty and one
warning line says so), 2 on bad input (a missing or unreadable file, images of
different sizes, a rig file with a missing or impossible field, NaN pixels, an
option out of range, an ``--out`` that is a file), 1 when the machine refuses
(permission denied, read-only or full file system, out of memory) or on an
internal error; 130 / 143 interrupted by Ctrl-C / SIGTERM (one line,
:mod:`omniflow.interrupts`). Every failure is one line on standard error naming the path,
option or value and what was expected; ``--debug`` shows the traceback
instead. The outputs are staged and moved into ``--out`` as a set
(:class:`omniflow.io.imageio.OutputSet`), so a failed run changes nothing there.
"""

from __future__ import annotations

import argparse
import math
import sys
import textwrap
import time
import traceback
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from omniflow.applications.regions import regions_csv_text
from omniflow.cli.common import (
    CLIError,
    Formatter,
    Parser,
    add_config_options,
    add_expert_options,
    check_rig_size,
    column_units,
    expand_settings,
    explain_error,
    flag,
    make_config,
    one_line,
    shorten_help,
    size_text,
)
from omniflow.cli.regions import (
    check_region_options,
    fit_odometry,
    position_fix_block,
    region_masks,
    region_rows,
)
from omniflow.config import PUBLIC_FIELDS
from omniflow.geometry.rig import Rig, Unit, load_rig, unwarp
from omniflow.io import ownership
from omniflow.io.imageio import (
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


#: The description of ``omniflow --help``.
DESCRIPTION = textwrap.dedent(
    """\
    Omni flow (Spacek) of a coaxial conical-mirror stereo rig: match the two
    cameras along radial lines, solve the direct 2x2 flow equations at every
    match, and write per-point results (CSV + JSON sidecar) and pictures.

    Frames are given as image files in time order, cam1 then cam2 for each
    time step: CAM1_T0 CAM2_T0 CAM1_T1 CAM2_T1 [CAM1_T2 CAM2_T2 ...]
    (PNG 8/16-bit, JPEG, TIFF or OpenEXR; colour is reduced to Rec. 709
    luminance). The flow is from time step --t (default 0) to the next;
    more time steps are used by --set fit.temporal=dct3d. Or read the frames from an
    omnisim dataset: --dataset DIR --frame K (flow from frame K to K + 1).
    """
)

#: The epilog of ``omniflow --help``: outputs, rig file, examples, exit status.
EPILOG = textwrap.dedent(
    """\
    outputs (in --out DIR, each written atomically):
      flow.csv         one row per matched point, after a '#' line of units; columns
                       x, y (cam1 px), theta (rad),
                       h1, h2 (px), r, h (m), dh1_dt (px/frame), dtheta_dt (rad/frame),
                       dr_dt (m/frame), dx, dy (cam1 px/frame), cam2 columns x2, y2,
                       dh2_dt, dx2, dy2, confidence, D, coupled (1: eq. 14 holds,
                       0: each camera's radial flow solved on its own),
                       time_to_contact (frames), and the predicted standard deviations
                       sigma_flow1, sigma_flow2 (RMS endpoint error of each camera's
                       flow, px/frame) and sigma_r (m); sigma_flow2 and sigma_r
                       are inf where coupled is 0 (not a confident answer)
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
)


#: The options ``omniflow pair --help`` shows (their dests); --help-expert shows all.
SHORT_HELP = {
    "images", "rig", "dataset", "frame", "radiance", "out", "odometry", "paper", "dense",
    "set_items", "help_expert",
    *(f"cfg_{name}" for name in PUBLIC_FIELDS),
}  # fmt: skip

#: The usage line of ``omniflow pair --help``.
SHORT_USAGE = "%(prog)s (CAM1_T0 CAM2_T0 CAM1_T1 CAM2_T1 --rig FILE | --dataset DIR) --out DIR ..."
#: The description of ``omniflow pair --help``.
SHORT_DESCRIPTION = (
    "The omni flow of one pair of time steps, cam1 then cam2 per step (PNG, JPEG, TIFF or\n"
    "OpenEXR), or of an omnisim dataset's frame K to K + 1: flow.csv, flow.json, pictures."
)

#: The epilog of ``omniflow pair --help``.
SHORT_EPILOG = textwrap.dedent(
    """\
    example: omniflow pair --dataset renders/room --frame 3 --out result --set pooling.pool_k=64
    --help-expert: every option (regions, steering, position fix, calibration, every
    knob), the outputs and the rig file. Exit status: 0 success, 2 bad input, 1 refused.
    """
)


def build_parser(prog: str = PROG, *, short: bool = False) -> argparse.ArgumentParser:
    """The ``omniflow`` argument parser (options for every OmniFlowConfig knob included);
    ``short``: ``--help`` shows only :data:`SHORT_HELP` (``omniflow pair``)."""
    parser = Parser(
        prog=prog,
        usage=SHORT_USAGE if short else None,
        allow_abbrev=False,
        formatter_class=Formatter,
        description=SHORT_DESCRIPTION if short else DESCRIPTION,
        epilog=SHORT_EPILOG if short else EPILOG,
    )
    _add_input_options(parser)
    _add_output_options(parser)
    _add_region_options(parser)
    _add_preset_options(parser)
    parser._config_fields = add_config_options(parser)  # type: ignore[attr-defined]
    add_expert_options(parser, lambda: build_parser(prog))
    if short:
        shorten_help(parser, SHORT_HELP)
    return parser


def _add_input_options(parser: argparse.ArgumentParser) -> None:
    """The input and calibration options of ``omniflow``."""
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
        "--radiance",
        action="store_true",
        help="--dataset only: read the clean EXR radiance instead of the camera images "
        "camN.png (the default, which the harness scores)",
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


def _add_output_options(parser: argparse.ArgumentParser) -> None:
    """The output and odometry options of ``omniflow``."""
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


def _add_region_options(parser: argparse.ArgumentParser) -> None:
    """The regions, steering and position-fix options of ``omniflow``."""
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


def _add_preset_options(parser: argparse.ArgumentParser) -> None:
    """The presets the config options start from."""
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
                f"images differ in size: {paths[0]} is {size_text(images[0].shape)} "
                f"but {p} is {size_text(img.shape)}"
            )
    return images[0::2], images[1::2]


def _read_dataset(directory: str, k: int, window: int, radiance: bool = False):
    """Frames around K of an omnisim dataset: (frames1, frames2, t, rig, info).

    ``window`` time steps are read, placed so that K .. K + 1 sits in the middle
    where the dataset allows; ``t`` is K's index in the returned lists. The frames are
    the camera images (``Dataset.read_image``, what the harness scores), or with
    ``radiance`` (or a dataset without camera images) the EXR radiance's luminance.
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
        bits = ds.camera_bits
        camera = not radiance and bits is not None
        read = ds.read_image if camera else ds.read_grey
        f1 = [read(j, "cam1") for j in frames]
        f2 = [read(j, "cam2") for j in frames]
    except DatasetError as exc:
        raise CLIError(str(exc)) from exc
    except UnicodeDecodeError as exc:  # omnisim reads dataset.json as UTF-8 text
        raise CLIError(f"{meta}: not UTF-8 text ({one_line(exc)}); expected JSON") from exc
    for j, a, b in zip(frames, f1, f2, strict=True):
        for cam, img in (("cam1", a), ("cam2", b)):
            bad = ~np.isfinite(img)
            if bad.any():
                raise CLIError(f"{ds.path(j, cam)}: {int(bad.sum())} pixel(s) are NaN or infinite")
    images = (f"camera images camN.png ({bits} bits)" if camera else
              "EXR radiance (luminance)" + ("" if radiance else ": the dataset has no camera "
                                            "images"))  # fmt: skip
    info = {"dataset": str(directory), "frames_read": list(frames), "frame": k,
            "frame_interval_s": ds.frame_interval, "images": images}  # fmt: skip
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
        raise CLIError(f"--calibrate: {one_line(exc)}") from exc
    rig = Rig(cam1=u1, cam2=u2, s=s)
    rig.validate("--calibrate")
    return rig


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
    check_region_options(args)


def _load_inputs(args, config):
    """(frames1, frames2, t, rig, rig_source, info) from the command line."""
    dct3d = config.fit.temporal == "dct3d"
    window = max(2, config.fit.temporal_frames) if dct3d else 2
    if args.dataset:
        if args.images:
            raise CLIError("give either IMAGE files or --dataset, not both")
        if args.t is not None:
            raise CLIError("--t applies to IMAGE files; with --dataset use --frame K")
        f1, f2, t, rig, info = _read_dataset(args.dataset, args.frame, window, args.radiance)
        rig_source = str(Path(args.dataset) / "dataset.json")
        if args.rig:
            rig, rig_source = load_rig(args.rig), args.rig
    else:
        if not args.images:
            raise CLIError("no input: give IMAGE files (CAM1_T0 CAM2_T0 CAM1_T1 ...) or --dataset")
        if args.frame != 0:
            raise CLIError("--frame applies to --dataset; with IMAGE files use --t")
        if args.radiance:
            raise CLIError("--radiance applies to --dataset; IMAGE files are read as they are")
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
                f"--fit.temporal dct3d needs {window} time steps (--fit.temporal-frames); "
                f"got {len(f1)}"
            )
        info = {"images": [str(Path(p)) for p in args.images], "t": t}
    if args.calibrate:
        rig = _calibrated_rig(args, rig, f1[t], f2[t])
        rig_source = f"--calibrate (rims found; d, R, s from {args.rig or 'options'})"
    elif any(v is not None for v in (args.d, args.R, args.s)):
        raise CLIError("--d, --R and --s apply with --calibrate only; edit the rig file instead")
    check_rig_size(rig, f1[0].shape, rig_source)
    return f1, f2, t, rig, rig_source, info


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


# -- main ---------------------------------------------------------------------------------


def run(args: argparse.Namespace, config_fields: list[str], argv: list[str]) -> dict:
    """Do the work of one ``omniflow`` invocation; return the summary written to flow.json.

    Inputs and options are checked before anything is computed; the outputs are
    staged and moved into ``--out`` together (:class:`omniflow.io.imageio.OutputSet`).
    """
    from omniflow.applications.navigation import time_to_contact
    from omniflow.pipeline import estimate

    config = make_config(args, config_fields)
    _check_options(args)
    t0 = time.perf_counter()
    f1, f2, t, rig, rig_source, info = _load_inputs(args, config)
    masks = region_masks(args, rig, f1[0].shape)
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
    ownership.claim_names(out, prog=PROG, owned=OUTPUTS.__contains__, legacy=_legacy_out)
    with OutputSet(out, owned=(*OUTPUTS, ownership.MARKER), manifest="flow.json") as stage:
        ownership.write_marker(stage, PROG)
        t1 = time.perf_counter()
        try:
            result = estimate(f1, f2, rig, config, t=t)
        except ValueError as exc:  # inputs and single knobs are checked: a combination is not
            given = ", ".join(
                f"{flag(name)} {getattr(args, f'cfg_{name}')}"
                for name in config_fields
                if hasattr(args, f"cfg_{name}")
            )
            given = given or "the default options"
            raise CLIError(
                f"the algorithm options do not fit these images ({given}): {one_line(exc)}"
            ) from exc
        t_estimate = time.perf_counter() - t1

        t2 = time.perf_counter()
        cols = result.columns
        cols["time_to_contact"] = time_to_contact(cols["r"], cols["dr_dt"])
        fit, odometry_block = None, None
        if args.odometry or args.auto_regions:
            fit, odometry_block = fit_odometry(cols, args.odometry_radial_weight)
            cols["odometry_inlier"] = (
                fit.inliers.astype(float) if fit is not None else np.full(len(cols["x"]), np.nan)
            )
        rows, outlines, regions_block = [], [], None
        if with_regions:
            # estimate() fills every monocular column (possibly empty) when it is configured
            mono = result.monocular if config.monocular_gap is not None else None
            rows, outlines, regions_block = region_rows(args, cols, masks, fit, rig, frame_interval,
                                                     mono)  # fmt: skip
            atomic_write_text(stage / "regions.csv", regions_csv_text(rows))
        result.to_csv(stage / "flow.csv", column_units())
        if config.monocular_gap is not None:
            result.monocular_to_csv(stage / "monocular.csv")
        if not args.no_pictures:
            _pictures(stage, f1[t], rig.cam1, cols, args.arrow_scale, outlines)
        t_write = time.perf_counter() - t2

        n = len(cols["x"])
        units = column_units()
        summary: dict[str, Any] = {
            "command": [PROG, *argv],
            "inputs": info,
            "rig_source": rig_source,
            "rig": rig.to_dict(),
            "config": jsonable(config.to_dict()),
            "points": n,
            # flow.csv's columns in its order, the sigmas last (OmniFlowResult.to_csv)
            "columns": {c: units.get(c, "") for c in (*cols, *result.sigma)},
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
            summary["position_fix"] = position_fix_block(args, rows)
        atomic_write_text(stage / "flow.json", json_text(summary))
    return summary


def _legacy_out(folder: Path) -> bool:
    """An --out written before markers existed: a flow.json of an omniflow command."""
    body = ownership.read_json(folder / "flow.json")
    command = body.get("command") if isinstance(body, dict) else None
    return isinstance(command, list) and bool(command) and str(command[0]).startswith("omniflow")


def _busy(out: str) -> str:
    """The one line when another process writes ``out`` (pid filled in by the lock)."""
    return (
        f"{out}: another omniflow process (pid {{pid}}) is writing this folder; wait for it "
        "to finish or choose another --out"
    )


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """warnings.showwarning for the command: ``omniflow: warning: ...`` on one line."""
    print(f"{PROG}: warning: {one_line(message)}", file=sys.stderr if file is None else file)


def main(argv: list[str] | None = None, *, prog: str = PROG, short: bool = False) -> int:
    """Entry point of ``omniflow pair`` (``short``: its short help) and of the older
    ``omniflow IMAGE...`` / ``omniflow --dataset DIR``; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(prog, short=short)
    args = parser.parse_args(expand_settings(argv, parser))
    with warnings.catch_warnings():
        warnings.simplefilter("default")  # shown, once per place, as one line each
        warnings.showwarning = _one_line_warning
        try:
            with ownership.held_lock(args.out, _busy(args.out)):  # one run per --out
                summary = run(args, parser._config_fields, argv)  # type: ignore[attr-defined]
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
    from omniflow.cli import PAIR_NOTE
    from omniflow.interrupts import run_main

    sys.exit(run_main(PROG, main, note=PAIR_NOTE, keep=True))
