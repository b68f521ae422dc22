"""No command loses data it did not create, and a damaged store says so in one line and is
repaired by render to the bytes of a clean render (issue 37)."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr
from click.testing import CliRunner
from sceneforge.cli.main import cli

from sceneforge.config import load_config
from sceneforge.errors import EXIT_ERROR, DamagedStoreError, SceneforgeError
from sceneforge.houses import BUNDLED_TOY
from sceneforge.pipeline import render_dataset
from sceneforge.store import array_digests, open_store, validate_store
from sceneforge.store.guard import check_apart, enclosing_store, store_kind


@pytest.fixture
def clean(small_store) -> Path:
    """A clean store of every kind of array (:data:`conftest.SMALL`), never written to."""
    return small_store


@pytest.fixture
def store(clean, tmp_path) -> Path:
    out = tmp_path / "data" / "small.zarr"
    shutil.copytree(clean, out)
    return out


def tree_digest(path: Path) -> dict[str, str]:
    """SHA-256 of every file under ``path`` (or of the file), by relative path."""
    path = Path(path)
    if path.is_file():
        return {".": hashlib.sha256(path.read_bytes()).hexdigest()}
    return {str(p.relative_to(path)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(path.rglob("*")) if p.is_file()}


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def one_red_line(res, *words):
    """The command failed with exit 1 and one line naming ``words``, no traceback."""
    assert res.exit_code == EXIT_ERROR, res.output
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
    for w in words:
        assert w in lines[0], lines[0]


# ------------------------------------------------------------------------- the guard

def test_store_kind_tells_datasets_predictions_and_other_zarr_apart(store, tmp_path):
    assert store_kind(store) == "dataset"
    zarr.open_group(str(store), mode="r+").attrs["prediction"] = {"views": []}
    assert store_kind(store) == "prediction"
    zarr.open_group(str(tmp_path / "plain.zarr"), mode="w")
    assert store_kind(tmp_path / "plain.zarr") == "zarr"
    assert store_kind(tmp_path) is None
    assert store_kind(tmp_path / "nothing") is None


def test_outputs_apart_from_inputs_and_outside_stores(store, tmp_path):
    check_apart(tmp_path / "out", "store", [("houses", tmp_path / "houses"), ("run", None)])
    for out, relation in ((tmp_path / "houses", "is"), (tmp_path, "holds"), (tmp_path / "houses" / "x", "is inside")):
        with pytest.raises(SceneforgeError, match=f"the store {relation} the houses"):
            check_apart(out, "store", [("houses", tmp_path / "houses")])
    assert enclosing_store(store / "depth" / "x.png") == store
    assert enclosing_store(store) is None


# ------------------------------------------------------------- each command, each case

def test_predict_refuses_its_input_store_as_out_even_with_overwrite(store, tmp_path):
    before = tree_digest(store)
    (tmp_path / "run").mkdir()
    res = run("predict", tmp_path / "run", store, store, "--overwrite")
    one_red_line(res, "is the input store", "another path")
    assert tree_digest(store) == before


def test_predict_never_replaces_a_dataset_store(store, clean, tmp_path):
    before = tree_digest(store)
    (tmp_path / "run").mkdir()
    res = run("predict", tmp_path / "run", clean, store, "--overwrite")
    one_red_line(res, "holds a dataset store (sceneforge render wrote it)", "choose another path")
    assert tree_digest(store) == before


def test_render_never_replaces_a_prediction_store_nor_foreign_data(store, tmp_path):
    zarr.open_group(str(store), mode="r+").attrs["prediction"] = {"views": []}
    before = tree_digest(store)
    for extra in ((), ("--overwrite",)):
        one_red_line(run("render", BUNDLED_TOY, store, *extra), "holds a prediction store", "another path")
        assert tree_digest(store) == before
    plain = tmp_path / "plain.zarr"
    zarr.open_group(str(plain), mode="w").attrs["mine"] = 1
    files = tmp_path / "notes"
    files.mkdir()
    (files / "thesis.tex").write_text("months of work")
    for target, words in ((plain, "a zarr store sceneforge did not write"), (files, "not a sceneforge store")):
        before = tree_digest(target)
        one_red_line(run("render", BUNDLED_TOY, target, "--overwrite"), words)
        assert tree_digest(target) == before


def test_render_refuses_its_houses_folder_and_a_place_inside_a_store(store, tmp_path):
    houses = tmp_path / "houses"
    shutil.copytree(_bundled(), houses)
    before = tree_digest(houses)
    for out in (houses, houses / "out.zarr"):
        one_red_line(run("render", houses, out, "--overwrite"), "an input of this command")
    assert tree_digest(houses) == before
    before = tree_digest(store)
    one_red_line(run("render", BUNDLED_TOY, store / "inner.zarr"), "inside the store")
    assert tree_digest(store) == before


def _bundled() -> Path:
    from sceneforge.houses import bundled_toy_dir

    return bundled_toy_dir()


def test_show_evaluate_and_toy_houses_write_nothing_inside_a_store(store):
    before = tree_digest(store)
    one_red_line(run("show", store, "--view", 0, "-o", store / "panel.png"), "inside the store")
    one_red_line(run("evaluate", "coverage", store, "--plot", store / "c.png"), "inside the store")
    one_red_line(run("toy-houses", store / "houses"), "inside the store")
    assert tree_digest(store) == before


def test_toy_houses_keep_a_folder_they_did_not_write(tmp_path):
    assert run("toy-houses", tmp_path, "--count", 1).exit_code == 0
    again = tree_digest(tmp_path)
    assert run("toy-houses", tmp_path, "--count", 1).exit_code == 0  # the same bytes: kept as they are
    assert tree_digest(tmp_path) == again
    mine = tmp_path / "toy_0_000" / "house.json"
    mine.write_text(mine.read_text().replace('"toy_0_000"', '"toy_0_000" ', 1))  # a user's edit
    before = tree_digest(tmp_path)
    one_red_line(run("toy-houses", tmp_path, "--count", 1), "holds another house than toy_0_000")
    assert tree_digest(tmp_path) == before


def test_reconstruct_refuses_its_photo_folder_and_files_it_did_not_write(tmp_path):
    from PIL import Image

    photos, out, runs = tmp_path / "photos", tmp_path / "out", tmp_path / "run"
    photos.mkdir()
    runs.mkdir()
    Image.fromarray(np.zeros((24, 32, 3), np.uint8)).save(photos / "kitchen.png")
    before = tree_digest(photos)
    one_red_line(run("reconstruct", runs, photos, "--out", photos), "holds the image")
    assert tree_digest(photos) == before
    out.mkdir()
    (out / "kitchen.png").write_bytes(b"someone's picture")
    one_red_line(run("reconstruct", runs, photos, "--out", out), "already holds kitchen.png", "--overwrite")
    assert (out / "kitchen.png").read_bytes() == b"someone's picture"


# ------------------------------------------------------------------ damaged stores

def _damageable(clean: Path) -> dict[str, str]:
    """Every array of the store → the key of its first file (that the manifest records)."""
    manifest = json.loads((clean / "manifest.json").read_text())["files"]
    first = {}
    for key, digest in manifest.items():
        array = key.rsplit("/c/", 1)[0]
        if digest is not None and array not in first:
            first[array] = key
    return first


DAMAGE = {
    "truncated": lambda p: p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2]),
    "zeroed": lambda p: p.write_bytes(bytes(len(p.read_bytes()))),
    "deleted": lambda p: p.unlink(),
}


def test_every_array_of_the_store_has_a_file_to_damage(clean):
    arrays = set(_damageable(clean))
    assert {"depth", "category", "instance", "valid", "K", "normal", "overhead_height",
            "mesh/objects/vertices", "mesh/envelope/faces", "mesh/objects/face_offsets"} <= arrays


@pytest.mark.parametrize("how", DAMAGE)
def test_reading_a_damaged_file_of_any_array_is_one_line_naming_it(clean, tmp_path, how):
    for array, key in _damageable(clean).items():
        store = tmp_path / how / array.replace("/", "_") / "s.zarr"
        shutil.copytree(clean, store)
        DAMAGE[how](store / key)
        s = open_store(str(store))
        with pytest.raises(DamagedStoreError) as e:
            if array.startswith("mesh/"):  # ragged: read whole (store.mesh(i) leaves out the instances)
                s.array(array)[:]
            else:
                for i in range(len(s)):
                    s.view(i)
        line = str(e.value)
        assert "\n" not in line and key in line and "sceneforge validate" in line, line
        assert ("is missing" if how == "deleted" else "cannot be decoded") in line, line


@pytest.mark.parametrize("how", DAMAGE)
def test_reading_whole_views_of_a_damaged_file_is_the_same_one_line(clean, tmp_path, how):
    """Training reads views through ``array.views`` (the shard files read without zarr):
    a damaged file fails as the same one line."""
    for array, key in _damageable(clean).items():
        if array.startswith("mesh/"):
            continue
        store = tmp_path / how / array.replace("/", "_") / "s.zarr"
        shutil.copytree(clean, store)
        DAMAGE[how](store / key)
        s = open_store(str(store))
        with pytest.raises(DamagedStoreError) as e:
            s.array(array).views(range(len(s)))
        line = str(e.value)
        assert "\n" not in line and key in line and "sceneforge validate" in line, line
        assert ("is missing" if how == "deleted" else "cannot be decoded") in line, line


def test_a_damaged_store_is_one_red_line_in_the_cli(store):
    DAMAGE["truncated"](store / "depth" / "c" / "1" / "0" / "0" / "0")
    one_red_line(run("show", store, "--view", 5, "-o", store.parent / "p.png"),
                 "depth of views 4-5", "depth/c/1/0/0/0", "sceneforge validate")
    res = run("validate", store)
    assert f"sceneforge render {BUNDLED_TOY} {store} --repair" in res.output


@pytest.mark.parametrize("how", DAMAGE)
def test_render_repairs_every_array_to_the_bytes_of_a_clean_render(clean, tmp_path, how):
    want, files = array_digests(str(clean)), tree_digest(clean)
    arrays = _damageable(clean)
    # one render per damage mode: a file of every array at once, the per-view ones in both shards
    store = tmp_path / "s.zarr"
    shutil.copytree(clean, store)
    for key in arrays.values():
        DAMAGE[how](store / key)
    (store / "depth" / "c" / "9").mkdir()
    (store / "depth" / "c" / "9" / "stray").write_bytes(b"x")  # a file no run wrote
    res = run("render", BUNDLED_TOY, store, "--repair")
    assert res.exit_code == 0, res.output
    assert "repaired:" in res.output and "removed: 1 file no run wrote" in res.output
    assert validate_store(str(store)) == []
    assert array_digests(str(store)) == want
    ours = tree_digest(store)
    assert {k: v for k, v in ours.items() if k != "zarr.json"} == {k: v for k, v in files.items() if k != "zarr.json"}


def test_render_repairs_exactly_the_damaged_shard(clean, tmp_path):
    store = tmp_path / "s.zarr"
    shutil.copytree(clean, store)
    DAMAGE["zeroed"](store / "overhead_height" / "c" / "1" / "0" / "0")
    res = run("render", BUNDLED_TOY, store, "--repair")
    assert res.exit_code == 0, res.output
    assert "(1 written now)" in res.output
    assert array_digests(str(store)) == array_digests(str(clean))


def test_training_on_a_damaged_store_ends_in_one_line_with_its_loader_workers(tmp_path):
    """The damage surfaces in a DataLoader worker; the process must end too (its workers
    ignore the SIGTERM multiprocessing ends them with at exit: the trainer ends them)."""
    import subprocess
    import sys

    store = tmp_path / "s.zarr"
    render_dataset(BUNDLED_TOY, str(store), load_config(None, {"width": 32, "height": 24, "views_per_house": 2,
                                                               "view": {"overhead": {"resolution": 16}}}))
    DAMAGE["zeroed"](store / "depth" / "c" / "1" / "0" / "0" / "0")
    args = ["train", store, "--stage", "depth", "--run", tmp_path / "run", "--max-steps", 2, "--batch-size", 6,
            "--width", 0.125, "--val-fraction", 0, "--test-fraction", 0, "--device", "cpu", "--no-tensorboard",
            "--workers", 1]
    done = subprocess.run([sys.executable, "-c", "from sceneforge.cli.main import main; main()", *map(str, args)],
                          capture_output=True, text=True, timeout=300)
    errors = [line for line in done.stderr.splitlines() if line.startswith("error: ")]
    assert done.returncode == EXIT_ERROR and "Traceback" not in done.stderr, done.stderr
    assert len(errors) == 1 and "depth of views 4-5" in errors[0] and "sceneforge validate" in errors[0]


def test_evaluate_never_writes_over_its_inputs(store, tmp_path):
    split = tmp_path / "small.split.json"
    split.write_text('{"a split": "of someone"}')
    before = tree_digest(split)
    one_red_line(run("evaluate", "predictions", store, store, "--split-file", split, "--json", split),
                 "the JSON file is the split file")
    one_red_line(run("evaluate", "predictions", store, store, "--plot", store / "pr.png"), "inside the store")
    assert tree_digest(split) == before
