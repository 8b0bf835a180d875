"""The public API of omniflow (docs/api.md): every name importable from the package,
imported lazily, and documented on the one page."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest

import omniflow

ROOT = Path(__file__).resolve().parents[2]


def test_every_public_name_is_its_modules_object():
    for name, module in omniflow._PUBLIC.items():
        assert getattr(omniflow, name) is getattr(importlib.import_module(module), name)
    assert set(omniflow.__all__) == {"__version__", *omniflow._PUBLIC}


def test_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'estimat'"):
        omniflow.estimat  # noqa: B018


def test_import_is_lazy():
    # `import omniflow` alone must not import the pipeline (and so compile no kernel)
    code = "import sys, omniflow; print(sorted(m for m in sys.modules if m.startswith('omniflow')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "['omniflow']"


def test_the_page_names_every_public_name():
    page = (ROOT / "docs" / "api.md").read_text(encoding="utf-8")
    missing = [name for name in omniflow._PUBLIC if f"`{name}" not in page]
    assert not missing, f"docs/api.md does not document {missing}"
