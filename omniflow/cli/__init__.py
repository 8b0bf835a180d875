"""The ``omniflow`` command: ``omniflow pair`` (:mod:`omniflow.cli.pair`),
``omniflow stream`` (:mod:`omniflow.cli.stream`, also ``omniflow-stream``) and
``omniflow calibrate`` (:mod:`omniflow.cli.calibrate`). The older
``omniflow IMAGE...`` / ``omniflow --dataset DIR`` form is ``omniflow pair`` with every
option in its help. Nothing else in ``omniflow`` imports this package."""

from __future__ import annotations

import sys

from omniflow.interrupts import run_main

__all__ = ["HELP", "main", "stream_main"]

#: What an interrupted ``omniflow pair`` leaves (the outputs move into --out as a set).
PAIR_NOTE = "nothing was written to --out"
#: What an interrupted ``omniflow stream`` leaves.
STREAM_NOTE = "every file in --out is whole; run the same command again to resume"

#: ``omniflow --help``.
HELP = """\
usage: omniflow {pair,stream,calibrate} ... [--help | --help-expert]

Omni flow (Spacek) of a coaxial conical-mirror stereo rig.

commands:
  pair       the flow of one pair of time steps (image files or an omnisim dataset frame)
  stream     the flow of every consecutive pair of a sequence, each frame read once
  calibrate  register both units from test card images (a rig file with rig.errors)

Each command's --help shows its common options; --help-expert every option, and
--set NAME=VALUE sets any OmniFlowConfig field. `omniflow IMAGE... --out DIR` (no
command) is `omniflow pair`.
"""


def _pair(argv: list[str], **kw: object) -> int:
    # imported here, not above: the signal handler is installed before numpy and the rest
    from omniflow.cli import pair

    return pair.main(argv, **kw)  # type: ignore[arg-type]


def _stream(argv: list[str], **kw: object) -> int:
    # imported here, not above: `python -m omniflow.cli.stream` (the omniflow-stream
    # script's module) would otherwise find it imported before it runs (runpy warns)
    from omniflow.cli import stream

    return stream.main(argv, **kw)  # type: ignore[arg-type]


def _calibrate(argv: list[str], **kw: object) -> int:
    from omniflow.cli import calibrate

    return calibrate.main(argv, **kw)  # type: ignore[arg-type]


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``omniflow``; returns the exit status (130 / 143 if interrupted)."""
    keep = argv is None  # a console script: keep the handler for the shutdown
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["pair"]:
        return run_main("omniflow pair", lambda: _pair(argv[1:], prog="omniflow pair",
                        short=True), note=PAIR_NOTE, keep=keep)  # fmt: skip
    if argv[:1] == ["stream"]:
        return run_main("omniflow stream", lambda: _stream(argv[1:], prog="omniflow stream",
                        short=True), note=STREAM_NOTE, keep=keep)  # fmt: skip
    if argv[:1] == ["calibrate"]:
        return run_main("omniflow calibrate", lambda: _calibrate(argv[1:]),
                        note="a file in --out is whole or absent", keep=keep)  # fmt: skip
    if argv in (["-h"], ["--help"]):
        print(HELP, end="")
        return 0
    return run_main("omniflow", lambda: _pair(argv), note=PAIR_NOTE, keep=keep)


def stream_main(argv: list[str] | None = None) -> int:
    """Entry point of ``omniflow-stream``."""
    keep = argv is None  # a console script: keep the handler for the shutdown
    argv = list(sys.argv[1:] if argv is None else argv)
    return run_main("omniflow-stream", lambda: _stream(argv), note=STREAM_NOTE, keep=keep)
