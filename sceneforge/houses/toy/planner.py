"""Procedural toy houses: small furnished multi-room houses, deterministic from a seed.

A toy house is a grid of 2–4 rooms (living room, bedroom and some of kitchen, bathroom,
office, dining room) on one level with ``floor_y = 0``:

- every room owns its envelope: a floor slab, a ceiling slab and four wall slabs, all
  closed boxes. A wall between two rooms is two 0.1 m slabs, one per room (like SUNCG's
  per-room wall meshes); an exterior wall is one 0.2 m slab. Floors and ceilings cover
  the walls' footprint too, so no ray can leave through a seam;
- interior door openings join the rooms into one connected plan; their door leaves stand
  open against the wall. The front door is an exterior opening closed by its leaf, which
  overlaps the opening by 1 cm on the sides and top. Windows are exterior openings with a
  frame only: the glass is left out so rays leave the house there, and only there;
- furniture of more than twelve NYU40 classes, built from closed boxes and vertical
  cylinders, one mesh per instance, every part axis-aligned. Pieces stand against walls
  or on the floor, small things stand exactly on tables, shelves, beds and sofas, chairs
  are tucked under tables and desks. No two instances overlap (touching is allowed).

Everything is drawn from one ``np.random.Generator`` seeded with the house's seed and
passed down; sizes are rounded to centimetres and positions to millimetres. The circle
used for cylinders is a fixed rounded table, so houses are byte-identical on every
platform.

Regenerate the bundled houses with ``python -m sceneforge.houses.toy --bundle``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...conventions import NYU40_IDS
from ...errors import SceneforgeError
from .. import bundled_toy_dir
from ..model import House, Level, Material, Room, make_instance

__all__ = [
    "BUNDLE_COUNT", "BUNDLE_SEED", "Opening", "ToyHouse", "build_toy_house",
    "generate_house", "house_seed", "toy_house_id", "write_bundle", "write_toy_houses",
]

#: the bundled houses are ``toy_0_000`` .. ``toy_0_002``
BUNDLE_SEED = 0
BUNDLE_COUNT = 3

#: half the thickness of a wall between two rooms; exterior walls are twice as thick
HALF_WALL = 0.1
FLOOR_THICKNESS = 0.1
CEILING_THICKNESS = 0.1
#: corners of a cylinder's polygon on the unit circle, (12, 2) float64 (cos, sin). Rounded
#: so that a last-bit difference between platforms' libm cannot change the written bytes.
_CIRCLE = np.round(
    np.array([(math.cos(a), math.sin(a)) for a in np.arange(12) * (2 * math.pi / 12)]), 12
)
_EPS = 1e-9  # parts closer than this count as touching, not overlapping
_TRIES = 80  # random placements tried before a piece is given up

ROOM_TYPES = ("living_room", "bedroom", "kitchen", "bathroom", "office", "dining_room")

#: a base colour per label family; each instance jitters it into a colour of its own
_PALETTE = {
    "wall": (0.85, 0.83, 0.78), "floor": (0.55, 0.40, 0.28), "ceiling": (0.93, 0.93, 0.91),
    "door": (0.60, 0.45, 0.30), "window": (0.90, 0.90, 0.92), "curtain": (0.70, 0.25, 0.28),
    "blinds": (0.85, 0.85, 0.78), "picture": (0.30, 0.50, 0.70), "floor_mat": (0.60, 0.30, 0.30),
    "mirror": (0.80, 0.86, 0.90), "bed": (0.45, 0.35, 0.60), "pillow": (0.92, 0.88, 0.82),
    "night_stand": (0.50, 0.35, 0.20), "lamp": (0.92, 0.84, 0.50), "dresser": (0.55, 0.40, 0.25),
    "box": (0.70, 0.60, 0.40), "bookshelf": (0.45, 0.30, 0.20), "books": (0.25, 0.40, 0.60),
    "sofa": (0.30, 0.45, 0.35), "table": (0.60, 0.45, 0.30), "otherprop": (0.85, 0.85, 0.85),
    "cabinet": (0.65, 0.55, 0.45), "television": (0.12, 0.12, 0.14), "counter": (0.75, 0.75, 0.72),
    "refridgerator": (0.90, 0.90, 0.92), "chair": (0.50, 0.30, 0.20), "bathtub": (0.95, 0.95, 0.95),
    "toilet": (0.94, 0.94, 0.94), "sink": (0.92, 0.92, 0.94), "desk": (0.55, 0.45, 0.35),
    "shelves": (0.50, 0.40, 0.30),
}


# --------------------------------------------------------------------------- public records

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


@dataclass
class ToyHouse:
    """A generated house and what the generator knows about it, for tests and demos.

    interiors : room id → ((3,), (3,)) float corners of the room's free space (inside its
                walls, between floor and ceiling)
    supports  : (item name, supporting instance name): the item's bottom lies exactly on an
                upward face of the support (a table top, a shelf board, a mattress)
    tucked    : (chair name, table or desk name): the chair's seat is partly under the top
    """

    house: House
    openings: list[Opening]
    interiors: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]]
    supports: list[tuple[str, str]]
    tucked: list[tuple[str, str]]


# --------------------------------------------------------------------------- geometry

@dataclass(frozen=True)
class _Part:
    """A closed primitive given by its axis-aligned bounds: a box, or a vertical cylinder
    inscribed in them (``cyl``; its footprint is square)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    cyl: bool = False


def _box(x0, y0, z0, x1, y1, z1) -> _Part:
    return _Part((x0, y0, z0), (x1, y1, z1))


def _cyl(cx, cz, r, y0, y1) -> _Part:
    return _Part((cx - r, y0, cz - r), (cx + r, y1, cz + r), cyl=True)


# corner i of a box is (x[i & 1], y[i >> 1 & 1], z[i >> 2 & 1]); faces wind outwards
_BOX_FACES = np.array([
    [0, 4, 6], [0, 6, 2], [1, 3, 7], [1, 7, 5],  # -x, +x
    [0, 1, 5], [0, 5, 4], [2, 6, 7], [2, 7, 3],  # -y, +y
    [0, 2, 3], [0, 3, 1], [4, 5, 7], [4, 7, 6],  # -z, +z
], dtype=np.int64)


def _part_mesh(part: _Part) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(n, 3) float64`` and outward-wound faces ``(m, 3) int64`` of one part.

    Vertices are the part's bounds themselves (no transform), so faces meant to touch
    another part's lie exactly in the same plane.
    """
    lo, hi = np.array(part.lo), np.array(part.hi)
    if not part.cyl:
        i = np.arange(8)
        v = np.stack([np.where(i & 1, hi[0], lo[0]), np.where(i >> 1 & 1, hi[1], lo[1]),
                      np.where(i >> 2 & 1, hi[2], lo[2])], axis=1)
        return v, _BOX_FACES
    n = len(_CIRCLE)
    r, cx, cz = (hi[0] - lo[0]) / 2, (hi[0] + lo[0]) / 2, (hi[2] + lo[2]) / 2
    ring = np.stack([cx + r * _CIRCLE[:, 0], cz + r * _CIRCLE[:, 1]], axis=1)
    v = np.concatenate([
        np.insert(ring, 1, lo[1], axis=1), np.insert(ring, 1, hi[1], axis=1),
        [[cx, lo[1], cz], [cx, hi[1], cz]],
    ])
    k, k1 = np.arange(n), (np.arange(n) + 1) % n
    bottom, top = 2 * n, 2 * n + 1
    f = np.concatenate([
        np.stack([k, n + k, k1], 1), np.stack([k1, n + k, n + k1], 1),
        np.stack([np.full(n, bottom), k, k1], 1), np.stack([np.full(n, top), n + k1, n + k], 1),
    ])
    return v, f


def _mesh(parts: list[_Part]) -> tuple[np.ndarray, np.ndarray]:
    vs, fs, n = [], [], 0
    for p in parts:
        v, f = _part_mesh(p)
        vs.append(v)
        fs.append(f + n)
        n += len(v)
    return np.concatenate(vs), np.concatenate(fs)


@dataclass(frozen=True)
class _Frame:
    """A placement: local x runs along a wall (or a table edge), local z away from it, y up.

    World ``b``-axis (X when ``baxis == 0``, else Z) = ``b + sb * z_local`` and the other
    horizontal axis = ``u + su * x_local``: one of the four rotations about +Y, so boxes
    stay axis-aligned and heights are never touched.
    """

    baxis: int
    sb: int
    su: int
    b: float
    u: float

    def point(self, lx: float, lz: float) -> tuple[float, float]:
        """World (x, z) of local (x, z)."""
        pb, pu = self.b + self.sb * lz, self.u + self.su * lx
        return (pb, pu) if self.baxis == 0 else (pu, pb)

    def part(self, p: _Part) -> _Part:
        (ax, az), (bx, bz) = self.point(p.lo[0], p.lo[2]), self.point(p.hi[0], p.hi[2])
        return _Part((min(ax, bx), p.lo[1], min(az, bz)), (max(ax, bx), p.hi[1], max(az, bz)), p.cyl)

    def shifted(self, lx: float, lz: float) -> "_Frame":
        """The same orientation with its origin at this frame's local (lx, lz)."""
        return _Frame(self.baxis, self.sb, self.su, self.b + self.sb * lz, self.u + self.su * lx)


#: wall side → (b axis, sb, su) of a frame whose back is on that wall, facing the room
_SIDES = {"south": (2, 1, 1), "north": (2, -1, -1), "west": (0, 1, -1), "east": (0, -1, 1)}
_SIDE_ORDER = ("south", "north", "west", "east")


@dataclass
class _Piece:
    """A future instance: label, NYU40 class, parts and upward support surfaces (parts of
    zero height), plus what it stands on or is tucked under (pieces of the same group)."""

    label: str
    category: str
    parts: list[_Part]
    tops: list[_Part] = field(default_factory=list)
    support: "_Piece | None" = None
    under: "_Piece | None" = None

    def moved(self, frame: _Frame) -> "_Piece":
        return _Piece(self.label, self.category, [frame.part(p) for p in self.parts],
                      [frame.part(t) for t in self.tops], self.support, self.under)


def _moved(group: list[_Piece], frame: _Frame) -> list[_Piece]:
    """Move a group, keeping support/tucked links pointing inside the moved group."""
    out = [p.moved(frame) for p in group]
    index = {id(p): q for p, q in zip(group, out)}
    for q in out:
        q.support = index.get(id(q.support), q.support)
        q.under = index.get(id(q.under), q.under)
    return out


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    """A length drawn uniformly from [lo, hi], rounded to the centimetre."""
    return round(float(rng.uniform(lo, hi)), 2)


# --------------------------------------------------------------------------- furniture (local)
# Builders return a group of pieces in a local frame: x centred on the piece, z from its
# back (0, at the wall) towards its front, y up from the floor. The first piece is the
# main one; the others stand on it.

def _lamp(x: float, z: float, y: float) -> _Piece:
    """A table lamp standing at height ``y``: foot, stem, shade."""
    return _Piece("lamp", "lamp", [
        _cyl(x, z, 0.07, y, y + 0.03), _cyl(x, z, 0.012, y + 0.03, y + 0.25),
        _cyl(x, z, 0.12, y + 0.25, y + 0.45),
    ])


def _floor_lamp(rng) -> list[_Piece]:
    h = _u(rng, 1.3, 1.5)
    return [_Piece("floor_lamp", "lamp", [
        _cyl(0.0, 0.25, 0.15, 0.0, 0.03), _cyl(0.0, 0.25, 0.015, 0.03, h), _cyl(0.0, 0.25, 0.2, h, h + 0.3),
    ])]


def _cup(x: float, z: float, y: float) -> _Piece:
    return _Piece("cup", "otherprop", [_cyl(x, z, 0.04, y, y + 0.1)])


def _book_stack(rng, x: float, z: float, y: float) -> _Piece:
    """Two to four books lying flat, each exactly on the one below."""
    parts = []
    w, d = _u(rng, 0.16, 0.24), _u(rng, 0.22, 0.3)
    for _ in range(int(rng.integers(2, 5))):
        t = _u(rng, 0.02, 0.05)
        parts.append(_box(x - w / 2, y, z - d / 2, x + w / 2, y + t, z + d / 2))
        y = parts[-1].hi[1]
        w, d = w - 0.01, d - 0.01
    return _Piece("books", "books", parts)


def _bed(rng) -> list[_Piece]:
    w = _u(rng, 1.4, 1.8) if rng.random() < 0.6 else _u(rng, 0.9, 1.0)
    d = _u(rng, 1.95, 2.1)
    top = 0.52
    bed = _Piece("bed", "bed", [
        _box(-w / 2, 0, 0, w / 2, 0.95, 0.06),
        _box(-w / 2, 0, 0.06, w / 2, 0.3, d),
        _box(-w / 2 + 0.02, 0.3, 0.06, w / 2 - 0.02, top, d - 0.02),
    ], tops=[_box(-w / 2 + 0.02, top, 0.06, w / 2 - 0.02, top, d - 0.02)])
    centres = [-w / 4, w / 4] if w > 1.2 else [0.0]
    pw = min(0.6, w / len(centres) - 0.1)
    pillows = [_Piece("pillow", "pillow", [_box(c - pw / 2, top, 0.1, c + pw / 2, top + 0.12, 0.45)],
                      support=bed) for c in centres]
    return [bed, *pillows]


def _night_stand(rng) -> list[_Piece]:
    w, d, h = _u(rng, 0.4, 0.5), _u(rng, 0.35, 0.42), _u(rng, 0.5, 0.6)
    stand = _Piece("night_stand", "night_stand", [_box(-w / 2, 0, 0, w / 2, h, d)],
                   tops=[_box(-w / 2, h, 0, w / 2, h, d)])
    lamp = _lamp(0.0, d / 2, h)
    lamp.support = stand
    return [stand, lamp]


def _dresser(rng) -> list[_Piece]:
    w, d, h = _u(rng, 1.0, 1.4), _u(rng, 0.45, 0.55), _u(rng, 0.8, 0.95)
    parts = [_box(-w / 2, 0, 0, w / 2, h, d)]
    step = (h - 0.1) / 3
    for k in range(3):  # drawer fronts
        y0 = 0.08 + k * step
        parts.append(_box(-w / 2 + 0.04, y0, d, w / 2 - 0.04, y0 + step - 0.03, d + 0.02))
    return [_Piece("dresser", "dresser", parts, tops=[_box(-w / 2, h, 0, w / 2, h, d)])]


def _cabinet(rng, *, tv: bool = False) -> list[_Piece]:
    w, d = _u(rng, 1.0, 1.6) if tv else _u(rng, 0.7, 1.2), _u(rng, 0.4, 0.5)
    h = _u(rng, 0.45, 0.55) if tv else _u(rng, 0.6, 0.9)
    cab = _Piece("cabinet", "cabinet", [
        _box(-w / 2, 0, 0, w / 2, h, d),
        _box(-w / 2 + 0.03, 0.05, d, -0.01, h - 0.05, d + 0.02),
        _box(0.01, 0.05, d, w / 2 - 0.03, h - 0.05, d + 0.02),
    ], tops=[_box(-w / 2, h, 0, w / 2, h, d)])
    if not tv:
        return [cab]
    tw, th, c = min(_u(rng, 0.8, 1.2), w - 0.1), _u(rng, 0.45, 0.65), d / 2
    television = _Piece("television", "television", [
        _box(-0.15, h, c - 0.08, 0.15, h + 0.02, c + 0.08),
        _box(-0.03, h + 0.02, c - 0.02, 0.03, h + 0.1, c + 0.02),
        _box(-tw / 2, h + 0.1, c - 0.025, tw / 2, h + 0.1 + th, c + 0.025),
    ], support=cab)
    return [cab, television]


def _bookshelf(rng) -> list[_Piece]:
    w, d, h = _u(rng, 0.8, 1.2), _u(rng, 0.3, 0.36), _u(rng, 1.6, 2.0)
    t, n = 0.02, int(rng.integers(3, 5))
    xi0, xi1 = -w / 2 + t, w / 2 - t
    parts = [
        _box(-w / 2, 0, 0, w / 2, h, t),
        _box(-w / 2, 0, t, xi0, h, d), _box(xi1, 0, t, w / 2, h, d),
        _box(xi0, 0, t, xi1, 0.08, d), _box(xi0, h - t, t, xi1, h, d),
    ]
    levels = [0.08]
    gap = (h - t - 0.08 - (n - 1) * t) / n
    for k in range(1, n):
        y0 = round(0.08 + k * gap + (k - 1) * t, 4)
        parts.append(_box(xi0, y0, t, xi1, y0 + t, d))
        levels.append(parts[-1].hi[1])
    shelf = _Piece("bookshelf", "bookshelf", parts,
                   tops=[_box(xi0, y, t, xi1, y, d) for y in levels])
    group = [shelf]
    for y in levels:  # a row of standing books per shelf, starting at a random side
        x, books = xi0 + 0.01, []
        end = xi0 + (xi1 - xi0) * float(rng.uniform(0.4, 0.9))
        while True:
            bt, bh = _u(rng, 0.025, 0.05), _u(rng, 0.18, min(0.28, gap - 0.04))
            bd = _u(rng, 0.15, d - t - 0.02)
            if x + bt > end:
                break
            books.append(_box(x, y, d - bd, x + bt, y + bh, d))
            x += bt + 0.003
        if books:
            if rng.random() < 0.5:  # mirror the row to the other side
                books = [_box(xi0 + xi1 - b.hi[0], b.lo[1], b.lo[2], xi0 + xi1 - b.lo[0], b.hi[1], b.hi[2])
                         for b in books]
            group.append(_Piece("books", "books", books, support=shelf))
    return group


def _sofa(rng) -> list[_Piece]:
    w, d = _u(rng, 1.6, 2.2), _u(rng, 0.8, 0.95)
    arm, seat = 0.15, 0.42
    sofa = _Piece("sofa", "sofa", [
        _box(-w / 2, 0, 0, -w / 2 + arm, 0.62, d), _box(w / 2 - arm, 0, 0, w / 2, 0.62, d),
        _box(-w / 2 + arm, 0, 0, w / 2 - arm, 0.85, 0.2),
        _box(-w / 2 + arm, 0, 0.2, w / 2 - arm, seat, d),
    ], tops=[_box(-w / 2 + arm, seat, 0.2, w / 2 - arm, seat, d)])
    n = int(rng.integers(2, 4))
    span = (w - 2 * arm) / n
    pillows = [
        _Piece("pillow", "pillow",
               [_box(-w / 2 + arm + k * span + 0.05, seat, 0.2, -w / 2 + arm + (k + 1) * span - 0.05,
                     seat + 0.35, 0.32)], support=sofa)
        for k in range(n)
    ]
    return [sofa, *pillows]


def _chair() -> _Piece:
    """A chair facing local +z: back at z 0..0.05, seat front at z 0.45, seat top 0.45."""
    s, leg = 0.45, 0.04
    legs = [_box(x, 0, z, x + leg, 0.41, z + leg) for x in (-s / 2, s / 2 - leg) for z in (0, s - leg)]
    seat, back = _box(-s / 2, 0.41, 0, s / 2, s, s), _box(-s / 2, s, 0, s / 2, 0.9, 0.05)
    return _Piece("chair", "chair", [*legs, seat, back])


def _tuck(chair: _Piece, under: _Piece, frame: _Frame) -> _Piece:
    tucked = chair.moved(frame)
    tucked.under = under
    return tucked


def _table(rng, *, coffee: bool = False, chairs: int = 0) -> list[_Piece]:
    """A table centred on the local origin, with ``chairs`` chairs (0, 2 or 4) tucked under."""
    if coffee:
        w, d, h, t, leg = _u(rng, 0.9, 1.2), _u(rng, 0.5, 0.6), _u(rng, 0.42, 0.46), 0.03, 0.04
    else:
        w, d, h, t, leg = _u(rng, 1.2, 1.6), _u(rng, 0.8, 0.9), 0.75, 0.04, 0.06
    legs = [_box(x, 0, z, x + leg, h - t, z + leg)
            for x in (-w / 2 + 0.04, w / 2 - 0.04 - leg) for z in (-d / 2 + 0.04, d / 2 - 0.04 - leg)]
    table = _Piece("coffee_table" if coffee else "table", "table",
                   [*legs, _box(-w / 2, h - t, -d / 2, w / 2, h, d / 2)],
                   tops=[_box(-w / 2, h, -d / 2, w / 2, h, d / 2)])
    group = [table]
    sides = [(2, 1, 1, -d / 2), (2, -1, -1, d / 2), (0, 1, -1, -w / 2), (0, -1, 1, w / 2)][:chairs]
    for baxis, sb, su, edge in sides:
        overlap = _u(rng, 0.12, 0.2)
        frame = _Frame(baxis, sb, su, edge + sb * (overlap - 0.45), _u(rng, -0.05, 0.05))
        group.append(_tuck(_chair(), table, frame))
    return group


def _desk(rng) -> list[_Piece]:
    w, d, h = _u(rng, 1.2, 1.6), _u(rng, 0.6, 0.7), 0.75
    desk = _Piece("desk", "desk", [
        _box(-w / 2, h - 0.03, 0, w / 2, h, d),
        _box(-w / 2, 0, 0, -w / 2 + 0.03, h - 0.03, d), _box(w / 2 - 0.03, 0, 0, w / 2, h - 0.03, d),
        _box(-w / 2 + 0.03, 0.3, 0, w / 2 - 0.03, h - 0.03, 0.02),
    ], tops=[_box(-w / 2, h, 0, w / 2, h, d)])
    overlap = _u(rng, 0.12, 0.2)
    chair = _tuck(_chair(), desk, _Frame(2, -1, -1, d - overlap + 0.45, _u(rng, -0.1, 0.1)))
    return [desk, chair]


def _counter(rng, length: float) -> list[_Piece]:
    w = min(_u(rng, 1.4, 2.4), round(length - 0.1, 2))
    return [_Piece("counter", "counter", [
        _box(-w / 2, 0, 0, w / 2, 0.86, 0.56), _box(-w / 2, 0.86, 0, w / 2, 0.9, 0.6),
    ], tops=[_box(-w / 2, 0.9, 0, w / 2, 0.9, 0.6)])]


def _fridge(rng) -> list[_Piece]:
    w, d, h = _u(rng, 0.6, 0.8), _u(rng, 0.62, 0.7), _u(rng, 1.7, 1.9)
    return [_Piece("refrigerator", "refridgerator", [
        _box(-w / 2, 0, 0, w / 2, h, d), _box(w / 2 - 0.08, h / 2, d, w / 2 - 0.05, h - 0.2, d + 0.04),
    ])]


def _bathtub(rng) -> list[_Piece]:
    w, d, h, t = _u(rng, 1.5, 1.7), _u(rng, 0.7, 0.75), 0.55, 0.08
    return [_Piece("bathtub", "bathtub", [
        _box(-w / 2, 0, 0, w / 2, 0.1, d),
        _box(-w / 2, 0.1, 0, w / 2, h, t), _box(-w / 2, 0.1, d - t, w / 2, h, d),
        _box(-w / 2, 0.1, t, -w / 2 + t, h, d - t), _box(w / 2 - t, 0.1, t, w / 2, h, d - t),
    ])]


def _toilet(rng) -> list[_Piece]:
    return [_Piece("toilet", "toilet", [
        _box(-0.2, 0, 0, 0.2, 0.8, 0.12), _box(-0.12, 0, 0.14, 0.12, 0.3, 0.5),
        _cyl(0.0, 0.31, 0.19, 0.3, 0.42),
    ])]


def _sink(rng) -> list[_Piece]:
    """A pedestal wash basin and the mirror above it (flush with the wall)."""
    mw = _u(rng, 0.45, 0.6)
    return [
        _Piece("sink", "sink", [_cyl(0.0, 0.2, 0.08, 0, 0.7), _box(-0.28, 0.7, 0, 0.28, 0.86, 0.45)],
               tops=[_box(-0.28, 0.86, 0, 0.28, 0.86, 0.45)]),
        _Piece("mirror", "mirror", [_box(-mw / 2, 1.15, 0, mw / 2, 1.15 + _u(rng, 0.6, 0.8), 0.02)]),
    ]


def _wall_shelves(rng) -> list[_Piece]:
    w, y = _u(rng, 0.6, 1.0), _u(rng, 1.2, 1.5)
    shelves = _Piece("shelves", "shelves", [
        _box(-w / 2, y, 0, -w / 2 + 0.02, y + 0.4, 0.25), _box(w / 2 - 0.02, y, 0, w / 2, y + 0.4, 0.25),
        _box(-w / 2 + 0.02, y, 0, w / 2 - 0.02, y + 0.02, 0.25),
        _box(-w / 2 + 0.02, y + 0.38, 0, w / 2 - 0.02, y + 0.4, 0.25),
    ], tops=[_box(-w / 2 + 0.02, y + 0.02, 0, w / 2 - 0.02, y + 0.02, 0.25),
             _box(-w / 2 + 0.02, y + 0.4, 0, w / 2 - 0.02, y + 0.4, 0.25)])
    return [shelves]


def _picture(rng) -> list[_Piece]:
    w, h = _u(rng, 0.4, 0.9), _u(rng, 0.3, 0.7)
    y = _u(rng, 1.3, 1.7) - h / 2
    return [_Piece("picture", "picture", [_box(-w / 2, y, 0, w / 2, y + h, 0.03)])]


def _cardboard_box(rng) -> list[_Piece]:
    s = _u(rng, 0.25, 0.5)
    return [_Piece("box", "box", [_box(-s / 2, 0, 0, s / 2, _u(rng, 0.2, 0.45), s)])]


def _rug(w: float, d: float) -> list[_Piece]:
    """A rug 1 mm thick lying on the floor, centred on the local origin."""
    return [_Piece("rug", "floor_mat", [_box(-w / 2, 0, -d / 2, w / 2, 0.001, d / 2)])]


# --------------------------------------------------------------------------- rooms

@dataclass
class _Plan:
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
    pieces: list[_Piece] = field(default_factory=list)
    obstacles: list[tuple[tuple, tuple]] = field(default_factory=list)

    @property
    def lo(self):
        x0, _, z0, _ = self.cell
        return (x0 + HALF_WALL, 0.0, z0 + HALF_WALL)

    @property
    def hi(self):
        _, x1, _, z1 = self.cell
        return (x1 - HALF_WALL, self.height, z1 - HALF_WALL)

    def along(self, side: str) -> tuple[float, float]:
        """Range of the wall's free face along the wall (world X for south/north, Z else)."""
        return (self.lo[0], self.hi[0]) if side in ("south", "north") else (self.lo[2], self.hi[2])

    def frame(self, side: str, u: float) -> _Frame:
        """Frame with its back on the inner face of ``side``, centred at ``u`` along it."""
        baxis, sb, su = _SIDES[side]
        b = (self.lo if sb > 0 else self.hi)[baxis]
        return _Frame(baxis, sb, su, b, u)

    def fits(self, group: list[_Piece]) -> bool:
        """True when every part is inside the room and overlaps nothing placed or kept clear."""
        boxes = np.array([(p.lo, p.hi) for piece in group for p in piece.parts])
        lo, hi = np.array(self.lo), np.array(self.hi)
        if (boxes[:, 0] < lo - _EPS).any() or (boxes[:, 1] > hi + _EPS).any():
            return False
        owner = np.repeat(np.arange(len(group)), [len(p.parts) for p in group])
        overlap = _overlaps(boxes, boxes) & (owner[:, None] != owner[None, :])
        if overlap.any():
            return False
        return not self.obstacles or not _overlaps(boxes, np.array(self.obstacles)).any()

    def add(self, group: list[_Piece]) -> list[_Piece]:
        self.pieces += group
        self.obstacles += [(p.lo, p.hi) for piece in group for p in piece.parts]
        return group

    def keep_clear(self, lo, hi) -> None:
        self.obstacles.append((tuple(lo), tuple(hi)))


def _overlaps(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n, m) bool: boxes ``a`` (n, 2, 3) and ``b`` (m, 2, 3) share a volume (not just a face)."""
    return ((a[:, None, 0] < b[None, :, 1] - _EPS) & (b[None, :, 0] < a[:, None, 1] - _EPS)).all(-1)


def _half_width(group: list[_Piece]) -> float:
    return max(max(abs(p.lo[0]), abs(p.hi[0])) for piece in group for p in piece.parts)


def _extent(group: list[_Piece]) -> tuple[float, float, float, float]:
    """Local (x min, x max, z min, z max) of a group's main piece."""
    parts = group[0].parts
    return (min(p.lo[0] for p in parts), max(p.hi[0] for p in parts),
            min(p.lo[2] for p in parts), max(p.hi[2] for p in parts))


@dataclass
class _Placed:
    """A group as built (local frame) and as placed (world), with the frame between them."""

    local: list[_Piece]
    frame: _Frame
    world: list[_Piece]


def _place(room: _Plan, group: list[_Piece], frame: _Frame) -> _Placed | None:
    world = _moved(group, frame)
    if not room.fits(world):
        return None
    room.add(world)
    return _Placed(group, frame, world)


def _against_wall(rng, room: _Plan, build, sides=_SIDE_ORDER) -> _Placed | None:
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


def _free_standing(rng, room: _Plan, build) -> _Placed | None:
    """Put a group built around the local origin anywhere on the floor, any of 4 headings."""
    for _ in range(_TRIES):
        group = build(rng)
        baxis, sb, su = _SIDES[_SIDE_ORDER[int(rng.integers(4))]]
        x = round(float(rng.uniform(room.lo[0], room.hi[0])), 3)
        z = round(float(rng.uniform(room.lo[2], room.hi[2])), 3)
        placed = _place(room, group, _Frame(baxis, sb, su, x if baxis == 0 else z, z if baxis == 0 else x))
        if placed:
            return placed
    return None


def _beside(rng, room: _Plan, anchor: _Placed, build) -> _Placed | None:
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


def _on_top(rng, room: _Plan, support: _Piece, build) -> _Piece | None:
    """Stand a small piece built by ``build(rng, x, z, y)`` exactly on one of ``support``'s tops."""
    for _ in range(30):
        top = support.tops[int(rng.integers(len(support.tops)))]
        piece = build(rng, 0.0, 0.0, top.lo[1])
        half = max(max(-p.lo[0], p.hi[0], -p.lo[2], p.hi[2]) for p in piece.parts) + 0.02
        x0, x1, z0, z1 = top.lo[0] + half, top.hi[0] - half, top.lo[2] + half, top.hi[2] - half
        if x0 > x1 or z0 > z1:
            continue
        x, z = round(float(rng.uniform(x0, x1)), 3), round(float(rng.uniform(z0, z1)), 3)
        piece = piece.moved(_Frame(2, 1, 1, z, x))
        piece.support = support
        if room.fits([piece]):
            return room.add([piece])[0]
    return None


def _rug_anywhere(rng, room: _Plan, w: tuple[float, float], d: tuple[float, float]) -> None:
    """A rug as large as fits, trying smaller ones when big ones hit furniture legs."""
    for scale in (1.0, 0.8, 0.6, 0.45):
        if _free_standing(rng, room, lambda r, s=scale: _rug(_u(r, *w) * s, _u(r, *d) * s)):
            return


def _pictures(rng, room: _Plan, n: int) -> None:
    for _ in range(n):
        _against_wall(rng, room, _picture)


def _cups(rng, room: _Plan, support: _Piece, n: int) -> None:
    for _ in range(n):
        _on_top(rng, room, support, lambda r, x, z, y: _cup(x, z, y))


def _living_room(rng, room: _Plan) -> None:
    sofa = _against_wall(rng, room, _sofa)
    if sofa:
        depth = _extent(sofa.local)[3]
        table = None
        for gap in (0.4, 0.5, 0.35):
            group = _table(rng, coffee=True)
            table = _place(room, group, sofa.frame.shifted(0.0, depth + gap - _extent(group)[2]))
            if table:
                break
        table = table or _free_standing(rng, room, lambda r: _table(r, coffee=True))
        if table:
            _cups(rng, room, table.world[0], int(rng.integers(1, 3)))
            _on_top(rng, room, table.world[0], _book_stack)
        _beside(rng, room, sofa, _floor_lamp)
    tv = _against_wall(rng, room, lambda r: _cabinet(r, tv=True))
    if tv and rng.random() < 0.5:
        _on_top(rng, room, tv.world[0], _book_stack)
    _against_wall(rng, room, _bookshelf)
    _against_wall(rng, room, _cardboard_box)
    _pictures(rng, room, 2)
    _rug_anywhere(rng, room, (1.4, 2.2), (1.0, 1.6))


def _bedroom(rng, room: _Plan) -> None:
    bed = _against_wall(rng, room, _bed)
    if bed:
        first = _beside(rng, room, bed, _night_stand)
        if first and rng.random() < 0.6:
            _beside(rng, room, bed, _night_stand)
    dresser = _against_wall(rng, room, _dresser)
    if dresser:
        _on_top(rng, room, dresser.world[0], lambda r, x, z, y: _lamp(x, z, y))
    if rng.random() < 0.5:
        _free_standing(rng, room, _cardboard_box)
    else:
        _against_wall(rng, room, _cardboard_box)
    _pictures(rng, room, 1 + int(rng.integers(2)))
    _rug_anywhere(rng, room, (1.2, 2.0), (0.8, 1.4))


def _kitchen(rng, room: _Plan) -> None:
    shortest_wall = min(room.hi[0] - room.lo[0], room.hi[2] - room.lo[2])
    counter = _against_wall(rng, room, lambda r: _counter(r, shortest_wall))
    if counter:
        _cups(rng, room, counter.world[0], int(rng.integers(1, 4)))
    _against_wall(rng, room, _fridge)
    _against_wall(rng, room, _cabinet)
    table = _free_standing(rng, room, lambda r: _table(r, chairs=2))
    if table:
        _cups(rng, room, table.world[0], int(rng.integers(1, 3)))
    shelves = _against_wall(rng, room, _wall_shelves)
    if shelves:
        _cups(rng, room, shelves.world[0], 1)
    _against_wall(rng, room, _cardboard_box)


def _bathroom(rng, room: _Plan) -> None:
    _against_wall(rng, room, _bathtub)
    _against_wall(rng, room, _toilet)
    sink = _against_wall(rng, room, _sink)
    if sink:
        _cups(rng, room, sink.world[0], 1)
    _rug_anywhere(rng, room, (0.7, 0.9), (0.5, 0.6))


def _office(rng, room: _Plan) -> None:
    desk = _against_wall(rng, room, _desk)
    if desk:
        _on_top(rng, room, desk.world[0], lambda r, x, z, y: _lamp(x, z, y))
        _on_top(rng, room, desk.world[0], _book_stack)
        _cups(rng, room, desk.world[0], 1)
    _against_wall(rng, room, _bookshelf)
    _against_wall(rng, room, _cabinet)
    _free_standing(rng, room, _cardboard_box)
    _pictures(rng, room, 1)
    _rug_anywhere(rng, room, (1.2, 1.8), (0.8, 1.2))


def _dining_room(rng, room: _Plan) -> None:
    table = _free_standing(rng, room, lambda r: _table(r, chairs=4))
    table = table or _free_standing(rng, room, lambda r: _table(r, chairs=2))
    if table:
        _cups(rng, room, table.world[0], int(rng.integers(2, 4)))
        _on_top(rng, room, table.world[0], _book_stack)
    sideboard = _against_wall(rng, room, _cabinet)
    if sideboard:
        _on_top(rng, room, sideboard.world[0], lambda r, x, z, y: _lamp(x, z, y))
    shelves = _against_wall(rng, room, _wall_shelves)
    if shelves:
        _on_top(rng, room, shelves.world[0], _book_stack)
    _pictures(rng, room, 2)


_FURNISH = {
    "living_room": _living_room, "bedroom": _bedroom, "kitchen": _kitchen,
    "bathroom": _bathroom, "office": _office, "dining_room": _dining_room,
}


# --------------------------------------------------------------------------- envelope

def _wall_part(side: str, across: tuple[float, float], along: tuple[float, float],
               ys: tuple[float, float]) -> _Part:
    """A box in the wall of ``side``: ``across`` along the wall's normal, ``along`` along it."""
    if side in ("south", "north"):
        return _box(along[0], ys[0], across[0], along[1], ys[1], across[1])
    return _box(across[0], ys[0], along[0], across[1], ys[1], along[1])


def _wall_span(room: _Plan, side: str) -> tuple[tuple[float, float], tuple[float, float]]:
    """(across, along) ranges of a room's wall slab: exterior slabs are twice as thick and the
    south/north slabs also cover the corners."""
    x0, x1, z0, z1 = room.cell
    t, ext = HALF_WALL, room.exterior
    ox = (x0 - t if ext["west"] else x0, x1 + t if ext["east"] else x1)
    across = {
        "south": (z0 - t if ext["south"] else z0, z0 + t), "north": (z1 - t, z1 + t if ext["north"] else z1),
        "west": (x0 - t if ext["west"] else x0, x0 + t), "east": (x1 - t, x1 + t if ext["east"] else x1),
    }[side]
    return across, (ox if side in ("south", "north") else room.along(side))


def _walls(room: _Plan) -> list[_Part]:
    """The room's four wall slabs as closed boxes, cut around the openings."""
    parts = []
    for side in _SIDE_ORDER:
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


def _slabs(room: _Plan) -> tuple[_Part, _Part]:
    """Floor and ceiling slabs covering the room and its walls' footprint."""
    (x0, _), _ = _wall_span(room, "west")
    (_, x1), _ = _wall_span(room, "east")
    (z0, _), _ = _wall_span(room, "south")
    (_, z1), _ = _wall_span(room, "north")
    return (_box(x0, -FLOOR_THICKNESS, z0, x1, 0.0, z1),
            _box(x0, room.height, z0, x1, room.height + CEILING_THICKNESS, z1))


def _opening(kind: str, rooms: list[_Plan], side: str, grid: float, along, ys) -> Opening:
    part = _wall_part(side, (grid - HALF_WALL, grid + HALF_WALL), along, ys)
    return Opening(kind, tuple(r.id for r in rooms), 0 if side in ("west", "east") else 2, part.lo, part.hi)


def _grid_line(room: _Plan, side: str) -> float:
    x0, x1, z0, z1 = room.cell
    return {"south": z0, "north": z1, "west": x0, "east": x1}[side]


def _interior_door(rng, a: _Plan, side_a: str, b: _Plan, side_b: str) -> Opening:
    """Cut a door between two rooms; its leaf stands open against one room's wall."""
    w, h = _u(rng, 0.8, 0.9), _u(rng, 2.0, 2.1)
    a0, a1 = a.along(side_a)
    m = _u(rng, 0.15, 0.4)
    near_start = rng.random() < 0.5
    s0 = a0 + m if near_start else a1 - m - w
    leaf_u = s0 + 1.5 * w + 0.02 if near_start else s0 - 0.5 * w - 0.02
    for room, side in ((a, side_a), (b, side_b)):
        room.holes.setdefault(side, []).append((s0, s0 + w, 0.0, h))
        room.keep_clear(*_clear_zone(room, side, s0 + w / 2, w, 0.0, h, 0.8))
    leaf = _Piece("door", "door", [_box(-w / 2, 0.01, 0.01, w / 2, h - 0.01, 0.05)])
    sides = ((a, side_a), (b, side_b)) if rng.random() < 0.5 else ((b, side_b), (a, side_a))
    for owner, side in sides:  # an open leaf in the first room where it touches nothing
        if _place(owner, [leaf], owner.frame(side, leaf_u)):
            break
    return _opening("door", [a, b], side_a, _grid_line(a, side_a), (s0, s0 + w), (0.0, h))


def _clear_zone(room: _Plan, side: str, u: float, w: float, y0: float, y1: float, depth: float):
    zone = room.frame(side, u).part(_box(-w / 2, y0, 0, w / 2, y1, depth))
    return zone.lo, zone.hi


def _front_door(rng, room: _Plan, side: str) -> Opening:
    """A closed exterior door: the leaf covers the hole with 1 cm to spare on three sides."""
    w, h = _u(rng, 0.9, 1.0), 2.1
    a0, a1 = room.along(side)
    s0 = round(float(rng.uniform(a0 + 0.3, a1 - 0.3 - w)), 3)
    room.holes.setdefault(side, []).append((s0, s0 + w, 0.0, h))
    leaf = _Piece("front_door", "door", [_box(-w / 2 - 0.01, 0.0, 0.0, w / 2 + 0.01, h + 0.01, 0.05)])
    # interior door leaves keep 0.15 m from the corners and this hole 0.3 m, so it always fits
    placed = _place(room, [leaf], room.frame(side, s0 + w / 2))
    assert placed, "front door leaf does not fit"
    room.keep_clear(*_clear_zone(room, side, s0 + w / 2, w, 0.0, h, 0.8))
    return _opening("front_door", [room], side, _grid_line(room, side), (s0, s0 + w), (0.0, h))


def _windows(rng, room: _Plan, side: str) -> list[Opening]:
    """One or two windows in an exterior wall, each with a frame and curtains or blinds."""
    a0, a1 = room.along(side)
    count = 2 if a1 - a0 > 3.6 and rng.random() < 0.4 else 1
    seg = (a1 - a0) / count
    grid = _grid_line(room, side)
    out = []
    for k in range(count):
        w, sill, wh = min(_u(rng, 0.8, 1.4), round(seg - 1.0, 2)), _u(rng, 0.8, 1.0), _u(rng, 1.0, 1.3)
        lo = a0 + k * seg + 0.45
        s0 = round(float(rng.uniform(lo, lo + seg - 0.9 - w)), 3)
        s1, top = s0 + w, sill + wh
        room.holes.setdefault(side, []).append((s0, s1, sill, top))
        bar, across = 0.05, (grid - 0.05, grid + 0.05)
        frame = _Piece("window", "window", [
            _wall_part(side, across, (s0, s1), (sill, sill + bar)),
            _wall_part(side, across, (s0, s1), (top - bar, top)),
            _wall_part(side, across, (s0, s0 + bar), (sill + bar, top - bar)),
            _wall_part(side, across, (s1 - bar, s1), (sill + bar, top - bar)),
        ])
        room.pieces.append(frame)  # inside the wall, so never in the way of furniture
        u = s0 + w / 2
        if rng.random() < 0.6:
            ctop = min(top + 0.15, room.height - 0.05)
            dressing = _Piece("curtain", "curtain", [
                _box(-w / 2 - 0.25, 0.02, 0.03, -w / 2 + 0.1, ctop, 0.06),
                _box(w / 2 - 0.1, 0.02, 0.03, w / 2 + 0.25, ctop, 0.06),
            ])
        else:
            dressing = _Piece("blinds", "blinds",  # rolled up: the window stays open
                              [_box(-w / 2 - 0.05, top - 0.3, 0.02, w / 2 + 0.05, top + 0.08, 0.05)])
        dressing = _moved([dressing], room.frame(side, u))
        if room.fits(dressing):
            room.add(dressing)
        room.keep_clear(*_clear_zone(room, side, u, w, sill, top, 0.4))
        out.append(_opening("window", [room], side, grid, (s0, s1), (sill, top)))
    return out


def _rooms(rng) -> list[_Plan]:
    """A grid of 2–4 rooms of random sizes; the first is the living room, the second a bedroom."""
    rows, cols = ((1, 2), (2, 1), (1, 3), (3, 1), (2, 2))[int(rng.integers(5))]
    xs = np.round(np.cumsum([0.0, *(_u(rng, 3.4, 5.0) for _ in range(cols))]), 2)
    zs = np.round(np.cumsum([0.0, *(_u(rng, 3.4, 4.8) for _ in range(rows))]), 2)
    others = ROOM_TYPES[2:]
    types = ["living_room", "bedroom", *(others[i] for i in rng.permutation(len(others)))]
    height = _u(rng, 2.6, 2.9)
    rooms = []
    for r in range(rows):
        for c in range(cols):
            k = len(rooms)
            rooms.append(_Plan(
                f"room{k}", types[k], (float(xs[c]), float(xs[c + 1]), float(zs[r]), float(zs[r + 1])),
                {"south": r == 0, "north": r == rows - 1, "west": c == 0, "east": c == cols - 1}, height,
            ))
    return rooms


def _doors(rng, rooms: list[_Plan]) -> list[Opening]:
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


# --------------------------------------------------------------------------- the house

def house_seed(seed: int, index: int) -> int:
    """Seed of house ``index`` of a batch generated with ``seed`` (independent streams)."""
    return int(np.random.SeedSequence(seed, spawn_key=(index,)).generate_state(1, np.uint64)[0])


def toy_house_id(seed: int, index: int) -> str:
    return f"toy_{seed}_{index:03d}"


def _check_seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise SceneforgeError(f"toy houses: seed must be a non-negative integer, got {seed!r}")
    return int(seed)


def build_toy_house(seed: int, house_id: str | None = None) -> ToyHouse:
    """Generate the toy house of ``seed`` and the facts tests need about it.

    The same ``seed`` always gives the same house, down to the bytes it is written as.
    """
    seed = _check_seed(seed)
    rng = np.random.default_rng(seed)
    house = House(id=house_id or f"toy_{seed}", instances=[], levels=[Level(0, 0.0)],
                  source_format="toy", source_path=None)
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

    names: dict[int, str] = {}
    used: set[tuple[float, ...]] = set()
    for room in rooms:
        house.rooms.append(Room(room.id, room.type, 0))
        floor, ceiling = _slabs(room)
        envelope = [_Piece("floor", "floor", [floor]), _Piece("ceiling", "ceiling", [ceiling]),
                    _Piece("wall", "wall", _walls(room))]
        counts: dict[str, int] = {}
        for piece in envelope + room.pieces:
            k = counts[piece.label] = counts.get(piece.label, -1) + 1
            v, f = _mesh(piece.parts)
            inst = make_instance(
                house, name=f"{room.id}/{piece.label}_{k}", category=NYU40_IDS[piece.category],
                label=piece.label, room_id=room.id, vertices=v, faces=f,
                material=Material(base_color=_colour(rng, piece.category, used)),
            )
            names[id(piece)] = inst.name
    pieces = [p for room in rooms for p in room.pieces]
    return ToyHouse(
        house=house.check_not_empty(),
        openings=openings,
        interiors={r.id: (r.lo, r.hi) for r in rooms},
        supports=[(names[id(p)], names[id(p.support)]) for p in pieces if p.support is not None],
        tucked=[(names[id(p)], names[id(p.under)]) for p in pieces if p.under is not None],
    )


def _colour(rng, category: str, used: set) -> tuple[float, float, float, float]:
    """The category's base colour, jittered until no other instance of the house has it."""
    base = np.array(_PALETTE[category])
    while True:
        rgb = tuple(round(float(c), 3) for c in np.clip(base + rng.uniform(-0.1, 0.1, 3), 0.02, 0.98))
        if rgb not in used:
            used.add(rgb)
            return (*rgb, 1.0)


def generate_house(seed: int, house_id: str | None = None) -> House:
    """The toy house of ``seed`` (id ``house_id``, default ``toy_<seed>``); see the module doc."""
    return build_toy_house(seed, house_id).house


def write_toy_houses(out: str | Path, count: int, seed: int, progress=None) -> list[Path]:
    """Write ``count`` toy houses into ``out/<id>/`` in sceneforge's format; return the folders.

    House ``i`` has id ``toy_<seed>_<i:03d>`` and seed :func:`house_seed` ``(seed, i)``.
    ``progress(house, folder)`` is called after each house is written.
    """
    from ..formats.native import write_house

    seed = _check_seed(seed)
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
        raise SceneforgeError(f"toy houses: count must be a positive integer, got {count!r}")
    folders = []
    for i in range(count):
        house = generate_house(house_seed(seed, i), toy_house_id(seed, i))
        folder = Path(out) / house.id
        try:
            write_house(house, folder)
        except OSError as e:
            raise SceneforgeError(f"toy houses: cannot write {folder}: {e.strerror or e}") from None
        folders.append(folder)
        if progress is not None:
            progress(house, folder)
    return folders


def write_bundle(out: str | Path | None = None) -> list[Path]:
    """(Re)write the bundled toy houses (into the package unless ``out`` is given)."""
    return write_toy_houses(out or bundled_toy_dir(), BUNDLE_COUNT, BUNDLE_SEED)


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description="Regenerate sceneforge's bundled toy houses.")
    parser.add_argument("--bundle", action="store_true", required=True,
                        help=f"write houses toy_{BUNDLE_SEED}_000.. into sceneforge/data/toy_houses")
    parser.parse_args()
    for folder in write_bundle():
        print(folder)
