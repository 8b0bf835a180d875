"""What the mirrors hang on: struts and mount flanges, as occluders of the rig.

``[[rig.struts]]`` (any number of sets) and ``rig.mount_radius`` (``docs/scene_format.md``)
become scene objects that move with the robot, so they are real occluders in the render
and in every ground-truth trace. They are not scene content: the ground truth marks them
``gt.valid`` = 0 (:data:`RIG_PART_KINDS`, ``omnisim.groundtruth``) while ``gt.object``
still names them, and the loader's rig-in-scene checks leave them out.

Geometry (rig frame, ``omniflow.conventions``): a strut set is ``count`` round rods of
diameter ``width``, parallel to the axis at ``radius`` from it, the first at
``azimuth`` (degrees from +X towards +Y) and the others evenly spaced; they run the
rig's height, from cam2's camera centre (h = -d) to cam1's mirror base (h = s + R). A
mount flange is a disc of ``mount_radius`` and ``FLANGE_THICKNESS`` on the back of each
mirror, its lower face in the mirror's base plane (h = R for cam2, s + R for cam1): a
flange wider than R clips the outer field, the rays leaving the mirror near its rim.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from omniflow.geometry.rig import Rig
from omnisim import geometry
from omnisim.scene_checker import Checker

__all__ = ["FLANGE_THICKNESS", "PART_ALBEDO", "RIG_PART_KINDS", "STRUT_KEYS", "rig_parts"]

STRUT_KEYS = frozenset({"count", "radius", "width", "azimuth"})
#: Kinds of the scene objects that are parts of the rig (not scene content).
RIG_PART_KINDS = ("strut", "mount")
#: Thickness of a mount flange, metres.
FLANGE_THICKNESS = 0.002
#: Albedo of the struts and flanges (black anodised aluminium, diffuse).
PART_ALBEDO = 0.04
_SECTIONS = 32


def rig_parts(chk: Checker, tbl: dict, rig: Rig, first_id: int) -> list[dict[str, Any]]:
    """The struts and flanges of the ``[rig]`` table as object descriptions.

    Each is ``{"id", "name", "kind", "mesh"}`` (mesh in the rig frame), ids from
    ``first_id`` on; the loader makes them scene objects moving with the robot.
    """
    items = tbl.get("struts", [])
    if not isinstance(items, list):
        raise chk.bad("rig.struts", items, "a list of tables ([[rig.struts]])")
    parts = []
    for i, st in enumerate(items):
        where = f"rig.struts[{i}]"
        chk.table(st, where, STRUT_KEYS)
        count = chk.integer(st, "count", where, lo=1, hi=64)
        width = chk.number(st, "width", where, lo=0, lo_open=True)
        radius = chk.number(st, "radius", where, lo=0, lo_open=True)
        azimuth = chk.number(st, "azimuth", where, 0.0)
        if radius - width / 2 <= rig.R:
            raise chk.bad(
                f"{where}.radius",
                radius,
                f"more than R + width / 2 = {rig.R + width / 2:g} m (a strut outside the mirror)",
            )
        mesh = _struts(count, radius, width, np.radians(azimuth), -rig.d, rig.s + rig.R)
        parts.append({"name": where, "kind": "strut", "mesh": mesh})
    if "mount_radius" in tbl:
        mount = chk.number(tbl, "mount_radius", "rig", lo=rig.R)
        parts.append({"name": "rig.mount", "kind": "mount", "mesh": _flanges(mount, rig)})
    for k, part in enumerate(parts):
        part["id"] = first_id + k
    return parts


def _struts(count, radius, width, azimuth, z_lo, z_hi):
    rods = []
    for k in range(count):
        a = azimuth + 2 * np.pi * k / count
        rod = geometry.cylinder(width / 2, z_hi - z_lo, sections=_SECTIONS, caps=True)
        rod.apply_translation([radius * np.cos(a), radius * np.sin(a), (z_lo + z_hi) / 2])
        rods.append(rod)
    return _concatenate(rods)


def _flanges(mount_radius: float, rig: Rig):
    discs = []
    for base in (rig.R, rig.s + rig.R):  # cam2's and cam1's mirror base planes
        disc = geometry.cylinder(mount_radius, FLANGE_THICKNESS, sections=4 * _SECTIONS)
        disc.apply_translation([0.0, 0.0, base + FLANGE_THICKNESS / 2])
        discs.append(disc)
    return _concatenate(discs)


def _concatenate(meshes):
    """One textured mesh of several, keeping UVs and shading normals."""
    verts, faces, uvs, normals, offset = [], [], [], [], 0
    for m in meshes:
        verts.append(np.asarray(m.vertices))
        faces.append(np.asarray(m.faces) + offset)
        uvs.append(np.asarray(m.visual.uv))
        normals.append(np.asarray(m.vertex_normals))
        offset += len(m.vertices)
    out = geometry.textured_mesh(np.concatenate(verts), np.concatenate(faces), np.concatenate(uvs))
    out.vertex_normals = np.concatenate(normals)
    return out
