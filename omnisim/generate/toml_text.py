"""Write a scene description (nested dicts and lists) as TOML text, byte for byte the same
on every machine.

Floats are written with :data:`DECIMALS` fixed decimals (trailing zeros cut), so the text
does not depend on how a platform prints the shortest ``repr`` of a float; keys come out
in the order the generator inserted them. Only what scene files use is supported:
scalars, flat or nested lists of scalars, sub-tables and arrays of tables.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

__all__ = ["DECIMALS", "format_value", "to_toml"]

#: Decimals of every float written (0.01 mm, 1e-5 deg/s, 1e-5 of an albedo).
DECIMALS = 5


def _float(x: float) -> str:
    s = f"{x:.{DECIMALS}f}".rstrip("0")
    if s.endswith("."):
        s += "0"
    return "0.0" if float(s) == 0.0 else s  # no "-0.0"


def format_value(v: Any) -> str:
    """One TOML value: bool, int, float (fixed decimals), string or list of these."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return _float(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, Sequence):
        return "[" + ", ".join(format_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} as a TOML value")


def _is_table_list(v: Any) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, Mapping) for x in v)


def _emit(table: Mapping[str, Any], prefix: str, out: list[str]) -> None:
    subs = []
    for key, v in table.items():
        if isinstance(v, Mapping) or _is_table_list(v):
            subs.append((key, v))
        else:
            out.append(f"{key} = {format_value(v)}")
    for key, v in subs:
        name = f"{prefix}{key}"
        if isinstance(v, Mapping):
            out.extend(["", f"[{name}]"])
            _emit(v, name + ".", out)
        else:
            for item in v:
                out.extend(["", f"[[{name}]]"])
                _emit(item, name + ".", out)


def to_toml(data: Mapping[str, Any], header: Sequence[str] = ()) -> str:
    """TOML text of ``data``, preceded by ``header`` lines written as ``# `` comments."""
    out = [f"# {line}".rstrip() for line in header]
    if out:
        out.append("")
    _emit(data, "", out)
    return "\n".join(out) + "\n"
