"""omniflow.io.jsonio: the one rule for values JSON cannot hold (non-finite -> null)."""

from __future__ import annotations

import dataclasses
import doctest
import json
import math
from pathlib import Path

import numpy as np

from omniflow.io import jsonio
from omniflow.io.jsonio import json_text, jsonable


@dataclasses.dataclass
class _Config:
    band: float = 0.25
    limit: float = math.inf
    where: Path = Path("/tmp/x")


def test_non_finite_is_null_everywhere():
    obj = {
        "pos": math.inf,
        "neg": -math.inf,
        "nan": math.nan,
        "np": np.float32(np.inf),
        "arr": np.array([1.0, np.nan, -np.inf]),
        "tuple": (np.int64(3), np.bool_(True)),
        "cfg": _Config(),
        5: "key made a string",
    }
    got = jsonable(obj)
    assert got == {
        "pos": None,
        "neg": None,
        "nan": None,
        "np": None,
        "arr": [1.0, None, None],
        "tuple": [3, True],
        "cfg": {"band": 0.25, "limit": None, "where": "/tmp/x"},
        "5": "key made a string",
    }
    text = json_text(obj)
    assert json.loads(text) == got and text.endswith("\n")
    assert "Infinity" not in text and "NaN" not in text and '"inf"' not in text


def test_large_arrays_described_only_when_asked():
    img = np.zeros((10, 10, 3), np.float32)
    assert jsonable(img, max_array=64) == "<array float32 [10, 10, 3]>"
    assert jsonable(img[:2, :2, 0], max_array=64) == [[0.0, 0.0], [0.0, 0.0]]
    assert len(jsonable(img)) == 10


def test_finite_values_unchanged():
    assert jsonable([0.1, -2, "s", None, False]) == [0.1, -2, "s", None, False]
    assert json_text({"a": 1e308}, indent=None) == '{"a": 1e+308}\n'


def test_docstring_example():
    assert doctest.testmod(jsonio).failed == 0
