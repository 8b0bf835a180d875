"""Write a suite submission: one method's outputs for every rendered scene of a suite run.

    omnivalidate suite SUITE --split test --out RUN           # renders RUN/renders/NAME/
    python -m validation.examples.suite_submission RUN SUBMISSION
    omnivalidate suite SUITE --split test --out RUN --method-output my-DIS=SUBMISSION

The submission layout (docs/suite.md) is one folder per scene, named as the suite
names it, each in the ``--method-output`` layout of ``omnivalidate DATASET``::

    SUBMISSION/NAME/frames/NNNNNN/cam1.flo, cam2.flo   dense flow, frame NNNNNN -> next
    SUBMISSION/NAME/frames/NNNNNN/flow.csv             or per-point flow (x, y, dx, dy, ...)

This example stands for a method we did not write: OpenCV DIS (medium) on every
frame pair of every scene in ``RUN/renders/`` (:mod:`validation.examples.dis_method_output`
for one scene). A real method reads the same images (each scene's dataset) and writes
its own flow in the same places.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

__all__ = ["main", "write_submission"]


def write_submission(run_dir: str | Path, out: str | Path) -> dict[str, int]:
    """DIS flow for every scene rendered under ``run_dir/renders``; scene -> frame pairs."""
    from validation.examples.dis_method_output import write_dis_outputs

    renders = Path(run_dir) / "renders"
    scenes = sorted(p for p in renders.iterdir() if (p / "dataset.json").is_file())
    return {p.name: write_dis_outputs(p, Path(out) / p.name) for p in scenes}


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m validation.examples.suite_submission",
                                 description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("run", help="an omnivalidate suite --out directory (holds renders/)")
    ap.add_argument("out", help="the submission directory to write")
    args = ap.parse_args(argv)
    if not (Path(args.run) / "renders").is_dir():
        print(f"suite_submission: error: {args.run}: no renders/ folder; expected the --out "
              "directory of an omnivalidate suite run", file=sys.stderr)  # fmt: skip
        return 2
    done = write_submission(args.run, args.out)
    print(f"wrote {sum(done.values())} frame pair(s) of {len(done)} scene(s) to {args.out}",
          file=sys.stderr)  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
