"""3D-FRONT as real files are: a house shaped like the released scene JSONs
(:func:`sceneforge.testing.front3d.write_real_shaped`), and the rules real files need."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner

from sceneforge.cameras import look_at_camera, write_pbrs_cameras
from sceneforge.conventions import NYU40_IDS, NYU40_NAMES
from sceneforge.errors import HouseError
from sceneforge.houses import House, LoadOptions, load
from sceneforge.houses.formats import front3d
from sceneforge.houses.formats.front3d import lookup, opening_rectangle, title_names
from sceneforge.houses.inspect import summarize
from sceneforge.layers import frontal_layers
from sceneforge.raytrace import HouseTracer
from sceneforge.testing.front3d import (
    DOOR,
    EXPECTED_LOSSES,
    HOLE,
    UV_TRANSFORMS,
    WINDOW,
    write_real_shaped,
)

STRICT = LoadOptions(strict=True)


@pytest.fixture(scope="module")
def real_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("front")
    write_real_shaped(root)
    return root


@pytest.fixture(scope="module")
def real(real_root) -> House:
    return load(real_root / "3D-FRONT" / "real-shaped.json", STRICT)


def _by_label(house: House, label: str):
    found = [i for i in house.instances if i.label == label]
    assert found, f"no instance labelled {label!r}"
    return found


# ---- validity, categories, losses -----------------------------------------------------------


def test_strict_accepts_the_real_shaped_house_and_counts_every_loss(real):
    assert real.losses == {getattr(front3d, k): n for k, n in EXPECTED_LOSSES.items()}
    # the counts are all the house reports: no void category, no other repair
    assert real.warnings == [f"{reason}: {n}" for reason, n in real.losses.items()]
    problems = summarize(real).problems
    for reason, n in real.losses.items():
        assert f"{reason}: {n}" in problems


def test_unreleased_pieces_are_skipped_before_their_category_is_looked_up(tmp_path):
    future = tmp_path / "3D-FUTURE-model"
    (future / "m-a").mkdir(parents=True)
    (future / "m-a" / "raw_model.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (future / "model_info.json").write_text("[]")
    furniture = [{"uid": "a", "jid": "m-a", "category": "Spaceship"},  # a model, but no 'valid'
                 {"uid": "b", "jid": "m-b", "aid": [], "title": "window/floor-based window"},
                 {"uid": "c", "jid": "m-c", "category": "furniture without a category", "valid": False}]
    meshes = [{"uid": "f", "type": "Floor", "xyz": [0, 0, 0, 1, 0, 0, 0, 0, 1], "faces": [0, 2, 1]},
              {"uid": "e", "type": "", "xyz": [], "faces": [], "uv": []}]  # empty, untyped: no void warning
    doc = {"furniture": furniture, "mesh": meshes, "material": [],
           "scene": {"room": [{"type": "Hall", "instanceid": "Hall-1",
                               "children": [{"ref": r, "instanceid": r} for r in "abcfe"]}]}}
    path = tmp_path / "3D-FRONT" / "s.json"
    path.parent.mkdir()
    path.write_text(json.dumps(doc))
    house = load(path, STRICT)
    assert [i.label for i in house.instances] == ["Floor"]
    assert house.warnings == [f"{front3d.UNRELEASED}: 3"]


@pytest.mark.parametrize("names, expected", [
    (["Nightstand", "cabinet", "Cabinet/Shelf/Desk"], ("Nightstand", "night_stand", False)),  # finest first
    ([None, "plants", "Others"], ("plants", "otherprop", True)),  # a plant by its title: dropped
    (["", "Others", "Plants"], ("Others", "otherprop", True)),  # ... or by any other of its names
    (["Person"], ("Person", None, True)),  # a dropped class is no class
    (["Lounge Chair/Cafe Chair/Office Chair"], ("Lounge Chair/Cafe Chair/Office Chair", "chair", False)),
    (["cabinet / shelf / desk"], ("cabinet / shelf / desk", "cabinet", False)),  # " / " spacing
    (["200 - On the floor"], ("200 - On the floor", "otherprop", False)),
    (["400 - attach to wall - frame"], ("400 - attach to wall - frame", "otherprop", False)),  # the family
    (["500 - attach to ceiling"], ("500 - attach to ceiling", "otherprop", False)),
    (["build element/column"], ("build element/column", "otherstructure", False)),
    (["Build Element"], ("Build Element", "otherstructure", False)),
])
def test_lookup_finest_name_first_and_dropped_by_any(names, expected):
    label, cid, dropped = lookup(names)
    assert (label, NYU40_NAMES[cid] if cid is not None else None, dropped) == expected


@pytest.mark.parametrize("title, names", [
    ("plants/plants - on top of others", ["plants"]),
    ("window/floor-based window", ["window"]),
    ("Corner/Side Table", ["Corner/Side Table"]),  # the table knows the whole title
    ("Pendant Lamp", ["Pendant Lamp"]),
    ("", []),
    (None, []),
])
def test_title_super_category(title, names):
    assert title_names(title) == names


def test_fine_category_from_model_info_beats_the_coarse_scene_category(real):
    classes = {i.label: i.category_name for i in real.instances if not i.envelope}
    assert classes["Nightstand"] == "night_stand"  # scene entry: Cabinet/Shelf/Desk
    assert classes["King-size Bed"] == "bed"  # scene entry: Bed, title bed/king-size bed
    assert classes["Footstool/Sofastool/Bed End Stool/Stool"] == "chair"  # " / " spacing of the table
    assert classes["300 - On top of others"] == "otherprop"  # null fine category: the scene entry
    assert classes["build element/beam"] == "otherstructure"  # the title's family
    assert not [i for i in real.instances if "plant" in i.label.lower()]  # null fine category, plant title


# ---- meshes: strings, empties, exterior shells, textures, cabinets ------------------------------


def test_exterior_shells_are_skipped(real):
    types = {i.label for i in real.instances}
    assert not types & {"WallOuter", "SlabSide", "SlabBottom"}
    assert real.bounds()[0][1] == 0.0  # the slab's underside at y = -0.1 is gone


def test_string_typed_arrays_and_textures_by_material_jid_with_uv_transform(real, real_root):
    floors = _by_label(real, "Floor")
    assert [f.room_id for f in floors] == ["LivingRoom-1", "Bedroom-2"]  # Bedroom-2's arrays are strings
    m = np.asarray(UV_TRANSFORMS["tex-floor"]).reshape(3, 3)[:2, :2]
    for floor, (x0, x1) in zip(floors, ((0.0, 4.0), (4.2, 8.2))):
        np.testing.assert_allclose(floor.vertices.min(0), [x0, 0, 0])
        np.testing.assert_allclose(floor.vertices.max(0), [x1, 0, 4])
        # the file's uv are the (x, z) metres of each vertex; UVTransform[:2, :2] applies
        raw = floor.vertices[:, [0, 2]]
        np.testing.assert_allclose(floor.uv, raw @ m.T, atol=1e-6)
        assert floor.material.texture == real_root / "3D-FRONT-texture" / "tex-floor" / "texture.png"
        assert floor.material.base_color == (1.0, 1.0, 1.0, 1.0)
    wall = _by_label(real, "WallInner")[0]
    assert wall.material.texture == real_root / "3D-FRONT-texture" / "tex-wall" / "texture.png"
    door = _by_label(real, "Door")[0]
    assert door.material.texture is None  # tex-missing: counted, see EXPECTED_LOSSES["NO_TEXTURE"]


def test_uv_transform_is_row_major(tmp_path):
    quad = {"xyz": [0, 0, 0, 1, 0, 0, 1, 0, 1, 0, 0, 1], "faces": [0, 2, 1, 0, 3, 2], "uv": [0, 0, 1, 0, 1, 1, 0, 1]}
    doc = {"furniture": [], "mesh": [{"uid": "m", "type": "Floor", "material": "mt", **quad}],
           "material": [{"uid": "mt", "jid": "t", "texture": "", "color": [255, 255, 255, 255],
                         "UVTransform": ["2", "3", "9", "5", "7", "9", "0", "0", "1"]}],
           "scene": {"room": [{"type": "Hall", "instanceid": "Hall-1", "children": [{"ref": "m"}]}]}}
    path = tmp_path / "3D-FRONT" / "s.json"
    path.parent.mkdir()
    path.write_text(json.dumps(doc))
    floor = load(path).instances[0]
    # u' = 2u + 3v, v' = 5u + 7v; the translation column (9, 9) is unused, as in the toolbox
    np.testing.assert_allclose(floor.uv, [[0, 0], [2, 5], [5, 12], [3, 7]])


def test_cabinet_boards_of_one_construct_are_one_instance(real):
    [unit, loose] = _by_label(real, "Cabinet")
    assert unit.name == "Cabinet#kitchen-1" and len(unit.faces) == 4 * 12  # four boards
    np.testing.assert_allclose(unit.vertices.min(0), [0.0, 0.0, 2.8])
    np.testing.assert_allclose(unit.vertices.max(0), [0.6, 0.85, 3.8])
    assert len(loose.faces) == 12  # no constructid: its own instance
    [band] = _by_label(real, "Cabinet/LightBand")  # same construct, another class (envelope)
    assert band.category_name == "ceiling" and band.envelope


def test_raw_model_quads_placed_by_the_xyzw_quaternion(real):
    [bed] = _by_label(real, "King-size Bed")
    mesh = trimesh.Trimesh(bed.vertices, bed.faces, process=False)
    assert len(bed.faces) == 12 and mesh.is_watertight and mesh.volume == pytest.approx(2.0 * 0.5 * 1.8)
    np.testing.assert_allclose(mesh.bounds, [[5.5, 0, 2.1], [7.5, 0.5, 3.9]], atol=1e-12)
    [night] = _by_label(real, "Nightstand")  # +90° about +Y: x → -z
    np.testing.assert_allclose(trimesh.Trimesh(night.vertices, night.faces).bounds,
                               [[7.6, 0, 3.4], [8.0, 0.5, 3.8]], atol=1e-12)
    [lamp] = _by_label(real, "Pendant Lamp")  # the flagged y-scale 7.16 is kept
    assert np.ptp(lamp.vertices[:, 1]) == pytest.approx(0.716)


# ---- openings --------------------------------------------------------------------------------


def _rect(corners) -> tuple:
    lo, hi = np.min(corners, axis=0), np.max(corners, axis=0)
    return tuple(np.round(np.concatenate([lo, hi]), 9))


def test_every_opening_gets_one_closing_surface(real):
    closing = [i for i in real.instances if i.label.endswith(" opening")]
    assert [(i.label, i.category_name, i.room_id, i.envelope) for i in closing] == [
        ("Door opening", "door", "LivingRoom-1", True),  # the Pocket on the same opening adds none
        ("Window opening", "window", "LivingRoom-1", True),
        ("Hole opening", "window", "Bedroom-2", True),  # its sill is 0.8 m above the floor
    ]
    mid = {k: sum(o["wall"]) / 2 for k, o in (("door", DOOR), ("window", WINDOW), ("hole", HOLE))}
    assert _rect(closing[0].vertices) == _rect([[mid["door"], 0.0, 1.5], [mid["door"], 2.1, 2.4]])
    assert _rect(closing[1].vertices) == _rect([[1.5, 0.9, mid["window"]], [2.7, 2.1, mid["window"]]])
    assert _rect(closing[2].vertices) == _rect([[mid["hole"], 0.8, 1.0], [mid["hole"], 2.0, 2.0]])
    assert sum(trimesh.Trimesh(i.vertices, i.faces).area for i in closing) == pytest.approx(
        0.9 * 2.1 + 1.2 * 1.2 + 1.0 * 1.2)


def _box(lo, hi):
    return trimesh.creation.box(bounds=[lo, hi])


@pytest.mark.parametrize("angle", [0.0, 30.0, 90.0, 135.0])
def test_opening_rectangle_of_a_jamb_in_any_wall_direction(angle):
    # the reveal of a 1.0 × 2.0 m opening through a 0.3 m wall: two sides and a top
    sides = [_box((-0.55, 0, -0.15), (-0.5, 2.0, 0.15)), _box((0.5, 0, -0.15), (0.55, 2.0, 0.15))]
    top = _box((-0.5, 2.0, -0.15), (0.5, 2.05, 0.15))
    # only the faces inside the opening: normals along the wall or down
    faces, verts = [], []
    for part, keep in ((sides[0], [1, 0, 0]), (sides[1], [-1, 0, 0]), (top, [0, -1, 0])):
        sel = np.flatnonzero(part.face_normals @ keep > 0.99)
        faces.append(part.faces[sel] + sum(len(v) for v in verts))
        verts.append(part.vertices)
    a = math.radians(angle)
    rot = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    v = np.concatenate(verts) @ rot.T + (3.0, 0.0, -1.0)
    corners = opening_rectangle(v, np.concatenate(faces))
    expected = np.array([[-0.5, 0, 0], [0.5, 0, 0], [0.5, 2.0, 0], [-0.5, 2.0, 0]]) @ rot.T + (3.0, 0.0, -1.0)
    # the same rectangle, whatever the corner order the eigenvectors' signs give
    assert sorted(map(tuple, np.round(corners, 9))) == sorted(map(tuple, np.round(expected, 9)))


@pytest.mark.parametrize("mesh", [
    _box((-0.45, 0, -0.02), (0.45, 2.0, 0.02)),  # a door leaf
    _box((0, 0, 0), (1, 1, 1)),  # anything box-like
])
def test_a_model_that_faces_along_the_wall_is_not_a_jamb(mesh):
    assert opening_rectangle(mesh.vertices, mesh.faces) is None


def test_a_toy_window_frame_is_not_a_jamb():
    from sceneforge.houses.toy import generate_house

    frames = [i for i in generate_house(0).instances if i.category_name == "window"]
    assert frames and all(opening_rectangle(i.vertices, i.faces) is None for i in frames)


def _through(camera, axis: int, opening) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (bool (H*W,)) whose rays cross both faces of ``opening``'s wall inside the opening
    (1 cm in from its edges), and each ray's planar depth at the middle of the wall."""
    origins, directions, depth_scale = camera.rays()
    (w0, w1), (s0, s1), (y0, y1) = opening["wall"], opening["span"], opening["height"]
    along = 2 - axis
    inside = np.ones(len(directions), dtype=bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for w in (w0, w1):
            t = (w - origins[:, axis]) / directions[:, axis]
            p = origins + t[:, None] * directions
            inside &= (t > 0) & (p[:, along] > s0 + 0.01) & (p[:, along] < s1 - 0.01)
            inside &= (p[:, 1] > y0 + 0.01) & (p[:, 1] < y1 - 0.01)
        t_mid = ((w0 + w1) / 2 - origins[:, axis]) / directions[:, axis]
    return inside, t_mid * depth_scale


@pytest.mark.parametrize("opening, axis, position, view, kind", [
    (DOOR, 0, (2.0, 1.2, 1.9), (1.0, -0.05, 0.03), "door"),  # room A → room B
    (WINDOW, 2, (2.2, 1.6, 2.5), (-0.05, -0.02, -1.0), "window"),  # room A → outside
    (HOLE, 0, (6.5, 1.3, 1.6), (1.0, 0.05, -0.04), "window"),  # room B → outside
])
def test_a_ray_toward_an_opening_stops_there(real, opening, axis, position, view, kind):
    camera = look_at_camera(position, view, width=48, height=36)
    inside, expected = _through(camera, axis, opening)
    assert inside.sum() > 200  # most of the view looks through the opening
    layers = frontal_layers(real, camera, HouseTracer(real))
    d5 = layers.depth[4].reshape(-1)
    np.testing.assert_allclose(d5[inside], expected[inside], rtol=1e-5)
    assert set(np.unique(layers.envelope_category.reshape(-1)[inside]).tolist()) == {NYU40_IDS[kind]}
    # without the closing surfaces the same rays pass into the next room or out of the house
    open_house = House(id="open", instances=[i for i in real.instances if not i.label.endswith(" opening")])
    open_d5 = frontal_layers(open_house, camera).depth[4].reshape(-1)[inside]
    assert not (np.abs(open_d5 - expected[inside]) < 0.05).any()


# ---- files that are wrong ----------------------------------------------------------------------


def test_nested_model_folder_is_an_error_naming_the_expected_path(tmp_path):
    path = write_real_shaped(tmp_path, nested_models=True)
    future = tmp_path / "3D-FUTURE-model"
    with pytest.raises(HouseError, match=r"models are one folder too deep: expected "
                       + f"{future}/<jid>/raw_model.obj and {future / 'model_info.json'}".replace(".", r"\.")):
        load(path)
    # as the message says: the inner folder as --future-dir
    assert load(path, LoadOptions(future_dir=str(future / "3D-FUTURE-model"), strict=True)).instances


def test_missing_model_info_is_an_error_naming_the_expected_path(tmp_path):
    path = write_real_shaped(tmp_path, model_info=False)
    expected = tmp_path / "3D-FUTURE-model" / "model_info.json"
    with pytest.raises(HouseError, match=f"model info not found: expected {expected}".replace(".", r"\.")):
        load(path)
    (tmp_path / "model_info.json").write_text("[]")  # misplaced: beside the model folder
    with pytest.raises(HouseError, match=r"\(found .*/model_info\.json: move it there\)"):
        load(path)


def test_a_broken_obj_skips_that_piece_with_a_warning(tmp_path):
    path = write_real_shaped(tmp_path, broken_model=True)
    house = load(path, STRICT)
    assert not [i for i in house.instances if i.label == "Nightstand"]
    assert [i.label for i in house.instances if i.label == "King-size Bed"]  # the others load
    obj = tmp_path / "3D-FUTURE-model" / "m-nightstand" / "raw_model.obj"
    [warning] = [w for w in house.warnings if w.startswith("furniture model m-nightstand")]
    assert f"cannot read {obj}: line " in warning and "cannot read face" in warning
    assert house.losses[front3d.BAD_MODEL] == 1


# ---- where the counts are shown ----------------------------------------------------------------


def test_houses_inspect_and_the_store_provenance_show_the_counts(real_root, real, tmp_path):
    from sceneforge.cli.main import cli

    from sceneforge.config import load_config
    from sceneforge.pipeline import render_dataset
    from sceneforge.store import open_store

    lines = [f"{reason}: {n}" for reason, n in real.losses.items()]
    result = CliRunner().invoke(cli, ["houses", "inspect", str(real_root), "--strict"])
    assert result.exit_code == 0, result.output
    for line in lines:
        assert f"problem: {line}" in result.output
    cams = tmp_path / "cams" / "real-shaped" / "room_camera.txt"  # PBRS: <house>/room_camera.txt
    cams.parent.mkdir(parents=True)
    write_pbrs_cameras(cams, [look_at_camera((2.0, 1.2, 1.9), (1.0, -0.05, 0.03), width=16, height=12)])
    config = load_config(None, {"width": 16, "height": 12, "cameras": str(tmp_path / "cams"),
                                "rgb": {"enabled": False}, "view": {"overhead": {"resolution": 8}}})
    summary = render_dataset(str(real_root), str(tmp_path / "out.zarr"), config)
    assert summary.failed_houses == ()
    [record] = open_store(str(tmp_path / "out.zarr")).attrs["houses"]
    assert record["warnings"] == lines
