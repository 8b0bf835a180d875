"""Triangle meshes with per-vertex UVs for scene objects (trimesh, no renderer).

Every builder returns a :class:`trimesh.Trimesh` made with ``process=False``
(vertices are duplicated along UV seams and creases on purpose: do not merge
them) whose ``visual`` is a ``TextureVisuals`` holding ``uv`` of shape
(n_vertices, 2). UVs are in tiles: u = (surface coordinate in metres) / tile,
so a texture that covers ``tile`` metres maps at its true size and repeats
(see :mod:`omnisim.textures` for the texel convention).

Shading normals: ``mesh.vertex_normals`` are the exact surface normals for the
cylinder's side and caps and the sphere (smooth shading of the facets); flat
faces have their vertices split, so their vertex normals are the face normals.

Orientation: faces are counter-clockwise seen from the side their normal
points to. Closed primitives (box, cylinder, sphere) have outward normals; the
room's floor, ceiling and walls have normals pointing INTO the room, so a ray
from a rig inside the room meets their front faces. (Materials are also
two-sided by default, see :mod:`omnisim.scene`, so a renderer that honours
``two_sided`` shades either side.)

Object frames: box, cylinder and sphere are centred on the origin with the
cylinder's axis along Z; a plane lies in z = 0 centred on the origin with its
normal +Z; the room's origin is the centre of its floor, walls at
x = +-size_x / 2, y = +-size_y / 2, floor at z = 0 and ceiling at z = size_z.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from numpy.typing import NDArray

__all__ = [
    "ROOM_PARTS",
    "box",
    "box_project_uv",
    "cylinder",
    "load_mesh_file",
    "plane",
    "room",
    "sphere",
    "test_card",
    "textured_mesh",
]

#: The parts of a room, in the order their object ids are given.
ROOM_PARTS = ("floor", "ceiling", "wall_xp", "wall_xn", "wall_yp", "wall_yn")

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")


def textured_mesh(vertices: NDArray, faces: NDArray, uv: NDArray) -> trimesh.Trimesh:
    """A Trimesh with per-vertex UVs, kept exactly as given (no vertex merging)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    uv = np.asarray(uv, dtype=np.float64)
    if uv.shape != (len(vertices), 2):
        raise ValueError(f"uv has shape {uv.shape}: expected ({len(vertices)}, 2)")
    visual = trimesh.visual.TextureVisuals(uv=uv)
    return trimesh.Trimesh(vertices=vertices, faces=faces, visual=visual, process=False)


def _grid(points: NDArray, uv: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Triangulate a (ni+1, nj+1) grid of points; the normal is d/di x d/dj.

    Zero-area triangles (at a sphere's poles) are dropped.
    """
    ni, nj = points.shape[0] - 1, points.shape[1] - 1
    idx = np.arange((ni + 1) * (nj + 1)).reshape(ni + 1, nj + 1)
    p00, p10 = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    p11, p01 = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([p00, p10, p11], 1), np.stack([p00, p11, p01], 1)])
    verts = points.reshape(-1, 3)
    tri = verts[faces]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    faces = faces[area2 > 1e-12 * max(1.0, float(np.abs(verts).max()) ** 2)]
    return verts, uv.reshape(-1, 2), faces


def _quad(origin, a, b, tile: float) -> tuple[NDArray, NDArray, NDArray]:
    """One parallelogram origin + [0, 1] a + [0, 1] b, normal along a x b, UVs in metres / tile."""
    origin, a, b = (np.asarray(x, dtype=float) for x in (origin, a, b))
    s = np.array([0.0, 1.0])
    i, j = np.meshgrid(s, s, indexing="ij")
    pts = origin + i[..., None] * a + j[..., None] * b
    uv = np.stack([i * np.linalg.norm(a), j * np.linalg.norm(b)], axis=-1) / tile
    return _grid(pts, uv)


def _join(parts) -> trimesh.Trimesh:
    verts, uvs, faces, offset = [], [], [], 0
    for v, uv, f in parts:
        verts.append(v)
        uvs.append(uv)
        faces.append(f + offset)
        offset += len(v)
    return textured_mesh(np.concatenate(verts), np.concatenate(faces), np.concatenate(uvs))


def plane(size, *, tile: float = 1.0) -> trimesh.Trimesh:
    """A rectangle size[0] x size[1] in z = 0, centred, normal +Z."""
    sx, sy = (float(x) for x in size)
    return _join([_quad((-sx / 2, -sy / 2, 0), (sx, 0, 0), (0, sy, 0), tile)])


def box(size, *, tile: float = 1.0) -> trimesh.Trimesh:
    """An axis-aligned box of the given (x, y, z) size, centred, outward normals."""
    hx, hy, hz = (float(x) / 2 for x in size)
    x, y, z = np.eye(3)
    faces = [
        ((hx, -hy, -hz), 2 * hy * y, 2 * hz * z),  # +X
        ((-hx, hy, -hz), -2 * hy * y, 2 * hz * z),  # -X
        ((hx, hy, -hz), -2 * hx * x, 2 * hz * z),  # +Y
        ((-hx, -hy, -hz), 2 * hx * x, 2 * hz * z),  # -Y
        ((-hx, -hy, hz), 2 * hx * x, 2 * hy * y),  # +Z
        ((-hx, hy, -hz), 2 * hx * x, -2 * hy * y),  # -Z
    ]
    return _join([_quad(o, a, b, tile) for o, a, b in faces])


def room(size, *, tile: float = 1.0) -> dict[str, trimesh.Trimesh]:
    """Floor, ceiling and four walls of a box room, normals pointing inwards.

    Keys are :data:`ROOM_PARTS`. Wall UVs: u runs along the wall, v up it.
    """
    sx, sy, sz = (float(v) for v in size)
    hx, hy = sx / 2, sy / 2
    x, y, z = np.eye(3)
    spec = {
        "floor": ((-hx, -hy, 0), sx * x, sy * y),
        "ceiling": ((-hx, hy, sz), sx * x, -sy * y),
        "wall_xp": ((hx, hy, 0), -sy * y, sz * z),
        "wall_xn": ((-hx, -hy, 0), sy * y, sz * z),
        "wall_yp": ((-hx, hy, 0), sx * x, sz * z),
        "wall_yn": ((hx, -hy, 0), -sx * x, sz * z),
    }
    return {name: _join([_quad(o, a, b, tile)]) for name, (o, a, b) in spec.items()}


def _repeats(length: float, tile: float) -> int:
    """Whole texture repeats around a closed loop of the given length (no seam)."""
    return max(1, round(length / tile))


def cylinder(
    radius: float, height: float, *, tile: float = 1.0, sections: int = 96, caps: bool = True
) -> trimesh.Trimesh:
    """A cylinder about Z, centred, outward normals, ``sections`` facets around.

    Side UVs: u = angle / 2 pi times a whole number of repeats (about the
    circumference / tile), v = (z + height / 2) / tile. Caps are mapped
    planarly.
    """
    th = np.linspace(0.0, 2 * np.pi, sections + 1)
    zs = np.array([-height / 2, height / 2])
    t, zz = np.meshgrid(th, zs, indexing="ij")
    pts = np.stack([radius * np.cos(t), radius * np.sin(t), zz], axis=-1)
    n_rep = _repeats(2 * np.pi * radius, tile)
    uv = np.stack([t / (2 * np.pi) * n_rep, (zz + height / 2) / tile], axis=-1)
    parts = [_grid(pts, uv)]
    if caps:
        ring = np.stack([radius * np.cos(th[:-1]), radius * np.sin(th[:-1])], axis=-1)
        k = np.arange(sections)
        fan = np.stack([np.zeros(sections, int), 1 + k, 1 + (k + 1) % sections], axis=1)
        for zc, flip in ((height / 2, False), (-height / 2, True)):
            v = np.concatenate([[[0.0, 0.0, zc]], np.column_stack([ring, np.full(sections, zc)])])
            cap_uv = (v[:, :2] + radius) / tile
            parts.append((v, cap_uv, fan[:, ::-1] if flip else fan))
    mesh = _join(parts)
    # Smooth shading normals: radial on the side, +-Z on the caps (the side comes first).
    normals = np.zeros_like(mesh.vertices)
    side = len(parts[0][0])
    normals[:side, :2] = mesh.vertices[:side, :2] / radius
    normals[side:, 2] = np.sign(mesh.vertices[side:, 2])
    mesh.vertex_normals = normals
    return mesh


def test_card(card, *, sections: int = 1440) -> trimesh.Trimesh:
    """The tube of a registration card (``omniflow.geometry.test_card.TestCard``), open.

    Centred, axis along Z, outward normals; UVs from ``card.uv`` so the card's one-tile
    texture repeats as its checkerboard (a sector edge at every 2 pi / sectors, a ring
    edge every ``ring_spacing``). 1440 facets: the flat facets lie within
    radius (1 - cos(pi / 1440)) = 1.2 um of the tube at r = 0.5 m.
    """
    th = np.linspace(0.0, 2 * np.pi, sections + 1)
    zs = np.array([-card.height / 2, card.height / 2])
    t, zz = np.meshgrid(th, zs, indexing="ij")
    pts = np.stack([card.radius * np.cos(t), card.radius * np.sin(t), zz], axis=-1)
    u, v = card.uv(t, zz)
    mesh = _join([_grid(pts, np.stack([u, v], axis=-1))])
    normals = np.zeros_like(mesh.vertices)
    normals[:, :2] = mesh.vertices[:, :2] / card.radius
    mesh.vertex_normals = normals
    return mesh


def sphere(radius: float, *, tile: float = 1.0, sections: int = 96) -> trimesh.Trimesh:
    """A UV sphere, centred, outward normals; u around (whole repeats), v along meridians."""
    rings = max(4, sections // 2)
    th = np.linspace(0.0, 2 * np.pi, sections + 1)
    ph = np.linspace(np.pi, 0.0, rings + 1)  # polar angle from +Z: south pole first
    t, p = np.meshgrid(th, ph, indexing="ij")
    pts = radius * np.stack([np.sin(p) * np.cos(t), np.sin(p) * np.sin(t), np.cos(p)], axis=-1)
    n_rep = _repeats(2 * np.pi * radius, tile)
    uv = np.stack([t / (2 * np.pi) * n_rep, (np.pi - p) * radius / tile], axis=-1)
    mesh = _join([_grid(pts, uv)])
    mesh.vertex_normals = mesh.vertices / radius  # smooth shading normals, exact
    return mesh


def box_project_uv(mesh: trimesh.Trimesh, *, tile: float = 1.0) -> trimesh.Trimesh:
    """Give a mesh UVs by box projection: each face takes the plane its normal is nearest.

    Vertices are split per face (so no UV seam is interpolated across); UVs
    are the two other coordinates in metres / tile.
    """
    tri = mesh.vertices[mesh.faces]  # (F, 3, 3)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    axis = np.argmax(np.abs(normals), axis=1)
    others = np.array([[1, 2], [0, 2], [0, 1]])[axis]  # (F, 2)
    uv = np.take_along_axis(tri, np.repeat(others[:, None, :], 3, axis=1), axis=2) / tile
    verts = tri.reshape(-1, 3)
    faces = np.arange(len(verts)).reshape(-1, 3)
    return textured_mesh(verts, faces, uv.reshape(-1, 2))


def load_mesh_file(
    path: str | Path,
    *,
    scale=1.0,
    uv: str = "auto",
    tile: float = 1.0,
    center: bool = False,
) -> trimesh.Trimesh:
    """Read a mesh file (OBJ, PLY, STL, GLB, ...) as one Trimesh with per-vertex UVs.

    ``scale`` (a number or three) multiplies the file's coordinates (metres
    after scaling); ``center`` moves the bounding-box centre to the origin.
    ``uv``: ``"file"`` keeps the file's UVs (error if it has none),
    ``"box"`` replaces them by :func:`box_project_uv`, ``"auto"`` keeps them
    when present and box-projects otherwise. Raises ValueError on an
    unreadable or empty mesh.
    """
    path = Path(path)
    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for bad files
        raise ValueError(f"{path}: could not read a mesh: {exc}") from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ValueError(f"{path}: no triangles in the file")
    mesh = loaded
    scale_v = np.broadcast_to(np.asarray(scale, dtype=float), (3,))
    verts = np.asarray(mesh.vertices, dtype=float) * scale_v
    if center:
        lo, hi = verts.min(axis=0), verts.max(axis=0)
        verts = verts - (lo + hi) / 2
    if not np.all(np.isfinite(verts)):
        raise ValueError(f"{path}: non-finite vertex coordinates")
    file_uv = getattr(mesh.visual, "uv", None)
    has_uv = file_uv is not None and len(file_uv) == len(verts)
    if uv == "file" and not has_uv:
        raise ValueError(f"{path}: the file has no texture coordinates (uv = 'file')")
    scaled = trimesh.Trimesh(vertices=verts, faces=np.asarray(mesh.faces), process=False)
    if uv in ("file", "auto") and has_uv:
        return textured_mesh(verts, np.asarray(mesh.faces), np.asarray(file_uv, dtype=float))
    return box_project_uv(scaled, tile=tile)
