"""``omniflow-stream``: the flow of every consecutive pair of a sequence, each frame fitted once.

Reads an omnisim dataset or a folder of images one stereo frame at a time,
runs :class:`omniflow.stream.OmniFlowStream` and writes one CSV per pair into
``--out`` (``flow_K0_K1.csv``, the flow from frame K0 to K1, the columns of
``omniflow``'s flow.csv) and ``stream.json`` (input, rig, config, how many
pairs are present, this run's pairs, points and time). Nothing the command
keeps grows with the length of the sequence. Every file is written under a temporary name and
renamed, so an interrupted run leaves only whole files; run the same command
again and it resumes after the last pair written (``stream.json`` must hold
the same input, rig and options, else exit 2). Exit status as ``omniflow``:
0 success, 2 bad input, 1 the machine refused or an internal error, 130 / 143
interrupted by Ctrl-C / SIGTERM (one line, :mod:`omniflow.interrupts`).
"""

from __future__ import annotations

import argparse
import collections
import re
import sys
import textwrap
import time
import traceback
import warnings
from pathlib import Path
from typing import Any

import numpy as np

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
    make_config,
    one_line,
    shorten_help,
)
from omniflow.config import PUBLIC_FIELDS
from omniflow.geometry.rig import Rig, load_rig
from omniflow.io import ownership
from omniflow.io.imageio import atomic_write_text, read_image, to_grey
from omniflow.io.jsonio import json_text, jsonable

PROG = "omniflow-stream"
MANIFEST = "stream.json"
IMAGE_SUFFIXES = (".png", ".exr", ".tif", ".tiff", ".jpg", ".jpeg")


#: The epilog of ``omniflow stream --help-expert``: outputs, resuming, examples.
EPILOG = textwrap.dedent(
    """\
    outputs (in --out DIR, each written under a temporary name, then renamed):
      flow_K0_K1.csv  the flow from frame K0 to K1 (six digits each), the columns of
                      omniflow's flow.csv (see omniflow --help), time_to_contact last
      monocular_K0_K1.csv  with --monocular-gap PX: cam1's flow alone away from the
                      matches (see omniflow --help)
      stream.json     input, rig, config; pairs present; this run's pairs, points, time
    Run the same command again to resume after the last pair written.

    examples:
      omniflow-stream renders/room --out room_flow
      omniflow-stream frames/ --rig rig.toml --out flow --start 100 --stop 200
      python -m omniflow.cli.stream renders/room --out room_flow  (the same)
    """
)
#: The epilog of ``omniflow stream --help``.
SHORT_EPILOG = (
    "outputs: flow_K0_K1.csv per pair and stream.json in --out; run again to resume.\n"
    "--help-expert: every option and the outputs in full. Exit status: 0, 2 bad input, 1."
)


def build_parser(prog: str = PROG, *, short: bool = False) -> argparse.ArgumentParser:
    """The ``omniflow stream`` argument parser (every OmniFlowConfig knob included);
    ``short``: ``--help`` shows the stream's own options and the public knobs only."""
    parser = Parser(
        prog=prog,
        allow_abbrev=False,
        formatter_class=Formatter,
        description=textwrap.dedent(
            """\
            Omni flow of every consecutive pair of a sequence, streamed: each stereo frame
            is read, fitted and matched once and reused as the first frame of the next
            pair (omniflow.stream.OmniFlowStream). INPUT is an omnisim dataset folder
            (with dataset.json) or a folder of images whose names contain "cam1" and
            "cam2" (one of each per time step; time order is the natural order of the
            names, e.g. cam1_0.png, cam1_1.png, ..., cam1_10.png), with --rig.
            """
        ),
        epilog=SHORT_EPILOG if short else EPILOG,
    )
    parser.add_argument("input", metavar="INPUT", help="omnisim dataset folder or image folder")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    parser.add_argument("--rig", metavar="FILE", help="rig file (required for an image folder)")
    parser.add_argument(
        "--radiance",
        action="store_true",
        help="a dataset: read the EXR radiance instead of the camera images",
    )
    parser.add_argument("--start", type=int, default=0, metavar="K", help="first frame (0)")
    parser.add_argument(
        "--stop", type=int, metavar="K", help="stop before this frame (default: the last + 1)"
    )
    parser.add_argument(
        "--background", action="store_true",
        help="match each frame in a second thread while the next is read (same results)",
    )  # fmt: skip
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--debug", action="store_true", help="on an error, show the traceback")
    parser.add_argument(
        "--paper", action="store_true", help="start from OmniFlowConfig.paper() (see omniflow)"
    )
    parser.add_argument(
        "--dense", action="store_true", help="start from OmniFlowConfig.dense() (see omniflow)"
    )
    parser._config_fields = add_config_options(parser)  # type: ignore[attr-defined]
    add_expert_options(parser, lambda: build_parser(prog))
    if short:
        own = {a.dest for a in parser._actions if not a.dest.startswith("cfg_")}
        shorten_help(parser, own | {f"cfg_{name}" for name in PUBLIC_FIELDS})
    return parser


# -- inputs ---------------------------------------------------------------------------------


class _Source:
    """Frames of a sequence, read one stereo frame at a time."""

    def __init__(self, rig: Rig, count: int, read, describe: dict, name_of):
        self.rig, self.count, self._read, self.describe = rig, count, read, describe
        self.name_of = name_of

    def read(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        pair = self._read(k)
        check_rig_size(self.rig, pair[0].shape, "the rig")
        for cam, img in zip(("cam1", "cam2"), pair, strict=True):
            if img.shape != pair[0].shape:
                raise CLIError(f"{self.name_of(k, cam)}: {img.shape} pixels, cam1 {pair[0].shape}")
            bad = ~np.isfinite(img)
            if bad.any():
                raise CLIError(f"{self.name_of(k, cam)}: {int(bad.sum())} pixel(s) are NaN or inf")
        return pair


def _natural_key(name: str) -> list:
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", name)]


def open_source(path: str, rig_file: str | None, radiance: bool = False) -> _Source:
    """The sequence at ``path``: an omnisim dataset (its camera images camN.png, or with
    ``radiance`` or no camera images the EXR radiance), or a folder of cam1 / cam2 images."""
    folder = Path(path)
    if not folder.is_dir():
        raise CLIError(f"{path}: not a folder; expected an omnisim dataset or an image folder")
    if (folder / "dataset.json").exists():
        from omniflow.io.dataset import DatasetError, open_dataset

        try:
            ds = open_dataset(folder)
            count = ds.frame_count
        except DatasetError as exc:
            raise CLIError(str(exc)) from exc
        rig = load_rig(rig_file) if rig_file else ds.rig
        try:
            camera = not radiance and ds.camera_bits is not None
        except DatasetError as exc:
            raise CLIError(str(exc)) from exc
        grey = ds.read_image if camera else ds.read_grey

        def read(k):
            try:
                return grey(k, "cam1"), grey(k, "cam2")
            except DatasetError as exc:
                raise CLIError(str(exc)) from exc

        images = "camera images camN.png" if camera else "EXR radiance (luminance)"
        describe = {"dataset": str(folder), "frames": count, "images": images}
        return _Source(rig, count, read, describe, lambda k, cam: str(ds.path(k, cam)))
    files = sorted(
        (p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()),
        key=lambda p: _natural_key(p.name),
    )
    cams = {c: [p for p in files if c in p.name] for c in ("cam1", "cam2")}
    both = [p.name for p in files if "cam1" in p.name and "cam2" in p.name]
    if both:
        raise CLIError(f"{folder / both[0]}: the name contains both cam1 and cam2; expected one")
    if not cams["cam1"] or len(cams["cam1"]) != len(cams["cam2"]):
        raise CLIError(
            f"{path}: {len(cams['cam1'])} cam1 and {len(cams['cam2'])} cam2 image(s); "
            "expected an omnisim dataset (dataset.json) or equally many cam1 and cam2 images"
        )
    if rig_file is None:
        raise CLIError(f"{path}: an image folder needs --rig FILE")
    rig = load_rig(rig_file)

    def read_images(k):
        return tuple(to_grey(read_image(cams[c][k])) for c in ("cam1", "cam2"))

    describe = {"images": str(folder), "frames": len(cams["cam1"]),
                "cam1_first": cams["cam1"][0].name, "cam2_first": cams["cam2"][0].name}  # fmt: skip
    return _Source(rig, len(cams["cam1"]), read_images, describe,
                   lambda k, cam: str(cams[cam][k]))  # fmt: skip


def pair_name(k0: int, k1: int) -> str:
    """The CSV of the flow from frame k0 to k1."""
    return f"flow_{k0:06d}_{k1:06d}.csv"


# -- the run --------------------------------------------------------------------------------


#: The names the command writes in --out (with the marker).
_OWNED_RE = re.compile(rf"(flow|monocular)_\d{{6}}_\d{{6}}\.csv|{re.escape(MANIFEST)}")


def _owned(name: str) -> bool:
    return _OWNED_RE.fullmatch(name) is not None


def _legacy_out(folder: Path) -> bool:
    """An --out written before markers existed: a stream.json of an omniflow command."""
    body = ownership.read_json(folder / MANIFEST)
    command = body.get("command") if isinstance(body, dict) else None
    return isinstance(command, list) and bool(command) and str(command[0]).startswith("omniflow")


def _check_resume(out: Path, header: dict) -> None:
    """Refuse an --out written by the same command with another input, rig or options."""
    manifest = out / MANIFEST
    if not manifest.exists():
        return
    import json

    try:
        old = json.loads(manifest.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise CLIError(f"{manifest}: not a stream manifest ({one_line(exc)})") from exc
    for key in ("input", "rig", "config"):
        if old.get(key) != header[key]:
            raise CLIError(
                f"{manifest}: written with another {key}; use another --out (or delete the "
                "folder) to stream with these options"
            )


def run(args: argparse.Namespace, config_fields: list[str], argv: list[str]) -> dict:
    from omniflow.applications.navigation import time_to_contact
    from omniflow.stream import OmniFlowStream

    config = make_config(args, config_fields)
    if args.radiance and not (Path(args.input) / "dataset.json").exists():
        raise CLIError("--radiance applies to an omnisim dataset; image folders are read as "
                       "they are")  # fmt: skip
    source = open_source(args.input, args.rig, args.radiance)
    stop = source.count if args.stop is None else args.stop
    need = config.fit.temporal_frames if config.fit.temporal == "dct3d" else 2
    if not (0 <= args.start and args.start + need <= stop <= source.count):
        raise CLIError(
            f"--start {args.start} --stop {stop}: expected 0 <= start, start + {need} <= stop "
            f"<= {source.count} (the frames of {args.input})"
        )
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CLIError(f"--out {out}: exists and is not a folder; expected a folder")
    header: dict[str, Any] = {
        "command": [PROG, *argv],
        "input": jsonable(source.describe),
        "rig": source.rig.to_dict(),
        "config": jsonable(config.to_dict()),
        "columns": column_units(),
    }
    ownership.claim_names(out, prog=PROG, owned=_owned, legacy=_legacy_out)
    _check_resume(out, header)
    out.mkdir(parents=True, exist_ok=True)
    if not ownership.has_marker(out):
        ownership.write_marker(out, PROG)
    # this run's figures: bounded, so nothing grows with the length of the sequence
    recent_ms: collections.deque = collections.deque(maxlen=1000)
    # the first pair's time apart: it loads the compiled kernels (about 10x a warm pair)
    run_stats = {"pairs": 0, "points": 0, "seconds": 0.0, "first_pair_ms": None}

    def write_manifest(complete: bool, present: int) -> None:
        this_run = {**run_stats, "median_ms_per_frame_last_1000": (
            float(np.median(recent_ms)) if recent_ms else None)}  # fmt: skip
        summary = {**header, "complete": complete, "pairs_in_out": present,
                   "this_run": this_run}  # fmt: skip
        atomic_write_text(out / MANIFEST, json_text(summary))

    # dct3d streams the causal window of its last temporal_frames frames: the first
    # pair it can give ends at start + temporal_frames - 1
    window = config.fit.temporal_frames if config.fit.temporal == "dct3d" else 2
    wanted = range(args.start + window - 1, stop)
    # the CSVs are renamed into place whole, so one that exists is complete
    todo = [k for k in wanted if not (out / pair_name(k - 1, k)).is_file()]
    present = len(wanted) - len(todo)
    try:
        stream = OmniFlowStream(source.rig, config, background=args.background)
    except ValueError as exc:  # an option the stream does not support (flow_shading)
        raise CLIError(str(exc)) from exc
    from tqdm import tqdm

    bar = tqdm(total=len(todo), desc=PROG, unit="pair", disable=args.quiet, file=sys.stderr)
    last_written = time.perf_counter()
    try:
        pushed = None
        for k in todo:
            # the frames the stream needs before k (after a skipped pair, or at the start)
            first = max(args.start, k - window + 1)
            if pushed is None or pushed != k - 1:
                stream.reset()
                for j in range(first, k):
                    stream.push(*source.read(j))
            f1, f2 = source.read(k)
            t0 = time.perf_counter()
            try:
                result = stream.push(f1, f2)
            except ValueError as exc:  # a knob combination these images do not allow
                raise CLIError(
                    f"the algorithm options do not fit frame {k}: {one_line(exc)}"
                ) from exc
            ms = 1e3 * (time.perf_counter() - t0)
            pushed = k
            cols = result.columns
            cols["time_to_contact"] = time_to_contact(cols["r"], cols["dr_dt"])
            name = pair_name(k - 1, k)
            if result.config.monocular_gap is not None:  # before the flow CSV that marks done
                result.monocular_to_csv(out / f"monocular{name.removeprefix('flow')}")
            result.to_csv(out / name)
            present += 1
            run_stats["pairs"] += 1
            run_stats["points"] += len(result)
            run_stats["seconds"] += ms / 1e3
            if run_stats["first_pair_ms"] is None:
                run_stats["first_pair_ms"] = ms
            else:
                recent_ms.append(ms)
            bar.update(1)
            bar.set_postfix(points=len(result), ms=f"{ms:.0f}")
            if time.perf_counter() - last_written > 5.0:  # progress on disk, cheaply
                write_manifest(False, present)
                last_written = time.perf_counter()
    finally:
        bar.close()
        stream.close()
        write_manifest(present == len(wanted), present)
    median = float(np.median(recent_ms)) if recent_ms else None
    return {"written": run_stats["pairs"], "present": present, "out": str(out), "median_ms": median,
            "first_ms": run_stats["first_pair_ms"]}  # fmt: skip


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """warnings.showwarning for the command: ``omniflow-stream: warning: ...`` on one line."""
    print(f"{PROG}: warning: {one_line(message)}", file=sys.stderr if file is None else file)


def main(argv: list[str] | None = None, *, prog: str = PROG, short: bool = False) -> int:
    """Entry point of ``omniflow stream`` (``short``: its short help) and
    ``omniflow-stream``; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(prog, short=short)
    args = parser.parse_args(expand_settings(argv, parser))
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        warnings.showwarning = _one_line_warning
        try:
            busy = (f"{args.out}: another {PROG} process (pid {{pid}}) is writing this folder; "
                    "wait for it to finish or choose another --out")  # fmt: skip
            with ownership.held_lock(args.out, busy):  # one run per --out
                summary = run(args, parser._config_fields, argv)  # type: ignore[attr-defined]
        except Exception as exc:  # every failure becomes one line (or, with --debug, a trace)
            if args.debug:
                traceback.print_exc()
            status, message = explain_error(exc, args.out)
            print(f"{PROG}: error: {message}", file=sys.stderr)
            return status
    med, first = summary["median_ms"], summary["first_ms"]
    med_text = f"; median {med:.1f} ms per pair after the first" if med is not None else ""
    if first is not None:  # the first call loads the compiled kernels
        med_text += f" (the first {first:.0f} ms, with loading the compiled kernels)"
    print(f"{PROG}: {summary['written']} pair(s) written, {summary['present']} in "
          f"{summary['out']}{med_text}")  # fmt: skip
    return 0


if __name__ == "__main__":  # python -m omniflow.cli.stream
    from omniflow.cli import STREAM_NOTE
    from omniflow.interrupts import run_main

    sys.exit(run_main(PROG, main, note=STREAM_NOTE, keep=True))
