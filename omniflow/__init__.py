"""Omni Flow (Spacek): optic flow and stereo of a coaxial conical-mirror rig.

Packages, from the base up (``tests/test_layout.py`` guards the order):

- :mod:`omniflow.conventions` axes, angle sense, pixel centres, units
- :mod:`omniflow.geometry` the rig, eq. (1)-(7), and its calibration
- :mod:`omniflow.paper` the paper's equations as written: DCT fit (17-18), polar
  edges (19-20), radial matching (5.2), the flow equation and eq. (16)
- :mod:`omniflow.fit` each unit's fitted series, the flow band, sampling at points
- :mod:`omniflow.matching` the robust radial matcher
- :mod:`omniflow.solve` the pooled solver and its extensions
- :mod:`omniflow.config`, :mod:`omniflow.result`, :mod:`omniflow.pipeline`
  (``estimate``), :mod:`omniflow.stream` (``OmniFlowStream``): the flow step
- :mod:`omniflow.applications` section 6: time to contact, steering, position fix,
  odometry; regions
- :mod:`omniflow.io` image, JSON and dataset files, pictures
- :mod:`omniflow.cli` the commands (nothing imports them)

The public API is importable from here (docs/api.md)::

    from omniflow import OmniFlowConfig, estimate, load_rig

    rig = load_rig("rig.toml")
    result = estimate([img1_t, img1_t1], [img2_t, img2_t1], rig, OmniFlowConfig.preset("dense"))

Each name is imported on first use (PEP 562), so ``import omniflow`` stays cheap and a
command that needs one module does not compile the others' kernels.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

#: The public names and the module each comes from.
_PUBLIC = {
    "estimate": "omniflow.pipeline",
    "OmniFlowConfig": "omniflow.config",
    "PRESETS": "omniflow.config",
    "PUBLIC_FIELDS": "omniflow.config",
    "OmniFlowStream": "omniflow.stream",
    "OmniFlowResult": "omniflow.result",
    "NoMatchesWarning": "omniflow.result",
    "Rig": "omniflow.geometry.rig",
    "Unit": "omniflow.geometry.rig",
    "RigError": "omniflow.geometry.rig",
    "load_rig": "omniflow.geometry.rig",
    "rig_from_dict": "omniflow.geometry.rig",
}

__all__ = ["__version__", *_PUBLIC]


def __getattr__(name: str) -> Any:
    if name not in _PUBLIC:
        raise AttributeError(f"module 'omniflow' has no attribute {name!r}")
    value = getattr(importlib.import_module(_PUBLIC[name]), name)
    globals()[name] = value  # the next access is a plain attribute
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
