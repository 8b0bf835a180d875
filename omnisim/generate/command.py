"""``omnisim generate``: write generated scene files (one, or a batch of seeds).

    omnisim generate --family room --seed 7 --out room-7.toml
    omnisim generate --family hall --seeds 0-19 --out scenes/generated

Bad input (an unknown family, a bad seed or seed range, an output folder that does not
exist) is one line on stderr and exit status 2; nothing is written then.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from omnisim.generate import FAMILIES, MAX_SEED, GenerateError, generate_batch, write_scene

__all__ = ["add_generate_parser", "parse_seeds", "run_cli"]


def parse_seeds(text: str) -> list[int]:
    """``"0-19"``, ``"7"`` or ``"0-3,9,12-13"`` -> the seeds, in order, without repeats."""
    seeds: list[int] = []
    for part in text.split(","):
        m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", part)
        if not m:
            raise GenerateError(
                f"--seeds {text!r}: expected A-B, N or a comma list of these, e.g. 0-19"
            )
        a = int(m.group(1))
        b = int(m.group(2)) if m.group(2) else a
        if b < a or b > MAX_SEED:
            raise GenerateError(
                f"--seeds {text!r}: {part.strip()!r} is not a range A-B with A <= B"
            )
        if b - a >= 100000:
            raise GenerateError(f"--seeds {text!r}: more than 100000 seeds in {part.strip()!r}")
        seeds.extend(range(a, b + 1))
    return list(dict.fromkeys(seeds))


def _seed(text: str) -> int:
    if not re.fullmatch(r"\s*\d+\s*", text) or int(text) > MAX_SEED:
        raise argparse.ArgumentTypeError(f"{text!r}: expected an integer in 0 ... 2**63 - 1")
    return int(text)


def add_generate_parser(sub) -> argparse.ArgumentParser:
    """The ``generate`` sub-command on ``sub`` (the ``omnisim`` sub-parsers)."""
    g = sub.add_parser(
        "generate",
        help="write procedural scene files (seeded, deterministic)",
        description="Write the scene of FAMILY drawn from SEED as an ordinary scene file "
        "(docs/generator.md): the same family and seed give the same bytes. Families: "
        + ", ".join(FAMILIES)
        + ".",
    )
    g.add_argument("--family", required=True, metavar="F", help="one of " + ", ".join(FAMILIES))
    seeds = g.add_mutually_exclusive_group(required=True)
    seeds.add_argument("--seed", type=_seed, metavar="N", help="one scene; --out is a file")
    seeds.add_argument(
        "--seeds", metavar="A-B", help="a batch, e.g. 0-19; --out is a folder (created)"
    )
    g.add_argument("--out", "-o", type=Path, required=True, metavar="PATH")
    return g


def run_cli(args: argparse.Namespace) -> int:
    """Run ``omnisim generate``; 0 on success, 2 (one line on stderr) on bad input."""
    try:
        if args.family not in FAMILIES:
            raise GenerateError(
                f"--family {args.family!r}: unknown; expected one of {', '.join(FAMILIES)}"
            )
        if args.seeds is not None:
            seeds = parse_seeds(args.seeds)
            if args.out.exists() and not args.out.is_dir():
                raise GenerateError(f"--out {args.out}: is a file; expected a folder for --seeds")
            paths = generate_batch(args.family, seeds, args.out)
            print(f"{args.out}: {len(paths)} {args.family} scenes (seeds {args.seeds})")
            return 0
        out = args.out
        if out.is_dir():
            out = out / f"{args.family}-{args.seed}.toml"
        if not out.parent.is_dir():
            raise GenerateError(f"--out {args.out}: folder {out.parent} does not exist")
        write_scene(args.family, args.seed, out)
        print(f"{out}: {args.family} scene, seed {args.seed}")
        return 0
    except GenerateError as exc:
        print(f"omnisim: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
