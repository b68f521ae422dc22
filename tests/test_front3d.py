"""3D-FRONT loader and writer: round trip, the quaternion convention, categories, bad input."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from sceneforge.errors import HouseError
from sceneforge.houses import House, LoadOptions, Material, Room, discover, load
from sceneforge.houses.formats import front3d
from sceneforge.testing.front3d import write_house

from .conftest import assert_same_geometry, box_instance


def _volume(inst) -> float:
    return trimesh.Trimesh(inst.vertices, inst.faces, process=False).volume


# ---- round trip -------------------------------------------------------------------------


def test_round_trip_small_house(small_house, tmp_path):
    path = write_house(small_house, tmp_path)
    assert path == tmp_path / "3D-FRONT" / "small.json"
    [source] = discover(tmp_path)
    assert (source.id, source.format) == ("small", "front3d")
    back = load(source)
    assert back.source_format == "front3d" and back.warnings == []
    assert_same_geometry(small_house, back, atol=1e-12)  # one room: the order is kept
    for a, b in zip(small_house.instances, back.instances):
        np.testing.assert_allclose(b.vertices, a.vertices, atol=1e-12)
        np.testing.assert_array_equal(b.faces, a.faces)
    # object labels survive; envelope labels unknown to 3D-FRONT ("wall0") become the class name
    assert [i.label for i in back.instances] == ["floor", "ceiling", "wall", "wall", "wall", "wall",
                                                 "table", "chair", "cup"]
    assert [(r.id, r.type, r.level) for r in back.rooms] == [("r0", "kitchen", 0)]


def test_round_trip_toy_house(tmp_path):
    from sceneforge.houses.toy import generate_house

    house = generate_house(0)
    back = load(write_house(house, tmp_path))
    assert back.warnings == []
    rooms = [r.id for r in house.rooms]
    # documented order: room by room (house order), the room-less last, house order inside a room
    expected = sorted(house.instances, key=lambda i: rooms.index(i.room_id) if i.room_id else len(rooms))
    assert len(back.instances) == len(expected)
    for a, b in zip(expected, back.instances):
        assert (a.category, a.room_id, a.envelope) == (b.category, b.room_id, b.envelope)
        assert b.label in (a.label, a.category_name)
        np.testing.assert_allclose(b.vertices, a.vertices, atol=1e-12)
        np.testing.assert_array_equal(b.faces, a.faces)
    assert [(r.id, r.type, r.level) for r in back.rooms] == [(r.id, r.type, r.level) for r in house.rooms]


def test_round_trip_rooms_materials_textures(tmp_path):
    tex = tmp_path / "checker.png"
    pixels = np.arange(48, dtype=np.uint8).reshape(4, 4, 3)
    Image.fromarray(pixels).save(tex)
    h = House(id="flat", instances=[], rooms=[Room("LivingRoom-1", "LivingRoom", 0), Room("Bedroom-2", "Bedroom", 0)])
    box_instance(h, "bed", 4, (2, 0.5, 1.6), (3, 0.25, 0), room_id="Bedroom-2", label="King-size Bed")
    floor = box_instance(h, "floor", 2, (4, 0.1, 4), (0, -0.05, 0), room_id="LivingRoom-1", label="Floor")
    floor.material = Material(base_color=(0.2, 0.4, 0.6, 1.0), texture=tex)
    floor.uv = np.random.default_rng(1).random((len(floor.vertices), 2)).astype(np.float32)
    sofa = box_instance(h, "sofa", 6, (2, 0.8, 0.9), (0, 0.4, 1), room_id="LivingRoom-1", label="Loveseat Sofa")
    sofa.material = Material(base_color=(0.1, 0.2, 0.3, 0.5), texture=tex)
    sofa.uv = np.random.default_rng(2).random((len(sofa.vertices), 2)).astype(np.float32)
    box_instance(h, "lamp", 35, (0.3, 0.3, 0.3), (9, 2, 9), room_id=None, label="Pendant Lamp")
    # a label that 3D-FRONT maps to another class (chair) is replaced by the NYU40 name
    box_instance(h, "pouf", 39, (0.4, 0.4, 0.4), (1, 0.2, 3), room_id="Bedroom-2", label="armchair")
    write_house(h, tmp_path / "front")
    back = load(tmp_path / "front" / "3D-FRONT" / "flat.json")
    # room by room, rooms in house order, the room-less last
    assert [i.label for i in back.instances] == ["Floor", "Loveseat Sofa", "King-size Bed", "otherfurniture",
                                                 "Pendant Lamp"]
    assert [i.room_id for i in back.instances] == ["LivingRoom-1", "LivingRoom-1", "Bedroom-2", "Bedroom-2", None]
    assert [i.category_name for i in back.instances] == ["floor", "sofa", "bed", "otherfurniture", "lamp"]
    assert [(r.id, r.type) for r in back.rooms] == [("LivingRoom-1", "LivingRoom"), ("Bedroom-2", "Bedroom")]
    b_floor, b_sofa = back.instances[:2]
    assert b_floor.material.base_color == pytest.approx(floor.material.base_color, abs=0.5 / 255)
    assert b_sofa.material.base_color == sofa.material.base_color  # an MTL keeps full precision
    for src, b in ((floor, b_floor), (sofa, b_sofa)):
        np.testing.assert_array_equal(np.asarray(Image.open(b.material.texture)), pixels)
        np.testing.assert_allclose(b.uv, src.uv, atol=1e-7)
        np.testing.assert_allclose(b.vertices, src.vertices, atol=1e-12)
    info = json.loads((tmp_path / "front" / "3D-FUTURE-model" / "model_info.json").read_text())
    assert {e["category"]: e["super-category"] for e in info} == {
        "Loveseat Sofa": "sofa", "King-size Bed": "bed", "otherfurniture": "otherfurniture", "Pendant Lamp": "lamp"}


# ---- a hand-made scene --------------------------------------------------------------------

MODEL = trimesh.creation.box(extents=(0.5, 1.0, 2.0))  # asymmetric, centred on its origin, volume 1


def _obj(mesh) -> str:
    return "".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in mesh.vertices.tolist()) + "".join(
        f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in mesh.faces.tolist())


def _child(ref, k, pos=(0, 0, 0), rot=(0, 0, 0, 1), scale=(1, 1, 1)):
    return {"ref": ref, "instanceid": f"furniture/{k}", "pos": list(pos), "rot": list(rot), "scale": list(scale)}


S = math.sin(math.pi / 4)
C = math.cos(math.pi / 4)


def _scene(tmp_path: Path, *, furniture, children, meshes=(), info=(), models=("m-chair",)) -> Path:
    """A 3D-FRONT root: ``models`` get MODEL as raw_model.obj, ``info`` is model_info.json
    (None: none); one room holds ``children``."""
    future = tmp_path / "3D-FUTURE-model"
    for jid in models:
        (future / jid).mkdir(parents=True)
        (future / jid / "raw_model.obj").write_text(_obj(MODEL))
    future.mkdir(exist_ok=True)
    if info is not None:
        (future / "model_info.json").write_text(json.dumps(list(info)))
    doc = {"uid": "scene1", "furniture": furniture, "mesh": list(meshes), "material": [],
           "scene": {"room": [{"type": "Bedroom", "instanceid": "Bedroom-7", "children": children}]}}
    path = tmp_path / "3D-FRONT" / "scene1.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(doc))
    return path


# the title names the class before the entry's coarser category (model_info has no m-chair)
CHAIR = {"uid": "u-chair", "jid": "m-chair", "title": "chair", "category": "Dining Chair", "valid": True}


def test_quaternion_is_xyzw_and_placement_is_pos_plus_rotated_scaled(tmp_path):
    path = _scene(tmp_path, furniture=[CHAIR], children=[
        _child("u-chair", 0, pos=(1, 0, 2), rot=(0, S, 0, C), scale=(2, 1, 1)),  # +90° about +Y
        _child("u-chair", 1, rot=(S, 0, 0, C)),  # +90° about +X
    ])
    house = load(path)
    ry = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]])  # x → -z, z → x
    rx = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])  # y → z, z → -y
    v = np.asarray(MODEL.vertices)
    np.testing.assert_allclose(house.instances[0].vertices, (v * (2, 1, 1)) @ ry.T + (1, 0, 2), atol=1e-12)
    np.testing.assert_allclose(house.instances[1].vertices, v @ rx.T, atol=1e-12)
    assert [_volume(i) for i in house.instances] == pytest.approx([2.0, 1.0])
    assert [(i.category_name, i.label, i.room_id) for i in house.instances] == [
        ("chair", "chair", "Bedroom-7")] * 2


def test_mirroring_scale_flips_winding(tmp_path):
    path = _scene(tmp_path, furniture=[CHAIR], children=[_child("u-chair", 0, scale=(-1, 1, 1))])
    inst = load(path).instances[0]
    np.testing.assert_array_equal(inst.faces, np.asarray(MODEL.faces)[:, ::-1])
    assert _volume(inst) == pytest.approx(1.0)


def test_missing_model_is_counted_and_skips_that_piece(tmp_path):
    ghost = {"uid": "u-ghost", "jid": "m-ghost", "category": "Sofa", "valid": True}
    path = _scene(tmp_path, furniture=[CHAIR, ghost],
                  children=[_child("u-ghost", 0), _child("u-chair", 1), _child("u-ghost", 2)])
    house = load(path)
    assert [i.label for i in house.instances] == ["chair"]
    assert house.losses == {front3d.NO_MODEL: 2}
    assert house.warnings == [f"{front3d.NO_MODEL}: 2"]


def test_category_sources_drop_and_invalid(tmp_path):
    ok = {"valid": True}
    furniture = [
        {"uid": "a", "jid": "m-a", **ok},  # no category: model_info's category
        {"uid": "b", "jid": "m-b", "category": "  double   BED ", **ok},  # spacing and case do not matter
        {"uid": "c", "jid": "m-c", "title": "Desk", **ok},  # neither: the title
        {"uid": "d", "jid": "m-d", "category": "Plants", **ok},  # dropped
        {"uid": "e", "jid": "m-e", "category": "Sofa", "valid": False},  # unreleased
        {"uid": "f", "jid": "m-f", **ok},  # model_info: empty category, super-category decides
        {"uid": "g", "jid": "m-g", "category": "Sofa"},  # no 'valid': unreleased too
    ]
    info = [{"model_id": "m-a", "category": "Nightstand", "super-category": "Cabinet/Shelf/Desk"},
            {"model_id": "m-f", "category": "", "super-category": "Others"}]
    path = _scene(tmp_path, furniture=furniture, info=info, models=["m-a", "m-b", "m-c", "m-d", "m-e", "m-f", "m-g"],
                  children=[_child(u, k) for k, u in enumerate("abcdefg")])
    house = load(path)
    assert [(i.label, i.category_name) for i in house.instances] == [
        ("Nightstand", "night_stand"), ("double   BED", "bed"), ("Desk", "desk"), ("Others", "otherprop")]
    assert house.losses == {front3d.DROPPED: 1, front3d.UNRELEASED: 2}


def test_architecture_meshes(tmp_path):
    quad = {"xyz": [-2, 0, -2, -2, 0, 2, 2, 0, 2, 2, 0, -2], "faces": [0, 1, 2, 0, 2, 3],
            "uv": [0, 0, 0, 1, 1, 1, 1, 0], "normal": [0, 1, 0] * 4}
    meshes = [{"uid": "m1", "type": "Floor", "material": "mat1", **quad},
              {"uid": "m2", "type": "WallInner", **quad},
              {"uid": "m3", "type": "Door", **quad}]
    path = _scene(tmp_path, furniture=[], meshes=meshes, models=(),
                  children=[{"ref": "m1", "instanceid": "mesh/1"}, {"ref": "m2", "instanceid": "mesh/2"},
                            {"ref": "m3", "instanceid": "mesh/3"}, {"ref": "light-9", "instanceid": "light/9"}])
    doc = json.loads(path.read_text())
    doc["material"] = [{"uid": "mat1", "color": [255, 0, 51, 255], "texture": "https://x/tex-1/texture.png"}]
    (tmp_path / "3D-FRONT-texture" / "tex-1").mkdir(parents=True)
    Image.new("RGB", (2, 2)).save(tmp_path / "3D-FRONT-texture" / "tex-1" / "texture.png")
    path.write_text(json.dumps(doc))
    house = load(path)
    assert house.losses == {front3d.DANGLING: 1}  # light-9
    assert [(i.category_name, i.label, i.envelope, i.room_id) for i in house.instances] == [
        ("floor", "Floor", True, "Bedroom-7"), ("wall", "WallInner", True, "Bedroom-7"),
        ("door", "Door", True, "Bedroom-7")]
    floor = house.instances[0]
    assert floor.material.base_color == (1.0, 0.0, 0.2, 1.0)
    assert floor.material.texture == tmp_path / "3D-FRONT-texture" / "tex-1" / "texture.png"
    np.testing.assert_array_equal(floor.uv, [[0, 0], [0, 1], [1, 1], [1, 0]])
    assert trimesh.Trimesh(floor.vertices, floor.faces).face_normals[:, 1] == pytest.approx([1, 1])


def test_meshes_without_a_type_get_one_from_constructid_or_uid(tmp_path):
    """Real files' customised feature models have an empty ``type``: the rest of their
    construct types them, else their uid and orientation; ``--strict`` then passes."""
    wall = {"xyz": [-2, 0, -1.9, -2, 2.6, -1.9, 2, 2.6, -1.9, 2, 0, -1.9], "faces": [0, 1, 2, 0, 2, 3]}
    high = {"xyz": [-2, 2.7, -2, 2, 2.7, -2, 2, 2.7, 2, -2, 2.7, 2], "faces": [0, 1, 2, 0, 2, 3]}
    low = {"xyz": [-1, 0.1, -1, -1, 0.1, 1, 1, 0.1, 1, 1, 0.1, -1], "faces": [0, 1, 2, 0, 2, 3]}
    meshes = [{"uid": "6911/customizedfeaturemodel_1/0", "type": "", **wall},
              {"uid": "6911/customizedfeaturemodel_2/0", "type": "", **high},
              {"uid": "6911/customizedfeaturemodel_3/0", "type": "", **low},
              {"uid": "6911/customizedfeaturemodel_4/0", "type": "", "constructid": "c7", **low},
              {"uid": "6911/model_5/0", "type": "CustomizedFixedFurniture", "constructid": "c7", **high},
              {"uid": "6911/other_6/0", "type": "", **low}]
    children = [{"ref": m["uid"], "instanceid": f"mesh/{k}"} for k, m in enumerate(meshes)]
    path = _scene(tmp_path, furniture=[], meshes=meshes[:5], models=(), children=children[:5])
    house = load(path, LoadOptions(strict=True))
    assert [(i.category_name, i.label, i.envelope) for i in house.instances] == [
        ("wall", "CustomizedFeatureWall", True), ("ceiling", "CustomizedCeiling", True),
        ("floor", "CustomizedPlatform", True),
        ("otherfurniture", "CustomizedFixedFurniture", False)]  # the construct c7: one instance
    assert len(house.instances[3].faces) == 4
    assert house.losses == {front3d.UNTYPED: 4}
    from click.testing import CliRunner
    from sceneforge.cli.main import cli

    result = CliRunner().invoke(cli, ["houses", "inspect", str(path), "--strict"])
    assert result.exit_code == 0 and f"problem: {front3d.UNTYPED}: 4" in result.output, result.output
    # a mesh whose file says nothing still has no category
    (tmp_path / "b").mkdir()
    path = _scene(tmp_path / "b", furniture=[], meshes=meshes, models=(), children=children)
    with pytest.raises(HouseError, match="mesh without a category"):
        load(path, LoadOptions(strict=True))


def test_unknown_category_void_or_strict_error(tmp_path):
    odd = {"uid": "u-odd", "jid": "m-chair", "category": "Spaceship", "valid": True}
    path = _scene(tmp_path, furniture=[odd], children=[_child("u-odd", 0)])
    house = load(path)
    assert (house.instances[0].category, house.instances[0].label) == (0, "Spaceship")
    assert house.warnings == ["unknown category 'Spaceship' mapped to void"]
    with pytest.raises(HouseError, match=r"house scene1: .*scene1.json: unknown category 'Spaceship'"):
        load(path, LoadOptions(strict=True))


def test_future_dir_option_and_missing_model_folder(tmp_path):
    path = _scene(tmp_path / "a", furniture=[CHAIR], children=[_child("u-chair", 0)])
    moved = tmp_path / "elsewhere"
    (tmp_path / "a" / "3D-FUTURE-model").rename(moved)
    with pytest.raises(HouseError, match=r"3D-FUTURE model folder not found \(pass --future-dir\)"):
        load(path)
    assert len(load(path, LoadOptions(future_dir=str(moved))).instances) == 1


@pytest.mark.parametrize("child, message", [
    ({"rot": [0, 0, 0, 0]}, "non-zero quaternion"),
    ({"pos": [1, 2]}, r"child 'furniture/0': pos/rot/scale must be"),
])
def test_bad_placement_skips_that_piece_with_a_warning(tmp_path, child, message):
    path = _scene(tmp_path, furniture=[CHAIR], children=[{**_child("u-chair", 0), **child}, _child("u-chair", 1)])
    house = load(path)
    assert [i.name for i in house.instances] == ["chair#furniture/1"]
    assert re.search(message, house.warnings[0]) and house.losses == {front3d.BAD_PIECE: 1}
    with pytest.raises(HouseError, match=message):  # nothing else left: the house fails, saying why
        load(_scene(tmp_path / "alone", furniture=[CHAIR], children=[{**_child("u-chair", 0), **child}]))


def test_bad_mesh_arrays_skip_that_mesh_with_a_warning(tmp_path):
    meshes = [{"uid": "m1", "type": "Floor", "xyz": [0, 0, 0, 1], "faces": [0, 1, 2]}]
    path = _scene(tmp_path, furniture=[CHAIR], meshes=meshes,
                  children=[{"ref": "m1", "instanceid": "mesh/1"}, _child("u-chair", 0)])
    house = load(path)
    assert len(house.instances) == 1 and house.losses == {front3d.BAD_PIECE: 1}
    assert house.warnings[0].startswith("mesh 'm1': 'xyz' and 'faces' must be flat lists of 3k numbers")


def test_count_loss_keeps_one_running_line_per_reason():
    house = House(id="h", instances=[], warnings=["an earlier repair"])
    house.count_loss("pieces skipped")
    house.count_loss("children dangling", 3)
    house.count_loss("pieces skipped", 2)
    assert house.losses == {"pieces skipped": 3, "children dangling": 3}
    assert house.warnings == ["an earlier repair", "pieces skipped: 3", "children dangling: 3"]
