"""SUNCG loader and writer: round trip, the house.json rules on a hand-written house, bad input."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from sceneforge.errors import HouseError
from sceneforge.houses import House, Level, LoadOptions, Material, Room, discover, load
from sceneforge.houses.formats.obj import read_obj
from sceneforge.houses.formats.suncg import CSV_FIELDS
from sceneforge.testing.suncg import write_house

from .conftest import box_instance

PARTS = {2: "floor", 22: "ceiling", 1: "wall"}  # in the order the loader reads a room's files


def _volume(inst) -> float:
    return trimesh.Trimesh(inst.vertices, inst.faces, process=False).volume


def _area(instances) -> float:
    return sum(trimesh.Trimesh(i.vertices, i.faces, process=False).area for i in instances)


# ---- round trip -------------------------------------------------------------------------


def _expected_order(house: House) -> list[list]:
    """What the loader gives back, as groups of source instances: level by level, each room's
    floor, ceiling and walls merged (rooms in house order), then the level's other instances."""
    room_level = {r.id: r.level for r in house.rooms}

    def level_of(i):
        if i.room_id is not None:
            return room_level[i.room_id]
        below = [lv for lv in house.levels if lv.floor_y <= i.vertices[:, 1].min()]
        return max(below or [min(house.levels, key=lambda lv: lv.floor_y)], key=lambda lv: lv.floor_y).id

    out = []
    for lv in house.levels:
        for r in (r for r in house.rooms if r.level == lv.id):
            for cat in PARTS:
                group = [i for i in house.instances if i.room_id == r.id and i.category == cat]
                out += [group] if group else []
        out += [[i] for i in house.instances
                if level_of(i) == lv.id and not (i.room_id is not None and i.category in PARTS)]
    return out


def _assert_round_trip(house: House, back: House):
    """Room walls/floors/ceilings come back merged per room and class; the rest one to one."""
    expected = _expected_order(house)
    assert len(back.instances) == len(expected)
    for b, src in zip(back.instances, expected):
        assert (b.category, b.room_id) == (src[0].category, src[0].room_id)
        assert b.envelope == src[0].envelope
        if b.room_id is not None and b.category in PARTS:  # a merged room part
            assert b.label == PARTS[b.category]
            assert len(b.faces) == sum(len(i.faces) for i in src)
            np.testing.assert_allclose(_area([b]), _area(src), rtol=1e-12)
            v = np.concatenate([i.vertices for i in src])
            np.testing.assert_allclose(b.vertices.min(0), v.min(0), atol=1e-12)
            np.testing.assert_allclose(b.vertices.max(0), v.max(0), atol=1e-12)
        else:
            assert b.label == src[0].label
            np.testing.assert_allclose(b.vertices, src[0].vertices, atol=1e-12)
            np.testing.assert_array_equal(b.faces, src[0].faces)
    assert [(r.id, r.type, r.level) for r in back.rooms] == [(r.id, r.type, r.level) for r in house.rooms]
    assert [(lv.id, lv.floor_y) for lv in back.levels] == [(lv.id, lv.floor_y) for lv in house.levels]


def test_round_trip_small_house(small_house, tmp_path):
    path = write_house(small_house, tmp_path)
    assert path == tmp_path / "house" / "small" / "house.json"
    [source] = discover(tmp_path)
    assert (source.id, source.format) == ("small", "suncg")
    back = load(source)
    assert back.source_format == "suncg" and back.warnings == []
    _assert_round_trip(small_house, back)
    assert sum(i.category == 1 for i in back.instances) == 1  # four wall boxes, one wall file


def test_round_trip_toy_house(tmp_path):
    from sceneforge.houses.toy import generate_house

    house = generate_house(0)
    write_house(house, tmp_path)
    back = load(tmp_path / "house" / house.id)
    assert back.warnings == []
    _assert_round_trip(house, back)


def _two_level_house(tmp_path) -> House:
    """Two storeys, a floor outside any room (ground), a textured object, rooms with types."""
    h = House(id="duplex", instances=[], rooms=[Room("fr_0rm_0", "Living_Room,Kitchen", 0),
                                                  Room("fr_1rm_0", "Bedroom", 1)],
              levels=[Level(0, 0.0), Level(1, 3.0)])
    box_instance(h, "floor0", 2, (4, 0.1, 4), (0, -0.05, 0), room_id="fr_0rm_0")
    box_instance(h, "wall0", 1, (0.1, 3, 4), (-2.05, 1.5, 0), room_id="fr_0rm_0")
    box_instance(h, "sofa", 6, (2, 0.8, 0.9), (0, 0.4, 1), room_id="fr_0rm_0")
    box_instance(h, "lawn", 2, (10, 0.02, 10), (0, -0.2, 0), room_id=None, label="ground")
    box_instance(h, "floor1", 2, (4, 0.1, 4), (0, 2.95, 0), room_id="fr_1rm_0")
    box_instance(h, "ceiling1", 22, (4, 0.1, 4), (0, 6.05, 0), room_id="fr_1rm_0")
    bed = box_instance(h, "bed", 4, (2, 0.5, 1.6), (0.5, 3.25, 0), room_id="fr_1rm_0", label="double_bed")
    tex = tmp_path / "src" / "checker.png"
    tex.parent.mkdir()
    Image.fromarray(np.arange(48, dtype=np.uint8).reshape(4, 4, 3)).save(tex)
    bed.material = Material(base_color=(0.25, 0.5, 0.75, 1.0), texture=tex)
    bed.uv = np.random.default_rng(0).random((len(bed.vertices), 2)).astype(np.float32)
    box_instance(h, "fireplace", 38, (1, 1, 0.3), (1.5, 0.5, -1.8), room_id="fr_0rm_0", label="fireplace")
    return h


def test_round_trip_levels_ground_materials(tmp_path):
    house = _two_level_house(tmp_path)
    write_house(house, tmp_path / "suncg")
    # a sceneforge material is colour × texture, which the writer puts in Kd and map_Kd: the
    # multiply rule reads it back as it was (the default, replace, would show the texture alone)
    back = load(tmp_path / "suncg" / "house" / "duplex", LoadOptions(suncg_textures="multiply"))
    _assert_round_trip(house, back)
    ground = next(i for i in back.instances if i.label == "ground")
    assert ground.category == 2 and ground.envelope and ground.room_id is None
    assert next(i for i in back.instances if i.label == "fireplace").envelope
    bed = next(i for i in back.instances if i.label == "double_bed")
    assert bed.material.base_color == (0.25, 0.5, 0.75, 1.0)
    np.testing.assert_array_equal(np.asarray(Image.open(bed.material.texture)),
                                  np.arange(48, dtype=np.uint8).reshape(4, 4, 3))
    np.testing.assert_allclose(bed.uv, house.instances[6].uv, atol=1e-7)
    doc = json.loads((tmp_path / "suncg" / "house" / "duplex" / "house.json").read_text())
    assert [lv["bbox"]["min"][1] for lv in doc["levels"]] == [0.0, 3.0]
    # the bed sits on level 1, listed by level 1's room
    level1 = doc["levels"][1]["nodes"]
    assert [level1[k]["modelId"] for k in level1[0]["nodeIndices"]] == ["duplex_6"]


def test_two_houses_share_one_root_and_category_table(small_house, tmp_path):
    write_house(small_house, tmp_path)
    write_house(_two_level_house(tmp_path), tmp_path)
    assert [s.id for s in discover(tmp_path)] == ["duplex", "small"]
    with open(tmp_path / "metadata" / "ModelCategoryMapping.csv", newline="") as fh:
        ids = [r["model_id"] for r in csv.DictReader(fh)]
    assert len(ids) == len(set(ids)) and {"small_6", "duplex_6"} <= set(ids)
    assert len(load(tmp_path / "house" / "small").instances) == 6


# ---- a hand-written house ---------------------------------------------------------------

EXTENTS = (0.5, 1.0, 2.0)  # an asymmetric box, centred on its origin: volume 1


def _obj(vertices, faces) -> str:
    return "".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in np.asarray(vertices, float).tolist()) + "".join(
        f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in np.asarray(faces).tolist())


def _quad(y, up=True) -> str:
    v = [(-2, y, -2), (-2, y, 2), (2, y, 2), (2, y, -2)]
    return "".join(f"v {x} {yy} {z}\n" for x, yy, z in v) + ("f 1 2 3 4\n" if up else "f 4 3 2 1\n")


BOX = trimesh.creation.box(extents=EXTENTS)
# column-major: translation in elements 12..14
TRANSLATE = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 1, 2, 3, 1]
MIRROR = [-1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 5, 0, 0, 1]
ROT_Y90 = [0, 0, -1, 0, 0, 1, 0, 0, 1, 0, 0, 0, 0, 3, 0, 1]  # columns of Ry(+90°), then (0, 3, 0)


def _write_root(root: Path, doc: dict, files: dict[str, str], rows: list[tuple[str, str, str]]) -> Path:
    for rel, text in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)
    (root / "metadata").mkdir(parents=True, exist_ok=True)
    with open(root / "metadata" / "ModelCategoryMapping.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(CSV_FIELDS)
        for i, (model, fine, nyu) in enumerate(rows):
            w.writerow([i, model, fine, fine, "Object", nyu, "", ""])
    path = root / "house" / doc["id"] / "house.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc))
    return path


def _hand_doc() -> dict:
    return {
        "version": "suncg@1.0.0", "id": "h1", "up": [0, 1, 0], "front": [0, 0, 1], "scaleToMeters": 1,
        "levels": [
            {"id": "0", "bbox": {"min": [-2, 0, -2], "max": [6, 3, 4]}, "nodes": [
                {"id": "0_0", "type": "Room", "valid": 1, "modelId": "fr_0rm_0",
                 "roomTypes": ["Living_Room", "Kitchen"], "nodeIndices": [1, 2, 3, 4, 5, 6, 7],
                 "hideCeiling": 1, "hideFloor": 0, "hideWalls": 0},
                {"id": "0_1", "type": "Object", "valid": 1, "modelId": "chair1", "transform": TRANSLATE},
                {"id": "0_2", "type": "Object", "valid": 1, "modelId": "chair1", "transform": MIRROR,
                 "isMirrored": 1},
                {"id": "0_3", "type": "Object", "valid": 0, "modelId": "gone1", "transform": TRANSLATE},
                {"id": "0_4", "type": "Box", "valid": 1, "dimensions": [2, 1, 0.5], "transform": TRANSLATE,
                 "materials": [{"name": "m", "diffuse": "#ff8000"}]},
                {"id": "0_5", "type": "Object", "valid": 1, "modelId": "plant1"},
                {"id": "0_6", "type": "Object", "valid": 1, "modelId": "person1"},
                {"id": "0_7", "type": "Object", "valid": 1, "modelId": "odd1"},
                {"id": "0_8", "type": "Ground", "valid": 1, "modelId": "gr0",
                 "transform": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, -0.5, 0, 1]},
            ]},
            {"id": "1", "bbox": {"min": [-2, 3, -2], "max": [2, 6, 2]}, "nodes": [
                {"id": "1_0", "type": "Room", "valid": 1, "modelId": "fr_1rm_0", "roomTypes": ["Bedroom"],
                 "nodeIndices": [1], "hideCeiling": 1, "hideWalls": 1},
                {"id": "1_1", "type": "Object", "valid": 1, "modelId": "chair1", "transform": ROT_Y90},
            ]},
        ],
    }


def _hand_files() -> dict[str, str]:
    wall = trimesh.creation.box(extents=(0.1, 3, 4))
    wall.apply_translation((-2.05, 1.5, 0))
    return {
        "object/chair1/chair1.obj": _obj(BOX.vertices, BOX.faces),
        "object/plant1/plant1.obj": _obj(BOX.vertices, BOX.faces),
        "object/odd1/odd1.obj": _obj(BOX.vertices, BOX.faces),
        "room/h1/fr_0rm_0f.obj": _quad(0.0),
        "room/h1/fr_0rm_0c.obj": _quad(3.0, up=False),  # exists, but hidden by hideCeiling
        "room/h1/fr_0rm_0w.obj": _obj(wall.vertices, wall.faces),
        "room/h1/fr_1rm_0f.obj": _quad(3.0),
        "room/h1/gr0f.obj": _quad(0.0),
        # no object/person1: persons are dropped before their file is looked for
    }


ROWS = [("chair1", "chair", "chair"), ("plant1", "plant", "plant"), ("person1", "person", "person"),
        ("odd1", "spaceship", "spaceship")]


@pytest.fixture
def hand(tmp_path) -> House:
    return load(_write_root(tmp_path, _hand_doc(), _hand_files(), ROWS))


def _by_name(house: House, name: str):
    return next(i for i in house.instances if i.name == name)


def test_column_major_transforms(hand):
    np.testing.assert_allclose(_by_name(hand, "Object#0_1").vertices, BOX.vertices + (1, 2, 3))
    ry90 = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]])  # +90° about +Y: x → -z, z → x
    np.testing.assert_allclose(_by_name(hand, "Object#1_1").vertices, BOX.vertices @ ry90.T + (0, 3, 0),
                               atol=1e-12)
    assert _volume(_by_name(hand, "Object#1_1")) == pytest.approx(1.0)


def test_mirrored_transform_flips_winding(hand):
    mirrored = _by_name(hand, "Object#0_2")
    np.testing.assert_allclose(mirrored.vertices, BOX.vertices * (-1, 1, 1) + (5, 0, 0))
    np.testing.assert_array_equal(mirrored.faces, np.asarray(BOX.faces)[:, ::-1])
    assert _volume(mirrored) == pytest.approx(1.0)  # positive: normals still point outward
    assert _volume(_by_name(hand, "Object#0_1")) == pytest.approx(1.0)


def test_nodes_rooms_levels_and_hide_flags(hand):
    names = [i.name for i in hand.instances]
    assert "Object#0_3" not in names  # valid: 0, and its model file does not even exist
    assert [(r.id, r.type, r.level) for r in hand.rooms] == [
        ("fr_0rm_0", "Living_Room,Kitchen", 0), ("fr_1rm_0", "Bedroom", 1)]
    assert [(lv.id, lv.floor_y) for lv in hand.levels] == [(0, 0.0), (1, 3.0)]
    envelope = {(i.name, i.category_name, i.room_id) for i in hand.instances if i.envelope}
    assert envelope == {("Floor#0_0", "floor", "fr_0rm_0"), ("Wall#0_0", "wall", "fr_0rm_0"),
                        ("Ground#0_8", "floor", None), ("Floor#1_0", "floor", "fr_1rm_0")}
    assert _by_name(hand, "Object#1_1").room_id == "fr_1rm_0"
    assert _by_name(hand, "Object#0_1").room_id == "fr_0rm_0"
    floor = _by_name(hand, "Floor#0_0")
    assert trimesh.Trimesh(floor.vertices, floor.faces).face_normals[:, 1].min() == pytest.approx(1.0)
    np.testing.assert_allclose(_by_name(hand, "Ground#0_8").vertices[:, 1], -0.5)
    assert hand.warnings == ["unknown category 'spaceship' mapped to void"]


def test_box_node(hand):
    box = _by_name(hand, "Box#0_4")
    assert (box.category, box.label, box.envelope, box.room_id) == (0, "Box", False, "fr_0rm_0")
    np.testing.assert_allclose(box.vertices.min(0), np.array([1, 2, 3]) - (1, 0.5, 0.25))
    np.testing.assert_allclose(box.vertices.max(0), np.array([1, 2, 3]) + (1, 0.5, 0.25))
    assert _volume(box) == pytest.approx(1.0)
    assert box.material.base_color == pytest.approx((1.0, 128 / 255, 0.0, 1.0))


def test_person_and_plant_are_dropped(hand):
    assert not {"plant", "person"} & {i.label for i in hand.instances}
    assert {i.label for i in hand.instances if not i.envelope} == {"chair", "Box", "spaceship"}


def test_unknown_categories_void_or_strict_error(tmp_path):
    doc = _hand_doc()
    doc["levels"][1]["nodes"].append({"id": "1_2", "type": "Object", "valid": 1, "modelId": "nomodel"})
    files = {**_hand_files(), "object/nomodel/nomodel.obj": _obj(BOX.vertices, BOX.faces)}
    path = _write_root(tmp_path, doc, files, ROWS)
    house = load(path)
    assert _by_name(house, "Object#0_7").category == 0
    assert _by_name(house, "Object#1_2").category == 0
    assert "unknown category 'model nomodel (not in ModelCategoryMapping.csv)' mapped to void" in house.warnings
    with pytest.raises(HouseError, match=r"house h1: .*ModelCategoryMapping.csv: unknown category 'spaceship'"):
        load(path, LoadOptions(strict=True))


def test_scale_to_meters(tmp_path):
    doc = _hand_doc()
    doc["scaleToMeters"] = 0.01
    house = load(_write_root(tmp_path, doc, _hand_files(), ROWS))
    np.testing.assert_allclose(_by_name(house, "Object#0_1").vertices, (BOX.vertices + (1, 2, 3)) * 0.01)
    np.testing.assert_allclose(_by_name(house, "Floor#0_0").vertices.max(0), (0.02, 0, 0.02))
    assert [lv.floor_y for lv in house.levels] == [0.0, 0.03]


def test_missing_object_file_names_it(tmp_path):
    doc = _hand_doc()
    doc["levels"][0]["nodes"][1]["modelId"] = "ghost"
    path = _write_root(tmp_path, doc, _hand_files(), ROWS + [("ghost", "chair", "chair")])
    with pytest.raises(HouseError, match=r"house h1: .*object/ghost/ghost.obj: object node 0_1: model file is missing"):
        load(path)


def test_missing_room_file_is_skipped_with_warning(tmp_path):
    files = _hand_files()
    del files["room/h1/fr_0rm_0w.obj"]
    house = load(_write_root(tmp_path, _hand_doc(), files, ROWS))
    assert "Wall#0_0" not in [i.name for i in house.instances]
    assert any("fr_0rm_0w.obj is missing" in w for w in house.warnings)


@pytest.mark.parametrize("breakage, message", [
    ("no_csv", r"ModelCategoryMapping.csv: cannot read the SUNCG category table"),
    ("bad_obj", r"object/chair1/chair1.obj: cannot read OBJ: a face uses a vertex index outside the 1 vertices"),
    ("z_up", r"'up' is \[0, 0, 1\]; only \+Y-up"),
    ("bad_transform", r"node 0_1: 'transform' must be 16 finite numbers"),
])
def test_bad_input_raises_house_error(tmp_path, breakage, message):
    doc, files = _hand_doc(), _hand_files()
    if breakage == "z_up":
        doc["up"] = [0, 0, 1]
    if breakage == "bad_transform":
        doc["levels"][0]["nodes"][1]["transform"] = [1, 0, 0]
    if breakage == "bad_obj":
        files["object/chair1/chair1.obj"] = "v 0 0 0\nf 0 1 2\n"
    path = _write_root(tmp_path, doc, files, ROWS)
    if breakage == "no_csv":
        (tmp_path / "metadata" / "ModelCategoryMapping.csv").unlink()
    with pytest.raises(HouseError, match=message):
        load(path)


# ---- node material overrides and textured materials ------------------------------------

#: a chair model of two quads: the seat (usemtl cover, first used) and the back (usemtl frame);
#: its .mtl defines frame, cover, unused in that order, which SUNCG's overrides count by
CHAIR_OBJ = ("mtllib chair2.mtl\n"
             "v 0 0 0\nv 1 0 0\nv 1 0 1\nv 0 0 1\nv 0 1 0\nv 1 1 0\n"
             "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
             "usemtl cover\nf 1/1 4/4 3/3 2/2\n"
             "usemtl frame\nf 1/1 2/2 6/3 5/4\n")
CHAIR_MTL = ("newmtl frame\nKd 0.6 0.6 0.6\n"
             "newmtl cover\nKd 1 0.07 0.40\nmap_Kd white.png\n"
             "newmtl unused\nKd 0 1 0\n")
#: a SUNCG room wall: a saturated Kd under a pure white wallpaper
WALL_MTL = "newmtl wall_mat\nKd 1 0.07 0.40\nmap_Kd wallp_0.png\n"


def _override_root(tmp_path, materials, textures=("wood_9.jpg",)) -> Path:
    """The hand house with node 0_1 a chair2 whose ``materials`` are ``materials``, its room's
    walls textured with white wallpaper, and ``textures`` in ``<root>/texture/``."""
    doc = _hand_doc()
    doc["levels"][0]["nodes"][1].update(modelId="chair2", materials=materials)
    wall = trimesh.creation.box(extents=(0.1, 3, 4))
    wall.apply_translation((-2.05, 1.5, 0))
    uv = "".join(f"vt {u} {v}\n" for u, v in (wall.vertices[:, [1, 2]] / 4).tolist())
    files = {**_hand_files(), "object/chair2/chair2.obj": CHAIR_OBJ, "object/chair2/chair2.mtl": CHAIR_MTL,
             "room/h1/fr_0rm_0w.obj": "mtllib w.mtl\nusemtl wall_mat\n" + "".join(
                 f"v {x!r} {y!r} {z!r}\n" for x, y, z in wall.vertices.tolist()) + uv + "".join(
                 f"f {a}/{a} {b}/{b} {c}/{c}\n" for a, b, c in (np.asarray(wall.faces) + 1).tolist()),
             "room/h1/w.mtl": WALL_MTL}
    path = _write_root(tmp_path, doc, files, ROWS + [("chair2", "chair", "chair")])
    for folder, name, rgb in [("object/chair2", "white.png", 255), ("room/h1", "wallp_0.png", 255)]:
        Image.fromarray(np.full((2, 2, 3), rgb, np.uint8)).save(tmp_path / folder / name)
    (tmp_path / "texture").mkdir()
    for k, name in enumerate(textures):
        Image.fromarray(np.full((2, 2, 3), (90 + k, 60, 30), np.uint8)).save(tmp_path / "texture" / name)
    return path


def test_node_overrides_replace_the_models_ith_material(tmp_path):
    """SUNCGtoolbox's ParseSUNCGMaterials: entry i is the model's i-th .mtl material (not the
    i-th used); ``diffuse`` replaces its colour, ``texture`` its image (texture/<name>.png,
    else .jpg); entries past the model's materials do nothing."""
    path = _override_root(tmp_path, [{"name": "frame", "diffuse": "#336699"}, {"name": "cover", "texture": "wood_9"},
                                     {"name": "unused", "diffuse": "#ffffff"}, {"name": "extra", "texture": "x"}])
    chair = _by_name(load(path), "Object#0_1")
    cover, frame = chair.materials  # in order of first use
    assert frame.base_color == pytest.approx((0x33 / 255, 0x66 / 255, 0x99 / 255, 1.0)) and frame.texture is None
    assert cover.texture == tmp_path / "texture" / "wood_9.jpg"
    np.testing.assert_array_equal(chair.face_material, [0, 0, 1, 1])
    # the same model without overrides keeps its own materials
    plain = _override_root(tmp_path / "plain", [])
    cover, frame = _by_name(load(plain), "Object#0_1").materials
    assert frame.base_color == (0.6, 0.6, 0.6, 1.0) and cover.texture.name == "white.png"


def test_override_texture_png_first_and_a_missing_one_is_a_warning(tmp_path):
    path = _override_root(tmp_path, [{}, {"texture": "wood_9"}], textures=("wood_9.jpg", "wood_9.png"))
    assert _by_name(load(path), "Object#0_1").materials[0].texture == tmp_path / "texture" / "wood_9.png"
    path = _override_root(tmp_path / "b", [{}, {"texture": "ghost"}, {"diffuse": "red"}])
    house = load(path)
    cover, frame = _by_name(house, "Object#0_1").materials
    assert cover.texture.name == "white.png"
    assert f"object node 0_1: texture 'ghost' not found in {tmp_path / 'b' / 'texture'}, the model's own kept" \
        in house.warnings


@pytest.mark.parametrize("rule", ["replace", "multiply"])
def test_kd_under_a_white_texture(tmp_path, rule):
    """``replace`` (default, PBRS's Mitsuba): a textured material shows its texture alone, so
    the wall under white wallpaper is white; ``multiply``: Kd × texture, magenta. Materials
    without a texture keep their Kd either way; a node's diffuse on a textured one shows only
    under ``multiply``."""
    path = _override_root(tmp_path, [{}, {"diffuse": "#00ff00"}])
    house = load(path, LoadOptions(suncg_textures=rule)) if rule != "replace" else load(path)
    wall = _by_name(house, "Wall#0_0")
    cover, frame = _by_name(house, "Object#0_1").materials
    assert frame.base_color == (0.6, 0.6, 0.6, 1.0)
    if rule == "replace":
        assert wall.material.base_color == cover.base_color == (1.0, 1.0, 1.0, 1.0)
    else:
        assert wall.material.base_color == (1.0, 0.07, 0.40, 1.0)
        assert cover.base_color == (0.0, 1.0, 0.0, 1.0)
    assert wall.material.texture.name == "wallp_0.png"
    # what the raster mode shows of the wall, unlit (radiance = base colour × texture)
    from sceneforge.cameras import look_at_camera
    from sceneforge.render import RenderConfig, Renderer

    camera = look_at_camera([0.0, 1.5, 0.0], [-1.0, 0.0, 0.0], width=32, height=24)
    with Renderer(32, 24, config=RenderConfig(flat=True, ambient=1.0, exposure=1.0, tone="clip")) as r:
        rgb = r.render(house, camera)
    expected = (255, 255, 255) if rule == "replace" else (255, 74, 170)  # sRGB of 1, 0.07, 0.40
    np.testing.assert_allclose(rgb[8:16, 12:20].reshape(-1, 3), np.tile(expected, (64, 1)), atol=1)


# ---- the OBJ reader ---------------------------------------------------------------------


def test_read_obj_polygons_negative_indices_and_uv_seams(tmp_path):
    (tmp_path / "m.mtl").write_text("newmtl a\nKd 1 0 0\nnewmtl b\nKd 0 0 1\nd 0.5\n")
    (tmp_path / "m.obj").write_text(
        "mtllib m.mtl\n"
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\n"
        "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvt 0.5 0.5\n"
        "usemtl a\nf 1/1 2/2 3/3 4/4\n"  # a quad: fanned into 2 triangles
        "usemtl b\nf -5/-1 -4/2 -1/3\nf 2/2 5/3 3/3\nf 1/1 5/3 4/4\n")  # vertex 1 again, with vt 5
    m = read_obj(tmp_path / "m.obj")
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [0, 2, 3], [5, 1, 4], [1, 4, 2], [0, 4, 3]])
    # the five vertices keep their order; vertex 1 used with a second uv is appended
    np.testing.assert_array_equal(m.vertices, [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]])
    np.testing.assert_array_equal(m.uv, [[0, 0], [1, 0], [1, 1], [0, 1], [1, 1], [0.5, 0.5]])
    assert [c.base_color for c in m.materials] == [(1.0, 0.0, 0.0, 1.0), (0.0, 0.0, 1.0, 0.5)]
    np.testing.assert_array_equal(m.face_material, [0, 0, 1, 1, 1])  # "a": the quad, "b": the rest


# ---- models whose textured faces alone have uv (issue 40) -------------------------------

#: SUNCG's object/274 (a wall cabinet) as it is made: the faces of its textured materials
#: have texture coordinates (``f v/vt/vn``), those of its plain one none (``f v//vn``)
CABINET_OBJ = ("mtllib cab.mtl\n"
               "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nv 1 0 1\n"
               "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvn 0 0 1\n"
               "usemtl material_0\nf 1/1/1 2/2/1 3/3/1 4/4/1\n"
               "usemtl material_1\nf 1//1 5//1 6//1 2//1\n")
CABINET_MTL = ("newmtl material_0\nKd 0.64 0.64 0.64\nmap_Kd wood.png\n"
               "newmtl material_1\nKd 0.36 0.36 0.36\n")


def test_read_obj_keeps_uv_that_only_some_faces_have(tmp_path):
    """Before, one face without uv dropped the mesh's uv, and with them every texture of it
    (SUNCG's cabinet showed its wood white under ``replace``, +2 stops beside PBRS)."""
    (tmp_path / "cab.obj").write_text(CABINET_OBJ)
    (tmp_path / "cab.mtl").write_text(CABINET_MTL)
    Image.fromarray(np.full((2, 2, 3), (160, 80, 40), np.uint8)).save(tmp_path / "wood.png")
    m = read_obj(tmp_path / "cab.obj")
    assert m.uv is not None and m.materials[0].texture == tmp_path / "wood.png"
    np.testing.assert_array_equal(m.uv[:4], [[0, 0], [1, 0], [1, 1], [0, 1]])
    np.testing.assert_array_equal(m.uv[4:6], [[0, 0], [0, 0]])  # corners without uv: (0, 0)
    # a textured material none of whose faces has uv shows its colour (nothing places texels)
    (tmp_path / "cab.mtl").write_text(CABINET_MTL + "map_Kd wood.png\n")
    warnings = []
    m = read_obj(tmp_path / "cab.obj", warnings.append)
    assert m.materials[1].texture is None and m.materials[1].base_color == (0.36, 0.36, 0.36, 1.0)
    assert m.materials[0].texture is not None
    assert any("material_1" in w and "no texture coordinates" in w for w in warnings)


def test_suncg_node_texture_shows_on_a_model_with_plain_faces_too(tmp_path):
    """SUNCG's rule (module docs, SUNCGtoolbox ParseSUNCGMaterials): the node's entry i is the
    model's i-th .mtl material; its texture shows where the model's faces have uv: the cabinet's textured face shows the node's texture, its plain face the node's diffuse
    (the model as SUNCG ships it: uv on its textured faces only)."""
    doc = _hand_doc()
    doc["levels"][0]["nodes"][1].update(modelId="cab", materials=[{"texture": "wood_4"}, {"diffuse": "#5b5b5b"}])
    path = _write_root(tmp_path, doc, {**_hand_files(), "object/cab/cab.obj": CABINET_OBJ,
                                       "object/cab/cab.mtl": CABINET_MTL},
                       ROWS + [("cab", "wardrobe_cabinet", "cabinet")])
    Image.fromarray(np.full((2, 2, 3), 255, np.uint8)).save(tmp_path / "object" / "cab" / "wood.png")
    (tmp_path / "texture").mkdir()
    Image.fromarray(np.full((2, 2, 3), (164, 83, 47), np.uint8)).save(tmp_path / "texture" / "wood_4.png")
    cab = _by_name(load(path), "Object#0_1")
    assert cab.uv is not None
    wood, plain = cab.materials
    assert wood.texture == tmp_path / "texture" / "wood_4.png" and wood.base_color == (1.0, 1.0, 1.0, 1.0)
    assert plain.texture is None and plain.base_color == pytest.approx((0x5b / 255,) * 3 + (1.0,))
    from sceneforge.render.raster import house_batches

    # what both renderers draw: the wood batch with its texture and uv (before: no uv, the
    # texture dropped, its white base colour drawn)
    batches = [b for b in house_batches(load(path)) if b.material.texture is not None]
    assert any(b.material.texture.name == "wood_4.png" and b.uv is not None for b in batches)
