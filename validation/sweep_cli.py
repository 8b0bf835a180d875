"""``omnivalidate sweep SCENE --key KEY --values V1,V2,... --out DIR``: accuracy against one
scene key, one render per value (validation.sweep).

Exit status: 0 done; 2 bad input (one line naming the option, file or key); 130
interrupted by Ctrl-C, 143 by SIGTERM (one line, validation.cli's handler; what is
finished is kept: run the same command again to resume).
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from .suite_cli import _Parser, _split_names

__all__ = ["main"]

_EPILOG = """\
outputs in DIR:
  sweep.md, sweep.png, sweep.csv, sweep.json   every method's metrics at every value
  points/NN/render/, points/NN/report/         each value's render and omnivalidate report

values: V1,V2,... or a TOML array, each a TOML value (inf is a pinhole's f-number);
the metrics are the suite's (docs/suite.md).

examples:
  omnivalidate sweep scenes/default.toml --key optics.f_number --values 2.8,5.6,11,inf \\
      --out runs/sweep-f --methods omniflow:default,DIS-medium
  omnivalidate sweep scenes/default.toml --key rig.errors.cam1.cone_angle \\
      --values 89.8,90,90.2 --out runs/sweep-cone --registration recorded,none
  omnivalidate sweep scenes/default.toml --key camera.exposure --values 0.25,0.5,1,2 \\
      --out runs/sweep-exposure --set optics.focal_length=0.006
"""


def _parser() -> argparse.ArgumentParser:
    ap = _Parser(
        prog="omnivalidate sweep",
        description="Render one scene at each value of one scene key, score every method "
        "on each render and draw the metrics against the value (resumable).",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("scene", help="scene file (scenes/*.toml)")
    ap.add_argument("--key", required=True, help="the dotted scene key to sweep, e.g. "
                    "optics.f_number")  # fmt: skip
    ap.add_argument("--values", required=True, help="its values: V1,V2,... or a TOML array")
    ap.add_argument("--out", required=True, help="output directory (created; reused to resume)")
    ap.add_argument("--methods", default=None, metavar="NAME[,NAME...]",
                    help="methods to score, as omnivalidate suite --methods (default: "
                    "omniflow:default and DIS-medium)")  # fmt: skip
    ap.add_argument("--registration", default=None, metavar="recorded|none|RIG_FILE[,...]",
                    help="what omniflow is told about the rig, as omnivalidate DATASET "
                    "--registration: recorded (the true errors), none (eq. 1) or a rig file; "
                    "comma-separated, each omniflow method once per choice (default: "
                    "recorded)")  # fmt: skip
    ap.add_argument("--resolution", type=int, default=256, help="image size, px (default 256)")
    ap.add_argument("--frames", type=int, default=3, help="frames per render (default 3)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="another scene key at every point (repeatable)")  # fmt: skip
    ap.add_argument("--no-progress", action="store_true", help="no progress bars")
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[2:] if argv is None else argv)
    args = _parser().parse_args(argv)
    from omniflow.io.dataset import DatasetError
    from omnisim.job import ResourceError
    from omnisim.scene import parse_override
    from omnisim.scene_checker import SceneError

    from .inputs import InputError
    from .suite_run import resolve_methods
    from .sweep import parse_values, run_sweep

    def fail(msg: str) -> int:
        print(f"omnivalidate sweep: error: {msg}", file=sys.stderr)
        return 2

    if not Path(args.scene).is_file():
        return fail(f"{args.scene}: no such scene file")
    if args.resolution < 16 or args.frames < 2:
        return fail(f"--resolution {args.resolution} / --frames {args.frames}: expected at "
                    "least 16 px and 2 frames")  # fmt: skip
    start = time.perf_counter()
    try:
        values = parse_values(args.values)
        settings = dict(parse_override(s) for s in args.set)
        if args.key in settings:
            return fail(f"--set {args.key}: that is the swept --key")
        names = _split_names(args.methods or "omniflow:default,DIS-medium")
        methods = resolve_methods(names, registration=args.registration)
        command = "omnivalidate sweep " + " ".join(shlex.quote(a) for a in argv)
        sweep = run_sweep(Path(args.scene).resolve(), args.key, values, Path(args.out),
                          methods=methods, frames=args.frames, resolution=args.resolution,
                          settings=settings, progress=not args.no_progress,
                          command=command)  # fmt: skip
    except (InputError, SceneError, DatasetError, ResourceError) as exc:
        return fail(str(exc).splitlines()[0])
    except OSError as exc:
        return fail(f"{exc.filename or args.out}: {exc.strerror or exc}")
    print(f"omnivalidate sweep: {args.key} at {len(values)} values, "
          f"{len(sweep['methods']['omniflow']) + len(sweep['methods']['baselines'])} methods in "
          f"{time.perf_counter() - start:.1f} s: {Path(args.out) / 'sweep.md'}")  # fmt: skip
    return 0
