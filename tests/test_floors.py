"""Floor surfaces: what a camera stands on and where a view's heights start."""

from __future__ import annotations

import numpy as np
import pytest

from sceneforge.floors import floor_surfaces, level_at
from sceneforge.houses import House, Level, make_instance

from .conftest import box_instance
from .hard_houses import two_level_house


def test_walkable_faces_are_the_slab_tops_with_rooms_and_levels():
    house = two_level_house()
    floors = floor_surfaces(house)
    # two slabs, each a box: only the 2 top triangles of each are walkable
    assert len(floors) == 4
    assert floors.top.tolist() == [0.0, 0.0, 3.0, 3.0]
    assert floors.room.tolist() == ["r0", "r0", "r1", "r1"]
    assert floors.level.tolist() == [0, 0, 1, 1]
    assert floors.area.sum() == pytest.approx(50.0)
    assert (np.cross(floors.corners[:, 1] - floors.corners[:, 0],
                     floors.corners[:, 2] - floors.corners[:, 0])[:, 1] > 0).all()


def test_the_floor_below_a_point_is_the_highest_one_not_above_it():
    floors = floor_surfaces(two_level_house())
    assert floors.height_below([0.3, 1.5, -0.2]) == 0.0
    assert floors.height_below([0.3, 4.5, -0.2]) == 3.0
    assert floors.height_below([0.3, 3.0005, -0.2]) == 3.0  # within tol.eye_above_floor
    assert floors.height_below([0.3, -1.0, -0.2]) is None
    assert floors.height_below([2.5, 1.5, 2.5]) == 0.0  # a corner of the slab counts
    assert floors.height_below([2.6, 1.5, 0.0]) is None
    assert floors.level_height(1, 4.5) == 3.0 and floors.level_height(1, 1.5) is None


def test_a_sloped_flipped_roomless_floor():
    # A ramp rising 0.2 m over 4 m along x, wound clockwise (facing down), without a room,
    # in a house with levels at 0 and 2.5.
    house = House(id="ramp", instances=[], levels=[Level(0, 0.0), Level(1, 2.5)])
    make_instance(house, name="ramp", category=2, label="floor", room_id=None,
                  vertices=[[0, 0, 0], [4, 0.2, 0], [4, 0.2, 4], [0, 0, 4]], faces=[[0, 2, 1], [0, 3, 2]])
    box_instance(house, "upper", 2, (4, 0.1, 4), (10, 2.45, 0), room_id=None)
    floors = floor_surfaces(house)
    assert len(floors) == 2 + 2
    assert floors.level.tolist() == [0, 0, 1, 1]
    assert floors.height_below([2.0, 1.5, 1.0]) == pytest.approx(0.1, abs=1e-12)
    assert floors.height_below([10.0, 4.0, 0.0]) == 2.5
    assert level_at(house, 2.49).id == 0 and level_at(house, 2.5).id == 1 and level_at(house, -3).id == 0
    # the upper slab's top (2.5) is on level 1, though the level's floor_y is not above it
    assert floors.level_height(1, 4.0) == 2.5


def test_level_height_is_the_area_weighted_median_top():
    house = House(id="split", instances=[])
    box_instance(house, "big", 2, (4, 0.1, 4), (0, -0.05, 0), room_id=None)  # top 0, 16 m²
    box_instance(house, "dais", 2, (1, 0.1, 1), (5, 0.25, 0), room_id=None)  # top 0.3, 1 m²
    floors = floor_surfaces(house)
    assert floors.level_height(0, 1.5) == 0.0
    assert floor_surfaces(House(id="none", instances=[])).height_below([0, 1, 0]) is None
