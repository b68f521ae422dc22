"""Merged envelope meshes ("shells"): one mesh holding a room's walls, floor and ceiling, split
into the three by face orientation and height.

Scenes made in a modelling tool often keep the whole room envelope in one object (``Walls``
with its ceiling, ``room_skeleton``, ``Shell``). A name map sends such names to the
``shell`` target (:mod:`sceneforge.houses.names`) and :func:`split_shell` decides per face:

- a face is **horizontal** when its normal is within ``acos(horizontal_cos)`` of ±Y;
  horizontal faces are grouped by the way they face (up or down) and by height (gaps of
  more than ``height_gap`` separate groups);
- a group is a **floor or ceiling surface** only when it is room-sized: its footprint's
  bounding box is at least ``min_side`` on both sides and it covers at least ``min_cover``
  of the mesh's own footprint box (sampled on a ``grid`` × ``grid`` lattice of points).
  Window sills, the tops of thick walls and lintels stay wall;
- such a group is a **floor** when at least ``room_height`` of the mesh rises above it and
  a **ceiling** when at least ``room_height`` of the mesh lies below it; a group that could
  be both (the slab between two storeys) is a floor when it faces up, a ceiling when it
  faces down;
- every other face is **wall**.

Normals may point into the rooms or out of them: only the slab between two storeys needs
their sign.
"""

from __future__ import annotations

import numpy as np

from .rooms import points_in_triangles

__all__ = ["CEILING", "FLOOR", "PARTS", "WALL", "pieces", "split_shell"]

WALL, FLOOR, CEILING = 0, 1, 2
#: part index → the NYU40 class name it becomes
PARTS = ("wall", "floor", "ceiling")


def split_shell(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    horizontal_cos: float = 0.95,
    height_gap: float = 0.02,
    min_side: float = 1.0,
    min_cover: float = 0.3,
    room_height: float = 1.5,
    grid: int = 32,
) -> np.ndarray:
    """The part of every face of a merged envelope mesh (module doc for the rule).

    vertices : (n, 3) float   world coordinates, metres, +Y up
    faces    : (m, 3) int     indices into ``vertices``
    returns  : (m,) int8      :data:`WALL`, :data:`FLOOR` or :data:`CEILING` per face
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    part = np.full(len(f), WALL, dtype=np.int8)
    if not len(f):
        return part
    tri = v[f]  # (m, 3, 3)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1)
    ny = np.divide(normal[:, 1], length, out=np.zeros(len(f)), where=length > 0)
    horizontal = np.flatnonzero(np.abs(ny) >= horizontal_cos)
    if not len(horizontal):
        return part
    bottom, top = v[:, 1].min(), v[:, 1].max()
    lo, hi = v[:, [0, 2]].min(0), v[:, [0, 2]].max(0)
    steps = (np.arange(grid) + 0.5) / grid
    lattice = np.stack(np.meshgrid(lo[0] + steps * (hi[0] - lo[0]), lo[1] + steps * (hi[1] - lo[1]),
                                   indexing="ij"), -1).reshape(-1, 2)
    for facing in (horizontal[ny[horizontal] > 0], horizontal[ny[horizontal] < 0]):
        if not len(facing):
            continue
        height = tri[facing, :, 1].mean(1)
        order = facing[np.argsort(height, kind="stable")]
        breaks = np.flatnonzero(np.diff(np.sort(height, kind="stable")) > height_gap) + 1
        for group in np.split(order, breaks):
            part[group] = _group_part(tri[group], bool(ny[group[0]] > 0), lattice, bottom, top,
                                      min_side, min_cover, room_height)
    return part


def _group_part(tri: np.ndarray, up: bool, lattice: np.ndarray, bottom: float, top: float,
                min_side: float, min_cover: float, room_height: float) -> int:
    """The part of one group of horizontal faces facing the same way at one height:
    tri (t, 3, 3) float, lattice (g, 2) float the points sampling the mesh's footprint."""
    xz = tri[:, :, [0, 2]]
    extent = xz.reshape(-1, 2).max(0) - xz.reshape(-1, 2).min(0)
    if extent.min() < min_side or points_in_triangles(lattice, xz).mean() < min_cover:
        return WALL
    h = float(tri[..., 1].mean())
    can_floor, can_ceiling = h <= top - room_height, h >= bottom + room_height
    if can_floor and can_ceiling:
        return FLOOR if up else CEILING
    return FLOOR if can_floor else CEILING if can_ceiling else WALL


def pieces(faces: np.ndarray, part: np.ndarray):
    """The parts of a split mesh, each with the vertices its faces use: yields
    ``(name, used, local_faces, mask)`` per part present, in :data:`PARTS` order.

    faces : (m, 3) int     the mesh's faces
    part  : (m,) int8      :func:`split_shell`'s part per face
    name  : str            ``"wall"``, ``"floor"`` or ``"ceiling"``
    used  : (u,) int       the mesh's vertices the part uses (index its per-vertex arrays)
    local_faces : (k, 3) int   the part's faces, indexing ``used``
    mask  : (m,) bool      the part's faces among the mesh's (index its per-face arrays)
    """
    faces = np.asarray(faces).reshape(-1, 3)
    for k, name in enumerate(PARTS):
        mask = part == k
        if mask.any():
            used, local = np.unique(faces[mask], return_inverse=True)
            yield name, used, local.reshape(-1, 3), mask
