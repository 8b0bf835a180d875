"""``omnivalidate suite SUITE_FILE --split test --out DIR``: score every method on a suite.

Exit status: 0 done; 1 a figure outside its --check bound; 2 bad input (one line naming the
file, entry or option); 130 interrupted (what is finished is kept: run the same command
again to resume).
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
import typing
from collections.abc import Sequence
from pathlib import Path

__all__ = ["main"]

_EPILOG = """\
outputs in DIR:
  leaderboard.md, .html, .csv, .json   every method per scene and over all scenes,
                                       ranked by 1px (fraction of pixels with EPE > 1 px)
  scenes/NAME.toml, scenes/NAME/       each scene's TOML and its omnivalidate report
  renders/NAME/                        each scene's rendered dataset
  state/NAME.json                      what each report scored (the resume key)

splits: train is for choosing defaults and tuning; test is for reporting only, never
for choosing a default or a threshold (docs/suite.md).

external methods (--method-output NAME=DIR, repeatable): DIR/SCENE/frames/NNNNNN/
cam1.flo + cam2.flo (dense) or flow.csv (per point), one SCENE folder per scored scene;
example: python -m validation.examples.suite_submission RUN SUBMISSION

examples:
  omnivalidate suite scenes/suite/mini.toml --split test --out runs/mini
  omnivalidate suite scenes/suite/suite.toml --split all --out runs/suite \\
      --methods DIS-medium,zero-flow --method-output mine=runs/mine
"""


class _Parser(argparse.ArgumentParser):
    """Usage errors as one line, like the rest of omnivalidate."""

    def error(self, message: str) -> typing.NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _parser() -> argparse.ArgumentParser:
    ap = _Parser(
        prog="omnivalidate suite",
        description="Render what is missing of a suite's scenes, score every method on "
        "every scene and write the leaderboard (resumable).",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("suite_file", help="suite file (scenes/suite/*.toml)")
    ap.add_argument("--split", required=True, choices=("test", "train", "all"),
                    help="which scenes to score")  # fmt: skip
    ap.add_argument("--out", required=True, help="output directory (created; reused to resume)")
    ap.add_argument(
        "--methods",
        action="append",
        default=None,
        metavar="NAME[,NAME...]",
        help="methods to score: omniflow rows and baselines by name (default: omniflow's "
        "default, dense and paper rows and every baseline); repeatable",
    )
    ap.add_argument("--registration", default=None, metavar="recorded|none|RIG_FILE[,...]",
                    help="what omniflow is told about the rig, as omnivalidate DATASET "
                    "--registration: recorded (the true errors), none (eq. 1) or a rig file; "
                    "comma-separated, each omniflow method once per choice (default: "
                    "recorded)")  # fmt: skip
    ap.add_argument(
        "--method-output",
        action="append",
        default=[],
        metavar="NAME=DIR",
        help="score another method's outputs: DIR holds one folder per scene in the "
        "--method-output layout of omnivalidate DATASET; repeatable",
    )
    ap.add_argument("--scheduler", default=None, metavar="ADDR",
                    help="render the frames on this Dask scheduler (tcp://host:8786)")  # fmt: skip
    ap.add_argument("--check", default=None, metavar="BOUNDS",
                    help="compare the leaderboard with a bounds file (validation/mini_bounds."
                    "toml) and exit 1 if a figure is outside its bound")  # fmt: skip
    ap.add_argument("--no-progress", action="store_true", help="no progress bars")
    return ap


def _split_names(text: str) -> list[str]:
    """Split a comma-separated list of method names, keeping the commas inside a row
    name's brackets (``omniflow[robust,gradavg,diff,pooled]``)."""
    names, depth, cur = [], 0, ""
    for ch in text:
        depth += {"[": 1, "]": -1}.get(ch, 0)
        if ch == "," and depth == 0:
            names.append(cur)
            cur = ""
        else:
            cur += ch
    return [n.strip() for n in [*names, cur] if n.strip()]


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[2:] if argv is None else argv)
    args = _parser().parse_args(argv)
    from omniflow.cli.common import MACHINE_ERRNOS
    from omniflow.io.dataset import DatasetError
    from omnisim.distributed import ClusterError
    from omnisim.job import ResourceError
    from omnisim.scene_checker import SceneError

    from .inputs import InputError
    from .suite import SuiteError, load_suite
    from .suite_bounds import BoundsError, check_bounds, load_bounds
    from .suite_run import resolve_methods, run_suite

    def fail(msg: str, status: int = 2) -> int:
        print(f"omnivalidate suite: error: {msg}", file=sys.stderr)
        return status

    external: dict[str, Path] = {}
    for item in args.method_output:
        name, sep, folder = item.partition("=")
        if not sep or not name.strip() or not folder.strip():
            return fail(f"--method-output {item!r}: expected NAME=DIR")
        if not Path(folder).is_dir():
            return fail(f"--method-output {item}: {folder} is not a directory")
        external[name.strip()] = Path(folder)
    names = None
    if args.methods is not None:
        names = [n for text in args.methods for n in _split_names(text)]
    start = time.perf_counter()
    try:
        bounds = None if args.check is None else load_bounds(args.check)
    except BoundsError as exc:
        return fail(f"--check: {exc}")
    try:
        suite = load_suite(args.suite_file)
        methods = resolve_methods(names, external, args.registration)
        command = "omnivalidate suite " + " ".join(shlex.quote(a) for a in argv)
        board = run_suite(suite, args.out, split=args.split, methods=methods,
                          scheduler=args.scheduler, progress=not args.no_progress,
                          command=command)  # fmt: skip
    except (SuiteError, InputError, SceneError, DatasetError, ResourceError) as exc:
        return fail(str(exc).splitlines()[0])
    except ClusterError as exc:  # the scheduler did not answer: its own exit status
        print(f"omnivalidate suite: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return exc.exit_status
    except OSError as exc:
        if exc.errno in MACHINE_ERRNOS:  # a full disk: the machine refused (1), named by --out
            kept = "what is finished is kept: free some space, then run the same command again"
            return fail(f"--out {args.out}: {exc.strerror or exc}; {kept}", 1)
        return fail(f"{exc.filename or args.out}: {exc.strerror or exc}")
    top = board["methods"][0] if board["methods"] else None
    best = f"; first: {top['method']} (1px {100 * top['1px']:.1f} %)" if top else ""
    print(f"omnivalidate suite: {len(board['scenes'])} scenes, {len(board['methods'])} methods "
          f"in {time.perf_counter() - start:.1f} s{best}; leaderboard: "
          f"{Path(args.out) / 'leaderboard.html'}")  # fmt: skip
    if bounds is None:
        return 0
    verdicts = check_bounds(board, bounds)
    failed = [line for ok, line in verdicts if not ok]
    for line in failed:
        print(f"omnivalidate suite: FAIL {line}")
    print(f"omnivalidate suite: --check {args.check}: {len(verdicts) - len(failed)} of "
          f"{len(verdicts)} bounds met")  # fmt: skip
    return 1 if failed else 0
