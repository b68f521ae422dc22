"""Real datasets as they come: folder layouts and house ids, unreadable houses reported by name,
name maps that extend and drop, merged envelopes split, rooms derived from floors, the toy
generator's hard cases."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner
from sceneforge.cli.main import cli

from sceneforge.cameras import look_at_camera
from sceneforge.conventions import NYU40_IDS
from sceneforge.errors import EXIT_FAILURES, HouseError, SceneforgeError
from sceneforge.houses import House, LoadOptions, discover, iter_houses, load, make_instance
from sceneforge.houses.inspect import summarize
from sceneforge.houses.rooms import derive_rooms, points_in_triangles
from sceneforge.houses.shell import CEILING, FLOOR, WALL, split_shell
from sceneforge.houses.toy import ToyOptions, build_toy_house, generate_house
from sceneforge.store import open_store
from sceneforge.testing.generic import write_house
from sceneforge.testing.scenes import PLANT_PARTS, UNKNOWN_NAME, write_downloaded

CORRUPT_JSON = '{"id": "x",\n "levels": [1, 2\n}\n'  # line 3 column 1: the list is not closed


def run(*args):
    return CliRunner().invoke(cli, list(map(str, args)))


# --------------------------------------------------------------------------- house ids


def test_generic_file_names_take_the_folder_name(small_house, tmp_path):
    write_house(small_house, tmp_path / "a" / "scene.gltf")
    write_house(small_house, tmp_path / "b" / "scene.gltf")
    write_house(small_house, tmp_path / "c" / "kitchen.obj")
    sources = discover(tmp_path)
    assert [(s.id, s.problem) for s in sources] == [("a", None), ("b", None), ("kitchen", None)]
    assert [load(s).id for s in sources] == ["a", "b", "kitchen"]
    # a name several houses share is no name either, generic or not; nor a folder name shared
    write_house(small_house, tmp_path / "d" / "kitchen.obj")
    write_house(small_house, tmp_path / "set2" / "a" / "scene.glb")
    ids = [s.id for s in discover(tmp_path)]
    assert ids == ["a", "b", "c", "d", "set2/a"]
    # pointed at directly, a generic file is still named by its folder
    assert discover(tmp_path / "a" / "scene.gltf")[0].id == "a"


def test_colliding_ids_fail_only_those_houses_naming_both_files(small_house, tmp_path):
    write_house(small_house, tmp_path / "a" / "scene.gltf")
    write_house(small_house, tmp_path / "b.glb")
    write_house(small_house, tmp_path / "b" / "scene.gltf")
    results = [(s.id, h is not None, e) for s, h, e in iter_houses(tmp_path)]
    assert [(i, ok) for i, ok, _ in results] == [("a", True), ("b", False), ("b", False)]
    first, second = results[1][2], results[2][2]
    assert isinstance(first, HouseError)
    assert str(tmp_path / "b" / "scene.gltf") in str(first) and str(tmp_path / "b.glb") in str(first)
    assert str(tmp_path / "b.glb") in str(second) and str(tmp_path / "b" / "scene.gltf") in str(second)


# ------------------------------------------------------------------ unreadable houses


def test_corrupt_house_json_is_reported_with_the_json_error(small_house, tmp_path):
    from sceneforge.houses.formats.native import write_house as write_native

    write_native(small_house, tmp_path / "good")
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "house.json").write_text(CORRUPT_JSON)
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "meta.json").write_text("{}")  # any other JSON is not a house
    outcome = [(s.id, e) for s, _, e in iter_houses(tmp_path)]
    assert [i for i, _ in outcome] == ["broken", "good"]
    error = outcome[0][1]
    assert "house broken" in str(error) and "house.json" in str(error)
    assert "line 3 column 1" in str(error)
    # pointed at directly: the JSON error too, not "not a house in any supported format"
    with pytest.raises(HouseError, match="not JSON: .*line 3 column 1"):
        load(tmp_path / "broken" / "house.json")
    res = run("houses", "inspect", tmp_path)
    assert res.exit_code == EXIT_FAILURES  # some houses failed, the others were read
    failed = [line for line in res.output.splitlines() if line.startswith("failed:")]
    assert len(failed) == 1 and "house broken" in failed[0] and "line 3 column 1" in failed[0]
    assert "1 house read, 1 failed" in res.output


def test_render_failure_log_names_the_unreadable_and_colliding_houses(small_house, tmp_path):
    houses = tmp_path / "houses"
    write_house(small_house, houses / "a" / "scene.gltf")
    write_house(small_house, houses / "b" / "scene.gltf")
    write_house(small_house, houses / "c.glb")
    write_house(small_house, houses / "c" / "scene.gltf")
    (houses / "d").mkdir()
    (houses / "d" / "house.json").write_text(CORRUPT_JSON)
    out = tmp_path / "out.zarr"
    res = run("render", houses, out, "--resolution", "32x24", "--overhead-resolution", "16",
              "--views-per-house", "1", "--no-rgb")
    assert res.exit_code == EXIT_FAILURES, res.output
    assert "Traceback" not in res.output
    store = open_store(str(out))
    assert sorted({str(store.view(i)["house_id"]) for i in range(len(store))}) == ["a", "b"]
    log = {(f["house"], f["reason"]) for f in store.attrs["failures"]}
    assert len(log) == 3
    reasons = {h: [r for hh, r in log if hh == h] for h in ("c", "d")}
    assert all(str(houses / "c.glb") in r and str(houses / "c" / "scene.gltf") in r for r in reasons["c"])
    assert len(reasons["c"]) == 2 and "line 3 column 1" in reasons["d"][0]


# --------------------------------------------------------------------------- name maps

OBJECTS = ("Chair", "Stool", "Gizmo.003", "chair__Gizmo", "DecoPlant", "Leaves", "Branches", "Person.001",
           "room_skeleton", "Baseboard", "Carpet", "Curtain_Rod", "Cornice", "Blob")


#: the named scenes are a row of tilted triangles: no up axis to tell, so it is given
Y_UP = LoadOptions(up_axis="y")


def _named_scene(tmp_path, names=OBJECTS):
    """An OBJ with one small triangle per name, named so (no tags); read it with :data:`Y_UP`."""
    h = House(id="named", instances=[])
    for k, name in enumerate(names):
        make_instance(h, name=name, category=0, label=name, room_id=None,
                      vertices=[(k, 0, 0), (k + 0.5, 0, 0), (k, 0.5, 0.2)], faces=[(0, 1, 2)])
    return write_house(h, tmp_path / "named.obj", names=list(names))


def test_user_rules_come_before_the_bundled_ones_and_add_to_them(tmp_path):
    path = _named_scene(tmp_path)
    default = {i.name: i.category_name for i in load(path, Y_UP).instances}
    assert default == {"Chair": "chair", "Stool": "chair", "Gizmo.003": "void", "Gizmo": "chair",
                       "room_skeleton/wall": "wall", "Baseboard": "wall", "Carpet": "floor_mat",
                       "Curtain_Rod": "curtain", "Cornice": "wall", "Blob": "void"}
    one_rule = tmp_path / "map.json"
    one_rule.write_text(json.dumps({"patterns": [["stool|gizmo", "otherfurniture"]]}))
    custom = {i.name: i.category_name for i in load(path, replace(Y_UP, name_map=str(one_rule))).instances}
    # the user's rule wins over the bundled chair rule, the tag over both; the rest is bundled
    assert custom == default | {"Stool": "otherfurniture", "Gizmo.003": "otherfurniture"}


def test_drop_removes_instances(tmp_path):
    path = _named_scene(tmp_path)
    h = load(path, Y_UP)
    names = [i.name for i in h.instances]
    assert not {"DecoPlant", "Leaves", "Branches", "Person.001"} & set(names)
    dropped = [w for w in h.warnings if "dropped" in w]
    assert len(dropped) == 4 and all("name_patterns.json" in w for w in dropped)
    mapping = tmp_path / "drop.json"
    mapping.write_text(json.dumps([["^blob$", "drop"], ["^chair$", "drop"]]))
    h = load(path, replace(Y_UP, name_map=str(mapping)))
    assert [i.name for i in h.instances] == [n for n in names if n not in ("Blob", "Chair")]
    assert any("'Blob' dropped by drop.json #1 ('^blob$')" in w for w in h.warnings)


def test_a_bad_rule_is_one_clear_error(tmp_path):
    path = _named_scene(tmp_path)
    mapping = tmp_path / "bad.json"
    mapping.write_text(json.dumps([["ok", "chair"], ["plant", "greenery"]]))
    with pytest.raises(SceneforgeError, match=r"bad.json, rule 2: 'greenery' is not a target .*'drop'"):
        load(path, LoadOptions(name_map=str(mapping)))


# ---------------------------------------------------------------------- merged shells


def _quad(lo, hi, axis, flip=False):
    """Two triangles of the axis-aligned rectangle ``lo``..``hi`` (flat along ``axis``)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    u, w = [a for a in range(3) if a != axis]
    corners = []
    for du, dw in ((0, 0), (1, 0), (1, 1), (0, 1)):
        p = lo.copy()
        p[u] = (lo, hi)[du][u]
        p[w] = (lo, hi)[dw][w]
        corners.append(p)
    faces = [(0, 1, 2), (0, 2, 3)]
    return np.array(corners), np.array([f[::-1] for f in faces] if flip else faces)


def _box_shell(w=4.0, h=2.5, d=5.0, flip=False):
    """A single-surface room shell 0..w × 0..h × 0..d, plus a 1 × 0.2 m window sill at 0.9 m
    and a 1 × 0.2 m lintel underside at 2.1 m (both small horizontal faces: wall)."""
    quads = [((0, 0, 0), (w, 0, d), 1), ((0, h, 0), (w, h, d), 1),
             ((0, 0, 0), (0, h, d), 0), ((w, 0, 0), (w, h, d), 0),
             ((0, 0, 0), (w, h, 0), 2), ((0, 0, d), (w, h, d), 2),
             ((w - 0.2, 0.9, 1), (w, 0.9, 2), 1), ((w - 0.2, 2.1, 1), (w, 2.1, 2), 1)]
    vs, fs = [], []
    for k, (lo, hi, axis) in enumerate(quads):
        v, f = _quad(lo, hi, axis, flip=flip ^ (k % 2 == 1))
        fs.append(f + 4 * k)
        vs.append(v)
    return np.concatenate(vs), np.concatenate(fs)


@pytest.mark.parametrize("flip", [False, True])
def test_box_shell_splits_into_wall_floor_ceiling_with_exact_areas(flip):
    w, h, d = 4.0, 2.5, 5.0
    v, f = _box_shell(w, h, d, flip)
    part = split_shell(v, f)
    area = trimesh.Trimesh(v, f, process=False).area_faces
    assert area[part == FLOOR].sum() == pytest.approx(w * d, abs=1e-12)
    assert area[part == CEILING].sum() == pytest.approx(w * d, abs=1e-12)
    assert area[part == WALL].sum() == pytest.approx(2 * (w + d) * h + 2 * 0.2, abs=1e-12)
    assert (v[f[part == FLOOR]][..., 1] == 0).all() and (v[f[part == CEILING]][..., 1] == h).all()


def test_a_shell_in_a_file_loads_as_three_instances(tmp_path):
    v, f = _box_shell()
    h = House(id="shell", instances=[])
    make_instance(h, name="Shell", category=0, label="Shell", room_id=None, vertices=v, faces=f)
    back = load(write_house(h, tmp_path / "room.obj", names=["Shell"]))
    areas = {i.name: (i.category_name, trimesh.Trimesh(i.vertices, i.faces).area) for i in back.instances}
    assert areas == {"Shell/wall": ("wall", pytest.approx(2 * 9 * 2.5 + 0.4)),
                     "Shell/floor": ("floor", pytest.approx(20.0)), "Shell/ceiling": ("ceiling", pytest.approx(20.0))}
    assert len(back.rooms) == 1 and summarize(back).problems == ()


def test_two_storey_shell_slab_goes_by_its_normal():
    lower_v, lower_f = _box_shell(h=2.5)
    upper_v, upper_f = _box_shell(h=2.5)
    upper_v = upper_v + (0, 2.5, 0)
    v = np.concatenate([lower_v, upper_v])
    f = np.concatenate([lower_f, upper_f + len(lower_v)])
    part = split_shell(v, f)
    y = v[f][..., 1].mean(1)
    ny = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])[:, 1]
    slab = np.abs(y - 2.5) < 1e-9
    # the slab is drawn twice: as the lower ceiling (normal down) and the upper floor (up)
    assert set(part[slab & (ny < 0)]) == {CEILING} and set(part[slab & (ny > 0)]) == {FLOOR}
    assert set(part[np.abs(y) < 1e-9]) == {FLOOR} and set(part[np.abs(y - 5) < 1e-9]) == {CEILING}


def test_a_shell_without_floor_keeps_its_ceiling():
    v, f = _box_shell()
    f = f[2:]  # the floor quad left out: no face faces up but the sill
    part = split_shell(v, f)
    area = trimesh.Trimesh(v, f, process=False).area_faces
    assert area[part == CEILING].sum() == pytest.approx(20.0) and not (part == FLOOR).any()


def test_a_thick_wall_box_stays_wall():
    wall = trimesh.creation.box(bounds=[(0, 0, 0), (4, 2.7, 0.2)])
    assert (split_shell(wall.vertices, wall.faces) == WALL).all()


# ---------------------------------------------------------------------- derived rooms


def test_points_in_triangles_against_a_slow_reference():
    rng = np.random.default_rng(3)
    tri = rng.uniform(0, 1, (7, 3, 2))
    pts = rng.uniform(0, 1, (300, 2))

    def inside(p, t):  # barycentric coordinates
        m = np.array([t[1] - t[0], t[2] - t[0]]).T
        if abs(np.linalg.det(m)) < 1e-15:
            return False
        a, b = np.linalg.solve(m, p - t[0])
        return a >= 0 and b >= 0 and a + b <= 1

    expected = [any(inside(p, t) for t in tri) for p in pts]
    assert points_in_triangles(pts, tri).tolist() == expected


def test_a_gltf_of_two_rooms_gets_two_rooms(tmp_path):
    toy = build_toy_house(4)  # three rooms in a row
    two = House(id="two", instances=[])
    for inst in toy.house.instances:
        if inst.room_id in ("room0", "room1"):
            make_instance(two, name=inst.name, category=inst.category, label=inst.label, room_id=inst.room_id,
                          vertices=inst.vertices, faces=inst.faces)
    back = load(write_house(two, tmp_path / "two" / "scene.gltf"))
    assert back.id == "two" and [r.id for r in back.rooms] == ["room_0", "room_1"]
    assert [lv.floor_y for lv in back.levels] == [pytest.approx(0.0, abs=1e-6)]
    truth = {"room0": "room_0", "room1": "room_1"}
    assert [truth[i.room_id] for i in two.instances] == [i.room_id for i in back.instances]


def test_majority_room_is_no_longer_rejected_for_lack_of_rooms(tmp_path):
    from sceneforge.layers import frontal_layers
    from sceneforge.overhead import overhead_camera

    toy = build_toy_house(4)
    back = load(write_house(toy.house, tmp_path / "toy" / "scene.glb"))
    lo, hi = (np.array(c) for c in toy.interiors["room0"])
    position = (lo[0] + 0.3, 1.5, lo[2] + 0.3)
    view_dir = (hi[0] - lo[0], -0.2 * np.hypot(hi[0] - lo[0], hi[2] - lo[2]), hi[2] - lo[2])
    camera = look_at_camera(position, view_dir, width=64, height=48)
    votes = {}
    for name, house in (("derived", back), ("none", _without_rooms(back))):
        top = overhead_camera(house, camera, frontal_layers(house, camera))
        votes[name] = next(c for c in top.candidates if c.name == "majority_room")
    assert votes["none"].box is None and "0 room votes" in votes["none"].reason
    assert votes["derived"].box is not None, votes["derived"].reason


def _without_rooms(house: House) -> House:
    from dataclasses import replace

    return House(id=house.id, instances=[replace(i, room_id=None) for i in house.instances], rooms=[],
                 levels=house.levels)


def test_two_levels_get_two_levels_of_rooms(tmp_path):
    toy = build_toy_house(4, options=ToyOptions(two_levels=True))
    back = load(write_house(toy.house, tmp_path / "two.glb"))
    assert len(back.rooms) == len(toy.house.rooms) == 6
    assert [lv.floor_y for lv in back.levels] == pytest.approx([lv.floor_y for lv in toy.house.levels], abs=1e-6)
    pairs = {(a.room_id, b.room_id) for a, b in zip(toy.house.instances, back.instances, strict=True)}
    assert len(pairs) == 6 == len({b for _, b in pairs})


def test_inspect_reports_no_floor_no_rooms_and_void_names(tmp_path):
    path = _named_scene(tmp_path, ("Blob", "Blob.001", "Gizmo", "Chair"))
    s = summarize(load(path, Y_UP))
    assert "no floor instance" in s.problems and "no wall instance" in s.problems
    assert any(p.startswith("no rooms") for p in s.problems)
    assert s.void_names == (("Blob", 2, 2, pytest.approx(0.5)), ("Gizmo", 1, 1, pytest.approx(0.25)))
    assert not any(p.startswith("unknown category") for p in s.problems)  # listed once, as void names
    res = run("houses", "inspect", path, "--up-axis", "y")
    assert "names that fell to void:" in res.output and "'Blob'  2 instances  2 triangles  50.0 %" in res.output
    assert "problem: no rooms" in res.output


# ---------------------------------------------------------------------- toy hard cases


def test_toy_options_off_give_the_default_house():
    a, b = generate_house(5), generate_house(5, options=ToyOptions())
    assert len(a.instances) == len(b.instances)
    for x, y in zip(a.instances, b.instances):
        assert x.name == y.name and np.array_equal(x.vertices, y.vertices) and x.material == y.material


def test_room_rugs_cover_90_percent_of_every_floor():
    toy = build_toy_house(2, options=ToyOptions(room_rugs=True))
    for room_id, (lo, hi) in toy.interiors.items():
        rugs = [i for i in toy.house.instances if i.room_id == room_id and i.category_name == "floor_mat"]
        assert len(rugs) == 1
        (x0, _, z0), (x1, _, z1) = rugs[0].vertices.min(0), rugs[0].vertices.max(0)
        assert (x1 - x0) * (z1 - z0) >= 0.9 * (hi[0] - lo[0]) * (hi[2] - lo[2])


def test_two_levels_are_joined_by_stairs_under_a_hole():
    toy = build_toy_house(0, options=ToyOptions(two_levels=True))
    h = toy.house
    storey = h.levels[1].floor_y
    stairs = next(i for i in h.instances if i.label == "stairs")
    top = stairs.vertices[:, 1].max()
    assert top == pytest.approx(storey) and stairs.vertices[:, 1].min() == 0
    step = stairs.faces[np.argmax(stairs.vertices[stairs.faces][..., 1].mean(1))]
    centre = stairs.vertices[step].mean(0)  # on the top step's upper face
    upper = [r for r in h.rooms if r.level == 1]
    assert len(upper) == len([r for r in h.rooms if r.level == 0])
    ceiling_up = next(i for i in h.instances if i.room_id == f"{stairs.room_id}_l1" and i.category_name == "ceiling")
    floor_up = next(i for i in h.instances if i.room_id == f"{stairs.room_id}_l1" and i.category_name == "floor")
    ceiling_down = next(i for i in h.instances if i.room_id == stairs.room_id and i.category_name == "ceiling")
    # the lower ceiling and the upper floor have a hole over the stair, the upper ceiling none
    for slab in (floor_up, ceiling_down):
        xz = slab.vertices[slab.faces][..., [0, 2]]
        assert not points_in_triangles(centre[None, [0, 2]], xz, strict=True).any()
    assert points_in_triangles(centre[None, [0, 2]], ceiling_up.vertices[ceiling_up.faces][..., [0, 2]]).any()


def test_hidden_floor_and_ceiling():
    plain = build_toy_house(1).house
    toy = build_toy_house(1, options=ToyOptions(hidden_floor=True, hidden_ceiling=True)).house
    floors = lambda h: [i.room_id for i in h.instances if i.category_name == "floor"]  # noqa: E731
    ceilings = lambda h: [i.room_id for i in h.instances if i.category_name == "ceiling"]  # noqa: E731
    assert floors(toy) == floors(plain)[:-1] and ceilings(toy) == ceilings(plain)[1:]


def test_a_downloaded_toy_house_loads_with_its_classes(tmp_path):
    toy = build_toy_house(0)
    path = write_downloaded(toy.house, tmp_path / "toy" / "scene.glb", generic_names=True)
    back = load(path)
    assert back.id == "toy"
    names = {i.name for i in back.instances}
    assert not names & {name for name, _, _ in PLANT_PARTS}
    truth = [i.category_name for i in toy.house.instances]
    got = [i.category_name for i in back.instances]
    unknown = [k for k, i in enumerate(back.instances) if i.name == UNKNOWN_NAME]
    assert len(unknown) == 1 and got[unknown[0]] == "void" and truth[unknown[0]] == "otherprop"
    assert [g for k, g in enumerate(got) if k != unknown[0]] == [t for k, t in enumerate(truth) if k != unknown[0]]
    assert len(back.rooms) == len(toy.house.rooms)


def test_a_merged_toy_shell_keeps_every_visible_floor_and_ceiling(tmp_path):
    toy = build_toy_house(0)
    back = load(write_downloaded(toy.house, tmp_path / "merged.obj", merged_shell=True))
    by_name = {i.name: i for i in back.instances}
    assert {"Shell/wall", "Shell/floor", "Shell/ceiling"} <= set(by_name)

    def area_at(inst, y, up):
        tri = inst.vertices[inst.faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        keep = (np.abs(tri[..., 1] - y).max(1) < 1e-6) & ((n[:, 1] > 0) if up else (n[:, 1] < 0))
        return np.linalg.norm(n[keep], axis=1).sum() / 2

    floors = [i for i in toy.house.instances if i.category == NYU40_IDS["floor"]]
    ceilings = [i for i in toy.house.instances if i.category == NYU40_IDS["ceiling"]]
    height = toy.interiors["room0"][1][1]
    assert area_at(by_name["Shell/floor"], 0.0, True) == pytest.approx(sum(area_at(i, 0.0, True) for i in floors))
    assert area_at(by_name["Shell/ceiling"], height, False) == pytest.approx(
        sum(area_at(i, height, False) for i in ceilings))


def test_derive_rooms_leaves_a_house_with_rooms_alone(small_house):
    before = [(i.room_id) for i in small_house.instances]
    assert derive_rooms(small_house) is small_house and [i.room_id for i in small_house.instances] == before
