"""One toy house from a seed: the plan made into instances with colours of their own."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...conventions import NYU40_IDS
from ...errors import SceneforgeError
from ..model import House, Level, Material, Room, make_instance
from .colours import instance_colour
from .hard_cases import ToyOptions, apply_hard_cases
from .planner import Opening, envelope, plan_house
from .primitives import mesh


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


def build_toy_house(seed: int, house_id: str | None = None, options: ToyOptions | None = None) -> ToyHouse:
    """Generate the toy house of ``seed`` and the facts tests need about it, with the hard
    cases ``options`` asks for (:mod:`.hard_cases`; None: none).

    The same ``seed`` and options always give the same house, down to the bytes it is written as.
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
                material=Material(base_color=instance_colour(rng, piece.category, used)),
            )
            names[id(piece)] = inst.name
    pieces = [p for room in rooms for p in room.pieces]
    toy = ToyHouse(
        house=house.check_not_empty(),
        openings=openings,
        interiors={r.id: (r.lo, r.hi) for r in rooms},
        supports=[(names[id(p)], names[id(p.support)]) for p in pieces if p.support is not None],
        tucked=[(names[id(p)], names[id(p.under)]) for p in pieces if p.under is not None],
    )
    if options is None or not options.any:
        return toy
    # a generator of its own: the default house's draws stay as they are
    return apply_hard_cases(toy, options, np.random.default_rng([seed, 1]))


def generate_house(seed: int, house_id: str | None = None, options: ToyOptions | None = None) -> House:
    """The toy house of ``seed`` (id ``house_id``, default ``toy_<seed>``) with the hard cases
    ``options`` asks for; see the module doc."""
    return build_toy_house(seed, house_id, options).house
