"""One toy house from a seed: the plan made into instances with colours of their own."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...conventions import NYU40_IDS
from ...errors import SceneforgeError
from ..model import House, Level, Material, Room, make_instance
from .planner import Opening, envelope, plan_house
from .primitives import mesh

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


def check_seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise SceneforgeError(f"toy houses: seed must be a non-negative integer, got {seed!r}")
    return int(seed)


def build_toy_house(seed: int, house_id: str | None = None) -> ToyHouse:
    """Generate the toy house of ``seed`` and the facts tests need about it.

    The same ``seed`` always gives the same house, down to the bytes it is written as.
    """
    seed = check_seed(seed)
    rng = np.random.default_rng(seed)
    house = House(id=house_id or f"toy_{seed}", instances=[], levels=[Level(0, 0.0)],
                  source_format="toy", source_path=None)
    rooms, openings = plan_house(rng)
    names: dict[int, str] = {}
    used: set[tuple[float, ...]] = set()
    for room in rooms:
        house.rooms.append(Room(room.id, room.type, 0))
        counts: dict[str, int] = {}
        for piece in envelope(room) + room.pieces:
            k = counts[piece.label] = counts.get(piece.label, -1) + 1
            v, f = mesh(piece.parts)
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
