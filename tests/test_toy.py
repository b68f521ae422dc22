"""The procedural toy houses: determinism, contents, closed envelopes, exact placement."""

from __future__ import annotations

from collections import deque
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner
from sceneforge.cli.toy_houses import toy_houses

from sceneforge.errors import SceneforgeError
from sceneforge.houses import bundled_toy_dir
from sceneforge.houses.formats.native import load_house, write_house
from sceneforge.houses.toy import (
    BUNDLE_COUNT,
    BUNDLE_SEED,
    build_toy_house,
    generate_house,
    house_seed,
    toy_house_id,
    write_bundle,
    write_toy_houses,
)

BUNDLED_IDS = [toy_house_id(BUNDLE_SEED, i) for i in range(BUNDLE_COUNT)]
EPS = 1e-9


@lru_cache(maxsize=None)
def fresh(index: int):
    """The generator's own record of bundled house ``index`` (house, openings, supports, ...)."""
    return build_toy_house(house_seed(BUNDLE_SEED, index), toy_house_id(BUNDLE_SEED, index))


@lru_cache(maxsize=None)
def bundled(index: int):
    return load_house(bundled_toy_dir() / BUNDLED_IDS[index])


def files(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def parts(inst) -> list[trimesh.Trimesh]:
    """The closed primitives an instance is made of (its connected components)."""
    return trimesh.Trimesh(inst.vertices, inst.faces, process=False).split(only_watertight=False)


# ------------------------------------------------------------------ determinism and bundle

def test_same_seed_writes_identical_bytes_and_other_seeds_differ(tmp_path):
    write_house(generate_house(11, "h"), tmp_path / "a")
    write_house(generate_house(11, "h"), tmp_path / "b")
    write_house(generate_house(12, "h"), tmp_path / "c")
    a, b, c = files(tmp_path / "a"), files(tmp_path / "b"), files(tmp_path / "c")
    assert set(a) == {"house.json", "house.bin"}
    assert a == b
    assert a["house.bin"] != c["house.bin"]


def test_write_toy_houses_ids_and_derived_seeds(tmp_path):
    folders = write_toy_houses(tmp_path, 2, 5)
    assert [f.name for f in folders] == ["toy_5_000", "toy_5_001"]
    assert house_seed(5, 0) != house_seed(5, 1)
    for i, folder in enumerate(folders):
        loaded, made = load_house(folder), generate_house(house_seed(5, i), toy_house_id(5, i))
        assert loaded.id == made.id == folder.name
        assert [x.name for x in loaded.instances] == [x.name for x in made.instances]
        for x, y in zip(loaded.instances, made.instances):
            np.testing.assert_array_equal(x.vertices, y.vertices)
            np.testing.assert_array_equal(x.faces, y.faces)


def test_bundled_houses_equal_a_fresh_generation(tmp_path):
    assert sorted(p.name for p in bundled_toy_dir().iterdir() if p.is_dir()) == BUNDLED_IDS
    write_bundle(tmp_path)
    for house_id in BUNDLED_IDS:
        assert files(tmp_path / house_id) == files(bundled_toy_dir() / house_id), (
            f"{house_id} is stale: run `python -m sceneforge.houses.toy --bundle`"
        )
    total = sum(p.stat().st_size for p in bundled_toy_dir().rglob("*") if p.is_file())
    assert total < 1.5e6


@pytest.mark.parametrize("bad", [-1, 1.5, "3", True])
def test_bad_seed_or_count_is_a_clear_error(bad, tmp_path):
    with pytest.raises(SceneforgeError, match="seed must be a non-negative integer"):
        generate_house(bad)
    with pytest.raises(SceneforgeError, match="count must be a positive integer"):
        write_toy_houses(tmp_path, 0 if bad is True else bad, 0)


# ------------------------------------------------------------------ contents

def test_bundled_houses_have_envelope_rooms_and_many_categories():
    seen = set()
    for i in range(BUNDLE_COUNT):
        house = bundled(i)
        cats = {x.category_name for x in house.instances}
        seen |= cats
        assert {"wall", "floor", "ceiling", "door", "window"} <= cats, house.id
        assert house.warnings == []
        assert [lv.floor_y for lv in house.levels] == [0.0]
        room_ids = [r.id for r in house.rooms]
        assert 2 <= len(room_ids) <= 4
        for rid in room_ids:
            own = {x.category_name for x in house.instances if x.room_id == rid}
            assert {"wall", "floor", "ceiling", "window"} <= own, (house.id, rid)
        assert all(x.room_id in room_ids for x in house.instances)
        colours = [x.material.base_color for x in house.instances]
        assert len(set(colours)) == len(colours), "every instance has its own colour"
        assert all(np.isfinite(x.vertices).all() for x in house.instances)
        assert 1000 < house.triangle_count < 6000
    objects = {c for c in seen if c not in {"wall", "floor", "ceiling", "door", "window", "curtain",
                                            "blinds", "picture", "floor_mat", "mirror"}}
    assert len(seen) >= 12 and len(objects) >= 12, sorted(seen)


def test_every_part_is_a_closed_outward_solid_and_nothing_interpenetrates():
    for i in range(BUNDLE_COUNT):
        boxes, owner = [], []
        for k, inst in enumerate(bundled(i).instances):
            for part in parts(inst):
                assert part.is_watertight and part.is_winding_consistent, inst.name
                assert part.volume > 0, f"{inst.name}: faces wound inwards"
                boxes.append(part.bounds)
                owner.append(k)
        b, owner = np.array(boxes), np.array(owner)
        # every part is an axis-aligned box or a vertical cylinder inscribed in its bounds,
        # so positive overlap of bounds between two instances means they interpenetrate
        overlap = ((b[:, None, 0] < b[None, :, 1] - EPS) & (b[None, :, 0] < b[:, None, 1] - EPS)).all(-1)
        overlap &= owner[:, None] != owner[None, :]
        names = [bundled(i).instances[k].name for k in owner]
        pairs = sorted({tuple(sorted((names[p], names[q]))) for p, q in zip(*np.nonzero(overlap))})
        assert pairs == [], pairs


def test_rooms_are_connected_by_doors_and_have_windows():
    for i in range(BUNDLE_COUNT):
        toy = fresh(i)
        rooms = [r.id for r in toy.house.rooms]
        links = {r: set() for r in rooms}
        for o in toy.openings:
            if o.kind == "door":
                a, b = o.rooms
                links[a].add(b)
                links[b].add(a)
        reached, todo = {rooms[0]}, deque([rooms[0]])
        while todo:
            for nxt in links[todo.popleft()] - reached:
                reached.add(nxt)
                todo.append(nxt)
        assert reached == set(rooms)
        assert {o.rooms[0] for o in toy.openings if o.kind == "window"} == set(rooms)
        assert [o.kind for o in toy.openings].count("front_door") == 1


def _bottom_faces_y(mesh: trimesh.Trimesh, y: float) -> np.ndarray:
    """(k, 3, 3) triangles of ``mesh`` facing up (+Y) and lying in the plane ``y``."""
    tri = mesh.triangles
    up = (mesh.face_normals[:, 1] > 1 - 1e-12) & (np.abs(tri[:, :, 1] - y) <= EPS).all(1)
    return tri[up]


def test_small_objects_rest_exactly_on_their_supports():
    kinds = set()
    for i in range(BUNDLE_COUNT):
        by_name = {x.name: x for x in bundled(i).instances}
        for item_name, support_name in fresh(i).supports:
            item, support = by_name[item_name], by_name[support_name]
            kinds.add(item.category_name)
            bottom = item.vertices[:, 1].min()
            tops = _bottom_faces_y(trimesh.Trimesh(support.vertices, support.faces, process=False), bottom)
            assert len(tops), f"{item_name}: no upward face of {support_name} at y = {bottom}"
            # the item's footprint at its bottom lies on those faces
            foot = item.vertices[np.abs(item.vertices[:, 1] - bottom) <= EPS][:, [0, 2]]
            lo, hi = tops[:, :, [0, 2]].reshape(-1, 2).min(0), tops[:, :, [0, 2]].reshape(-1, 2).max(0)
            assert (foot >= lo - EPS).all() and (foot <= hi + EPS).all(), (item_name, support_name)
    assert {"otherprop", "books", "lamp", "pillow", "television"} <= kinds


def test_tucked_chairs_reach_under_the_top_without_touching_it():
    tucked = [(i, c, t) for i in range(BUNDLE_COUNT) for c, t in fresh(i).tucked]
    assert tucked
    for i, chair_name, table_name in tucked:
        by_name = {x.name: x for x in bundled(i).instances}
        chair, table = by_name[chair_name], by_name[table_name]
        assert chair.category_name == "chair" and table.category_name in ("table", "desk")
        tmesh = trimesh.Trimesh(table.vertices, table.faces, process=False)
        lo, hi = table.vertices[:, [0, 2]].min(0), table.vertices[:, [0, 2]].max(0)
        clo, chi = chair.vertices[:, [0, 2]].min(0), chair.vertices[:, [0, 2]].max(0)
        overlap = np.minimum(hi, chi) - np.maximum(lo, clo)
        assert (overlap > 0.05).all(), f"{chair_name} is not under {table_name}"
        underside = tmesh.triangles[tmesh.face_normals[:, 1] < -1 + 1e-12][:, :, 1].max()
        under = ((chair.vertices[:, [0, 2]] > lo) & (chair.vertices[:, [0, 2]] < hi)).all(1)
        assert under.any()
        assert chair.vertices[under, 1].max() < underside


def test_rugs_lie_within_a_millimetre_of_the_floor():
    rugs = [x for i in range(BUNDLE_COUNT) for x in bundled(i).instances if x.category_name == "floor_mat"]
    assert rugs
    for rug in rugs:
        assert rug.vertices[:, 1].min() == 0.0 and rug.vertices[:, 1].max() <= 0.001 + EPS


# ------------------------------------------------------------------ rays only leave through windows

def _escapes(house, toy, rays_per_room: int, seed: int):
    """Origins (n, 3) and directions (n, 3) of random rays from inside the rooms that hit nothing."""
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    mesh = trimesh.util.concatenate(
        [trimesh.Trimesh(x.vertices, x.faces, process=False) for x in house.instances])
    rng = np.random.default_rng(seed)
    origins = np.concatenate([
        rng.uniform(np.add(lo, 0.01), np.subtract(hi, 0.01), (rays_per_room, 3))
        for lo, hi in toy.interiors.values()
    ])
    dirs = rng.normal(size=origins.shape)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    miss = RayMeshIntersector(mesh).intersects_first(origins, dirs) < 0
    return origins[miss], dirs[miss]


def _through(opening, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(n,) bool: the ray crosses both faces of the wall inside the opening's rectangle."""
    a = opening.axis
    lo, hi = np.array(opening.lo), np.array(opening.hi)
    ok = np.ones(len(origins), bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for plane in (lo[a], hi[a]):
            t = (plane - origins[:, a]) / dirs[:, a]
            p = origins + t[:, None] * dirs
            inside = ((p >= lo - 1e-6) & (p <= hi + 1e-6)).all(1)
            ok &= (t > 0) & inside
    return ok


@pytest.mark.parametrize("index", range(BUNDLE_COUNT))
def test_rays_from_inside_escape_only_through_windows(index):
    toy, house = fresh(index), bundled(index)
    windows = [o for o in toy.openings if o.exterior and o.passable]
    assert all(o.kind == "window" for o in windows)
    origins, dirs = _escapes(house, toy, 2000, seed=index)
    assert len(origins) > 0, "no ray left the house: the windows are not open"
    through = np.zeros(len(origins), bool)
    for w in windows:
        through |= _through(w, origins, dirs)
    assert through.all(), f"{(~through).sum()} of {len(origins)} escaping rays missed every window"


def test_escape_check_catches_a_missing_wall():
    toy, house = fresh(0), bundled(0)
    house = type(house)(id=house.id, instances=[x for x in house.instances if x.name != "room0/wall_0"],
                        rooms=house.rooms)
    origins, dirs = _escapes(house, toy, 500, seed=0)
    through = np.zeros(len(origins), bool)
    for w in (o for o in toy.openings if o.kind == "window"):
        through |= _through(w, origins, dirs)
    assert (~through).sum() > 50


# ------------------------------------------------------------------ command line

def test_cli_writes_houses_and_prints_one_line_each(tmp_path):
    res = CliRunner().invoke(toy_houses, [str(tmp_path), "--count", "2", "--seed", "3"])
    assert res.exit_code == 0, res.output
    lines = res.output.strip().splitlines()
    assert [ln.split()[0] for ln in lines] == ["toy_3_000", "toy_3_001"]
    for ln in lines:
        house = load_house(tmp_path / ln.split()[0])
        assert f"rooms {len(house.rooms)}" in ln and f"instances {len(house.instances)}" in ln
        assert f"triangles {house.triangle_count:,}" in ln


def test_unwritable_output_is_a_clear_error(tmp_path):
    (tmp_path / "toy_0_000").write_text("a file where a house folder should go")
    with pytest.raises(SceneforgeError, match="cannot write .*toy_0_000"):
        write_toy_houses(tmp_path, 1, 0)


def test_a_house_failing_mid_write_leaves_no_partial_folder(tmp_path, monkeypatch):
    from sceneforge.houses.formats import native

    real = native.write_house

    def dies_after_the_first(house, out_dir):
        if house.id != "toy_0_000":
            Path(out_dir).mkdir(parents=True)
            (Path(out_dir) / "house.json").write_text("{")  # half written
            raise OSError(28, "No space left on device")
        return real(house, out_dir)

    monkeypatch.setattr(native, "write_house", dies_after_the_first)
    with pytest.raises(SceneforgeError, match="cannot write .*toy_0_001: No space left on device"):
        write_toy_houses(tmp_path, 3, 0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["toy_0_000"]
    assert load_house(tmp_path / "toy_0_000").id == "toy_0_000"


def test_a_house_folder_is_kept_when_it_holds_the_same_bytes_and_refused_otherwise(tmp_path):
    write_toy_houses(tmp_path, 1, 0)
    written = {p: p.read_bytes() for p in (tmp_path / "toy_0_000").rglob("*") if p.is_file()}
    write_toy_houses(tmp_path, 1, 0)  # the same seed and options: the same bytes, kept
    assert {p: p.read_bytes() for p in (tmp_path / "toy_0_000").rglob("*") if p.is_file()} == written
    (tmp_path / "toy_0_000" / "notes.txt").write_text("a user's file: nothing here made it")
    with pytest.raises(SceneforgeError, match="toy_0_000: holds another house than toy_0_000 of seed 0"):
        write_toy_houses(tmp_path, 1, 0)
    assert (tmp_path / "toy_0_000" / "notes.txt").read_text() == "a user's file: nothing here made it"
    assert load_house(tmp_path / "toy_0_000").id == "toy_0_000"


def test_cli_rejects_a_bad_count(tmp_path):
    res = CliRunner().invoke(toy_houses, [str(tmp_path), "--count", "0"])
    assert res.exit_code == 2 and "--count" in res.output
    assert not any(tmp_path.iterdir())

