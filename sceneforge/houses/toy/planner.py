"""The room planner: a grid of rooms, the doors and windows cut into their walls, and the
furniture placed in each room without overlaps.

:func:`plan_house` draws everything from the one ``rng`` it is given, in a fixed order;
:func:`envelope` gives a planned room's floor, ceiling and walls.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import furniture
from .furniture import Piece, moved_group
from .primitives import EPS, Frame, Part, box, cm, overlaps

#: thickness of the one partition wall between two rooms (both its faces are walls of a room)
PARTITION = 0.1
#: thickness of an exterior wall
EXTERIOR_WALL = 0.2
#: a floor is a slab this thick, closed, so that it has an underside as real floors do
FLOOR_THICKNESS = 0.05
CEILING_THICKNESS = 0.1
_TRIES = 80  # random placements tried before a piece is given up
ROOM_TYPES = ("living_room", "bedroom", "kitchen", "bathroom", "office", "dining_room")


@dataclass(frozen=True)
class Opening:
    """A hole through a wall: an axis-aligned box spanning the whole wall thickness.

    kind     : ``"door"`` (between two rooms, open), ``"front_door"`` (exterior, closed by
               its leaf) or ``"window"`` (exterior, no glass: rays leave the house here)
    rooms    : ids of the rooms whose walls it pierces (two for a door, one otherwise)
    axis     : 0 when the wall's normal is X, 2 when it is Z
    lo, hi   : (3,) float  corners of the hole; ``lo[axis]`` and ``hi[axis]`` are the two
               faces of the wall
    """

    kind: str
    rooms: tuple[str, ...]
    axis: int
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    @property
    def exterior(self) -> bool:
        return self.kind != "door"

    @property
    def passable(self) -> bool:
        """True when a ray can go through (everything but the closed front door)."""
        return self.kind != "front_door"


#: wall side → (b axis, sb, su) of a frame whose back is on that wall, facing the room
_SIDES = {"south": (2, 1, 1), "north": (2, -1, -1), "west": (0, 1, -1), "east": (0, -1, 1)}
_SIDE_ORDER = ("south", "north", "west", "east")


@dataclass
class Plan:
    """One room while it is being furnished.

    lo, hi    : (3,) float corners of the free space inside the walls
    holes     : side → [(along0, along1, y0, y1)] openings cut into that wall
    obstacles : (n, 2, 3) float bounds of everything placed so far, plus keep-clear zones
                (in front of doors and windows) that are not instances
    """

    id: str
    type: str
    cell: tuple[float, float, float, float]  # grid x0, x1, z0, z1
    exterior: dict[str, bool]
    height: float
    holes: dict[str, list[tuple[float, float, float, float]]] = field(default_factory=dict)
    pieces: list[Piece] = field(default_factory=list)
    obstacles: list[tuple[tuple, tuple]] = field(default_factory=list)

    @property
    def lo(self):
        x0, _, z0, _ = self.cell
        return (x0 + _half_wall(self, "west"), 0.0, z0 + _half_wall(self, "south"))

    @property
    def hi(self):
        _, x1, _, z1 = self.cell
        return (x1 - _half_wall(self, "east"), self.height, z1 - _half_wall(self, "north"))

    def along(self, side: str) -> tuple[float, float]:
        """Range of the wall's free face along the wall (world X for south/north, Z else)."""
        return (self.lo[0], self.hi[0]) if side in ("south", "north") else (self.lo[2], self.hi[2])

    def frame(self, side: str, u: float) -> Frame:
        """Frame with its back on the inner face of ``side``, centred at ``u`` along it."""
        baxis, sb, su = _SIDES[side]
        b = (self.lo if sb > 0 else self.hi)[baxis]
        return Frame(baxis, sb, su, b, u)

    def fits(self, group: list[Piece]) -> bool:
        """True when every part is inside the room and overlaps nothing placed or kept clear."""
        boxes = np.array([(p.lo, p.hi) for piece in group for p in piece.parts])
        lo, hi = np.array(self.lo), np.array(self.hi)
        if (boxes[:, 0] < lo - EPS).any() or (boxes[:, 1] > hi + EPS).any():
            return False
        owner = np.repeat(np.arange(len(group)), [len(p.parts) for p in group])
        overlap = overlaps(boxes, boxes) & (owner[:, None] != owner[None, :])
        if overlap.any():
            return False
        return not self.obstacles or not overlaps(boxes, np.array(self.obstacles)).any()

    def add(self, group: list[Piece]) -> list[Piece]:
        self.pieces += group
        self.obstacles += [(p.lo, p.hi) for piece in group for p in piece.parts]
        return group

    def keep_clear(self, lo, hi) -> None:
        self.obstacles.append((tuple(lo), tuple(hi)))


def _half_width(group: list[Piece]) -> float:
    return max(max(abs(p.lo[0]), abs(p.hi[0])) for piece in group for p in piece.parts)


def _extent(group: list[Piece]) -> tuple[float, float, float, float]:
    """Local (x min, x max, z min, z max) of a group's main piece."""
    parts = group[0].parts
    return (min(p.lo[0] for p in parts), max(p.hi[0] for p in parts),
            min(p.lo[2] for p in parts), max(p.hi[2] for p in parts))


@dataclass
class _Placed:
    """A group as built (local frame) and as placed (world), with the frame between them."""

    local: list[Piece]
    frame: Frame
    world: list[Piece]


def _place(room: Plan, group: list[Piece], frame: Frame) -> _Placed | None:
    world = moved_group(group, frame)
    if not room.fits(world):
        return None
    room.add(world)
    return _Placed(group, frame, world)


def _against_wall(rng, room: Plan, build, sides=_SIDE_ORDER) -> _Placed | None:
    """Put a group built by ``build(rng)`` with its back on a wall, or None if it never fits."""
    for _ in range(_TRIES):
        group = build(rng)
        side = sides[int(rng.integers(len(sides)))]
        a0, a1 = room.along(side)
        hw = _half_width(group)
        if a1 - a0 < 2 * hw:
            continue
        placed = _place(room, group, room.frame(side, round(float(rng.uniform(a0 + hw, a1 - hw)), 3)))
        if placed:
            return placed
    return None


def _free_standing(rng, room: Plan, build) -> _Placed | None:
    """Put a group built around the local origin anywhere on the floor, any of 4 headings."""
    for _ in range(_TRIES):
        group = build(rng)
        baxis, sb, su = _SIDES[_SIDE_ORDER[int(rng.integers(4))]]
        x = round(float(rng.uniform(room.lo[0], room.hi[0])), 3)
        z = round(float(rng.uniform(room.lo[2], room.hi[2])), 3)
        placed = _place(room, group, Frame(baxis, sb, su, x if baxis == 0 else z, z if baxis == 0 else x))
        if placed:
            return placed
    return None


def _beside(rng, room: Plan, anchor: _Placed, build) -> _Placed | None:
    """Put a group along the same wall as ``anchor``, just left or right of it."""
    x0, x1, _, _ = _extent(anchor.local)
    for sign in (1, -1) if rng.random() < 0.5 else (-1, 1):
        group = build(rng)
        hw = _half_width(group)
        offset = x1 + 0.05 + hw if sign > 0 else x0 - 0.05 - hw
        placed = _place(room, group, anchor.frame.shifted(offset, 0.0))
        if placed:
            return placed
    return None


def _on_top(rng, room: Plan, support: Piece, build) -> Piece | None:
    """Stand a small piece built by ``build(rng, x, z, y)`` exactly on one of ``support``'s tops."""
    for _ in range(30):
        top = support.tops[int(rng.integers(len(support.tops)))]
        piece = build(rng, 0.0, 0.0, top.lo[1])
        half = max(max(-p.lo[0], p.hi[0], -p.lo[2], p.hi[2]) for p in piece.parts) + 0.02
        x0, x1, z0, z1 = top.lo[0] + half, top.hi[0] - half, top.lo[2] + half, top.hi[2] - half
        if x0 > x1 or z0 > z1:
            continue
        x, z = round(float(rng.uniform(x0, x1)), 3), round(float(rng.uniform(z0, z1)), 3)
        piece = piece.moved(Frame(2, 1, 1, z, x))
        piece.support = support
        if room.fits([piece]):
            return room.add([piece])[0]
    return None


def _rug_anywhere(rng, room: Plan, w: tuple[float, float], d: tuple[float, float]) -> None:
    """A rug as large as fits, trying smaller ones when big ones hit furniture legs."""
    for scale in (1.0, 0.8, 0.6, 0.45):
        if _free_standing(rng, room, lambda r, s=scale: furniture.rug(cm(r, *w) * s, cm(r, *d) * s)):
            return


def _pictures(rng, room: Plan, n: int) -> None:
    for _ in range(n):
        _against_wall(rng, room, furniture.picture)


def _cups(rng, room: Plan, support: Piece, n: int) -> None:
    for _ in range(n):
        _on_top(rng, room, support, lambda r, x, z, y: furniture.cup(x, z, y))


def _living_room(rng, room: Plan) -> None:
    sofa = _against_wall(rng, room, furniture.sofa)
    if sofa:
        depth = _extent(sofa.local)[3]
        table = None
        for gap in (0.4, 0.5, 0.35):
            group = furniture.table(rng, coffee=True)
            table = _place(room, group, sofa.frame.shifted(0.0, depth + gap - _extent(group)[2]))
            if table:
                break
        table = table or _free_standing(rng, room, lambda r: furniture.table(r, coffee=True))
        if table:
            _cups(rng, room, table.world[0], int(rng.integers(1, 3)))
            _on_top(rng, room, table.world[0], furniture.book_stack)
        _beside(rng, room, sofa, furniture.floor_lamp)
    tv = _against_wall(rng, room, lambda r: furniture.cabinet(r, tv=True))
    if tv and rng.random() < 0.5:
        _on_top(rng, room, tv.world[0], furniture.book_stack)
    _against_wall(rng, room, furniture.bookshelf)
    _against_wall(rng, room, furniture.cardboard_box)
    _pictures(rng, room, 2)
    _rug_anywhere(rng, room, (1.4, 2.2), (1.0, 1.6))


def _bedroom(rng, room: Plan) -> None:
    bed = _against_wall(rng, room, furniture.bed)
    if bed:
        first = _beside(rng, room, bed, furniture.night_stand)
        if first and rng.random() < 0.6:
            _beside(rng, room, bed, furniture.night_stand)
    dresser = _against_wall(rng, room, furniture.dresser)
    if dresser:
        _on_top(rng, room, dresser.world[0], lambda r, x, z, y: furniture.lamp(x, z, y))
    if rng.random() < 0.5:
        _free_standing(rng, room, furniture.cardboard_box)
    else:
        _against_wall(rng, room, furniture.cardboard_box)
    _pictures(rng, room, 1 + int(rng.integers(2)))
    _rug_anywhere(rng, room, (1.2, 2.0), (0.8, 1.4))


def _kitchen(rng, room: Plan) -> None:
    shortest_wall = min(room.hi[0] - room.lo[0], room.hi[2] - room.lo[2])
    counter = _against_wall(rng, room, lambda r: furniture.counter(r, shortest_wall))
    if counter:
        _cups(rng, room, counter.world[0], int(rng.integers(1, 4)))
    _against_wall(rng, room, furniture.fridge)
    _against_wall(rng, room, furniture.cabinet)
    table = _free_standing(rng, room, lambda r: furniture.table(r, chairs=2))
    if table:
        _cups(rng, room, table.world[0], int(rng.integers(1, 3)))
    shelves = _against_wall(rng, room, furniture.wall_shelves)
    if shelves:
        _cups(rng, room, shelves.world[0], 1)
    _against_wall(rng, room, furniture.cardboard_box)


def _bathroom(rng, room: Plan) -> None:
    _against_wall(rng, room, furniture.bathtub)
    _against_wall(rng, room, furniture.toilet)
    sink = _against_wall(rng, room, furniture.sink)
    if sink:
        _cups(rng, room, sink.world[0], 1)
    _rug_anywhere(rng, room, (0.7, 0.9), (0.5, 0.6))


def _office(rng, room: Plan) -> None:
    desk = _against_wall(rng, room, furniture.desk)
    if desk:
        _on_top(rng, room, desk.world[0], lambda r, x, z, y: furniture.lamp(x, z, y))
        _on_top(rng, room, desk.world[0], furniture.book_stack)
        _cups(rng, room, desk.world[0], 1)
    _against_wall(rng, room, furniture.bookshelf)
    _against_wall(rng, room, furniture.cabinet)
    _free_standing(rng, room, furniture.cardboard_box)
    _pictures(rng, room, 1)
    _rug_anywhere(rng, room, (1.2, 1.8), (0.8, 1.2))


def _dining_room(rng, room: Plan) -> None:
    table = _free_standing(rng, room, lambda r: furniture.table(r, chairs=4))
    table = table or _free_standing(rng, room, lambda r: furniture.table(r, chairs=2))
    if table:
        _cups(rng, room, table.world[0], int(rng.integers(2, 4)))
        _on_top(rng, room, table.world[0], furniture.book_stack)
    sideboard = _against_wall(rng, room, furniture.cabinet)
    if sideboard:
        _on_top(rng, room, sideboard.world[0], lambda r, x, z, y: furniture.lamp(x, z, y))
    shelves = _against_wall(rng, room, furniture.wall_shelves)
    if shelves:
        _on_top(rng, room, shelves.world[0], furniture.book_stack)
    _pictures(rng, room, 2)


_FURNISH = {
    "living_room": _living_room, "bedroom": _bedroom, "kitchen": _kitchen,
    "bathroom": _bathroom, "office": _office, "dining_room": _dining_room,
}


def _wall_part(side: str, across: tuple[float, float], along: tuple[float, float],
               ys: tuple[float, float]) -> Part:
    """A box in the wall of ``side``: ``across`` along the wall's normal, ``along`` along it."""
    if side in ("south", "north"):
        return box(along[0], ys[0], across[0], along[1], ys[1], across[1])
    return box(across[0], ys[0], along[0], across[1], ys[1], along[1])


def _half_wall(room: Plan, side: str) -> float:
    """Half the thickness of the wall on ``side`` of ``room``: walls are centred on the grid."""
    return (EXTERIOR_WALL if room.exterior[side] else PARTITION) / 2


#: the interior sides whose partition a room builds: each partition is one wall shared by
#: the rooms on its two sides, built once, by the room west or south of it
_OWNED_PARTITIONS = ("north", "east")


def _outer_edge(room: Plan, side: str) -> float:
    """Where the room's share of the house ends on ``side``: the outer face of an exterior
    wall, the grid line in a partition (the neighbour's floor and walls go on from there)."""
    grid = _grid_line(room, side)
    if not room.exterior[side]:
        return grid
    return grid + (_half_wall(room, side) if side in ("north", "east") else -_half_wall(room, side))


def _wall_span(room: Plan, side: str) -> tuple[tuple[float, float], tuple[float, float]]:
    """(across, along) ranges of the wall on ``side`` of a room, centred on the grid line
    (0.2 m exterior walls, 0.1 m partitions). The south/north walls also cover the corners,
    the west/east walls run between them."""
    grid, half = _grid_line(room, side), _half_wall(room, side)
    along = (_outer_edge(room, "west"), _outer_edge(room, "east")) if side in ("south", "north") else room.along(side)
    return (grid - half, grid + half), along


def _walls(room: Plan) -> list[Part]:
    """The room's exterior walls and the partitions it owns (:data:`_OWNED_PARTITIONS`) as
    closed boxes, cut around the openings."""
    parts = []
    for side in _SIDE_ORDER:
        if not room.exterior[side] and side not in _OWNED_PARTITIONS:
            continue
        across, (a0, a1) = _wall_span(room, side)
        cursor = a0
        for h0, h1, y0, y1 in sorted(room.holes.get(side, [])):
            parts.append(_wall_part(side, across, (cursor, h0), (0.0, room.height)))
            if y0 > 0:
                parts.append(_wall_part(side, across, (h0, h1), (0.0, y0)))
            parts.append(_wall_part(side, across, (h0, h1), (y1, room.height)))
            cursor = h1
        parts.append(_wall_part(side, across, (cursor, a1), (0.0, room.height)))
    return parts


def _slabs(room: Plan) -> tuple[Part, Part]:
    """Floor and ceiling slabs under and over the room and its share of the walls."""
    x0, x1 = _outer_edge(room, "west"), _outer_edge(room, "east")
    z0, z1 = _outer_edge(room, "south"), _outer_edge(room, "north")
    return (box(x0, -FLOOR_THICKNESS, z0, x1, 0.0, z1),
            box(x0, room.height, z0, x1, room.height + CEILING_THICKNESS, z1))


def _opening(kind: str, rooms: list[Plan], side: str, grid: float, along, ys) -> Opening:
    half = _half_wall(rooms[0], side)
    part = _wall_part(side, (grid - half, grid + half), along, ys)
    return Opening(kind, tuple(r.id for r in rooms), 0 if side in ("west", "east") else 2, part.lo, part.hi)


def _grid_line(room: Plan, side: str) -> float:
    x0, x1, z0, z1 = room.cell
    return {"south": z0, "north": z1, "west": x0, "east": x1}[side]


def _interior_door(rng, a: Plan, side_a: str, b: Plan, side_b: str) -> Opening:
    """Cut a door between two rooms; its leaf stands open against one room's wall."""
    w, h = cm(rng, 0.8, 0.9), cm(rng, 2.0, 2.1)
    a0, a1 = a.along(side_a)
    m = cm(rng, 0.15, 0.4)
    near_start = rng.random() < 0.5
    s0 = a0 + m if near_start else a1 - m - w
    leaf_u = s0 + 1.5 * w + 0.02 if near_start else s0 - 0.5 * w - 0.02
    for room, side in ((a, side_a), (b, side_b)):
        room.holes.setdefault(side, []).append((s0, s0 + w, 0.0, h))
        room.keep_clear(*_clear_zone(room, side, s0 + w / 2, w, 0.0, h, 0.8))
    leaf = Piece("door", "door", [box(-w / 2, 0.01, 0.01, w / 2, h - 0.01, 0.05)])
    sides = ((a, side_a), (b, side_b)) if rng.random() < 0.5 else ((b, side_b), (a, side_a))
    for owner, side in sides:  # an open leaf in the first room where it touches nothing
        if _place(owner, [leaf], owner.frame(side, leaf_u)):
            break
    return _opening("door", [a, b], side_a, _grid_line(a, side_a), (s0, s0 + w), (0.0, h))


def _clear_zone(room: Plan, side: str, u: float, w: float, y0: float, y1: float, depth: float):
    zone = room.frame(side, u).part(box(-w / 2, y0, 0, w / 2, y1, depth))
    return zone.lo, zone.hi


def _front_door(rng, room: Plan, side: str) -> Opening:
    """A closed exterior door: the leaf covers the hole with 1 cm to spare on three sides."""
    w, h = cm(rng, 0.9, 1.0), 2.1
    a0, a1 = room.along(side)
    s0 = round(float(rng.uniform(a0 + 0.3, a1 - 0.3 - w)), 3)
    room.holes.setdefault(side, []).append((s0, s0 + w, 0.0, h))
    leaf = Piece("front_door", "door", [box(-w / 2 - 0.01, 0.0, 0.0, w / 2 + 0.01, h + 0.01, 0.05)])
    # interior door leaves keep 0.15 m from the corners and this hole 0.3 m, so it always fits
    placed = _place(room, [leaf], room.frame(side, s0 + w / 2))
    assert placed, "front door leaf does not fit"
    room.keep_clear(*_clear_zone(room, side, s0 + w / 2, w, 0.0, h, 0.8))
    return _opening("front_door", [room], side, _grid_line(room, side), (s0, s0 + w), (0.0, h))


def _windows(rng, room: Plan, side: str) -> list[Opening]:
    """One or two windows in an exterior wall, each with a frame and curtains or blinds."""
    a0, a1 = room.along(side)
    count = 2 if a1 - a0 > 3.6 and rng.random() < 0.4 else 1
    seg = (a1 - a0) / count
    grid = _grid_line(room, side)
    out = []
    for k in range(count):
        w, sill, wh = min(cm(rng, 0.8, 1.4), round(seg - 1.0, 2)), cm(rng, 0.8, 1.0), cm(rng, 1.0, 1.3)
        lo = a0 + k * seg + 0.45
        s0 = round(float(rng.uniform(lo, lo + seg - 0.9 - w)), 3)
        s1, top = s0 + w, sill + wh
        room.holes.setdefault(side, []).append((s0, s1, sill, top))
        bar, across = 0.05, (grid - 0.05, grid + 0.05)
        frame = Piece("window", "window", [
            _wall_part(side, across, (s0, s1), (sill, sill + bar)),
            _wall_part(side, across, (s0, s1), (top - bar, top)),
            _wall_part(side, across, (s0, s0 + bar), (sill + bar, top - bar)),
            _wall_part(side, across, (s1 - bar, s1), (sill + bar, top - bar)),
        ])
        room.pieces.append(frame)  # inside the wall, so never in the way of furniture
        u = s0 + w / 2
        if rng.random() < 0.6:
            ctop = min(top + 0.15, room.height - 0.05)
            dressing = Piece("curtain", "curtain", [
                box(-w / 2 - 0.25, 0.02, 0.03, -w / 2 + 0.1, ctop, 0.06),
                box(w / 2 - 0.1, 0.02, 0.03, w / 2 + 0.25, ctop, 0.06),
            ])
        else:
            dressing = Piece("blinds", "blinds",  # rolled up: the window stays open
                              [box(-w / 2 - 0.05, top - 0.3, 0.02, w / 2 + 0.05, top + 0.08, 0.05)])
        dressing = moved_group([dressing], room.frame(side, u))
        if room.fits(dressing):
            room.add(dressing)
        room.keep_clear(*_clear_zone(room, side, u, w, sill, top, 0.4))
        out.append(_opening("window", [room], side, grid, (s0, s1), (sill, top)))
    return out


def _rooms(rng) -> list[Plan]:
    """A grid of 2–4 rooms of random sizes; the first is the living room, the second a bedroom."""
    rows, cols = ((1, 2), (2, 1), (1, 3), (3, 1), (2, 2))[int(rng.integers(5))]
    xs = np.round(np.cumsum([0.0, *(cm(rng, 3.4, 5.0) for _ in range(cols))]), 2)
    zs = np.round(np.cumsum([0.0, *(cm(rng, 3.4, 4.8) for _ in range(rows))]), 2)
    others = ROOM_TYPES[2:]
    types = ["living_room", "bedroom", *(others[i] for i in rng.permutation(len(others)))]
    height = cm(rng, 2.6, 2.9)
    rooms = []
    for r in range(rows):
        for c in range(cols):
            k = len(rooms)
            rooms.append(Plan(
                f"room{k}", types[k], (float(xs[c]), float(xs[c + 1]), float(zs[r]), float(zs[r + 1])),
                {"south": r == 0, "north": r == rows - 1, "west": c == 0, "east": c == cols - 1}, height,
            ))
    return rooms


def _doors(rng, rooms: list[Plan]) -> list[Opening]:
    """Interior doors along a random spanning tree of the grid (plus, sometimes, a loop)."""
    edges = []
    for p in rooms:
        for q in rooms:
            if q.cell[0] == p.cell[1] and q.cell[2] == p.cell[2]:
                edges.append((p, "east", q, "west"))
            if q.cell[2] == p.cell[3] and q.cell[0] == p.cell[0]:
                edges.append((p, "north", q, "south"))
    group = {p.id: p.id for p in rooms}

    def root(i):
        while group[i] != i:
            i = group[i]
        return i

    out = []
    for k in rng.permutation(len(edges)):
        a, side_a, b, side_b = edges[k]
        joins = root(a.id) != root(b.id)
        if joins or rng.random() < 0.3:
            group[root(a.id)] = root(b.id)
            out.append(_interior_door(rng, a, side_a, b, side_b))
    return out


def plan_house(rng: np.random.Generator) -> tuple[list[Plan], list[Opening]]:
    """Rooms on a grid, doors joining them, the front door, windows, then each room furnished."""
    rooms = _rooms(rng)
    openings = _doors(rng, rooms)
    living = rooms[0]
    front_side = ("south", "west")[int(rng.integers(2))]
    openings.append(_front_door(rng, living, front_side))
    for room in rooms:
        sides = [s for s in _SIDE_ORDER if room.exterior[s] and not (room is living and s == front_side)]
        sides = [sides[i] for i in rng.permutation(len(sides))]
        for k, side in enumerate(sides):
            if k == 0 or rng.random() < 0.6:
                openings += _windows(rng, room, side)
    for room in rooms:
        _FURNISH[room.type](rng, room)
    return rooms, openings


def envelope(room: Plan) -> list[Piece]:
    """The room's floor, ceiling and walls (cut around its openings), one piece each."""
    floor, ceiling = _slabs(room)
    return [Piece("floor", "floor", [floor]), Piece("ceiling", "ceiling", [ceiling]),
            Piece("wall", "wall", _walls(room))]
