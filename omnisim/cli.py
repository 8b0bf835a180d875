"""The ``omnisim`` command: ``omnisim render SCENE --out DIR``, ``omnisim check DIR``,
``omnisim export DIR --format sintel|kitti|png --out OUT`` and
``omnisim generate --family F --seed N --out scene.toml`` (:mod:`omnisim.generate.command`).

Exit status: 0 success; 1 a self-check failed (``check``, or ``render --check``),
or the environment failed (a renderer package not installed, a Dask scheduler that
does not answer, a disk error); 2 bad input: a bad scene file, option, input image or
dataset, an output directory that holds another dataset or is being written by
another render, a request this machine cannot hold, an incomplete dataset to check
(reported as one line before any rendering starts); 130 interrupted by Ctrl-C, 143
by SIGTERM (one line; the frames finished so far are kept; run the same command again
to resume).

Every error is one line on stderr, ``omnisim: error: ...``, naming the file, key,
value or address and what was expected; ``--debug`` adds the Python traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import re
import sys
import tomllib
import traceback
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from omniflow.interrupts import run_main

__all__ = ["main"]

PROG = "omnisim"


class _UsageError(Exception):
    pass


class _IncompleteError(Exception):
    """A dataset to check has frames missing (and --partial was not given)."""


#: Modules of the ``sim`` extra (``pip install "omniflow-testbed[sim]"``).
SIM_MODULES = ("mitsuba", "drjit", "trimesh", "dask", "distributed", "psutil")
#: errno values that mean "the path you gave is wrong" (exit 2) rather than the machine.
_BAD_PATH_ERRNOS = {
    errno.ENOENT,
    errno.ENOTDIR,
    errno.EISDIR,
    errno.EEXIST,
    errno.EACCES,
    errno.EPERM,
    errno.EROFS,
    errno.ENAMETOOLONG,
    errno.ELOOP,
}


def _one_line(msg: object) -> str:
    return " ".join(str(msg).split())


def _parse_resolution(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(\d+)\s*(?:[xX]\s*(\d+))?\s*", text)
    if not m:
        raise argparse.ArgumentTypeError(f"{text!r}: expected N or WIDTHxHEIGHT, e.g. 128x128")
    w = int(m.group(1))
    h = int(m.group(2)) if m.group(2) else w
    return w, h


def _parse_set(text: str) -> tuple[str, Any]:
    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or not re.fullmatch(r"[A-Za-z_][\w-]*(\.[\w-]+)*", key):
        raise argparse.ArgumentTypeError(f"{text!r}: expected KEY=VALUE, e.g. render.spp=4")
    try:  # a TOML value: 4, 0.5, true, "text", [1, 2]
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    return key, value


def _positive(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a positive integer") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a positive integer")
    return v


def _nonneg(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected an integer >= 0") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: expected an integer >= 0")
    return v


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (no usage block): ``PROG CMD: error: ...``, exit 2."""

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {_one_line(message)} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog=PROG,
        description="Render coaxial conical-mirror stereo sequences with exact ground truth "
        "(Mitsuba 3) and check datasets.",
    )
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    r = sub.add_parser(
        "render",
        help="render a scene into a dataset directory (resumable)",
        description="Render SCENE (a TOML scene file) into DIR: dataset.json, then "
        "frames/NNNNNN/cam1.exr, cam2.exr, cam1.flo, cam2.flo, each frame written "
        "atomically. Run the same command again to resume an interrupted render.",
    )
    r.add_argument("scene", type=Path, help="scene file (.toml)")
    r.add_argument("--out", "-o", type=Path, required=True, metavar="DIR", help="dataset dir")
    r.add_argument("--frames", type=_positive, metavar="N", help="number of frames")
    r.add_argument(
        "--resolution",
        type=_parse_resolution,
        metavar="WxH",
        help="image size in pixels, WIDTHxHEIGHT or N for NxN",
    )
    r.add_argument("--spp", type=_positive, metavar="N", help="samples per pixel")
    r.add_argument("--seed", type=_nonneg, metavar="N", help="render seed")
    r.add_argument(
        "--set",
        dest="sets",
        type=_parse_set,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override any scene key (dotted, TOML value), e.g. render.max_depth=3; repeatable",
    )
    r.add_argument(
        "--camera",
        dest="camera_sets",
        type=_parse_set,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a camera-model parameter (the scene's [camera] table), e.g. "
        "read_noise=10, bits=12, response=srgb; repeatable; see docs/scene_format.md",
    )
    r.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="render frames as tasks on this Dask scheduler (tcp://host:8786); the "
        "workers need the scene file at the same path",
    )
    r.add_argument(
        "--scheduler-timeout",
        type=float,
        default=10.0,
        metavar="S",
        help="with --scheduler: seconds to wait for the scheduler to answer and for a "
        "worker to be there (default 10)",
    )
    r.add_argument(
        "--write-on",
        choices=("client", "worker"),
        default="client",
        help="with --scheduler: who writes the frames (worker: DIR must be on a "
        "shared file system; default: client)",
    )
    r.add_argument("--check", action="store_true", help="run omnisim check on DIR afterwards")
    r.add_argument(
        "--no-resource-check",
        action="store_true",
        help="skip the pre-flight estimate of memory and disk against this machine",
    )
    r.add_argument("--no-progress", action="store_true", help="no progress bar")
    r.add_argument(
        "--renderer", default=None, metavar="MODULE:FUNCTION", help=argparse.SUPPRESS
    )  # a plug-in backend or a test double

    c = sub.add_parser(
        "check",
        help="run the ground-truth self-checks on a dataset",
        description="Check a dataset: eq. (1) and (3)/(4) on the ground truth, world-point "
        "and photometric consistency of gt.flow. Prints each figure and its threshold; "
        "exit status 1 if any check fails.",
    )
    c.add_argument("dir", type=Path, metavar="DIR", help="dataset directory")
    c.add_argument("--frames", metavar="A:B", help="check frames A..B-1 only (Python slice)")
    c.add_argument(
        "--json", dest="json_out", type=Path, metavar="FILE", help="also write the results as JSON"
    )
    c.add_argument("--progress", action="store_true", help="progress bar")
    c.add_argument(
        "--partial",
        action="store_true",
        help="check the frames that are there even if some are missing (says how many)",
    )
    from omnisim.export import add_export_parser

    e = add_export_parser(sub)
    from omnisim.generate.command import add_generate_parser

    add_generate_parser(sub)
    for sp in (r, c, e):
        sp.add_argument(
            "--debug", action="store_true", help="show the Python traceback of an error"
        )
    return p


def _overrides(args: argparse.Namespace) -> dict[str, Any]:
    ov: dict[str, Any] = {}
    for key, value in args.sets:
        ov[key] = value
    for key, value in getattr(args, "camera_sets", []):
        ov[f"camera.{key.removeprefix('camera.')}"] = value
    if args.frames is not None:
        ov["frames"] = args.frames
    if args.resolution is not None:
        ov["render.width"], ov["render.height"] = args.resolution
    if args.spp is not None:
        ov["render.spp"] = args.spp
    if args.seed is not None:
        ov["render.seed"] = args.seed
    return ov


def _frame_slice(text: str | None, count: int) -> list[int] | None:
    if text is None:
        return None
    m = re.fullmatch(r"(-?\d*):(-?\d*)", text.strip())
    if not m:
        raise _UsageError(f"--frames {text!r}: expected A:B, e.g. 0:10")
    a = int(m.group(1)) if m.group(1) else None
    b = int(m.group(2)) if m.group(2) else None
    return list(range(count))[slice(a, b)]


def _check_json_out(path: Path) -> None:
    """Refuse a --json FILE that cannot be written, naming why (before any work)."""
    if path.is_dir():
        raise _UsageError(f"--json {path}: is a folder; expected a file name")
    parent = path.parent
    if not parent.is_dir():
        what = "is a file, not a folder" if parent.exists() else "does not exist"
        raise _UsageError(f"--json {path}: {parent} {what}; expected an existing folder")


def _cmd_check(args: argparse.Namespace) -> int:
    from omniflow.io.dataset import open_dataset
    from omnisim.check import format_results, run_checks

    ds = open_dataset(args.dir)
    if args.json_out:
        _check_json_out(args.json_out)  # before the checks, which can take minutes
    frames = _frame_slice(args.frames, ds.frame_count)
    done = ds.frames_done()
    wanted = list(range(ds.frame_count)) if frames is None else frames
    missing = sorted(set(wanted) - set(done))
    if not wanted:
        raise _UsageError(f"--frames {args.frames!r}: selects no frame of 0..{ds.frame_count - 1}")
    if missing and not getattr(args, "partial", False):
        shown = ", ".join(map(str, missing[:5])) + (", ..." if len(missing) > 5 else "")
        raise _IncompleteError(
            f"{args.dir}: incomplete dataset: {len(missing)} of {len(wanted)} frames to check "
            f"are missing (frame {shown}); render it to the end (run the same omnisim render "
            "again) or pass --partial to check the frames that are there"
        )
    print(
        f"{args.dir}: {len(done)} of {ds.frame_count} frames rendered; "
        f"checking {len(set(wanted) & set(done))}"
        + (f" ({len(missing)} missing, not checked)" if missing else "")
    )
    results = run_checks(ds, frames=frames, progress=args.progress)
    print(format_results(results))
    if args.json_out:
        from omniflow.io.jsonio import jsonable
        from omnisim.dataset import atomic_write_json

        atomic_write_json(
            args.json_out,
            jsonable([vars(r) | {"status": r.status} for r in results]),
        )
    return 1 if any(r.passed is False for r in results) else 0


@contextlib.contextmanager
def _writes_to(path: Path) -> Iterator[None]:
    """An OSError that names no file (a write to a full disk) names ``path`` instead."""
    try:
        yield
    except OSError as exc:
        if exc.filename is not None:
            raise
        raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc


def _cmd_render(args: argparse.Namespace) -> int:
    from omnisim.job import DEFAULT_RENDERER, render_dataset

    overrides = _overrides(args)
    with _writes_to(args.out):
        res = render_dataset(
            args.scene,
            args.out,
            overrides,
            renderer=args.renderer or DEFAULT_RENDERER,
            scheduler=args.scheduler,
            write_on=args.write_on,
            progress=not args.no_progress,
            resource_check=not args.no_resource_check,
            scheduler_timeout=args.scheduler_timeout,
        )
    print(
        f"{args.out}: {res.frames} frames ({len(res.rendered)} rendered now, "
        f"{len(res.skipped)} already done) in {res.seconds:.1f} s"
    )
    if args.check:
        ns = argparse.Namespace(
            dir=args.out, frames=None, json_out=None, progress=False, partial=False
        )
        return _cmd_check(ns)
    return 0


def _error(msg: object) -> None:
    print(f"{PROG}: error: {_one_line(msg)}", file=sys.stderr)


def _describe_exception(exc: BaseException) -> tuple[str, int] | None:
    """(one-line message, exit status) for an exception the handler knows, else None."""
    from omniflow.io.dataset import DatasetError
    from omnisim.distributed import ClusterError

    if isinstance(exc, DatasetError | _UsageError | _IncompleteError):
        return str(exc), 2
    if isinstance(exc, ClusterError):
        return str(exc), exc.exit_status
    if isinstance(exc, ModuleNotFoundError) and (exc.name or "").split(".")[0] in SIM_MODULES:
        return (
            f"the renderer needs the module {exc.name!r}, which is not installed; install "
            "the renderer with: pip install 'omniflow-testbed[sim]' (from a checkout: "
            "pip install '.[sim]')",
            1,
        )
    if isinstance(exc, UnicodeDecodeError):
        return f"a file is not UTF-8 text ({exc.reason} at byte {exc.start}); expected text", 2
    if isinstance(exc, MemoryError):
        return "out of memory; render fewer frames or smaller images", 1
    if isinstance(exc, OSError):
        path = exc.filename
        what = exc.strerror or str(exc)
        if path is None:
            return f"{what} (errno {exc.errno})", 1
        if exc.errno in _BAD_PATH_ERRNOS:
            return f"{path}: {what}; expected a path this user can read and write", 2
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return f"{path}: {what} (the disk is full: free some space, then run again)", 1
        return f"{path}: {what}", 1
    return None


#: What an interrupted render leaves.
RENDER_NOTE = "finished frames are kept; run the same command again to resume"


def main(argv: list[str] | None = None) -> int:
    """Run the command; the exit status (module docstring). Errors are one line; Ctrl-C
    or SIGTERM is one line too, status 130 / 143 (:mod:`omniflow.interrupts`)."""
    keep = argv is None  # a console script: keep the handler for the shutdown
    argv = list(sys.argv[1:] if argv is None else argv)
    note = RENDER_NOTE if argv[:1] == ["render"] else ""
    return run_main(PROG, lambda: _main(argv), note=note, keep=keep)


def _main(argv: list[str]) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    debug = bool(getattr(args, "debug", False))
    try:
        from omnisim.job import ResourceError

        try:
            from omnisim.scene import SceneError
        except ImportError:  # the sim extra is missing: reported when the scene is loaded
            SceneError = _IncompleteError
        try:
            if args.command == "render":
                return _cmd_render(args)
            if args.command == "generate":
                from omnisim.generate.command import run_cli as run_generate

                return run_generate(args)
            if args.command == "export":
                from omnisim.export import run_cli

                return run_cli(args)
            return _cmd_check(args)
        except (SceneError, ResourceError) as exc:
            if debug:
                traceback.print_exc()
            _error(exc)
            return 2
    except Exception as exc:
        if debug:
            traceback.print_exc()
        known = _describe_exception(exc)
        if known is None:
            _error(
                f"internal error: {type(exc).__name__}: {exc} (run again with --debug for the "
                "traceback, and please report it)"
            )
            return 1
        _error(known[0])
        return known[1]


if __name__ == "__main__":
    sys.exit(main())
