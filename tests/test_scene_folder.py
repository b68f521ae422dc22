"""One scene in many files: a folder of per-object meshes is one house (by its names, its
``scene.json`` or ``--format scene``) with the layers of the single-file export; ``houses
inspect`` suggests the manifest where it is not recognised; a bad manifest is one line; every
file is fingerprinted and the ground-truth meshes are made again from the folder."""

from __future__ import annotations

import json
from dataclasses import replace

import jsonschema
import numpy as np
import pytest
from click.testing import CliRunner
from sceneforge.cli.main import cli

from sceneforge import schemas
from sceneforge.errors import EXIT_FAILURES, HouseError, SceneforgeError
from sceneforge.houses import House, LoadOptions, discover, load
from sceneforge.houses.formats import detect
from sceneforge.houses.formats.generic import GENERIC_NAME
from sceneforge.houses.formats.native import write_house as write_native
from sceneforge.houses.toy import generate_house
from sceneforge.pipeline.gt_mesh import GroundTruthMeshes
from sceneforge.pipeline.inputs import changes
from sceneforge.store import MESH_KINDS, array_digests, open_store
from sceneforge.testing.generic import write_house
from sceneforge.testing.scenes import object_names, rotated_z_up, write_object_files

#: a tiny render: one view, 64×48, no RGB
RENDER = ["--views-per-house", "1", "--resolution", "64x48", "--overhead-resolution", "32", "--no-rgb"]


def run(*args):
    return CliRunner().invoke(cli, list(map(str, args)))


@pytest.fixture(scope="module")
def toy() -> House:
    return generate_house(3, "room")


def _triangles(house: House) -> list[tuple[str, int, bytes]]:
    """(name, class, its triangles' corners sorted) of every instance, sorted: equal for equal
    houses whatever the order of their instances."""
    return sorted((i.name, i.category, np.sort(i.vertices[i.faces].reshape(-1, 9), axis=0).tobytes())
                  for i in house.instances)


def test_a_folder_of_object_files_is_one_house_like_the_single_file(toy, tmp_path):
    names = object_names(toy)
    assert {"Floor", "Walls", "Ceiling", "CeilingLamp", "Chair.001"} <= set(names)
    write_object_files(toy, tmp_path / "scenes" / "room")
    single = load(write_house(toy, tmp_path / "single" / "room.obj", names=names))
    (source,) = discover(tmp_path / "scenes")
    assert (source.id, source.format, source.path) == ("room", "scene", tmp_path / "scenes" / "room")
    house = load(source)
    assert house.id == "room" and house.source_format == "scene"
    assert _triangles(house) == _triangles(single)
    assert [(r.id, r.level) for r in house.rooms] == [(r.id, r.level) for r in single.rooms]
    assert house.notes == single.notes and house.notes[0].startswith("up axis: y (detected: ")


def test_its_layers_equal_the_single_file_exports(toy, tmp_path):
    """Files listed in the objects' order (scene.json): the same house, instance for instance,
    so the same store, array for array (instance ids included)."""
    files = write_object_files(rotated_z_up(toy), tmp_path / "scenes" / "room")
    (tmp_path / "scenes" / "room" / "scene.json").write_text(json.dumps({"files": [f.name for f in files]}))
    single = write_house(toy, tmp_path / "single" / "room.obj", names=object_names(toy))
    for houses, out in ((tmp_path / "scenes", "folder.zarr"), (single, "single.zarr")):
        res = run("render", houses, tmp_path / out, *RENDER)
        assert res.exit_code == 0, res.output
    assert array_digests(str(tmp_path / "folder.zarr")) == array_digests(str(tmp_path / "single.zarr"))
    (record,) = open_store(str(tmp_path / "folder.zarr")).attrs["houses"]
    assert record["format"] == "scene" and record["notes"][0].startswith("up axis: z (detected: ")


@pytest.mark.parametrize("name, kept", [
    ("default", False), ("Mesh", False), ("Object001", False), ("node3", False), ("Cube.002", False),
    ("", False), ("mesh_0", False), ("Seat", True), ("Chair.001", True), ("Table", True),
])
@pytest.mark.parametrize("suffix", [".obj", ".glb", ".ply"])
def test_a_mesh_whose_name_says_nothing_is_named_after_its_file(tmp_path, name, kept, suffix):
    floor = generate_house(3).instances[0]
    write_object_files(House("f", [floor]), tmp_path / "room", names=["Stool.004"], object_name=name,
                       suffix=suffix)
    h = load(tmp_path / "room", LoadOptions(format="scene", up_axis="y"))
    assert [i.name for i in h.instances] == [name if kept else "Stool.004"]


def test_a_folder_is_a_scene_when_its_names_are_one_rooms_parts(toy, tmp_path):
    parts = {i.name: i for i in toy.instances}
    floor, wall, chair = parts["room0/floor_0"], parts["room0/wall_0"], parts["room3/chair_0"]
    folder = tmp_path / "room"
    write_object_files(House("r", [floor, chair]), folder, names=["Floor", "Chair"])
    assert detect(folder) is None  # a floor and a chair: a room without its walls
    write_object_files(House("r", [wall]), folder, names=["Walls"])
    assert detect(folder).name == "scene"
    houses = tmp_path / "houses"  # whole houses whose names say rooms: each its own house
    for name in ("kitchen", "bedroom", "floor2"):
        write_house(toy, houses / f"{name}.glb")
    assert [(s.id, s.format) for s in discover(houses)] == [("bedroom", "gltf"), ("floor2", "gltf"),
                                                            ("kitchen", "gltf")]


def test_the_manifest_given_itself_is_its_folder_and_a_house_folder_stays_one(toy, tmp_path, small_house):
    folder = tmp_path / "room"
    write_object_files(House("r", toy.instances[:3]), folder)
    (folder / "scene.json").write_text('{"files": ["*.obj"]}')
    assert [(s.id, s.format, s.path) for s in discover(folder / "scene.json")] == [("room", "scene", folder)]
    write_native(small_house, folder)  # a sceneforge house.json beside them: that house, as before
    assert detect(folder).name == "sceneforge"


def test_inspect_suggests_a_manifest_and_the_manifest_makes_one_house(toy, tmp_path):
    objects = House("o", [i for i in toy.instances if i.category not in (1, 22)])  # no walls, no ceilings
    folder = tmp_path / "export"
    write_object_files(objects, folder)
    res = run("houses", "inspect", folder)
    n = len(objects.instances)
    manifest = folder / "scene.json"
    assert res.output.splitlines()[-2] == (
        f"hint: these {n} files look like the objects of one scene: write {manifest} holding "
        '{"files": ["*.obj"]} to read them as one house, or pass --format scene')
    for how in (["--format", "scene"], []):
        if not how:
            (folder / "scene.json").write_text('{"files": ["*.obj"]}')
        res = run("houses", "inspect", folder, *how)
        assert res.exit_code == 0, res.output
        assert res.output.splitlines()[-1] == "1 house read, 0 failed" and "hint:" not in res.output
        assert f"export  (scene: {folder})" in res.output


def test_the_manifest_sets_axis_units_and_names(toy, tmp_path):
    """A Z-up folder in centimetres whose own name map classes its odd names."""
    cm = rotated_z_up(toy)
    for inst in cm.instances:
        inst.vertices = inst.vertices * 100
    names = [n.replace("CeilingLamp", "Glowbulb") for n in object_names(toy)]
    folder = tmp_path / "room"
    write_object_files(cm, folder, names=names)
    (folder / "names.json").write_text(json.dumps({"patterns": [["glowbulb", "lamp"]]}))
    (folder / "scene.json").write_text(json.dumps({"files": ["*.obj"], "up_axis": "z", "scale": 0.01,
                                                   "name_map": "names.json"}))
    house = load(folder, LoadOptions(up_axis="y", scale=5.0))  # the folder's own values win
    assert house.notes == []  # not detected: told
    np.testing.assert_allclose(house.bounds(), toy.bounds(), atol=1e-9)
    single = load(write_house(toy, tmp_path / "one" / "room.obj", names=object_names(toy)))
    assert sorted((i.name.replace("Glowbulb", "CeilingLamp"), i.category) for i in house.instances) == sorted(
        (i.name, i.category) for i in single.instances)


@pytest.mark.parametrize("doc, problem", [
    ('{"files": ["*.obj"',
     "cannot read the scene manifest: Expecting ',' delimiter: line 1 column 19 (char 18)"),
    ('{"files": []}', "scene manifest: does not match the scene schema: files: [] should be non-empty"),
    ('{"files": ["*.obj"], "up_axes": "z"}',
     "scene manifest: unknown key 'up_axes': Additional properties are not allowed by the scene schema; "
     "did you mean 'up_axis'?"),
    ('{"files": ["*.obj"], "up_axis": "x"}',
     "scene manifest: does not match the scene schema: up_axis: 'x' is not one of ['auto', 'y', 'z']"),
    ('{"files": ["*.fbx"]}',
     "files: '*.fbx' names no mesh file in {folder} (expected .gltf, .glb, .obj, .ply)"),
    ('{"files": ["../*.obj"]}', "files: '../*.obj' is outside the folder (give paths relative to it)"),
    ('{"files": ["*.obj"], "name_map": "missing.json"}',
     "cannot read name map {folder}/missing.json: No such file or directory"),
])
def test_a_bad_manifest_is_one_line(toy, tmp_path, doc, problem):
    folder = tmp_path / "room"
    write_object_files(House("r", toy.instances[:3]), folder)
    (folder / "scene.json").write_text(doc)
    with pytest.raises(HouseError) as e:
        load(folder)
    assert (e.value.house, e.value.file, e.value.problem) == ("room", str(folder / "scene.json"),
                                                              problem.format(folder=folder))
    res = run("houses", "inspect", folder)
    assert res.exit_code == EXIT_FAILURES and "Traceback" not in res.output
    assert res.output.splitlines() == [f"failed: {e.value}", "0 houses read, 1 failed"]


def test_the_manifest_schema_is_a_schema_and_ships_with_the_others():
    jsonschema.Draft202012Validator.check_schema(schemas.load("scene"))
    good = {"files": ["*.obj", "objects/*.glb"], "up_axis": "auto", "scale": 0.01, "name_map": "names.json"}
    assert schemas.errors(good, "scene") == []


def test_every_file_is_an_input_and_the_meshes_are_made_again_from_the_folder(toy, tmp_path):
    folder = tmp_path / "scenes" / "room"
    files = write_object_files(toy, folder)
    out = tmp_path / "full.zarr"
    res = run("render", tmp_path / "scenes", out, *RENDER, "--gt-mesh", "all")
    assert res.exit_code == 0, res.output
    store = open_store(str(out))
    (record,) = store.attrs["houses"]
    assert {str(f) for f in files} <= set(record["inputs"])  # every object file, and its MTL
    assert {str(f.with_suffix(".mtl")) for f in files} <= set(record["inputs"])
    stored = store.mesh(0)
    lean = open_store(str(out))
    lean.has_mesh = False  # made from the folder, as for a store that keeps none
    made = GroundTruthMeshes(lean).mesh(0)
    for kind in MESH_KINDS:
        for got, want in zip(made[kind], stored[kind], strict=True):
            np.testing.assert_array_equal(got, want)
    chair = next(f for f in files if f.stem == "Chair")
    chair.write_text(chair.read_text().replace("v ", "v  ", 1))
    assert changes(store.attrs["houses"], ["room"]).changed == ("room",)
    lean = open_store(str(out))
    lean.has_mesh = False
    with pytest.raises(SceneforgeError, match=f"house room: {chair} changed since the store was rendered"):
        GroundTruthMeshes(lean).mesh(0)


def test_generic_names():
    generic = ("default", "Default_Object", "Mesh.001", "Object001", "node12", "")
    assert all(GENERIC_NAME.match(n) for n in generic)
    assert not any(GENERIC_NAME.match(n) for n in ("Chair", "Floor.001", "Meshchair", "Objects"))


def test_the_hint_stands_when_a_few_files_have_a_floor_of_their_own(toy, tmp_path):
    # two floors of a two-room export (or wall boxes split into floors) among many objects
    # without one: still the objects of one scene; whole houses (each with its floor) get none
    objects = House("o", [i for i in toy.instances if i.category not in (1, 22)])  # no walls, no ceilings
    floors = sum(i.category == 2 for i in objects.instances)
    assert floors >= 2
    folder = tmp_path / "export"
    for inst, name in zip(objects.instances, object_names(objects)):  # each mesh named as its file
        write_house(House("o", [replace(inst, id=0)]), folder / f"{name}.obj", names=[name])
    res = run("houses", "inspect", folder, "--up-axis", "y")  # each floor file then loads, with its floor
    assert sum(line.startswith("Floor") for line in res.output.splitlines()) == floors
    assert f"hint: these {len(objects.instances)} files look like" in res.output
    houses = tmp_path / "houses"
    for name in ("kitchen", "bedroom"):
        write_house(toy, houses / f"{name}.obj")
    assert "hint:" not in run("houses", "inspect", houses).output


def test_a_file_added_to_a_scene_folder_is_a_change_and_update_takes_it_in(toy, tmp_path):
    """A scene folder's house is the files its folder holds: one added (here a chair read by
    the folder's names) or removed is named as a change, refused without --update, and
    --update renders the house again with it, as a fresh render does."""
    folder = tmp_path / "scenes" / "room"
    files = write_object_files(toy, folder)
    chair = next(f for f in files if f.stem == "Chair")
    spare = tmp_path / "spare"
    spare.mkdir()
    for f in (chair, chair.with_suffix(".mtl")):
        f.rename(spare / f.name)
    out = tmp_path / "out.zarr"
    assert run("render", tmp_path / "scenes", out, *RENDER).exit_code == 0
    (record,) = open_store(str(out)).attrs["houses"]
    assert str(folder) + "/" in record["inputs"] and changes([record], ["room"]).changed == ()
    for f in spare.iterdir():
        f.rename(folder / f.name)
    assert changes([record], ["room"]).changed == ("room",)
    refused = run("render", tmp_path / "scenes", out, *RENDER)
    assert refused.exit_code != 0 and "changed: room" in refused.output, refused.output
    done = run("render", tmp_path / "scenes", out, *RENDER, "--update")
    assert done.exit_code == 0, done.output
    fresh = tmp_path / "fresh.zarr"
    assert run("render", tmp_path / "scenes", fresh, *RENDER).exit_code == 0
    assert array_digests(str(out)) == array_digests(str(fresh))
    (hidden := folder / ".notes").write_text("not a house file")
    (record,) = open_store(str(out)).attrs["houses"]
    assert changes([record], ["room"]).changed == ()  # hidden files are not the house's
    hidden.unlink()
    (folder / "Chair.obj").unlink()
    assert changes([record], ["room"]).changed == ("room",)
