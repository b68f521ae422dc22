"""Hand-made houses with the hard cases of real datasets, with known floors.

Every room is a box room like ``conftest.box_room`` (floor, ceiling and four walls, each a
closed 0.1 m slab) placed anywhere, on any floor height, with any room id, and furnished
with a fixed set of boxes against its walls, so that sampled views see objects.
"""

from __future__ import annotations

from sceneforge.houses import House, Level, Room

from .conftest import box_instance

FLOOR, CEILING, WALL, FLOOR_MAT = 2, 22, 1, 20
SLAB = 0.1


def add_box_room(house: House, room_id: str, center=(0.0, 0.0), size: float = 5.0, height: float = 2.8,
                 floor_top: float = 0.0, wall_category: int = WALL, level: int = 0,
                 room_type: str = "room", walls=(0, 1, 2, 3)) -> None:
    """Add a size × height × size m room around (x, z) ``center`` whose floor top is at
    ``floor_top``, and its :class:`Room` record on ``level``. ``walls`` are the walls built:
    0 at -x, 1 at +x, 2 at -z, 3 at +z (void ones, ``wall_category`` 0, are labelled
    "room_skeleton")."""
    house.rooms.append(Room(room_id, room_type, level))
    cx, cz = center
    half, y0 = size / 2, floor_top
    box_instance(house, f"{room_id}_floor", FLOOR, (size, SLAB, size), (cx, y0 - SLAB / 2, cz), room_id)
    box_instance(house, f"{room_id}_ceiling", CEILING, (size, SLAB, size), (cx, y0 + height + SLAB / 2, cz),
                 room_id)
    for i, (ext, c) in enumerate([((SLAB, height, size), (cx - half - SLAB / 2, cz)),
                                  ((SLAB, height, size), (cx + half + SLAB / 2, cz)),
                                  ((size, height, SLAB), (cx, cz - half - SLAB / 2)),
                                  ((size, height, SLAB), (cx, cz + half + SLAB / 2))]):
        if i not in walls:
            continue
        box_instance(house, f"{room_id}_wall{i}", wall_category, ext, (c[0], y0 + height / 2, c[1]), room_id,
                     label="room_skeleton" if wall_category == 0 else None)


def furnish(house: House, room_id: str, center=(0.0, 0.0), floor_top: float = 0.0) -> None:
    """Add a sofa, a table, a cabinet, a bookshelf and a chair to a 5 × 5 m room, standing
    on its floor against the walls and in the middle, leaving free floor to stand on."""
    cx, cz = center
    for name, category, ext, (x, z) in [
        ("sofa", 6, (2.0, 0.8, 0.9), (0.0, -1.95)),
        ("table", 7, (1.2, 0.75, 0.8), (0.3, -0.2)),
        ("cabinet", 3, (0.6, 1.8, 0.5), (2.1, 1.6)),
        ("bookshelf", 10, (0.35, 2.0, 1.0), (-2.2, 1.0)),
        ("chair", 5, (0.45, 0.9, 0.45), (-0.6, 0.6)),
    ]:
        box_instance(house, f"{room_id}_{name}", category, ext, (cx + x, floor_top + ext[1] / 2, cz + z), room_id)


def rug_room(covered: tuple[float, float] = (-2.5, 2.0), thickness: float = 0.01, walls=(0, 1, 2, 3)) -> House:
    """A furnished 5 × 2.8 × 5 m room (floor top y = 0) whose rug (NYU40 floor_mat, source
    label "rug") lies ``thickness`` m thick on the floor over the whole width and z in
    ``covered``: by default 90 % of the floor, leaving a 0.5 m strip bare along the z = 2.5
    wall. The level's ``floor_y`` is the bottom of the floor slab (-0.1), as SUNCG's
    bounding-box levels are."""
    house = House(id="rug_room", instances=[], levels=[Level(0, -SLAB)])
    add_box_room(house, "r0", room_type="bedroom", walls=walls)
    z0, z1 = covered
    box_instance(house, "rug", FLOOR_MAT, (5.0, thickness, z1 - z0), (0.0, thickness / 2, 0.5 * (z0 + z1)), "r0",
                 label="rug")
    furnish(house, "r0")
    return house


def two_level_house(upper_floor_top: float = 3.0) -> House:
    """Two furnished 5 × 2.8 × 5 m rooms stacked: r0 on level 0 (floor top 0), r1 on level 1
    (floor top ``upper_floor_top``, its slab on r0's ceiling). Levels are at the bottoms of
    their floor slabs."""
    house = House(id="two_levels", instances=[], levels=[Level(0, -SLAB), Level(1, upper_floor_top - SLAB)])
    add_box_room(house, "r0", level=0)
    furnish(house, "r0")
    add_box_room(house, "r1", floor_top=upper_floor_top, height=2.8, level=1)
    furnish(house, "r1", floor_top=upper_floor_top)
    return house


def three_room_house() -> House:
    """Three furnished 5 × 2.8 × 5 m rooms r0, r1, r2 side by side along x (centres x = 0,
    5.2, 10.4), each with its own walls, floor top y = 0."""
    house = House(id="three_rooms", instances=[])
    for k in range(3):
        center = (5.2 * k, 0.0)
        add_box_room(house, f"r{k}", center=center)
        furnish(house, f"r{k}", center=center)
    return house
