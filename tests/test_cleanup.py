"""The geometry passes after a generic scene is named (:mod:`sceneforge.houses.cleanup`): a closed
room box split into wall, floor and ceiling whatever its name, and the light emitters outside
every room dropped. Small built scenes with known answers, written and read back as files."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from sceneforge.conventions import NYU40_IDS
from sceneforge.houses import House, LoadOptions, Material, load, make_instance
from sceneforge.houses.cleanup import drop_outside_emitters, split_room_box
from sceneforge.testing.generic import write_house

W, H, D = 4.0, 2.5, 5.0  # the room: 0..W × 0..H × 0..D
#: what an area light of a modelling tool gives off (more than 1: written with a strength in glTF)
GLOW = (2.0, 2.0, 1.5)


def _box(house, name, lo, hi, *, inward=False, category=0, material=None, open_top=False):
    b = trimesh.creation.box(bounds=np.array([lo, hi], float))
    faces = b.faces[:, ::-1] if inward else b.faces
    if open_top:
        faces = faces[b.triangles_center[:, 1] < hi[1] - 1e-9]
    return make_instance(house, name=name, category=category, label=name, room_id=None, vertices=b.vertices,
                         faces=faces, material=material)


def _quad(house, name, centre, size=2.0, material=None, category=0):
    """An upright area-light quad facing -x at ``centre``."""
    c, s = np.asarray(centre, float), size / 2
    v = c + np.array([(0, -s, -s), (0, -s, s), (0, s, s), (0, s, -s)])
    return make_instance(house, name=name, category=category, label=name, room_id=None, vertices=v,
                         faces=[(0, 1, 2), (0, 2, 3)], material=material)


def _furnished(house):
    _box(house, "Chair", (1, 0, 1), (1.5, 0.9, 1.5))
    _box(house, "Table", (2, 0, 2), (3.2, 0.75, 3))


def _area(inst) -> float:
    return float(trimesh.Trimesh(inst.vertices, inst.faces, process=False).area)


@pytest.mark.parametrize("suffix", [".obj", ".glb"])
@pytest.mark.parametrize("name, inward", [("Wall", True), ("Cube.001", False), ("Room", True)])
def test_a_closed_room_box_is_split_whatever_its_name(tmp_path, suffix, name, inward):
    h = House(id="box", instances=[])
    _box(h, name, (0, 0, 0), (W, H, D), inward=inward)
    _furnished(h)
    back = load(write_house(h, tmp_path / f"room{suffix}", names=[i.name for i in h.instances]))
    got = {i.name: (i.category_name, round(_area(i), 6)) for i in back.instances}
    assert got == {f"{name}/wall": ("wall", 2 * (W + D) * H), f"{name}/floor": ("floor", W * D),
                   f"{name}/ceiling": ("ceiling", W * D), "Chair": ("chair", 2.3), "Table": ("table", 5.7)}
    assert [i.id for i in back.instances] == list(range(5))
    assert [r.id for r in back.rooms] == ["room_0"] and {i.room_id for i in back.instances} == {"room_0"}
    assert sum("closed room" in w for w in back.warnings) == 1


def test_a_box_the_user_names_stays_whole(tmp_path):
    h = House(id="box", instances=[])
    _box(h, "Wall", (0, 0, 0), (W, H, D), inward=True)
    _furnished(h)
    path = write_house(h, tmp_path / "room.obj", names=["Wall", "Chair", "Table"])
    mapping = tmp_path / "map.json"
    mapping.write_text(json.dumps([["^wall$", "wall"]]))
    back = load(path, LoadOptions(name_map=str(mapping)))
    assert [(i.name, i.category_name) for i in back.instances] == [("Wall", "wall"), ("Chair", "chair"),
                                                                   ("Table", "table")]
    assert back.rooms == []


@pytest.mark.parametrize("case", ["an object outside it", "wardrobe", "open top"])
def test_what_is_not_a_room_box_stays_whole(case):
    h = House(id="not", instances=[])
    if case == "wardrobe":  # a closed box holding things, but 0.6 m deep: no room-sized floor
        _box(h, "Wardrobe", (0, 0, 0), (1.2, 2.0, 0.6), category=NYU40_IDS["cabinet"])
        _box(h, "Shirt", (0.2, 1.0, 0.1), (0.5, 1.6, 0.3))
    else:
        _box(h, "Wall", (0, 0, 0), (W, H, D), inward=True, open_top=case == "open top")
        _furnished(h)
        if case == "an object outside it":
            _box(h, "Bench", (W + 0.5, 0, 1), (W + 1.0, 0.5, 2))
    before = [(i.name, i.category) for i in h.instances]
    assert split_room_box(h) is None
    assert [(i.name, i.category) for i in h.instances] == before and not h.warnings


def _room_with_lights(h, lamp_material=None):
    """A room as separate floor and walls, a lamp over the table, a glowing panel in it, and
    the lights of the original scene outside: four area lights 5-7 m out, a glowing plane
    named nothing, a garden lamp; and a porch light just outside the wall (kept)."""
    glow = Material((1, 1, 1, 1), emission=GLOW)
    _box(h, "Floor", (0, -0.1, 0), (W, 0, D))
    _box(h, "Walls_Outer", (-0.2, 0, -0.2), (0, H, D + 0.2))
    _furnished(h)
    _box(h, "Lamp", (2.4, 1.8, 2.3), (2.8, 2.2, 2.7))
    _quad(h, "Plane.004", (W - 0.01, 1.5, 2.5), size=0.5, material=glow)
    _quad(h, "BackLight", (W + 6, 1.5, 2.5), material=lamp_material)
    _quad(h, "FrontLight", (-6, 1.5, 2.5), material=lamp_material)
    _quad(h, "LeftLight", (2, 1.5, -5), material=lamp_material)
    _quad(h, "RightLight", (2, 1.5, D + 7), material=lamp_material)
    _quad(h, "Plane.003", (W + 5, 3, 4), material=glow)
    _box(h, "Lamp_Garden", (W + 3, 0, 8), (W + 3.3, 1, 8.3))
    _box(h, "PorchLight", (-0.6, 2, 1), (-0.3, 2.3, 1.3))


@pytest.mark.parametrize("suffix", [".glb", ".gltf", ".obj"])
def test_light_emitters_outside_every_room_are_dropped(tmp_path, suffix):
    h = House(id="lights", instances=[])
    _room_with_lights(h)
    back = load(write_house(h, tmp_path / f"scene{suffix}", names=[i.name for i in h.instances]))
    assert [i.name for i in back.instances] == ["Floor", "Walls_Outer/wall", "Chair", "Table", "Lamp",
                                                "Plane.004", "PorchLight"]
    assert [i.id for i in back.instances] == list(range(7))
    assert back.instances[5].category_name == "void" and back.instances[5].material.emission == GLOW
    dropped = [w for w in back.warnings if "light emitter" in w]
    assert dropped == ["dropped 6 light emitters outside every room: BackLight, FrontLight, LeftLight, "
                       "RightLight, Plane.003 and 1 more (area lights of the original scene)"]
    assert {i.room_id for i in back.instances} == {"room_0"}


def test_the_reported_scene_a_room_box_named_wall_and_its_area_lights(tmp_path):
    # the scene: one closed box "Wall" (normals in) around everything but the four
    # area lights outside the windows; it used to load with no floor and four lamps outside
    h = House(id="reported", instances=[])
    _box(h, "Wall", (0, 0, 0), (W, H, D), inward=True)
    _furnished(h)
    _box(h, "CeilingLampshade", (1.8, 2.1, 2.3), (2.2, 2.5, 2.7))
    for name, centre in (("BackLight", (W + 6, 1.5, 2.5)), ("FrontLight", (-6, 1.5, 2.5)),
                         ("LeftLight", (2, 1.5, -5)), ("RightLight", (2, 1.5, D + 7))):
        _quad(h, name, centre)
    back = load(write_house(h, tmp_path / "scene.glb", names=[i.name for i in h.instances]))
    assert [(i.name, i.category_name) for i in back.instances] == [
        ("Wall/wall", "wall"), ("Wall/floor", "floor"), ("Wall/ceiling", "ceiling"), ("Chair", "chair"),
        ("Table", "table"), ("CeilingLampshade", "lamp")]
    assert "dropped 4 light emitters outside every room: BackLight, FrontLight, LeftLight, RightLight " \
           "(area lights of the original scene)" in back.warnings
    assert len(back.rooms) == 1


def test_without_a_floor_every_emitter_stays():
    h = House(id="nofloor", instances=[])
    _box(h, "Chair", (1, 0, 1), (1.5, 0.9, 1.5))
    _quad(h, "BackLight", (W + 6, 1.5, 2.5), category=NYU40_IDS["lamp"])
    assert drop_outside_emitters(h) == [] and len(h.instances) == 2 and not h.warnings
