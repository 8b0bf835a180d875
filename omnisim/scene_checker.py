"""Typed reads out of a scene file's tables, each failure a ``SceneError`` naming the key.

:class:`Checker` is the one place the loader (:mod:`omnisim.scene`) turns TOML values
into numbers, strings, vectors and file paths: a wrong type, a value out of range or an
unknown key raises :class:`SceneError` with the file, the dotted key (and whether a
command-line override set it) and what was expected.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray


class SceneError(ValueError):
    """A scene file is wrong: the message names the file, the key and what was expected."""


REQUIRED = object()

#: The scene library (``scenes/`` beside the package). A file path ``"library:P"`` in a
#: scene means ``LIBRARY_DIR / P``, so a generated scene can use the shipped assets
#: (``"library:assets/poster.png"``) wherever its file is written.
LIBRARY_DIR = Path(__file__).resolve().parents[1] / "scenes"
LIBRARY_PREFIX = "library:"


def resolve_scene_path(text: str, base: Path) -> Path:
    """The file a scene's path string names: ``library:P``, absolute, or relative to ``base``."""
    if text.startswith(LIBRARY_PREFIX):
        return LIBRARY_DIR / text[len(LIBRARY_PREFIX) :]
    p = Path(text)
    return p if p.is_absolute() else base / p


class Checker:
    """Reads typed values out of tables, raising SceneError naming file and key."""

    def __init__(self, file: Path, overridden: set[str]):
        self.scene_file = file
        self.overridden = overridden

    def error(self, key: str, msg: str) -> SceneError:
        note = " (set by an override)" if key in self.overridden else ""
        return SceneError(f"{self.scene_file}: {key}{note}: {msg}")

    def bad(self, key: str, value: Any, expected: str) -> SceneError:
        return self.error(key, f"got {value!r}, expected {expected}")

    def table(self, value: Any, key: str, allowed: set[str] | frozenset[str]) -> dict:
        if not isinstance(value, dict):
            raise self.bad(key, value, "a table")
        unknown = sorted(set(value) - set(allowed))
        if unknown:
            name = f"{key}.{unknown[0]}" if key else unknown[0]
            raise self.error(name, f"unknown key; expected one of: {', '.join(sorted(allowed))}")
        return value

    def _get(self, tbl: dict, key: str, where: str, default: Any) -> tuple[str, Any]:
        full = f"{where}.{key}" if where else key
        if key not in tbl:
            if default is REQUIRED:
                raise self.error(full, "missing; this key is required")
            return full, default
        return full, tbl[key]

    def number(
        self,
        tbl: dict,
        key: str,
        where: str,
        default: Any = REQUIRED,
        *,
        lo: float | None = None,
        hi: float | None = None,
        lo_open: bool = False,
    ) -> float:
        full, v = self._get(tbl, key, where, default)
        if v is default and key not in tbl:
            return v
        expected = _range_text("a number", lo, hi, lo_open)
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise self.bad(full, v, expected)
        if (lo is not None and (v < lo or (lo_open and v == lo))) or (hi is not None and v > hi):
            raise self.bad(full, v, expected)
        return float(v)

    def integer(
        self,
        tbl: dict,
        key: str,
        where: str,
        default: Any = REQUIRED,
        *,
        lo: int | None = None,
        hi: int | None = None,
    ) -> int:
        full, v = self._get(tbl, key, where, default)
        if v is default and key not in tbl:
            return v
        expected = _range_text("an integer", lo, hi, False)
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.bad(full, v, expected)
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise self.bad(full, v, expected)
        return int(v)

    def boolean(self, tbl: dict, key: str, where: str, default: Any = REQUIRED) -> bool:
        full, v = self._get(tbl, key, where, default)
        if not isinstance(v, bool):
            raise self.bad(full, v, "true or false")
        return v

    def string(
        self, tbl: dict, key: str, where: str, default: Any = REQUIRED, *, choices=None
    ) -> str:
        full, v = self._get(tbl, key, where, default)
        if not isinstance(v, str):
            expected = "one of " + ", ".join(repr(c) for c in choices) if choices else "a string"
            raise self.bad(full, v, expected)
        if choices is not None and v not in choices:
            raise self.bad(full, v, "one of " + ", ".join(repr(c) for c in choices))
        return v

    def vector(
        self,
        tbl: dict,
        key: str,
        where: str,
        default: Any = REQUIRED,
        *,
        n: int = 3,
        lo: float | None = None,
        hi: float | None = None,
        lo_open: bool = False,
        scalar_ok: bool = False,
    ) -> NDArray[np.float64]:
        full, v = self._get(tbl, key, where, default)
        if key not in tbl:
            return np.asarray(v, dtype=np.float64)
        unit = _range_text("numbers", lo, hi, lo_open)
        expected = f"a list of {n} {unit}" + (" (or one number)" if scalar_ok else "")
        if scalar_ok and isinstance(v, int | float) and not isinstance(v, bool):
            v = [v] * n
        if not isinstance(v, list | tuple) or len(v) != n:
            raise self.bad(full, v, expected)
        for x in v:
            if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x):
                raise self.bad(full, v, expected)
            if (lo is not None and (x < lo or (lo_open and x == lo))) or (
                hi is not None and x > hi
            ):
                raise self.bad(full, v, expected)
        return np.asarray(v, dtype=np.float64)

    def file(self, tbl: dict, key: str, where: str, base: Path, suffixes=None) -> Path:
        full, v = self._get(tbl, key, where, REQUIRED)
        if not isinstance(v, str) or not v:
            raise self.bad(full, v, "a file path (relative to the scene file)")
        p = resolve_scene_path(v, base)
        if suffixes is not None and p.suffix.lower() not in suffixes:
            raise self.bad(full, v, "a file ending in " + ", ".join(suffixes))
        if not p.is_file():
            raise self.error(full, f"file not found: {p} (expected an existing file)")
        return p


def _range_text(what: str, lo, hi, lo_open) -> str:
    if lo is not None and hi is not None:
        return f"{what} in {'(' if lo_open else '['}{lo:g}, {hi:g}]"
    if lo is not None:
        return f"{what} {'>' if lo_open else '>='} {lo:g}"
    if hi is not None:
        return f"{what} <= {hi:g}"
    return what
