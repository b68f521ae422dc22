"""Lean stores: a default render keeps no ground-truth meshes, ``evaluate`` makes them from the
houses the store records (refusing a house whose files changed) and caches them beside the
store; ``--gt-mesh all`` still writes them, and stores that keep them keep working."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr
from click.testing import CliRunner
from sceneforge.cli.main import LazyGroup

from sceneforge.config import DatasetConfig, load_config
from sceneforge.errors import SceneforgeError
from sceneforge.houses import bundled_toy_dir
from sceneforge.pipeline.gt_mesh import GroundTruthMeshes, cache_folder, ground_truth_meshes
from sceneforge.store import MESH_KINDS, array_digests, check_store, open_store
from sceneforge.store.reader import arrays_of

CLI = LazyGroup(name="sceneforge", lazy={"render": "render:render", "evaluate": "evaluate:evaluate",
                                         "overhead-camera": "overhead_camera:overhead_camera"})
#: the bundled toy houses, small and fast: one view each, no RGB
RENDER = ["--views-per-house", "1", "--resolution", "64x48", "--overhead-resolution", "32", "--no-rgb"]


def run(*args):
    return CliRunner().invoke(CLI, list(map(str, args)))


@pytest.fixture(scope="module")
def houses(tmp_path_factory):
    """A copy of the bundled toy houses (so that a test may change one)."""
    folder = tmp_path_factory.mktemp("houses")
    for house in sorted(bundled_toy_dir().iterdir()):
        if house.is_dir():
            shutil.copytree(house, folder / house.name)
    return folder


@pytest.fixture(scope="module")
def stores(houses, tmp_path_factory):
    """The same houses rendered lean (the default) and with ``--gt-mesh all``."""
    out = tmp_path_factory.mktemp("stores")
    for name, extra in (("lean", []), ("full", ["--gt-mesh", "all"])):
        res = run("render", houses, out / f"{name}.zarr", *RENDER, *extra)
        assert res.exit_code == 0, res.output
    return out / "lean.zarr", out / "full.zarr"


def test_a_default_store_keeps_no_meshes_and_validates(stores):
    lean, full = stores
    check = check_store(str(lean))
    assert check.valid, check.problems
    assert not open_store(str(lean)).has_mesh
    assert not any(name.startswith("mesh") for name, _ in arrays_of(zarr.open_group(str(lean), mode="r")))
    assert open_store(str(lean)).config.store.gt_mesh == "none"
    # both record the rules their meshes are made by
    assert open_store(str(lean)).attrs["ground_truth_mesh"] == open_store(str(full)).attrs["ground_truth_mesh"]
    with pytest.raises(SceneforgeError, match="keeps no ground-truth meshes"):
        open_store(str(lean)).mesh(0)


def test_gt_mesh_all_still_writes_them_and_the_other_arrays_are_the_same(stores):
    lean, full = stores
    assert check_store(str(full)).valid
    store = open_store(str(full))
    assert store.has_mesh and store.config.store.gt_mesh == "all"
    assert all(len(store.mesh(i)["envelope"][1]) > 0 for i in range(len(store)))
    with_meshes = array_digests(str(full))
    assert {k: v for k, v in with_meshes.items() if not k.startswith("mesh/")} == array_digests(str(lean))


def test_meshes_made_from_the_houses_equal_the_stored_ones_bit_for_bit(stores, tmp_path):
    lean, full = stores
    stored = open_store(str(full))
    made = GroundTruthMeshes(open_store(str(lean)), tmp_path / "cache")
    for i in range(len(stored)):
        for kind in MESH_KINDS:
            for got, want in zip(made.mesh(i)[kind], stored.mesh(i)[kind]):
                assert got.dtype == want.dtype
                np.testing.assert_array_equal(got, want)
    assert len(list((tmp_path / "cache").glob("view_*.npz"))) == len(stored)


def test_coverage_from_made_meshes_equals_coverage_from_stored_ones(stores, tmp_path):
    lean, full = stores
    tables = []
    for store in (full, lean):
        js = tmp_path / f"{store.stem}.json"
        res = run("evaluate", "coverage", store, "--density", 1000, "--plot", tmp_path / "cov.png", "--json", js)
        assert res.exit_code == 0, res.output
        tables.append(json.loads(js.read_text()))
    assert tables[0] == tables[1]
    assert cache_folder(str(lean)).is_dir() and not cache_folder(str(full)).exists()


def test_cached_meshes_are_read_back_and_a_changed_key_makes_them_again(stores, tmp_path, monkeypatch):
    import sceneforge.frustum

    lean, _ = stores
    store = open_store(str(lean))
    first = GroundTruthMeshes(store, tmp_path).mesh(1)

    def no_mesh(*args, **kwargs):
        raise AssertionError("made again")

    monkeypatch.setattr(sceneforge.frustum, "view_mesh", no_mesh)
    again = GroundTruthMeshes(store, tmp_path).mesh(1)  # from the cache: nothing is made
    for kind in MESH_KINDS:
        for a, b in zip(first[kind], again[kind]):
            np.testing.assert_array_equal(a, b)
    with np.load(tmp_path / "view_000001.npz") as f:
        arrays = dict(f)
    arrays["key"] = np.array("another house")
    np.savez(tmp_path / "view_000001.npz", **arrays)
    with pytest.raises(AssertionError, match="made again"):
        GroundTruthMeshes(store, tmp_path).mesh(1)


def test_a_changed_or_missing_house_is_one_line_naming_it(houses, tmp_path):
    folder = tmp_path / "houses"
    shutil.copytree(houses / "toy_0_001", folder / "toy_0_001")
    out = tmp_path / "one.zarr"
    assert run("render", folder, out, *RENDER).exit_code == 0
    house_json = folder / "toy_0_001" / "house.json"
    house_json.write_text(house_json.read_text() + " ")
    res = run("evaluate", "coverage", out, "--plot", tmp_path / "cov.png")
    assert res.exit_code == 1 and "Traceback" not in res.output
    assert res.output.strip().splitlines() == [
        f"error: house toy_0_001: {house_json} changed since the store was rendered, so its ground-truth meshes "
        "cannot be made (render the store again, with --update, or with --gt-mesh all)"]
    assert not cache_folder(str(out)).exists()
    shutil.rmtree(folder / "toy_0_001")
    with pytest.raises(SceneforgeError, match=f"house toy_0_001: {house_json.parent}/house.bin is missing since"):
        ground_truth_meshes(str(out)).mesh(0)


def test_a_store_written_before_lean_stores_keeps_working(stores, tmp_path):
    """Its config records ``view.with_mesh`` (now ``store.gt_mesh``), its meshes are in it."""
    _, full = stores
    old = tmp_path / "old.zarr"
    shutil.copytree(full, old)
    group = zarr.open_group(str(old), mode="r+")
    config = group.attrs["config"]
    del config["store"]["gt_mesh"]
    config["view"]["with_mesh"] = True
    group.attrs["config"] = config
    assert check_store(str(old)).valid
    store = open_store(str(old))
    assert store.config.store.gt_mesh == "all" and store.config.view.with_mesh
    np.testing.assert_array_equal(ground_truth_meshes(str(old)).mesh(0)["envelope"][1],
                                  open_store(str(full)).mesh(0)["envelope"][1])
    assert not cache_folder(str(old)).exists()  # its own meshes: nothing made


def test_the_config_moved_view_with_mesh_to_store_gt_mesh():
    assert load_config().store.gt_mesh == "none" and not load_config().view.with_mesh
    assert load_config(None, {"store": {"gt_mesh": "all"}}).view.with_mesh  # computed when kept
    recorded = load_config().to_dict()
    recorded["view"]["with_mesh"] = False
    del recorded["store"]["gt_mesh"]
    assert DatasetConfig.from_dict(recorded, recorded=True).store.gt_mesh == "none"
    with pytest.raises(SceneforgeError, match="'view.with_mesh' was removed: .*store.gt_mesh"):
        DatasetConfig.from_dict({"view": {"with_mesh": True}})
    assert "with_mesh" not in load_config().to_dict()["view"]


def test_houses_given_by_a_relative_path_are_found_from_another_folder(houses, tmp_path, monkeypatch):
    shutil.copytree(houses / "toy_0_002", tmp_path / "mine" / "toy_0_002")
    monkeypatch.chdir(tmp_path)
    assert run("render", "mine", "one.zarr", *RENDER, "--gt-mesh", "all").exit_code == 0
    store = open_store("one.zarr")
    assert store.attrs["houses"][0]["path"] == str(tmp_path / "mine" / "toy_0_002")  # recorded absolute
    assert store.attrs["houses_source"] == str((tmp_path / "mine").resolve())
    stored = store.mesh(0)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    explained = run("overhead-camera", "--store", "../one.zarr", "--view", 0)  # its house found the same way
    assert explained.exit_code == 0, explained.output
    lean = open_store("../one.zarr")
    lean.has_mesh = False  # make them, as for a store that keeps none
    made = GroundTruthMeshes(lean).mesh(0)
    for kind in MESH_KINDS:
        np.testing.assert_array_equal(made[kind][1], stored[kind][1])


def test_a_store_of_predictions_has_no_meshes_to_make(stores, tmp_path):
    lean, _ = stores
    copy = tmp_path / "pred.zarr"
    shutil.copytree(lean, copy)
    group = zarr.open_group(str(copy), mode="r+")
    group.attrs["prediction"] = {"views": [0]}
    with pytest.raises(SceneforgeError, match="a store of predictions has no ground-truth meshes"):
        ground_truth_meshes(str(copy)).mesh(0)


def test_a_relative_name_map_is_recorded_absolute_and_read_from_another_folder(tmp_path, monkeypatch):
    from sceneforge.houses import load
    from sceneforge.testing.generic import write_house

    monkeypatch.chdir(tmp_path)
    write_house(load(bundled_toy_dir() / "toy_0_002"), "scenes/living.glb")
    Path("scenes/living_map.json").write_text(json.dumps({"patterns": [["^never-a-name$", "chair"]]}))
    res = run("render", "scenes/living.glb", "one.zarr", *RENDER, "--name-map", "scenes/living_map.json")
    assert res.exit_code == 0, res.output
    recorded = open_store("one.zarr").config.houses.name_map
    assert recorded == str(tmp_path.resolve() / "scenes" / "living_map.json")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    lean = open_store("../one.zarr")
    made = GroundTruthMeshes(lean).mesh(0)  # the house loaded again with the recorded map
    assert len(made["envelope"][1])


def test_a_store_is_run_again_from_any_folder_and_an_older_relative_one_from_its_own(houses, tmp_path,
                                                                                      monkeypatch):
    shutil.copytree(houses / "toy_0_002", tmp_path / "mine" / "toy_0_002")
    monkeypatch.chdir(tmp_path)
    assert run("render", "mine", "one.zarr", *RENDER).exit_code == 0
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    again = run("render", "../mine", "../one.zarr", *RENDER, "--update")
    assert again.exit_code == 0 and "already complete" in again.output, again.output
    # a store written before paths were recorded absolute: as given, relative to where it ran
    group = zarr.open_group(str(tmp_path / "one.zarr"), mode="r+")
    group.attrs["houses_source"] = "mine"
    monkeypatch.chdir(tmp_path)
    again = run("render", "mine", "one.zarr", *RENDER)
    assert again.exit_code == 0 and "already complete" in again.output, again.output
