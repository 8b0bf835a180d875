"""A scene's rig errors: the ``[rig.errors.cam1]`` and ``[rig.errors.cam2]`` tables.

Each table holds some of the five keys of :class:`omniflow.geometry.rig_errors.UnitErrors`
(``docs/scene_format.md``, ``docs/decisions/rig_errors.md``); a missing key, or a missing
table, is the ideal unit. The units of the scene's rig carry them (``Unit.errors``), so
the sensor (:mod:`omnisim.sensor`) and the ground truth (:mod:`omnisim.groundtruth`)
trace the actual geometry, and ``dataset.json``'s ``rig.errors`` records them.
"""

from __future__ import annotations

from dataclasses import replace

from omniflow.geometry.rig import Rig
from omniflow.geometry.rig_errors import ERROR_KEYS, errors_from_dict
from omnisim.scene_checker import Checker

__all__ = ["ERROR_KEYS", "rig_with_errors"]


def rig_with_errors(chk: Checker, tbl: dict, rig: Rig) -> Rig:
    """``rig`` with the errors of the ``[rig]`` table's ``errors`` sub-tables (ideal: as is)."""
    errors = tbl.get("errors", {})
    if not isinstance(errors, dict):
        raise chk.bad("rig.errors", errors, "tables [rig.errors.cam1], [rig.errors.cam2]")
    chk.table(errors, "rig.errors", {"cam1", "cam2"})
    units = {"cam1": rig.cam1, "cam2": rig.cam2}
    for name, sub in errors.items():
        err = errors_from_dict(sub, f"rig.errors.{name}", rig.d, chk.bad)
        if not err.ideal:
            units[name] = replace(units[name], errors=err)
    return Rig(cam1=units["cam1"], cam2=units["cam2"], s=rig.s)
