"""The up axis of generic scenes, told from the geometry (``--up-axis auto``, the default): a Z-up
export of a known house loads as the Y-up one and renders the same layers; the reason shows in
``houses inspect``; what cannot be told fails with a one-line hint, and so does an upside-down
export; the real breakfast room."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner
from sceneforge.cli.main import cli

from sceneforge.errors import EXIT_FAILURES, HouseError
from sceneforge.houses import House, LoadOptions, load, make_instance
from sceneforge.houses.formats.generic import load_house
from sceneforge.houses.formats.meshio import Mesh
from sceneforge.houses.rooms import derive_rooms
from sceneforge.houses.toy import generate_house
from sceneforge.houses.up_axis import Part, detect_up_axis
from sceneforge.store import array_digests
from sceneforge.testing.generic import write_house
from sceneforge.testing.obj import write_obj
from sceneforge.testing.scenes import rotated_z_up

from .conftest import BREAKFAST_ROOM, needs_shared

#: a tiny render: one view, 64×48, no RGB
RENDER = ["--views-per-house", "1", "--resolution", "64x48", "--overhead-resolution", "32", "--no-rgb"]
#: glTF keeps float32 positions
ATOL = {".obj": 1e-12, ".ply": 1e-12, ".glb": 1e-5}


def run(*args):
    return CliRunner().invoke(cli, list(map(str, args)))


@pytest.fixture(scope="module")
def toy() -> House:
    return generate_house(3, "toy")


def _note(house: House) -> str:
    (note,) = [n for n in house.notes if n.startswith("up axis")]
    return note


@pytest.mark.parametrize("suffix", [".obj", ".glb", ".ply"])
def test_a_z_up_export_loads_as_the_y_up_one(toy, tmp_path, suffix):
    y = load(write_house(toy, tmp_path / "y" / f"toy{suffix}"))
    z = load(write_house(rotated_z_up(toy), tmp_path / "z" / f"toy{suffix}"))
    assert _note(y).startswith("up axis: y (detected: ") and _note(z).startswith("up axis: z (detected: ")
    assert [(i.name, i.category) for i in z.instances] == [(i.name, i.category) for i in y.instances]
    for a, b in zip(y.instances, z.instances, strict=True):
        np.testing.assert_allclose(b.vertices, a.vertices, atol=ATOL[suffix])
        np.testing.assert_array_equal(b.faces, a.faces)
    assert [(r.id, r.level) for r in z.rooms] == [(r.id, r.level) for r in y.rooms]
    assert {i.room_id for i in z.instances} == {i.room_id for i in y.instances}


def test_a_z_up_export_renders_the_layers_of_the_y_up_one(toy, tmp_path):
    """Same house id, same vertices: the same cameras and, array for array, the same store."""
    stores = []
    for up, house in (("y", toy), ("z", rotated_z_up(toy))):
        path = write_house(house, tmp_path / up / "toy.obj")
        stores.append(tmp_path / f"{up}.zarr")
        res = run("render", path, stores[-1], *RENDER)
        assert res.exit_code == 0, res.output
    assert array_digests(str(stores[0])) == array_digests(str(stores[1]))


def test_inspect_says_which_axis_and_why(toy, tmp_path):
    path = write_house(rotated_z_up(toy), tmp_path / "toy.obj")
    res = run("houses", "inspect", path)
    assert res.exit_code == 0, res.output
    (line,) = [line for line in res.output.splitlines() if line.startswith("note: up axis")]
    assert line.startswith("note: up axis: z (detected: 8 meshes named as floors or ceilings face ±Z")
    assert "objects stand at the bottom along +Z" in line and "of the area faces ±Z" in line
    assert line.endswith("; pass --up-axis to override")
    assert run("houses", "inspect", path, "--up-axis", "z").output.count("note:") == 0  # given, not detected


def test_names_are_not_needed(toy, tmp_path):
    """Every name void (``Object_<k>``): the objects standing on the floor and the floor area decide."""
    names = [f"Object_{k}" for k in range(len(toy.instances))]
    z = load(write_house(rotated_z_up(toy), tmp_path / "toy.obj", names=names))
    note = _note(z)
    assert note.startswith("up axis: z (detected: ") and "named" not in note
    assert "objects stand at the bottom along +Z" in note
    np.testing.assert_allclose(z.bounds(), toy.bounds(), atol=1e-12)


def test_the_decision_does_not_depend_on_the_order_or_the_units(toy, tmp_path):
    z = rotated_z_up(toy)
    order = np.random.default_rng(0).permutation(len(z.instances))
    shuffled = House(id="toy", instances=[z.instances[k] for k in order])
    scaled = House(id="toy", instances=[make_instance(House("s", []), name=i.name, category=i.category,
                                                      label=i.label, room_id=None, vertices=i.vertices * 100,
                                                      faces=i.faces) for i in z.instances])
    houses = (z, shuffled, scaled)
    notes = [_note(load(write_house(h, tmp_path / f"{k}" / "toy.obj"))) for k, h in enumerate(houses)]
    assert notes[0] == notes[1] == notes[2]


def _plane(name: str, z: float = 0.0, size: float = 4.0) -> Mesh:
    v = np.array([[0, 0, z], [size, 0, z], [size, size, z], [0, size, z]], float)
    return Mesh(v, np.array([[0, 1, 2], [0, 2, 3]]), name=name)


def _box(name: str, lo, hi) -> Mesh:
    b = trimesh.creation.box(bounds=np.array([lo, hi], float))
    return Mesh(np.asarray(b.vertices), np.asarray(b.faces), name=name)


def _add(house: House, mesh: Mesh, category: int = 0) -> None:
    make_instance(house, name=mesh.name, category=category, label=mesh.name, room_id=None,
                  vertices=mesh.vertices, faces=mesh.faces)


@pytest.mark.parametrize("meshes, suffix, why", [
    ([_box("Cube", (0, 0, 0), (1, 1, 1))], ".obj",
     "no mesh named as a floor or ceiling; one mesh, no objects standing on a floor; "
     "33 % of the area faces ±Y, 33 % ±Z"),
    ([_plane("Plane")], ".obj",
     "no mesh named as a floor or ceiling; one mesh, no objects standing on a floor; "
     "100 % of the area faces ±Z, 0 % ±Y and the scene is flat"),
    ([_box("Crate", (0, 0, 0), (1, 1, 1)), _box("Crate.001", (2, 0, 0), (3, 1, 1))], ".ply",
     "no mesh named as a floor or ceiling; 0 objects stand at the bottom along +Y, 0 along +Z; "
     "33 % of the area faces ±Y, 33 % ±Z"),
])
def test_what_cannot_be_told_fails_with_a_one_line_hint(tmp_path, meshes, suffix, why):
    path = tmp_path / f"thing{suffix}"
    house = House("thing", [])
    for m in meshes:
        _add(house, m)
    write_house(house, path, names=[m.name for m in meshes])
    message = f"cannot tell the up axis ({why}): pass --up-axis y or --up-axis z"
    with pytest.raises(HouseError) as e:
        load(path)
    assert e.value.problem == message
    res = run("houses", "inspect", path)
    assert res.exit_code == EXIT_FAILURES and "Traceback" not in res.output
    assert f"failed: house thing: {path}: {message}" in res.output.splitlines()
    assert load(path, LoadOptions(up_axis="z")).notes == []  # the hint works


def test_a_gltf_file_is_y_up_unless_clearly_z(tmp_path):
    cube = House("cube", [])
    _add(cube, _box("Cube", (0, 0, 0), (1, 1, 1)))
    house = load(write_house(cube, tmp_path / "cube.glb", names=["Cube"]))
    assert _note(house).startswith("up axis: y (glTF's convention, the evidence being unclear: ")
    with pytest.raises(HouseError, match="cannot tell the up axis"):
        load(write_house(cube, tmp_path / "cube.obj", names=["Cube"]))
    # a named floor lying flat to Z is clear enough, and so is gravity; area alone is not
    assert detect_up_axis([Part(_plane("f").vertices, _plane("f").faces, "floor")], prefer_y=True).axis == "z"
    assert detect_up_axis([Part(_plane("p").vertices, _plane("p").faces)], prefer_y=True).axis == "y"


def test_a_wrong_up_axis_is_a_clear_error_not_a_numpy_one(tmp_path):
    """A flat floor read with the wrong axis stands on its edge: no area seen from above."""
    path = write_obj(tmp_path / "room.obj", [_plane("Floor"), _box("Chair", (1, 1, 0), (1.5, 1.5, 0.9)),
                                             _box("Table", (2, 2, 0), (3, 3, 0.7))])
    assert _note(load(path)).startswith("up axis: z (detected: 1 mesh named as a floor or ceiling faces ±Z")
    with pytest.raises(HouseError) as e:
        load(path, LoadOptions(up_axis="y"))
    assert e.value.problem == ("the floors ('Floor') are vertical, with no area seen from above: the up axis "
                               "is wrong; pass --up-axis y or --up-axis z")
    house = House("h", [])
    _add(house, _plane("Floor"), category=2)
    with pytest.raises(HouseError, match="are vertical"):
        derive_rooms(house)


def test_a_broken_file_says_what_is_broken_before_the_up_axis(tmp_path):
    path = tmp_path / "nan.obj"
    path.write_text("o chair\nv 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(HouseError, match="1 vertices are NaN or infinite"):
        load_house(path)


# --------------------------------------------------------------------------- the real scene


@pytest.fixture(scope="module")
def breakfast_room() -> House:
    return load_house(BREAKFAST_ROOM)


@needs_shared(BREAKFAST_ROOM)
def test_the_breakfast_room_is_y_up(breakfast_room):
    assert _note(breakfast_room).startswith(
        "up axis: y (detected: 1 mesh named as a floor or ceiling faces ±Y with 100 % of its area")


@needs_shared(BREAKFAST_ROOM)
@pytest.mark.parametrize("suffix", [".glb", ".obj"])
def test_the_breakfast_room_turned_z_up_is_told_z(breakfast_room, tmp_path, suffix):
    z = rotated_z_up(breakfast_room)
    back = load(write_house(z, tmp_path / f"breakfast{suffix}"))
    assert _note(back).startswith("up axis: z (detected: ")
    np.testing.assert_allclose(back.bounds(), breakfast_room.bounds(), atol=ATOL[suffix])
    assert len(back.rooms) == len(breakfast_room.rooms) == 1


def _upside_down(house: House) -> House:
    """``house`` turned upside down (180° about X: ``(x, y, z)`` → ``(x, -y, -z)``)."""
    from dataclasses import replace

    flip = np.diag([1.0, -1.0, -1.0])
    return House(id=house.id, instances=[replace(i, vertices=i.vertices @ flip) for i in house.instances],
                 rooms=list(house.rooms), levels=list(house.levels))


@pytest.mark.parametrize("up", ["y", "z"])
@pytest.mark.parametrize("named", [True, False])
def test_an_upside_down_export_fails_with_a_one_line_reason(toy, tmp_path, up, named):
    """-Y or -Z up: the named floors above the ceilings, the objects hanging from the top;
    read as +Y or +Z its layers and cameras would be upside down, so the house fails in one
    line that says why, and the override reads it as told."""
    house = _upside_down(toy) if up == "y" else rotated_z_up(_upside_down(toy))
    names = None if named else [f"Object_{k}" for k in range(len(house.instances))]
    path = write_house(house, tmp_path / "toy.obj", names=names)
    with pytest.raises(HouseError) as e:
        load(path)
    axis = up.upper()
    floors = f"the meshes named as floors lie above those named as ceilings along +{axis}; " if named else ""
    assert e.value.problem == (f"the scene is upside down (-{axis} up: {floors}20 objects hang at the top along "
                               f"+{axis}, 4 stand at the bottom): export it +Y or +Z up (if it is not upside "
                               f"down, pass --up-axis {up})")
    res = run("houses", "inspect", path)
    assert res.exit_code == EXIT_FAILURES and "Traceback" not in res.output
    assert f"failed: house toy: {path}: {e.value.problem}" in res.output.splitlines()
    assert load(path, LoadOptions(up_axis=up)).notes == []  # told, it is read as it is


@pytest.mark.parametrize("kind", ["toy", "room"])
def test_upright_houses_are_not_upside_down(tmp_path, kind):
    """The check says nothing of upright scenes: 8 generated houses of each kind, named and
    unnamed, +Y and +Z up, all load."""
    for seed in range(8):
        house = generate_house(seed, kind)
        for named in (True, False):
            names = None if named else [f"Object_{k}" for k in range(len(house.instances))]
            for up, h in (("y", house), ("z", rotated_z_up(house))):
                loaded = load(write_house(h, tmp_path / f"{seed}{named}{up}" / "h.obj", names=names))
                assert _note(loaded).startswith(f"up axis: {up} (detected: ")
