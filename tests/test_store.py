"""The store: layout from the schema, read-back equals compute_view, validation, show, export."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from sceneforge.cli.main import cli

from sceneforge import conventions, schemas
from sceneforge.cameras import Camera
from sceneforge.config import DatasetConfig, config_schema, load_config
from sceneforge.errors import EXIT_FAILURES, SceneforgeError
from sceneforge.houses import BUNDLED_TOY, bundled_toy_dir, discover, load
from sceneforge.pipeline import render_dataset
from sceneforge.preview import layer_points
from sceneforge.store import (
    MANIFEST,
    array_digests,
    check_store,
    conventions_attrs,
    describe,
    layout,
    open_store,
    validate_store,
)
from sceneforge.view import compute_view

from .conftest import SMALL


@pytest.fixture(autouse=True)
def render_commands(monkeypatch):
    for name in ("validate", "show", "export"):
        monkeypatch.setitem(cli.lazy, name, f"render:{name}")


@pytest.fixture
def store_path(small_store) -> Path:
    return small_store


@pytest.fixture
def store_copy(store_path, tmp_path) -> Path:
    out = tmp_path / "copy.zarr"
    shutil.copytree(store_path, out)
    return out


# ------------------------------------------------------------------------------- config


def test_config_schema_file_is_the_one_generated_from_the_dataclasses():
    path = Path(schemas.__file__).parent / "config.schema.json"
    assert json.loads(path.read_text()) == config_schema(), "run: python -m sceneforge.config (writes " + str(path) + ")"


def test_config_round_trips_and_overrides_win(tmp_path):
    config = load_config(None, SMALL)
    assert DatasetConfig.from_dict(config.to_dict()) == config
    assert (config.sampler.width, config.sampler.height) == (32, 24)  # the image size is set once
    assert "width" not in config.to_dict()["sampler"]
    path = tmp_path / "c.json"
    path.write_text(json.dumps({"seed": 3, "width": 64.0, "view": {"overhead": {"weights": [1, 1, 1]}}}))
    config = load_config(path, {"seed": 5})
    assert (config.seed, config.width, config.height) == (5, 64, 240)
    assert isinstance(config.width, int) and config.view.overhead.weights == (1.0, 1.0, 1.0)
    with pytest.raises(SceneforgeError, match=r"c.json: does not match the config schema: store/views_per_shard"):
        path.write_text(json.dumps({"store": {"views_per_shard": "many"}}))
        load_config(path)
    with pytest.raises(SceneforgeError, match="views_per_shard must be at least 1"):
        load_config(None, {"store": {"views_per_shard": 0}})
    with pytest.raises(SceneforgeError, match="Additional properties are not allowed"):
        load_config(None, {"sampler": {"width": 10}})


# ------------------------------------------------------------------------------- layout


def test_layout_is_read_from_the_schema():
    specs = layout()
    per_view = [s.name for s in specs.values() if s.per_view]
    for name in ("rgb", "depth", "category", "instance", "overhead_depth", "overhead_height", "overhead_category",
                 "K", "cam_to_world", "overhead_cam_to_world", "overhead_params", "overhead_extent", "house_id",
                 "camera_id"):
        assert name in per_view
    assert specs["depth"].dims == ("N", 5, "H", "W") and specs["depth"].dtype == "float32"
    assert specs["category"].shape({"N": 2, "H": 3, "W": 4}) == (2, 3, 3, 4)
    assert np.isnan(specs["depth"].fill_value) and specs["instance"].fill_value == -1


def test_written_store_matches_the_schema(store_path):
    import zarr

    doc = describe(zarr.open_group(str(store_path), mode="r"))
    assert schemas.errors(doc, "store") == []
    assert validate_store(str(store_path)) == []
    depth = doc["arrays"]["depth"]
    assert depth["shape"] == [6, 5, 24, 32] and depth["chunks"] == [1, 5, 24, 32] and depth["shards"][0] == 4
    assert depth["codecs"] == ["sharding_indexed", "bytes", "blosc"]
    attrs = doc["attributes"]
    assert attrs["nyu40"][2] == {"id": 2, "name": "floor", "envelope": True}
    assert attrs["conventions"]["layers"] == ["D1", "D2", "D3", "D4", "D5"]
    assert attrs["conventions"] == conventions.record()
    assert attrs["config"] == load_config(None, SMALL).to_dict() and attrs["seed"] == 0
    assert [h["id"] for h in attrs["houses"]] == ["toy_0_000", "toy_0_001", "toy_0_002"]
    assert attrs["houses"][1]["views"] == [2, 4] and attrs["houses"][1]["cameras"]["accepted"] == 2


def test_store_conventions_are_generated_from_conventions_py(store_path, monkeypatch):
    import zarr

    record = conventions_attrs()
    assert record["category_layers"] == ["D1", "D3", "D5"] and record["instance_layers"] == ["D1", "D3"]
    assert record["object_layers"] == ["D1", "D2", "D3", "D4"] and record["envelope_layer"] == "D5"
    assert record["camera_axes"] == {"convention": "OpenCV", "x": "right", "y": "down", "z": "forward",
                                     "pose": "cam_to_world"}
    assert record["depth"]["no_surface"] == "NaN" and record["pixel_centres"]["offset"] == 0.5
    assert record["tolerances"]["rotation"] == conventions.tol.rotation == 1e-6
    # built from the constants, not restated: change one and the record follows
    monkeypatch.setattr(conventions, "CLASS_LAYERS", (0, 1, 4))
    assert conventions_attrs()["category_layers"] == ["D1", "D2", "D5"]
    # and the schema holds a store's record to the conventions
    doc = describe(zarr.open_group(str(store_path), mode="r"))
    doc["attributes"]["conventions"]["camera_axes"]["y"] = "up"
    assert [e.split(":")[0] for e in schemas.errors(doc, "store")] == ["attributes/conventions/camera_axes"]


def test_reading_a_view_back_equals_what_was_computed(store_path):
    from sceneforge.render import Renderer

    store = open_store(str(store_path))
    config = store.config
    houses = {s.id: load(s) for s in discover(BUNDLED_TOY)}
    with Renderer(32, 24) as renderer:
        for i in (0, 3, 5):
            v = store.view(i)
            house = houses[str(v["house_id"])]
            camera = Camera(v["K"], v["cam_to_world"], 32, 24)
            gt = compute_view(house, camera, config.view)
            np.testing.assert_array_equal(v["depth"], gt.layers.depth)
            np.testing.assert_array_equal(v["category"], gt.layers.category)
            np.testing.assert_array_equal(v["instance"], gt.layers.instance)
            np.testing.assert_array_equal(v["normal"], gt.layers.normal)
            np.testing.assert_array_equal(v["overhead_depth"], gt.overhead.layers.depth)
            np.testing.assert_array_equal(v["overhead_height"], gt.overhead.height)
            np.testing.assert_array_equal(v["overhead_category"], gt.overhead.category)
            np.testing.assert_array_equal(v["overhead_cam_to_world"], gt.overhead_camera.cam_to_world)
            np.testing.assert_array_equal(v["overhead_params"], gt.overhead_camera.params)
            assert v["overhead_extent"] == gt.overhead_camera.half_extent and bool(v["valid"])
            assert str(v["overhead_floor_source"]) == gt.overhead_camera.floor_source == "room floor"
            np.testing.assert_array_equal(v["rgb"], renderer.render(house, camera))
            mesh = store.mesh(i)
            for kind in ("objects", "envelope"):
                expected = getattr(gt.mesh, kind)
                np.testing.assert_array_equal(mesh[kind][0], expected.vertices.astype(np.float32))
                np.testing.assert_array_equal(mesh[kind][1], expected.faces)
            assert v["depth"].dtype == np.float32 and v["rgb"].shape == (24, 32, 3)
    assert np.isnan(store.view(0)["depth"]).any()  # NaN, never 0, marks no surface
    assert store.array("depth")[2:4].shape == (2, 5, 24, 32)


def test_a_house_gets_the_same_cameras_alone_or_among_others(store_path, tmp_path):
    shutil.copytree(bundled_toy_dir() / "toy_0_001", tmp_path / "houses" / "toy_0_001")
    render_dataset(str(tmp_path / "houses"), str(tmp_path / "one.zarr"),
                   load_config(None, {**SMALL, "rgb": {"enabled": False}}))
    alone, among = open_store(str(tmp_path / "one.zarr")), open_store(str(store_path))
    for i in range(2):
        np.testing.assert_array_equal(alone.view(i)["cam_to_world"], among.view(2 + i)["cam_to_world"])



def _views_and_zarr(store, rows) -> None:
    """Every per-view array's ``views(rows)`` against zarr's reads of the same rows."""
    for name in store.names:
        array = store.array(name)
        fast, slow = array.views(rows), np.stack([np.asarray(array[r]) for r in rows])
        assert fast.dtype == slow.dtype and fast.shape == slow.shape, name
        if fast.dtype.kind == "f":
            np.testing.assert_array_equal(fast, slow, err_msg=name)  # NaN where NaN
        else:
            assert (fast == slow).all(), name


def test_whole_views_read_from_the_shard_files_are_zarrs(store_copy):
    """``CheckedArray.views`` reads the shard files itself (not through zarr): the values zarr
    reads in any order, also for a view whose chunk zarr never wrote (all fill values) and a
    shard whose file is gone where the manifest records none."""
    import zarr

    zarr.open_group(str(store_copy), mode="r+")["depth"][1] = np.nan  # its chunk is dropped from shard 0
    manifest = json.loads((store_copy / MANIFEST).read_text())
    (store_copy / "category" / "c" / "1" / "0" / "0" / "0").unlink()
    manifest["files"]["category/c/1/0/0/0"] = None  # a shard of fill values has no file
    (store_copy / MANIFEST).write_text(json.dumps(manifest))
    store = open_store(str(store_copy))
    rows = [5, 0, 1, 5, 3, 2, 4]
    _views_and_zarr(store, rows)
    assert np.isnan(store.array("depth").views([1])).all() and (store.array("category").views([4, 5]) == 0).all()
    assert store.array("depth")._reader is not None  # the shard files were read, not zarr
    assert store.array("house_id")._reader is None  # strings: through zarr
    assert store.array("depth").views([]).shape == (0, 5, 24, 32)
    with pytest.raises(IndexError, match="out of range"):
        store.array("depth").views([6])


@pytest.mark.parametrize("codec, inner", [("zstd", "zstd"), ("blosc-zstd", "blosc")])
def test_every_codec_stores_the_same_arrays_and_validates(codec, inner, store_path, tmp_path):
    """Plain zstd (readers without Blosc) and the old uniform Blosc store what the default
    per-array Blosc stores."""
    import zarr

    out = tmp_path / f"{codec}.zarr"
    render_dataset(BUNDLED_TOY, str(out), load_config(None, {**SMALL, "store": {**SMALL["store"], "codec": codec}}))
    doc = describe(zarr.open_group(str(out), mode="r"))
    assert doc["arrays"]["depth"]["codecs"] == ["sharding_indexed", "bytes", inner]
    assert doc["arrays"]["mesh/envelope/faces"]["codecs"][-1] == inner
    assert validate_store(str(out)) == []
    other, default = array_digests(str(out)), array_digests(str(store_path))
    assert other.keys() == default.keys() and other == default
    _views_and_zarr(open_store(str(out)), [5, 0, 3])


def test_the_default_codec_shuffles_each_array_as_the_layout_says_one_block_per_chunk(store_path):
    import zarr

    group = zarr.open_group(str(store_path), mode="r")
    for name, chunk_bytes in (("depth", 5 * 24 * 32 * 4), ("instance", 2 * 24 * 32 * 4), ("rgb", 24 * 32 * 3),
                              ("mesh/objects/faces", (1 << 16) * 3 * 4)):
        blosc = group[name].metadata.codecs[-1]
        blosc = blosc.codecs[-1] if hasattr(blosc, "codecs") else blosc  # inside the sharding codec
        config = blosc.to_dict()["configuration"]
        assert config["shuffle"] == layout()[name].shuffle and config["blocksize"] == chunk_bytes, name
        assert config["cname"] == "zstd" and config["clevel"] == 3
    assert layout()["depth"].shuffle == "shuffle" and layout()["instance"].shuffle == "noshuffle"


@pytest.mark.parametrize("store, message", [
    ({"compression_level": 10}, "compression_level must be in 1..9 for codec blosc-zstd-per-array, got 10"),
    ({"codec": "blosc-zstd", "compression_level": 10}, "compression_level must be in 1..9 for codec blosc-zstd, got 10"),
    ({"codec": "zstd", "compression_level": 23}, "compression_level must be in 1..22 for codec zstd, got 23"),
])
def test_compression_level_range_follows_the_codec(store, message):
    with pytest.raises(SceneforgeError, match=f"config: {message}"):
        load_config(None, {"store": store})


def test_a_store_recorded_with_retired_lighting_keys_still_opens(store_copy):
    import zarr

    group = zarr.open_group(str(store_copy), mode="r+")
    config = group.attrs["config"]
    config["rgb"]["lighting"] |= {"light": 1.0, "window_light": 0.5}  # as the older renderer saved them
    group.attrs["config"] = config
    assert validate_store(str(store_copy)) == []
    assert open_store(str(store_copy)).config == load_config(None, SMALL)


def test_a_config_file_setting_a_retired_key_says_what_replaced_it():
    with pytest.raises(SceneforgeError, match=r"config: 'rgb.lighting.light' was removed: .*lamp_power"):
        load_config(None, {"rgb": {"lighting": {"light": 2.0}}})

# ----------------------------------------------------------------------------- checking


def test_validate_reports_broken_content(store_copy):
    import zarr

    group = zarr.open_group(str(store_copy), mode="r+")
    depth = group["depth"][1]
    pixel = tuple(np.argwhere(np.isfinite(depth[0]))[0])
    depth[1][pixel] = np.nan  # D2 missing where D1 is set
    group["depth"][1] = depth
    group["category"][2, 0, 0, 0] = 41
    pose = group["cam_to_world"][4]
    pose[:3, :3] *= 2.0
    group["cam_to_world"][4] = pose
    group["mesh/objects/faces"][0, 0] = 10_000
    problems = validate_store(str(store_copy))
    # the rewritten shards no longer hash as written, and each broken rule is one line
    assert problems[0].startswith("4 file(s) damaged (not the bytes written: truncated or changed): ")
    assert "D1 and D2 are not set on the same pixels (M1 != M2): 1 view (1)" in problems
    assert "a class outside 0..40: 1 view (2)" in problems
    assert "cam_to_world is not a rigid transform: 1 view (4)" in problems
    assert "mesh/objects/faces: face indices outside the view's vertices: 1 view (0)" in problems
    res = CliRunner().invoke(cli, ["validate", str(store_copy)])
    assert res.exit_code == EXIT_FAILURES
    lines = res.output.strip().splitlines()
    assert lines[0] == f"{store_copy}: invalid, {len(problems)} problems (dataset store, 6 views)"
    assert [line.strip() for line in lines[1:-1]] == problems
    # damaged files: the last line says how to repair them
    assert lines[-1].strip() == (f"note: repair: `sceneforge render bundled:toy {store_copy} --repair` re-renders "
                                 "exactly the damaged shards (with the config the store records) and removes the "
                                 "files no run wrote")
    quiet = CliRunner().invoke(cli, ["validate", str(store_copy), "--quiet"])
    assert quiet.exit_code == EXIT_FAILURES and quiet.output.strip().splitlines() == lines[:1]


def test_validate_finds_a_truncated_shard_a_missing_chunk_a_zeroed_mesh_and_leftover_staging(store_copy):
    import zarr

    assert validate_store(str(store_copy)) == []
    depth = store_copy / "depth" / "c" / "1" / "0" / "0" / "0"
    depth.write_bytes(depth.read_bytes()[:-100])  # a truncated shard
    (store_copy / "category" / "c" / "0" / "0" / "0" / "0").unlink()  # a shard file gone
    group = zarr.open_group(str(store_copy), mode="r+")
    vertices = group["mesh/envelope/vertices"]
    vertices[:] = np.zeros(vertices.shape, vertices.dtype)  # every envelope vertex read back as 0
    (store_copy / "_staging" / "done").mkdir(parents=True)
    problems = validate_store(str(store_copy))
    assert problems[0].startswith("_staging/: a run's staging folder is left in a complete store")
    # zarr writes no file for values that are all the fill value: the zeroed mesh has none left
    assert "2 file(s) missing (written by the run, gone since): category/c/0/0/0/0, " \
           "mesh/envelope/vertices/c/0/0" in problems
    assert "1 file(s) damaged (not the bytes written: truncated or changed): depth/c/1/0/0/0" in problems
    # views 4 and 5 are in the damaged depth shard: their layers are unknown
    assert "mesh/envelope: empty or degenerate (zero-area faces only) in a view whose D5 is set: 4 views " \
           "(0, 1, 2, 3)" in problems
    assert any(p.startswith("depth: shard 1 (views 4-5) cannot be decoded") for p in problems), problems


def test_validate_of_an_unfinished_store_is_one_line(store_copy):
    import zarr

    zarr.open_group(str(store_copy), mode="r+").attrs["complete"] = False
    res = CliRunner().invoke(cli, ["validate", str(store_copy)])
    assert res.exit_code == EXIT_FAILURES
    assert res.output.strip().splitlines() == [
        f"{store_copy}: incomplete: a run writing it is in progress or was interrupted; run the same command "
        "again to finish it"]


def test_validate_does_not_hold_a_prediction_store_to_ground_truth_rules(store_copy):
    import zarr

    group = zarr.open_group(str(store_copy), mode="r+")
    depth = group["depth"][1]
    depth[1] = depth[0] - 0.5  # D2 before D1: what a net may predict
    group["depth"][1] = depth
    group.attrs["prediction"] = {"stage": "depth"}
    check = check_store(str(store_copy))
    assert check.kind == "prediction"
    assert [p for p in check.problems if "D2 before D1" in p] == []
    assert any("ground-truth rules" in note for note in check.notes)


def test_validate_reports_layout_problems(store_copy):
    import zarr

    group = zarr.open_group(str(store_copy), mode="r+")
    del group["overhead_height"]
    group.create_array("extra", shape=(6,), dtype="int8")
    problems = validate_store(str(store_copy))
    assert any("arrays" in p and "overhead_height" in p for p in problems)
    assert any("extra" in p for p in problems)


def test_validate_cli_accepts_a_good_store(store_path):
    res = CliRunner().invoke(cli, ["validate", str(store_path)])
    assert res.exit_code == 0 and res.output.strip() == f"{store_path}: valid (dataset store, 6 views)"


def test_open_store_errors(store_copy, tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SceneforgeError, match="no zarr store"):
        open_store(str(tmp_path / "empty"))
    store = open_store(str(store_copy))
    with pytest.raises(IndexError, match="view 6 out of range for a store of 6 views"):
        store.view(6)
    assert str(store.view(-1)["house_id"]) == "toy_0_002"
    with pytest.raises(KeyError, match="no array 'rgbd'"):
        store.array("rgbd")
    import zarr

    zarr.open_group(str(store_copy), mode="r+").attrs["complete"] = False
    with pytest.raises(SceneforgeError, match="incomplete.*run the same command again"):
        open_store(str(store_copy))
    assert len(open_store(str(store_copy), allow_incomplete=True)) == 6


# ------------------------------------------------------------------------ show / export


def test_export_writes_readable_exr_with_camera_metadata(store_path, tmp_path):
    import OpenEXR

    res = CliRunner().invoke(cli, ["export", str(store_path), str(tmp_path / "exr"), "--format", "exr"])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in (tmp_path / "exr").iterdir()) == [f"view_{i:06d}.exr" for i in range(6)]
    v = open_store(str(store_path)).view(4)
    f = OpenEXR.File(str(tmp_path / "exr" / "view_000004.exr"))
    frontal, overhead = f.parts
    assert (frontal.name(), overhead.name()) == ("frontal", "overhead")
    for k, name in enumerate(("D1", "D2", "D3", "D4", "D5")):
        np.testing.assert_array_equal(frontal.channels[name].pixels, v["depth"][k])
        np.testing.assert_array_equal(overhead.channels[name].pixels, v["overhead_depth"][k])
    np.testing.assert_array_equal(overhead.channels["height"].pixels, v["overhead_height"])
    # the R, G, B channels read back as one group
    rgb = frontal.channels["RGB"].pixels
    assert rgb.shape == (24, 32, 3) and rgb.dtype == np.float32 and 0 <= rgb.min() <= rgb.max() <= 1
    np.testing.assert_array_equal(frontal.header["K"], v["K"])
    np.testing.assert_array_equal(frontal.header["cam_to_world"], v["cam_to_world"])
    np.testing.assert_array_equal(overhead.header["overhead_cam_to_world"], v["overhead_cam_to_world"])
    assert frontal.header["house_id"] == str(v["house_id"]) and frontal.header["view"] == 4


def test_show_writes_a_panel_and_a_point_cloud_on_the_layers(store_path, tmp_path):
    import trimesh
    from PIL import Image

    png, ply = tmp_path / "panel.png", tmp_path / "view.ply"
    res = CliRunner().invoke(cli, ["show", str(store_path), "--view", "1", "-o", str(png), "--3d", str(ply)])
    assert res.exit_code == 0, res.output
    assert Image.open(png).size == (1600, 960)
    v = open_store(str(store_path)).view(1)
    cloud = trimesh.load(ply)
    assert len(cloud.vertices) == np.isfinite(v["depth"]).sum()
    # every point projects back onto a pixel centre at its layer's depth
    camera = Camera(v["K"], v["cam_to_world"], 32, 24)
    uv, z = camera.project(cloud.vertices)
    np.testing.assert_allclose(uv % 1.0, 0.5, atol=1e-4)  # PLY stores float32
    layer_d1 = np.isfinite(v["depth"][0])
    np.testing.assert_allclose(z[: layer_d1.sum()], v["depth"][0][layer_d1], rtol=1e-5)
    res = CliRunner().invoke(cli, ["show", str(store_path), "--view", "6"])
    assert res.exit_code == 2 and "the store has 6 views" in res.output


def test_layer_points_are_the_back_projected_pixel_centres():
    K = np.array([[10.0, 0.0, 2.0], [0.0, 10.0, 1.5], [0.0, 0.0, 1.0]])
    pose = np.eye(4)
    pose[:3, 3] = (1.0, 2.0, 3.0)
    depth = np.full((2, 3, 4), np.nan, dtype=np.float32)
    depth[0] = 2.0
    depth[1, 2, 3] = 5.0
    points, layer = layer_points(K, pose, depth)
    assert points.shape == (13, 3) and layer.tolist() == [0] * 12 + [1]
    # pixel (row 0, column 0): centre (0.5, 0.5) → x = (0.5 - 2) / 10 · 2, y = (0.5 - 1.5) / 10 · 2
    np.testing.assert_allclose(points[0], [1.0 - 0.3, 2.0 - 0.2, 3.0 + 2.0])
    np.testing.assert_allclose(points[-1], [1.0 + (3.5 - 2.0) / 10 * 5, 2.0 + (2.5 - 1.5) / 10 * 5, 8.0])


_COMPRESS_AFTER_RENDERING = """
import numpy as np
from sceneforge.render.raster import _gl
gl = _gl()
gl.pyrender.OffscreenRenderer(8, 8).delete()  # an EGL context: Mesa's libraries are loaded
import numcodecs.blosc as blosc
data = np.random.default_rng(0).normal(size=200_000).astype(np.float32)
print(len(blosc.compress(data, b"zstd", 3, blosc.SHUFFLE, 0)))
"""


def test_a_process_that_rendered_compresses_to_the_same_bytes():
    """Mesa's EGL driver brings the system's libzstd into the global namespace; numcodecs'
    Blosc loaded after it compressed with that zstd (other bytes, so other shard files for
    the same arrays with 2 workers than with 1). The renderer loads the compressors first."""
    import subprocess
    import sys

    import numcodecs.blosc as blosc

    data = np.random.default_rng(0).normal(size=200_000).astype(np.float32)
    here = len(blosc.compress(data, b"zstd", 3, blosc.SHUFFLE, 0))
    out = subprocess.run([sys.executable, "-c", _COMPRESS_AFTER_RENDERING], capture_output=True, text=True, check=True)
    assert int(out.stdout.split()[-1]) == here
