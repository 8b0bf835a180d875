"""Ctrl-C and SIGTERM as one line, for every command of the project.

:func:`run_main` is the first thing each console entry point does (``omniflow``,
``omniflow-stream``, ``omnisim``, ``omnivalidate``), before the heavy imports
(numpy, Mitsuba, Dask): it installs one handler for SIGINT and SIGTERM, runs the
command, and turns an interruption into one line on standard error,
``PROG: interrupted (NOTE)``, and the exit status 130 (SIGINT) or 143 (SIGTERM).

The first signal raises :class:`Interrupted` (a ``KeyboardInterrupt``) in the
main thread, so the commands' ``finally`` and ``except BaseException`` blocks
remove their temporary files while every finished unit (a frame, a pair's CSV, a
report renamed into place) stays. From then on the command's own standard error
is silenced: an error that follows from the interruption (a library that turned
the ``KeyboardInterrupt`` into its own exception, a worker thread's traceback) is
not news, and the one line is all the user sees. A second signal is ignored. If
the command has not ended :data:`GRACE_S` seconds after the signal (stuck in a
native call, or a library that swallowed the exception), the line is printed and
the process ends at once with the same status; its temporary files then carry
their process id or marker and are removed by the next run.

This module imports nothing but the standard library's light modules.
"""

from __future__ import annotations

import io
import os
import signal
import sys
import threading
from collections.abc import Callable

__all__ = ["GRACE_S", "Interrupted", "check", "received", "run_main"]

#: Seconds between the signal and the forced exit of a command that did not end.
GRACE_S = 5.0

#: armed: the handler raises (while the command runs); after, it only records the signal.
_state: dict = {"prog": None, "note": "", "signum": None, "stderr": None, "said": False,
                "armed": False}  # fmt: skip
_said = threading.Lock()


class Interrupted(KeyboardInterrupt):
    """Raised in the main thread by the first SIGINT or SIGTERM."""


def received() -> int | None:
    """The signal number of the interruption, or None when none came."""
    return _state["signum"]


def check() -> None:
    """Raise :class:`Interrupted` if a signal came: for a loop between two units of work,
    in case a library swallowed the first (Mitsuba's start-up does, at times)."""
    if _state["signum"] is not None and _state["armed"]:
        raise Interrupted(signal.Signals(_state["signum"]).name)


def _status() -> int:
    return 128 + int(_state["signum"])


def _say() -> None:
    """Print the one line (once, whoever gets here first)."""
    with _said:
        if _state["said"]:
            return
        _state["said"] = True
    note = f" ({_state['note']})" if _state["note"] else ""
    stream = _state["stderr"] or sys.stderr
    try:
        stream.write(f"{_state['prog']}: interrupted{note}\n")
        stream.flush()
    except (OSError, ValueError):  # a closed or broken stderr: the status still says it
        pass


def _force_exit() -> None:
    _say()
    os._exit(_status())


def _handler(signum: int, frame: object) -> None:
    if _state["signum"] is not None:
        return  # a second signal while the first is being handled: ignored
    _state["signum"] = signum
    _state["stderr"] = sys.stderr
    sys.stderr = io.StringIO()  # silenced: what follows is the interruption's consequence
    timer = threading.Timer(GRACE_S, _force_exit)
    timer.daemon = True
    timer.start()
    if _state["armed"]:
        raise Interrupted(signal.Signals(signum).name)


def run_main(prog: str, main: Callable[[], int], *, note: str = "", keep: bool = False) -> int:
    """Run ``main()`` with the handler installed; its status, or 130 / 143 if interrupted.

    ``note`` says what an interruption leaves (``"finished frames are kept; run the
    same command again to resume"``). A ``KeyboardInterrupt`` raised without a signal
    counts as SIGINT. Standard error is restored on return, and the handlers when no
    signal came, unless ``keep`` (a console script, about to exit: a signal during
    the interpreter's shutdown is then recorded, not a traceback). After a signal
    ours stays, ignores the next, and the forced exit stays armed for the shutdown.
    """
    _state.update(prog=prog, note=note, signum=None, stderr=None, said=False, armed=True)
    try:
        previous = {sig: signal.signal(sig, _handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    except ValueError:  # not the main thread (a command run from a test's thread)
        previous = {}
    try:
        status = main()
        _state["armed"] = False
    except KeyboardInterrupt:
        _state["armed"] = False
        if received() is None:
            _state["signum"] = signal.SIGINT
        status = None
    except BaseException:
        _state["armed"] = False
        if received() is None:
            for sig, old in previous.items():
                signal.signal(sig, old)
            raise
        status = None
    if _state["stderr"] is None and not keep:  # no signal came: the caller's handlers back
        for sig, old in previous.items():
            signal.signal(sig, old)
    if received() is None:
        return status
    _say()
    if _state["stderr"] is not None:
        sys.stderr = _state["stderr"]
    return _status()
