"""The ``omniflow`` command: ``omniflow pair`` (:mod:`omniflow.cli.pair`) and
``omniflow stream`` (:mod:`omniflow.cli.stream`, also ``omniflow-stream``). The older
``omniflow IMAGE...`` / ``omniflow --dataset DIR`` form is ``omniflow pair`` with every
option in its help. Nothing else in ``omniflow`` imports this package."""

from __future__ import annotations

import sys

from omniflow.cli import pair

__all__ = ["HELP", "main"]

#: ``omniflow --help``.
HELP = """\
usage: omniflow {pair,stream} ... [--help | --help-expert]

Omni flow (Spacek) of a coaxial conical-mirror stereo rig.

commands:
  pair     the flow of one pair of time steps (image files or an omnisim dataset frame)
  stream   the flow of every consecutive pair of a sequence, each frame read once

Each command's --help shows its common options; --help-expert every option, and
--set NAME=VALUE sets any OmniFlowConfig field. `omniflow IMAGE... --out DIR` (no
command) is `omniflow pair`.
"""


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``omniflow``; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["pair"]:
        return pair.main(argv[1:], prog="omniflow pair", short=True)
    if argv[:1] == ["stream"]:
        # imported here, not above: `python -m omniflow.cli.stream` (the omniflow-stream
        # script's module) would otherwise find it imported before it runs (runpy warns)
        from omniflow.cli import stream

        return stream.main(argv[1:], prog="omniflow stream", short=True)
    if argv in (["-h"], ["--help"]):
        print(HELP, end="")
        return 0
    return pair.main(argv)
