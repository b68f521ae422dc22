"""Rooms and levels derived from the floors, for scenes that have none (glTF, OBJ, PLY).

The rule (:func:`derive_rooms`):

- a **room** is a connected floor region: the faces of the ``floor`` instances, joined where
  they share a vertex (positions equal to 1 mm, within one instance) and, across instances,
  where two regions overlap with some area at about the same height (``same_floor``).
  Two floors that only touch along an edge (two rooms' slabs meeting under a wall) stay two
  rooms;
- a region's floor height is its highest point (the top of a slab); regions form **levels**
  from the lowest up, a new level starting where a floor is more than ``level_gap`` above
  the first floor of the current level; a level's ``floor_y`` is its lowest floor;
- every other instance goes to a room of its level (the highest level whose floor is at
  most 5 cm above the instance's lowest point) by **footprint**: the room
  whose floor lies under most of its sample points (up to 64 vertices and the centre of
  its bounding box, seen from above); one under none goes to the nearest room of the level
  (distance from its centre to the room floor's bounding box). Floors go to their own region.

Rooms are numbered ``room_0``, ``room_1``, ... by level, then by the lowest x and z of their
floor, so the same scene always gets the same rooms.
"""

from __future__ import annotations

import numpy as np

from ..conventions import NYU40_IDS
from ..errors import HouseError, listed
from .model import House, Level, Room

__all__ = ["derive_rooms", "points_in_triangles"]

_FLOOR = NYU40_IDS["floor"]
_WELD = 1e-3  # vertex positions equal to 1 mm are one vertex
_SAMPLES = 64
# how far below a level's floor an instance's lowest point may be and still stand on it
# (legs sunk into a rug, a slab's rounding)
_CONTACT = 0.05


def points_in_triangles(points: np.ndarray, triangles: np.ndarray, *, strict: bool = False,
                        chunk: int = 4096) -> np.ndarray:
    """Which 2D points lie inside (or, unless ``strict``, on the edge of) any of the triangles.

    points    : (p, 2) float
    triangles : (t, 3, 2) float   any winding; degenerate triangles contain nothing
    returns   : (p,) bool
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    tri = np.asarray(triangles, dtype=np.float64).reshape(-1, 3, 2)
    inside = np.zeros(len(pts), dtype=bool)
    p = pts[:, None]  # (p, 1, 2)
    for s in range(0, len(tri), chunk):
        a, b, c = (tri[s:s + chunk, k][None] for k in range(3))  # (1, t, 2)
        d1, d2, d3 = _cross(a, b, p), _cross(b, c, p), _cross(c, a, p)
        area = _cross(a, b, c)
        if strict:
            pos, neg = (d1 > 0) & (d2 > 0) & (d3 > 0), (d1 < 0) & (d2 < 0) & (d3 < 0)
        else:
            pos, neg = (d1 >= 0) & (d2 >= 0) & (d3 >= 0), (d1 <= 0) & (d2 <= 0) & (d3 <= 0)
        inside |= ((pos | neg) & (area != 0)).any(1)
    return inside


def _cross(u: np.ndarray, w: np.ndarray, q: np.ndarray) -> np.ndarray:
    """z of (w - u) × (q - u) for 2D points: > 0 when q is left of the line u → w."""
    return (w[..., 0] - u[..., 0]) * (q[..., 1] - u[..., 1]) - (w[..., 1] - u[..., 1]) * (q[..., 0] - u[..., 0])


def _vertex_components(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m,) int component label of every face: faces sharing a (welded) vertex are one."""
    _, weld = np.unique(np.round(vertices / _WELD).astype(np.int64), axis=0, return_inverse=True)
    f = weld.reshape(-1)[faces]
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]]])
    label = np.arange(int(f.max()) + 1)
    while True:
        a, b = label[edges[:, 0]], label[edges[:, 1]]
        low = np.minimum(a, b)
        new = label.copy()
        for ends in (edges[:, 0], edges[:, 1], a, b):
            np.minimum.at(new, ends, low)
        while not np.array_equal(new, new[new]):
            new = new[new]
        if np.array_equal(new, label):
            break
        label = new
    return label[f[:, 0]]


class _Region:
    """A connected floor region: its height and its triangles seen from above."""

    def __init__(self, owner: int, tri: np.ndarray):
        self.owners = [owner]
        self.top = float(tri[..., 1].max())
        xz = tri[..., [0, 2]]
        e1, e2 = xz[:, 1] - xz[:, 0], xz[:, 2] - xz[:, 0]
        # the faces seen edge-on from above (a slab's sides) cover nothing
        self.xz = xz[np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) > 1e-12]  # (t, 3, 2)
        self.level = 0

    def overlaps(self, other: "_Region", same_floor: float) -> bool:
        """True when the two overlap with some area (touching along an edge is not enough)."""
        if abs(self.top - other.top) > same_floor:
            return False
        a, b = self.xz, other.xz
        return bool(points_in_triangles(a.mean(1), b, strict=True).any()
                    or points_in_triangles(b.mean(1), a, strict=True).any())


def derive_rooms(house: House, *, level_gap: float = 1.0, same_floor: float = 0.3) -> House:
    """Give a house without rooms rooms and levels from its floors (module doc); returns it.

    A house that has rooms, or no floor instance, is returned unchanged (``houses inspect``
    reports the second). A floor region seen edge-on from above (its faces all vertical)
    covers nothing and makes no room; when no floor region is left, the floors stand on
    their edges, as in a Z-up scene read +Y up: :class:`HouseError` says so.
    """
    if house.rooms:
        return house
    floors = [i for i in house.instances if i.category == _FLOOR]
    regions: list[_Region] = []
    for inst in floors:
        label = _vertex_components(inst.vertices, inst.faces)
        for comp in np.unique(label):
            region = _Region(inst.id, inst.vertices[inst.faces[label == comp]])
            if len(region.xz):
                regions.append(region)
    if floors and not regions:
        raise HouseError(house.id, house.source_path,
                         f"the floors ({listed([repr(i.name) for i in floors], 3)}) are vertical, with no "
                         "area seen from above: the up axis is wrong; pass --up-axis y or --up-axis z")
    if not regions:
        return house
    regions = _merge_overlapping(regions, same_floor)
    regions.sort(key=lambda r: r.top)
    level_floors: list[float] = []
    for r in regions:
        if not level_floors or r.top - level_floors[-1] > level_gap:
            level_floors.append(r.top)
        r.level = len(level_floors) - 1
    regions.sort(key=lambda r: (r.level, *np.round(r.xz.reshape(-1, 2).min(0), 3)))
    house.levels = [Level(k, y) for k, y in enumerate(level_floors)]
    house.rooms = [Room(f"room_{k}", "", r.level) for k, r in enumerate(regions)]
    floor_room = {}
    for k, r in enumerate(regions):
        for owner in r.owners:  # a floor spanning several regions goes to its largest
            if owner not in floor_room or len(r.xz) > len(regions[floor_room[owner]].xz):
                floor_room[owner] = k
    for inst in house.instances:
        k = floor_room.get(inst.id)
        if k is None:
            k = _room_by_footprint(inst.vertices, regions, level_floors)
        inst.room_id = house.rooms[k].id
    return house


def _merge_overlapping(regions: list[_Region], same_floor: float) -> list[_Region]:
    """Regions of different instances that overlap at about the same height, made one."""
    merged = True
    while merged:
        merged = False
        for i in range(len(regions)):
            for j in range(i + 1, len(regions)):
                if regions[i].overlaps(regions[j], same_floor):
                    regions[i].owners += regions[j].owners
                    regions[i].xz = np.concatenate([regions[i].xz, regions[j].xz])
                    regions[i].top = max(regions[i].top, regions[j].top)
                    del regions[j]
                    merged = True
                    break
            if merged:
                break
    return regions


def _room_by_footprint(vertices: np.ndarray, regions: list[_Region], level_floors: list[float]) -> int:
    """Index of the region an instance with these (n, 3) vertices stands in (module doc)."""
    bottom = vertices[:, 1].min()
    level = max([k for k, y in enumerate(level_floors) if y <= bottom + _CONTACT], default=0)
    lo, hi = vertices[:, [0, 2]].min(0), vertices[:, [0, 2]].max(0)
    centre = (lo + hi) / 2
    step = max(1, len(vertices) // _SAMPLES)
    samples = np.concatenate([vertices[::step, [0, 2]], centre[None]])
    candidates = [k for k, r in enumerate(regions) if r.level == level]
    votes = [int(points_in_triangles(samples, regions[k].xz).sum()) for k in candidates]
    if max(votes) > 0:
        return candidates[int(np.argmax(votes))]
    distance = []
    for k in candidates:
        flat = regions[k].xz.reshape(-1, 2)
        gap = np.maximum(np.maximum(flat.min(0) - centre, centre - flat.max(0)), 0)
        distance.append(float(np.hypot(*gap)))
    return candidates[int(np.argmin(distance))]
