"""The floors of a house: where sampled cameras stand and where a view's heights start.

A floor *surface* is the set of up-facing, near-horizontal faces of a floor instance
(NYU40 ``floor``): the top a person stands on, not a floor slab's underside or its sides.
A floor whose horizontal faces all face down has its winding flipped; those faces are
used instead. Heights are read from these faces themselves, never from a bounding box:
a SUNCG level's ``floor_y`` is the bottom of its bounding box, the underside of a 5 cm
slab, while the floor a camera stands on is the slab's top.

Each floor triangle belongs to a room (its instance's ``room_id``) and a level: its room's
level, or, for a floor without a known room, the highest level whose ``floor_y`` is at most
``tol.level_floor`` above the triangle (:func:`level_at`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .conventions import NYU40_IDS, tol

if TYPE_CHECKING:
    from .houses.model import House, Level

FLOOR = NYU40_IDS["floor"]


def level_at(house: "House", y: float) -> "Level":
    """The storey a point at height ``y`` is on: the level with the highest ``floor_y`` at or
    below ``y`` (the lowest level when ``y`` is below all of them)."""
    levels = sorted(house.levels, key=lambda lv: lv.floor_y)
    below = [lv for lv in levels if lv.floor_y <= y]
    return below[-1] if below else levels[0]


@dataclass(frozen=True, eq=False)
class FloorSurfaces:
    """The walkable floor triangles of a house.

    corners  : (m, 3, 3) float64  triangle corners, world, counter-clockwise seen from above
    area     : (m,) float64       triangle areas, m²
    top      : (m,) float64       highest corner y of each triangle (its height when flat)
    instance : (m,) int64         index of the triangle's floor instance in ``house.instances``
    room     : (m,) object        room id of that instance (None: no room)
    level    : (m,) int64         level id of the triangle
    """

    corners: np.ndarray
    area: np.ndarray
    top: np.ndarray
    instance: np.ndarray
    room: np.ndarray
    level: np.ndarray

    def __len__(self) -> int:
        return len(self.area)

    def subset(self, keep: np.ndarray) -> "FloorSurfaces":
        """The triangles where ``keep`` ((m,) bool or indices) selects them."""
        return FloorSurfaces(self.corners[keep], self.area[keep], self.top[keep], self.instance[keep],
                             self.room[keep], self.level[keep])

    def height_below(self, point) -> float | None:
        """World height of the floor straight below ``point`` ((3,) world), or None.

        The floor triangles whose footprint (x, z) contains the point (edges included) are
        intersected with the vertical line through it; the highest intersection at most
        ``tol.eye_above_floor`` above the point is the floor it stands over. A flat
        triangle gives its corners' y exactly.
        """
        p = np.asarray(point, dtype=np.float64).reshape(3)
        if not len(self):
            return None
        a, b, c = self.corners[:, 0], self.corners[:, 1], self.corners[:, 2]
        inside = _footprint_contains(a, b, c, p)
        if not inside.any():
            return None
        a, b, c = a[inside], b[inside], c[inside]
        n = np.cross(b - a, c - a)
        # On the face's plane; n_x = n_z = 0 exactly for a flat face, so y is a's y exactly.
        y = a[:, 1] - (n[:, 0] * (p[0] - a[:, 0]) + n[:, 2] * (p[2] - a[:, 2])) / n[:, 1]
        y = y[y <= p[1] + tol.eye_above_floor]
        return float(y.max()) if len(y) else None

    def level_height(self, level: int, below: float) -> float | None:
        """The floor height of level ``level`` for a point at height ``below``: the
        area-weighted median top of the level's floor triangles at most
        ``tol.eye_above_floor`` above that point, or None when it has none."""
        keep = (self.level == level) & (self.top <= below + tol.eye_above_floor)
        if not keep.any():
            return None
        top, area = self.top[keep], self.area[keep]
        order = np.argsort(top, kind="stable")
        cumulative = np.cumsum(area[order])
        return float(top[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])


def _footprint_contains(a: np.ndarray, b: np.ndarray, c: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(m,) bool: the (x, z) footprint of triangles (a, b, c), each (m, 3), contains p's (x, z).

    Barycentric coordinates in the x–z plane, each at least ``-tol.floor_footprint``: a point
    on an edge shared by two triangles is inside both, never neither.
    """
    ax, az = a[:, 0], a[:, 2]
    e1x, e1z = b[:, 0] - ax, b[:, 2] - az
    e2x, e2z = c[:, 0] - ax, c[:, 2] - az
    px, pz = p[0] - ax, p[2] - az
    det = e1x * e2z - e1z * e2x
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (px * e2z - pz * e2x) / det
        v = (e1x * pz - e1z * px) / det
    slack = tol.floor_footprint
    return (det != 0) & (u >= -slack) & (v >= -slack) & (u + v <= 1 + slack)


def floor_surfaces(house: "House") -> FloorSurfaces:
    """The walkable floor triangles of ``house`` (see the module docstring); empty when it
    has no floor instance or none with a horizontal face."""
    room_level = {r.id: r.level for r in house.rooms}
    corners, instance, rooms = [], [], []
    for k, inst in enumerate(house.instances):
        if inst.category != FLOOR:
            continue
        t = inst.vertices[inst.faces]
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        length = np.linalg.norm(n, axis=1)
        up = n[:, 1] > tol.floor_face_cos * length
        down = -n[:, 1] > tol.floor_face_cos * length
        # A flipped floor: its horizontal faces seen from above run clockwise; reorder them.
        t = t[up] if up.any() else t[down][:, ::-1]
        corners.append(t)
        instance.append(np.full(len(t), k, dtype=np.int64))
        rooms += [inst.room_id] * len(t)
    if not corners:
        corners, instance = [np.zeros((0, 3, 3))], [np.zeros(0, dtype=np.int64)]
    tris = np.concatenate(corners)
    area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    top = tris[:, :, 1].max(axis=1) if len(tris) else np.zeros(0)
    room = np.empty(len(tris), dtype=object)
    room[:] = rooms
    level = np.array([room_level[r] if r in room_level else level_at(house, y + tol.level_floor).id
                      for r, y in zip(rooms, top)], dtype=np.int64)
    return FloorSurfaces(tris, area, top, np.concatenate(instance), room, level)
