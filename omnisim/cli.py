"""The ``omnisim`` command: ``omnisim render SCENE --out DIR`` and ``omnisim check DIR``.

Exit status: 0 success; 1 a self-check failed (``check``, or ``render --check``);
2 a bad scene file, bad option, or an output directory that holds another dataset
(reported as one line before any rendering starts); 130 interrupted (the frames
finished so far are kept; run the same command again to resume).
"""

from __future__ import annotations

import argparse
import re
import signal
import sys
import tomllib
from pathlib import Path
from typing import Any

__all__ = ["main"]

PROG = "omnisim"


class _UsageError(Exception):
    pass


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


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
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
        "--write-on",
        choices=("client", "worker"),
        default="client",
        help="with --scheduler: who writes the frames (worker: DIR must be on a "
        "shared file system; default: client)",
    )
    r.add_argument("--check", action="store_true", help="run omnisim check on DIR afterwards")
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


def _cmd_check(args: argparse.Namespace) -> int:
    from omnisim.check import format_results, run_checks
    from omnisim.dataset import open_dataset

    ds = open_dataset(args.dir)
    frames = _frame_slice(args.frames, ds.frame_count)
    done = ds.frames_done()
    print(
        f"{args.dir}: {len(done)} of {ds.frame_count} frames rendered; "
        f"checking {len(done) if frames is None else len(set(frames) & set(done))}"
    )
    results = run_checks(ds, frames=frames, progress=args.progress)
    print(format_results(results))
    if args.json_out:
        from omnisim.dataset import atomic_write_json

        atomic_write_json(
            args.json_out,
            [
                {k: (None if isinstance(v, float) and v != v else v) for k, v in vars(r).items()}
                | {"status": r.status}
                for r in results
            ],
        )
    return 1 if any(r.passed is False for r in results) else 0


def _cmd_render(args: argparse.Namespace) -> int:
    from omnisim.job import DEFAULT_RENDERER, render_dataset

    overrides = _overrides(args)
    res = render_dataset(
        args.scene,
        args.out,
        overrides,
        renderer=args.renderer or DEFAULT_RENDERER,
        scheduler=args.scheduler,
        write_on=args.write_on,
        progress=not args.no_progress,
    )
    print(
        f"{args.out}: {res.frames} frames ({len(res.rendered)} rendered now, "
        f"{len(res.skipped)} already done) in {res.seconds:.1f} s"
    )
    if args.check:
        ns = argparse.Namespace(dir=args.out, frames=None, json_out=None, progress=False)
        return _cmd_check(ns)
    return 0


def _sigterm(signum, frame):  # let finally/except blocks clean temporaries up
    raise KeyboardInterrupt(f"signal {signum}")


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from omnisim.dataset import DatasetError

    try:
        from omnisim.scene import SceneError
    except ImportError:  # pragma: no cover - the scene model is part of the package
        SceneError = ValueError

    old = signal.getsignal(signal.SIGTERM)
    try:
        signal.signal(signal.SIGTERM, _sigterm)
    except ValueError:  # not the main thread
        old = None
    try:
        if args.command == "render":
            return _cmd_render(args)
        return _cmd_check(args)
    except SceneError as exc:
        print(f"{PROG}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except (DatasetError, _UsageError) as exc:
        print(f"{PROG}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(
            f"{PROG}: interrupted; finished frames are kept, run the same command again to resume",
            file=sys.stderr,
        )
        return 130
    finally:
        if old is not None:
            signal.signal(signal.SIGTERM, old)


if __name__ == "__main__":
    sys.exit(main())
