"""``omniflow calibrate``: register both units from an image of the test card.

Fits each unit's mirror tilt, mirror offset (x, y) and cone angle to the card's edges
(:mod:`omniflow.geometry.registration`), checks the fitted model's rim against the rim
found in the image about it (:func:`~omniflow.geometry.registration.check_rim`), and
writes a rig file whose ``[rig.errors.camN]`` tables ``omniflow pair`` / ``stream`` use
(:mod:`omniflow.registration`). Bad input is one line and exit status 2.
"""

from __future__ import annotations

import json
import math
import sys
import textwrap
import time
import traceback
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from omniflow.cli.common import CLIError, Formatter, Parser, explain_error, one_line, size_text
from omniflow.geometry.rig import Rig, load_rig

__all__ = ["build_parser", "main", "rig_toml"]

PROG = "omniflow calibrate"

EPILOG = """\
outputs (in --out):
  rig.toml          the rig with [rig.errors.cam1] and [rig.errors.cam2]: mirror_tilt,
                    mirror_offset (z 0) and cone_angle fitted (camera_tilt too with
                    --camera-tilt); camera_offset 0: a card cannot tell it from the
                    mirror's offset (docs/decisions/registration.md); intrinsics as given
  calibration.json  per unit: the errors, edge counts, residual rms (px), the rim found
                    and the fitted model's rim against it (rms, px)

the card: a test_card object (omnisim scene files, docs/scene_format.md), read from
  --card (a scene file or dataset.json; default: the dataset's own) and placed in the
  rig frame by its pose and the robot's at --frame.

examples:
  omniflow calibrate --dataset card_ds --out cal
  omniflow calibrate --rig rig.toml --card scenes/test_card.toml c1.png c2.png --out cal
  omniflow pair --dataset scene_ds --rig cal/rig.toml --out result

exit status: 0 success, 2 bad input, 1 refused (e.g. a full disk).
"""


def build_parser(prog: str = PROG) -> Parser:
    """The ``omniflow calibrate`` argument parser."""
    parser = Parser(
        prog=prog,
        allow_abbrev=False,
        formatter_class=Formatter,
        description=textwrap.dedent(
            """\
            Register both units of a rig (paper section 2.1) from one image of the test
            card per unit: CAM1 CAM2 with --rig, or frame --frame of an omnisim dataset.
            """
        ),
        epilog=EPILOG,
    )
    parser.add_argument("images", nargs="*", metavar="IMAGE", help="CAM1 CAM2 card images")
    parser.add_argument("--rig", metavar="FILE", help="nominal rig (d, R, s, intrinsics)")
    parser.add_argument("--dataset", metavar="DIR", help="omnisim dataset of the card")
    parser.add_argument("--frame", type=int, default=0, metavar="K", help="dataset frame (0)")
    parser.add_argument("--card", metavar="FILE", help="scene file or dataset.json of the card")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    parser.add_argument(
        "--fit-rim", action="store_true",
        help="fit the rim circle with the card's edges (default: the rim is only checked)",
    )  # fmt: skip
    parser.add_argument(
        "--camera-tilt", action="store_true",
        help="fit camera_tilt too (7 parameters; for a camera tilted more than 0.05 deg)",
    )  # fmt: skip
    parser.add_argument(
        "--rim-only", action="store_true",
        help="no card: fit mirror_offset x, y and cone_angle to the rim alone (tilts 0)",
    )  # fmt: skip
    parser.add_argument("--debug", action="store_true", help="on an error, show the traceback")
    return parser


# -- inputs ---------------------------------------------------------------------------


def _card_of(data: dict, where: str, robot_pose, object_pose):
    """The test card of a parsed scene or dataset.json ``data``, in the rig frame."""
    from omniflow.geometry.test_card import card_from_table, card_in_rig

    scene = data.get("scene", {}).get("data", data) if "scene" in data else data
    objects = scene.get("objects", []) if isinstance(scene, dict) else []
    cards = [(i, o) for i, o in enumerate(objects) if isinstance(o, dict)
             and o.get("type") == "test_card"]  # fmt: skip
    if len(cards) != 1:
        raise CLIError(f"{where}: {len(cards)} test_card objects; expected exactly one")
    i, tbl = cards[0]

    def fail(key, value, expected):
        return CLIError(f"{where}: objects[{i}].{key}: got {value!r}, expected {expected}")

    card = card_from_table(tbl, fail)
    try:
        return card_in_rig(card, np.linalg.inv(robot_pose(scene)), object_pose(i, tbl))
    except ValueError as exc:
        raise CLIError(f"{where}: objects[{i}]: {exc}; expected it along the rig's axis") from exc


def _pose(tbl: dict, key_pos: str, default_pos, where: str) -> np.ndarray:
    """A scene file's static pose (position, rotation in degrees, extrinsic x-y-z)."""
    from scipy.spatial.transform import Rotation

    pos, rot = tbl.get(key_pos, default_pos), tbl.get("rotation", [0, 0, 0])
    for name, v in (("position", pos), ("rotation", rot)):
        ok = isinstance(v, list) and len(v) == 3
        if not ok or not all(isinstance(x, int | float) and math.isfinite(x) for x in v):
            raise CLIError(f"{where}: {name} = {v!r}: expected 3 numbers")
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("xyz", rot, degrees=True).as_matrix()
    m[:3, 3] = pos
    return m


def _card_from_file(path: str, frame: int):
    from omniflow.input_files import InputFileError, parse_text, read_input

    p = Path(path)
    try:
        text = read_input(p, "scene file (TOML) or dataset.json")
        data = parse_text(text, p, "json" if p.suffix.lower() == ".json" else "toml")
    except InputFileError as exc:
        raise CLIError(one_line(exc)) from None
    if not isinstance(data, dict):
        raise CLIError(f"{path}: expected a scene file or dataset.json")
    if "scene" in data and "robot" in data and "poses" in data.get("robot", {}):
        robot_pose = lambda s: _dataset_pose(data["robot"], frame, path)  # noqa: E731
        object_pose = lambda i, t: _dataset_pose(_object_meta(data, i, path), frame, path)  # noqa: E731
        return _card_of(data, path, robot_pose, object_pose)
    robot = data.get("robot", {})
    robot_pose = lambda s: _pose(robot, "position", [0, 0, 0.5], f"{path}: robot")  # noqa: E731
    object_pose = lambda i, t: _pose(t, "position", [0, 0, 0], f"{path}: objects[{i}]")  # noqa: E731
    return _card_of(data, path, robot_pose, object_pose)


def _object_meta(meta: dict, i: int, where: str) -> dict:
    """dataset.json's entry of the scene's objects[i] (rooms make six entries)."""
    scene_objs = meta["scene"]["data"]["objects"]
    name = scene_objs[i].get("name", f"test_card{i}")
    for obj in meta.get("objects", []):
        if obj.get("name") == name:
            return obj
    raise CLIError(f"{where}: no poses for object {name!r}; expected them in 'objects'")


def _dataset_pose(entry: dict, frame: int, where: str) -> np.ndarray:
    poses = entry.get("poses", [])
    if not 0 <= frame < len(poses):
        raise CLIError(f"{where}: no pose at frame {frame}; expected 0..{len(poses) - 1}")
    return np.asarray(poses[frame], dtype=np.float64)


def _inputs(args) -> tuple[Rig, list[np.ndarray], Any, dict]:
    """(nominal rig without errors, [cam1 image, cam2 image], card, info)."""
    from omniflow.io.imageio import read_image, to_grey

    if args.dataset and args.images:
        raise CLIError("give IMAGE files with --rig, or --dataset DIR, not both")
    if args.dataset:
        from omniflow.io.dataset import DatasetError, open_dataset

        try:
            ds = open_dataset(args.dataset)
            if not 0 <= args.frame < ds.frame_count:
                raise CLIError(f"--frame {args.frame}: expected 0..{ds.frame_count - 1}")
            read = ds.read_image if ds.camera_bits is not None else ds.read_grey
            images = [read(args.frame, cam) for cam in ("cam1", "cam2")]
        except DatasetError as exc:
            raise CLIError(one_line(exc)) from exc
        rig = load_rig(args.rig) if args.rig else ds.rig
        card_file = args.card or str(Path(args.dataset) / "dataset.json")
        info = {"dataset": args.dataset, "frame": args.frame}
    else:
        if len(args.images) != 2 or not args.rig:
            raise CLIError("expected CAM1 CAM2 image files and --rig FILE (or --dataset DIR)")
        if not args.card and not args.rim_only:
            raise CLIError("--card FILE is needed with image files (where the card is)")
        rig = load_rig(args.rig)
        images = [to_grey(read_image(p)) for p in args.images]
        card_file = args.card
        info = {"images": list(args.images)}
    for cam, img in zip(("cam1", "cam2"), images, strict=True):
        unit = getattr(rig, cam)
        if img.shape[:2] != (unit.height, unit.width):
            raise CLIError(f"{cam} image is {size_text(img.shape)}; the rig's {cam} is "
                           f"{unit.width} x {unit.height}")  # fmt: skip
        if not np.isfinite(img).all():
            raise CLIError(f"{cam} image has NaN or infinite pixels")
    ideal = Rig(cam1=replace(rig.cam1, errors=None), cam2=replace(rig.cam2, errors=None), s=rig.s)
    if args.rim_only:
        return ideal, images, None, info
    card = _card_from_file(card_file, args.frame)
    info["card"] = card_file
    return ideal, images, card, info


# -- outputs --------------------------------------------------------------------------


def rig_toml(rig: Rig) -> str:
    """A rig file (TOML) of ``rig``, errors included (``omniflow.geometry.rig``)."""
    d = rig.to_dict()

    def val(v):
        if isinstance(v, list):
            return "[" + ", ".join(val(x) for x in v) + "]"
        if isinstance(v, str):
            return json.dumps(v)
        return repr(float(v)) if isinstance(v, float) else str(v)

    lines = ["# written by omniflow calibrate (docs/decisions/registration.md)", "[rig]"]
    lines += [f"{k} = {val(v)}" for k, v in d["rig"].items() if k != "errors"]
    for name, tbl in d["rig"].get("errors", {}).items():
        lines += ["", f"[rig.errors.{name}]"] + [f"{k} = {val(v)}" for k, v in tbl.items()]
    for cam in d["cameras"]:
        lines += ["", "[[cameras]]"] + [f"{k} = {val(v)}" for k, v in cam.items() if k != "v"]
    return "\n".join(lines) + "\n"


def run(args) -> dict:
    from omniflow.geometry.calibration import find_rim
    from omniflow.geometry.registration import check_rim, register_unit, rim_residual_rms
    from omniflow.io.imageio import atomic_write_text

    if args.frame < 0:
        raise CLIError(f"--frame {args.frame}: expected an integer >= 0")
    if args.rim_only and (args.fit_rim or args.card or args.camera_tilt):
        raise CLIError("--rim-only fits the rim alone: no --fit-rim, --camera-tilt or --card")
    rig, images, card, info = _inputs(args)
    units, report = {}, {"inputs": info, "units": {}}
    for cam, img in zip(("cam1", "cam2"), images, strict=True):
        unit = getattr(rig, cam)
        t0 = time.perf_counter()
        try:
            if args.rim_only:  # no model yet: the rim searched over the image, near r_m
                c = find_rim(img, r_min=0.92 * unit.r_m, r_max=1.08 * unit.r_m)
                rim = (c.x_c, c.y_c, c.r_m)
                reg = register_unit(img, unit, None, rim=rim)
            else:  # the card first; the rim searched about the fitted model's rim
                reg = register_unit(img, unit, card, camera_tilt=args.camera_tilt)
                rim, _ = check_rim(img, unit, reg.errors)
                if args.fit_rim:
                    reg = register_unit(img, unit, card, rim=rim, camera_tilt=args.camera_tilt)
        except ValueError as exc:  # RimError included
            raise CLIError(f"{cam}: {one_line(exc)}") from exc
        units[cam] = replace(unit, errors=reg.errors)
        report["units"][cam] = {
            "errors": reg.errors.as_dict(),
            "ring_edges": reg.n_rings,
            "sector_edges": reg.n_lines,
            "residual_rms_px": reg.rms_px,
            "rim_found": None
            if rim is None
            else dict(zip(("x_c", "y_c", "r_m"), rim, strict=True)),
            "rim_fitted": bool(args.fit_rim or args.rim_only),
            "rim_residual_rms_px": rim_residual_rms(unit, reg.errors, rim),
            "seconds": time.perf_counter() - t0,
        }
    out = Rig(cam1=units["cam1"], cam2=units["cam2"], s=rig.s)
    folder = Path(args.out)
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_text(folder / "rig.toml", rig_toml(out))
    atomic_write_text(folder / "calibration.json", json.dumps(report, indent=2) + "\n")
    return report


def main(argv: list[str] | None = None, *, prog: str = PROG) -> int:
    """Entry point of ``omniflow calibrate``; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(prog)
    args = parser.parse_args(argv)
    try:
        report = run(args)
    except Exception as exc:  # every failure becomes one line (or, with --debug, a trace)
        if args.debug:
            traceback.print_exc()
        status, message = explain_error(exc, args.out)
        print(f"{prog}: error: {message}", file=sys.stderr)
        return status
    for cam, u in report["units"].items():
        e = u["errors"]
        tilt = [round(x, 4) for x in e["mirror_tilt"]]
        offset = [round(x * 1e3, 4) for x in e["mirror_offset"][:2]]
        n = u["ring_edges"] + u["sector_edges"]
        fit = (f"residual {u['residual_rms_px']:.3f} px over {n} edges" if n else
               f"rim residual {u['rim_residual_rms_px']:.3f} px")  # fmt: skip
        print(f"{prog}: {cam}: mirror_tilt {tilt} deg, mirror_offset {offset} mm, "
              f"cone_angle {e['cone_angle']:.4f} deg; {fit}")  # fmt: skip
    print(f"{prog}: wrote {Path(args.out) / 'rig.toml'}")
    return 0
