"""A user's input file (scene, rig, dataset.json, suite, thresholds, bounds) as text and
as parsed JSON or TOML, with what a hostile or careless file can do refused in one line.

* **Size**: a file over :data:`MAX_INPUT_BYTES` is refused from its size, before it is
  read (the project's largest, a long dataset's dataset.json, is a few MiB).
* **Depth**: a file nested deeper than the parser's recursion limit (Python's
  ``json`` and ``tomllib`` recurse per level, about 1000 levels) is refused as such,
  not reported as an internal ``RecursionError``.
* **Text**: a file that is not UTF-8 is refused naming the byte.

Each refusal is an :class:`InputFileError` (a ``ValueError``) whose message names the
file; every reader turns it into its own error class (SceneError, RigError, ...).
"""

from __future__ import annotations

import json
import os
import sys
import tomllib
from pathlib import Path
from typing import Any

__all__ = ["MAX_INPUT_BYTES", "InputFileError", "parse_text", "read_input"]

#: The largest input text file read, bytes.
MAX_INPUT_BYTES = 64 * 2**20


class InputFileError(ValueError):
    """An input file refused: one line naming the file and what was expected."""


def read_input(path: str | os.PathLike[str], what: str) -> str:
    """The UTF-8 text of ``path`` (a ``what``: "TOML scene", "rig file", ...).

    OSError (missing, unreadable) passes through for the caller's message."""
    path = Path(path)
    size = path.stat().st_size
    if size > MAX_INPUT_BYTES:
        raise InputFileError(f"{path}: {size} bytes; expected a {what} of at most "
                             f"{MAX_INPUT_BYTES // 2**20} MiB")  # fmt: skip
    try:
        return path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputFileError(f"{path}: not UTF-8 text (byte {exc.start}); expected a "
                             f"{what}") from None  # fmt: skip


def parse_text(text: str, path: str | os.PathLike[str], fmt: str) -> Any:
    """``text`` parsed as ``fmt`` ("json" or "toml"); InputFileError for invalid or too
    deeply nested text (the message as ``PATH: not valid JSON: ...``)."""
    try:
        return json.loads(text) if fmt == "json" else tomllib.loads(text)
    except RecursionError:
        limit = sys.getrecursionlimit()
        raise InputFileError(f"{path}: nested deeper than {limit} levels; expected a "
                             f"{fmt.upper()} file of tables and lists") from None  # fmt: skip
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise InputFileError(f"{path}: not valid {fmt.upper()}: {exc}") from exc
