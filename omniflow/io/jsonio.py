"""JSON out: the project's one rule for values JSON cannot hold.

Every JSON file the project writes (``dataset.json``, the omniflow command's
``flow.json``, the validation summary) goes through :func:`jsonable` first:

- a non-finite float (NaN, +inf, -inf) becomes ``null`` (Python ``None``): JSON
  has no infinity, and a reader in any language takes ``null`` for "no value"
  without parsing a string (``omniflow.conventions``, "JSON");
- numpy scalars become Python numbers and arrays nested lists (an array of more
  than ``max_array`` elements, an image say, becomes the string
  ``"<array float32 [H, W, 3]>"`` when ``max_array`` is given);
- dataclasses become dicts of their fields, mapping keys strings, tuples lists,
  paths strings; dates their ISO text; anything else its ``repr``.

The result is then written with ``allow_nan=False``, so a value that slipped
past is an error, not an ``Infinity`` token other JSON parsers reject.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Mapping
from pathlib import Path, PurePath
from typing import Any

import numpy as np

__all__ = ["json_text", "jsonable"]


def jsonable(obj: Any, *, max_array: int | None = None) -> Any:
    """A JSON-safe copy of ``obj`` under the module's rule (non-finite floats -> None).

    Parameters
    ----------
    obj : any
        Nested dicts, lists, tuples, dataclasses, numpy arrays and scalars, numbers,
        strings, paths.
    max_array : int, optional
        Arrays with more elements become a short ``"<array dtype [shape]>"`` string
        (for metadata that must not hold images); default: every array in full.

    Examples
    --------
    >>> jsonable({"a": float("inf"), "b": np.float32(0.5), "c": (1, float("nan"))})
    {'a': None, 'b': 0.5, 'c': [1, None]}
    """
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {
            f.name: jsonable(getattr(obj, f.name), max_array=max_array)
            for f in dataclasses.fields(obj)
        }
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v, max_array=max_array) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v, max_array=max_array) for v in obj]
    if isinstance(obj, np.ndarray):
        if max_array is not None and obj.size > max_array:
            return f"<array {obj.dtype} {list(obj.shape)}>"
        return jsonable(obj.tolist(), max_array=max_array)
    if isinstance(obj, np.generic):
        return jsonable(obj.item(), max_array=max_array)
    if isinstance(obj, bool | int | str) or obj is None:
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, PurePath | os.PathLike):
        return str(Path(obj))
    return obj.isoformat() if hasattr(obj, "isoformat") else repr(obj)


def json_text(obj: Any, *, indent: int | None = 2, max_array: int | None = None) -> str:
    """``json.dumps`` of :func:`jsonable` ``(obj)``, no NaN/inf tokens, ending in a newline."""
    return json.dumps(jsonable(obj, max_array=max_array), indent=indent, allow_nan=False) + "\n"
