"""The real-world hard cases a toy house can be given, as options (:class:`ToyOptions`).

Each case is a step applied to a generated house, in this order, drawing nothing from the
house's generator (the default house, and the bundled ones, stay the same bytes):

- ``room_rugs``: every room's rugs give way to one rug 1 mm thick covering its floor but a
  5 cm margin (≥ 90 % of the floor: SUNCG's room-sized floor_mat);
- ``two_levels``: a second storey, a copy of the first (room ids ``<id>_l1``), its floor
  slab on the ceiling slab below, joined to the first by a straight stair of solid steps
  in a corner of the living room (or the next room whose corners are clear of doors), under a hole through the ceiling and the floor above;
  furniture in the stair's way is left out;
- ``hidden_floor``: the floor of the last room of the first level is left out (SUNCG's
  ``hideFloor``), ``hidden_ceiling``: the ceiling of the first room of the top level.

How a house looks when it comes from a download (one merged envelope, generic object
names, plants) is a matter of how it is written: :func:`sceneforge.testing.scenes.as_downloaded`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np

from ...conventions import NYU40_IDS, NYU40_NAMES
from ..model import House, Level, Material, Room, make_instance
from .colours import PALETTE, instance_colour
from .planner import CEILING_THICKNESS, FLOOR_THICKNESS, Opening
from .primitives import box, mesh

__all__ = ["ToyOptions", "apply_hard_cases"]

_RUG_MARGIN = 0.05
_STAIR_WIDTH = 0.9
_STAIR_RISE = 0.25  # at most; the steps share the storey height equally
_STAIR_TREAD = 0.2
_DOOR_CLEARANCE = 0.9  # no stair within this of a door or window opening


@dataclass(frozen=True)
class ToyOptions:
    """The hard cases of a toy house (module doc); all off gives the default house."""

    #: one rug covering >= 90 % of every room's floor, in place of the room's rugs
    room_rugs: bool = False
    #: a second storey joined to the first by stairs
    two_levels: bool = False
    #: no floor in the last room of the first level
    hidden_floor: bool = False
    #: no ceiling in the first room of the top level
    hidden_ceiling: bool = False

    @property
    def any(self) -> bool:
        return any(getattr(self, f.name) for f in fields(self))


def apply_hard_cases(toy, options: ToyOptions, rng: np.random.Generator):
    """The :class:`~sceneforge.houses.toy.ToyHouse` ``toy`` with the cases ``options`` asks for.

    ``rng`` jitters the colours of new instances (so that every instance keeps a colour of
    its own); the geometry draws nothing from it.
    """
    parts = [_Item.of(i) for i in toy.house.instances]
    rooms = list(toy.house.rooms)
    levels = list(toy.house.levels)
    interiors = dict(toy.interiors)
    openings = list(toy.openings)
    if options.room_rugs:
        parts = _room_rugs(parts, interiors)
    if options.two_levels:
        parts, rooms, levels, interiors, openings = _two_levels(parts, rooms, interiors, openings)
    if options.hidden_floor:
        last = [r.id for r in rooms if r.level == levels[0].id][-1]
        parts = [p for p in parts if not (p.room_id == last and p.category == NYU40_IDS["floor"])]
    if options.hidden_ceiling:
        first = next(r.id for r in rooms if r.level == levels[-1].id)
        parts = [p for p in parts if not (p.room_id == first and p.category == NYU40_IDS["ceiling"])]
    used = {p.material.base_color[:3] for p in parts if p.material is not None}
    house = House(id=toy.house.id, instances=[], rooms=rooms, levels=levels,
                  source_format=toy.house.source_format, source_path=toy.house.source_path)
    for p in parts:
        family = NYU40_NAMES[p.category] if NYU40_NAMES[p.category] in PALETTE else "otherprop"
        material = p.material or Material(base_color=instance_colour(rng, family, used))
        make_instance(house, name=p.name, category=p.category, label=p.label, room_id=p.room_id,
                      vertices=p.vertices, faces=p.faces, material=material)
    kept = {i.name for i in house.instances}
    return replace(
        toy, house=house, openings=openings, interiors=interiors,
        supports=[s for s in toy.supports if s[0] in kept and s[1] in kept],
        tucked=[t for t in toy.tucked if t[0] in kept and t[1] in kept],
    )


@dataclass
class _Item:
    """An instance while the cases rework the house (ids are given when it is rebuilt);
    ``material`` None: a new instance, coloured then."""

    name: str
    category: int
    label: str
    room_id: str
    vertices: np.ndarray
    faces: np.ndarray
    material: Material | None

    @classmethod
    def of(cls, inst) -> "_Item":
        return cls(inst.name, inst.category, inst.label, inst.room_id, inst.vertices, inst.faces, inst.material)

    def bounds(self) -> np.ndarray:
        return np.stack([self.vertices.min(0), self.vertices.max(0)])


def _new(name: str, category: str, label: str, room_id: str, parts) -> _Item:
    v, f = mesh(parts)
    return _Item(name, NYU40_IDS[category], label, room_id, v, f, None)


def _room_rugs(parts: list[_Item], interiors: dict) -> list[_Item]:
    out = [p for p in parts if p.category != NYU40_IDS["floor_mat"]]
    for room_id, (lo, hi) in interiors.items():
        m = _RUG_MARGIN
        out.append(_new(f"{room_id}/room_rug_0", "floor_mat", "rug", room_id,
                        [box(lo[0] + m, lo[1], lo[2] + m, hi[0] - m, lo[1] + 0.001, hi[2] - m)]))
    return out


def _two_levels(parts, rooms, interiors, openings):
    storey = max(hi[1] for _, hi in interiors.values()) + CEILING_THICKNESS + FLOOR_THICKNESS
    up = {r.id: f"{r.id}_l1" for r in rooms}
    upper = []
    for p in parts:
        room, _, rest = p.name.partition("/")
        upper.append(replace(p, name=f"{up[room]}/{rest}", room_id=up[p.room_id],
                             vertices=p.vertices + (0.0, storey, 0.0), material=None))
    for room in rooms:  # the living room first
        stair_room = room.id
        lo, hi = interiors[stair_room]
        place = _stair_footprint(lo, hi, storey, parts, stair_room, openings)
        if place is not None:
            break
    else:
        raise ValueError("toy house: no corner of any room takes a stair clear of the doors")
    (sx0, sz0, sx1, sz1), axis, sign = place
    n = math.ceil(storey / _STAIR_RISE - 1e-9)
    rise = storey / n
    steps = []
    for k in range(n):
        a = k * _STAIR_TREAD
        if axis == 2:
            z0, z1 = (sz0 + a, sz0 + a + _STAIR_TREAD) if sign > 0 else (sz1 - a - _STAIR_TREAD, sz1 - a)
            steps.append(box(sx0, 0.0, z0, sx1, round((k + 1) * rise, 6), z1))
        else:
            x0, x1 = (sx0 + a, sx0 + a + _STAIR_TREAD) if sign > 0 else (sx1 - a - _STAIR_TREAD, sx1 - a)
            steps.append(box(x0, 0.0, sz0, x1, round((k + 1) * rise, 6), sz1))
    hole = (sx0, sz0, sx1, sz1)
    out = []
    for p in parts + upper:
        b = p.bounds()
        over = b[0, 0] < hole[2] and hole[0] < b[1, 0] and b[0, 2] < hole[3] and hole[1] < b[1, 2]
        if p.room_id in (stair_room, up[stair_room]) and over:
            is_ceiling = p.category == NYU40_IDS["ceiling"] and p.room_id == stair_room
            is_floor = p.category == NYU40_IDS["floor"] and p.room_id == up[stair_room]
            if is_ceiling or is_floor:
                out.append(replace(p, **_slab_with_hole(b, hole)))
            elif p.category in (NYU40_IDS["wall"], NYU40_IDS["floor"], NYU40_IDS["ceiling"]):
                out.append(p)
            continue  # furniture in the stair's way, or above its hole
        out.append(p)
    out.append(_new(f"{stair_room}/stairs_0", "otherstructure", "stairs", stair_room, steps))
    new_rooms = rooms + [Room(up[r.id], r.type, 1) for r in rooms]
    levels = [Level(0, 0.0), Level(1, round(storey, 6))]
    new_interiors = dict(interiors)
    for rid, (a, b) in interiors.items():
        new_interiors[up[rid]] = ((a[0], a[1] + storey, a[2]), (b[0], b[1] + storey, b[2]))
    new_openings = openings + [
        Opening(o.kind, tuple(up[r] for r in o.rooms), o.axis, (o.lo[0], o.lo[1] + storey, o.lo[2]),
                (o.hi[0], o.hi[1] + storey, o.hi[2])) for o in openings]
    return out, new_rooms, levels, new_interiors, new_openings


def _stair_footprint(lo, hi, storey, parts, room_id, openings):
    """((x0, z0, x1, z1), run axis, run sign) of the stair in a corner of the room: the first
    corner clear of every door, fewest pieces of furniture in the way first; None when
    every corner is in a door's way."""
    run = math.ceil(storey / _STAIR_RISE - 1e-9) * _STAIR_TREAD
    furniture = [p.bounds() for p in parts if p.room_id == room_id and not _is_structure(p)]
    best = None
    for axis in (2, 0):
        for cx in (0, 1):
            for cz in (0, 1):
                w, d = (_STAIR_WIDTH, run) if axis == 2 else (run, _STAIR_WIDTH)
                x0 = lo[0] if cx == 0 else hi[0] - w
                z0 = lo[2] if cz == 0 else hi[2] - d
                rect = (x0, z0, x0 + w, z0 + d)
                if rect[2] > hi[0] or rect[3] > hi[2]:
                    continue
                c = _DOOR_CLEARANCE
                if any(o.lo[0] - c < rect[2] and rect[0] < o.hi[0] + c and o.lo[2] - c < rect[3]
                       and rect[1] < o.hi[2] + c for o in openings if o.kind != "window"):
                    continue
                blocked = sum(b[0, 0] < rect[2] and rect[0] < b[1, 0] and b[0, 2] < rect[3] and rect[1] < b[1, 2]
                              for b in furniture)
                sign = 1 if (cz == 0 if axis == 2 else cx == 0) else -1
                if best is None or blocked < best[0]:
                    best = (blocked, tuple(round(float(x), 6) for x in rect), axis, sign)
    return None if best is None else best[1:]


def _is_structure(p: _Item) -> bool:
    return p.category in (NYU40_IDS["wall"], NYU40_IDS["floor"], NYU40_IDS["ceiling"], NYU40_IDS["door"],
                          NYU40_IDS["window"])


def _slab_with_hole(bounds: np.ndarray, hole) -> dict:
    """Vertices and faces of the slab box ``bounds`` (2, 3) with the rectangle ``hole``
    (x0, z0, x1, z1) cut out (the hole's sides clipped to the slab)."""
    (x0, y0, z0), (x1, y1, z1) = bounds
    hx0, hz0, hx1, hz1 = max(hole[0], x0), max(hole[1], z0), min(hole[2], x1), min(hole[3], z1)
    pieces = [(x0, z0, x1, hz0), (x0, hz1, x1, z1), (x0, hz0, hx0, hz1), (hx1, hz0, x1, hz1)]
    v, f = mesh([box(a, y0, b, c, y1, d) for a, b, c, d in pieces if c - a > 1e-9 and d - b > 1e-9])
    return {"vertices": v, "faces": f}
