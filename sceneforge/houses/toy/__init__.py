"""Procedural toy houses: small furnished multi-room houses, deterministic from a seed.

A toy house is a grid of 2–4 rooms (living room, bedroom and some of kitchen, bathroom,
office, dining room) on one level with ``floor_y = 0``:

- every room owns its envelope: a 5 cm floor slab, a ceiling slab, its 0.2 m exterior
  walls and the partitions on its north and east sides, all closed boxes. A wall between
  two rooms is one 0.1 m partition shared by both, each of its faces a wall of one room;
  a floor slab has an underside. Real houses are built so, and their ground truth must
  leave out what no camera sees (docs/spec.md §5.2). Floors and ceilings cover the walls' footprint
  too, so no ray can leave through a seam;
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

The modules follow the steps: :mod:`.primitives` (boxes, cylinders, placements),
:mod:`.furniture` (the builders), :mod:`.planner` (rooms, openings, placing furniture),
:mod:`.colours` (a colour of its own per instance), :mod:`.house` (a plan made a
:class:`~sceneforge.houses.House`), :mod:`.bundle` (batches and the bundled set),
:mod:`.hard_cases` (room-sized rugs, two levels and stairs, hidden floors and ceilings:
:class:`ToyOptions`, off by default). Regenerate the bundled houses with
``python -m sceneforge.houses.toy --bundle``.
"""

from .bundle import BUNDLE_COUNT, BUNDLE_SEED, house_seed, toy_house_id, write_bundle, write_toy_houses
from .hard_cases import ToyOptions
from .house import ToyHouse, build_toy_house, generate_house
from .planner import Opening

__all__ = [
    "BUNDLE_COUNT", "BUNDLE_SEED", "Opening", "ToyHouse", "ToyOptions", "build_toy_house",
    "generate_house", "house_seed", "toy_house_id", "write_bundle", "write_toy_houses",
]
