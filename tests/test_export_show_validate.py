"""``export``, ``show`` and ``validate`` on a tiny store and a prediction store made from it:
where export may write, the class and instance layers of its EXR files, a view predict
skipped, and the predicted views in validate's summary."""

from __future__ import annotations

import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner
from sceneforge.cli.main import cli

from sceneforge.conventions import CLASS_LAYERS, FRONT_LAYERS, LAYER_NAMES
from sceneforge.errors import SceneforgeError
from sceneforge.evaluate.stores import check_predicted
from sceneforge.store import open_store

#: the views the prediction store predicted, of the tiny store's 3
PREDICTED = [0, 2]


def run(*args):
    return CliRunner().invoke(cli, list(map(str, args)))


def snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every file (its bytes) and folder (None) under ``folder``, by relative path."""
    return {str(p.relative_to(folder)): None if p.is_dir() else p.read_bytes() for p in sorted(folder.rglob("*"))}


def make_prediction_store(store: Path, out: Path) -> Path:
    """A copy of ``store`` that says it is predict's, of views :data:`PREDICTED` of the test split."""
    import zarr

    shutil.copytree(store, out)
    zarr.open_group(str(out), mode="r+").attrs["prediction"] = {"views": PREDICTED, "split": "test"}
    return out


@pytest.fixture
def work(tiny_toy_store, tmp_path) -> Path:
    """A folder holding a copy of the tiny store (toy.zarr, 3 views), a prediction store
    made from it (pred.zarr) and a zarr store sceneforge did not write (foreign.zarr)."""
    import zarr

    shutil.copytree(tiny_toy_store, tmp_path / "toy.zarr")
    make_prediction_store(tiny_toy_store, tmp_path / "pred.zarr")
    zarr.open_group(str(tmp_path / "foreign.zarr"), mode="w")
    return tmp_path


def one_error_line(res) -> str:
    lines = res.output.strip().splitlines()
    assert res.exit_code == 1 and len(lines) == 1 and lines[0].startswith("error: "), res.output
    return lines[0]


# ------------------------------------------------------------------------------- export


@pytest.mark.parametrize("out, says", [
    ("toy.zarr", "the export folder is the store"),
    ("toy.zarr/exr", "the export folder is inside the store"),
    (".", "the export folder holds the store"),
    ("pred.zarr/exr", "would be written inside the store"),
    ("pred.zarr", "the export folder is a prediction store (sceneforge predict wrote it)"),
    ("foreign.zarr", "the export folder is a zarr store sceneforge did not write"),
])
def test_export_refuses_the_store_a_folder_in_or_around_it_and_any_zarr_store(work, out, says):
    before = snapshot(work)
    line = one_error_line(run("export", work / "toy.zarr", work / out))
    assert says in line
    assert snapshot(work) == before


def test_export_refuses_a_folder_of_other_files_with_or_without_overwrite(work):
    out = work / "exr"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    (out / "view_000000.exr").write_bytes(b"an earlier export")
    (out / "renders").mkdir()
    before = snapshot(work)
    for flags in ([], ["--overwrite"]):
        line = one_error_line(run("export", work / "toy.zarr", out, *flags))
        assert "holds files export did not write: notes.txt, renders/;" in line
        assert snapshot(work) == before


def test_export_over_an_earlier_export_needs_overwrite(work):
    out = work / "exr"
    assert run("export", work / "toy.zarr", out).exit_code == 0
    before = snapshot(work)
    line = one_error_line(run("export", work / "toy.zarr", out))
    assert line.endswith("holds an earlier export (3 files); pass --overwrite to replace it")
    assert snapshot(work) == before


def test_overwrite_replaces_every_file_of_an_earlier_export(work):
    # an earlier export of a 6-view store, one of its writes killed: all of it is export's
    out = work / "exr"
    out.mkdir()
    for i in range(6):
        (out / f"view_{i:06d}.exr").write_bytes(b"an earlier export")
    (out / ".view_000004.1a2b3c4d.partial.exr").write_bytes(b"half a file")
    res = run("export", work / "toy.zarr", out, "--overwrite")
    assert res.exit_code == 0 and res.output.strip() == f"3 views written to {out}", res.output
    # the views beyond this store's 3 are gone: the folder is this export alone
    assert sorted(p.name for p in out.iterdir()) == [f"view_{i:06d}.exr" for i in range(3)]
    assert all(p.read_bytes() != b"an earlier export" for p in out.iterdir())


def test_exr_files_carry_the_class_and_instance_layers(work):
    import OpenEXR

    assert run("export", work / "toy.zarr", work / "exr").exit_code == 0
    store = open_store(str(work / "toy.zarr"))
    instances = []
    for i in range(len(store)):
        v = store.view(i)
        frontal, overhead = OpenEXR.File(str(work / "exr" / f"view_{i:06d}.exr")).parts
        for k, layer in enumerate(CLASS_LAYERS):
            pixels = frontal.channels[f"category.{LAYER_NAMES[layer]}"].pixels
            assert pixels.dtype == np.uint32
            np.testing.assert_array_equal(pixels, v["category"][k])
        for k, layer in enumerate(FRONT_LAYERS):
            pixels = frontal.channels[f"instance.{LAYER_NAMES[layer]}"].pixels
            assert pixels.dtype == np.uint32
            np.testing.assert_array_equal(pixels.view(np.int32), v["instance"][k])
            instances.append(v["instance"][k])
        assert overhead.channels["category"].pixels.dtype == np.uint32
        np.testing.assert_array_equal(overhead.channels["category"].pixels, v["overhead_category"])
    # both kinds of instance pixel were compared: surfaces and none (-1)
    instances = np.concatenate([a.ravel() for a in instances])
    assert (instances == -1).any() and (instances >= 0).any()


# --------------------------------------------------------------------------------- show


@pytest.mark.parametrize("truth", [True, False])
def test_show_refuses_a_view_predict_skipped_naming_those_it_made(work, truth):
    png = work / "panel.png"
    with_truth = ["--truth", work / "toy.zarr"] if truth else []
    before = snapshot(work)
    line = one_error_line(run("show", work / "pred.zarr", "--view", 1, *with_truth, "-o", png))
    assert line == "error: view 1 was not predicted: the store predicts views 0, 2 (2 views of the test split)"
    assert snapshot(work) == before
    res = run("show", work / "pred.zarr", "--view", 2, *with_truth, "-o", png)
    assert res.exit_code == 0 and png.stat().st_size > 1000, res.output


def test_the_views_a_refusal_names_are_runs_around_the_view_asked_for():
    store = SimpleNamespace(attrs={"prediction": {"views": [*range(0, 100, 2), 120, 121, 122], "split": "all"}})
    with pytest.raises(SceneforgeError) as e:
        check_predicted(store, 51)
    assert str(e.value) == ("view 51 was not predicted: the store predicts views ..., 44, 46, 48, 50, 52, 54, 56, "
                            "58, ... (53 views)")
    with pytest.raises(SceneforgeError, match=r"views \.\.\., 86, 88, 90, 92, 94, 96, 98, 120-122 \(53 views\)$"):
        check_predicted(store, 110)
    check_predicted(store, 121)
    check_predicted(SimpleNamespace(attrs={}), 1)  # a store of ground truth: every view


# ----------------------------------------------------------------------------- validate


def test_validate_counts_the_views_a_prediction_store_predicted(work):
    res = run("validate", work / "pred.zarr", "--quiet")
    assert res.exit_code == 0
    assert res.output.strip() == f"{work / 'pred.zarr'}: valid (prediction store, 2 predicted views of 3, split test)"
    res = run("validate", work / "toy.zarr")
    assert res.exit_code == 0 and res.output.strip() == f"{work / 'toy.zarr'}: valid (dataset store, 3 views)"


def test_validate_checks_the_predicted_views_against_the_store(work):
    import zarr

    zarr.open_group(str(work / "pred.zarr"), mode="r+").attrs["prediction"] = {"views": [0, 5], "split": "test"}
    res = run("validate", work / "pred.zarr", "--quiet")
    assert res.exit_code == 3
    assert res.output.strip().splitlines()[0] == (f"{work / 'pred.zarr'}: invalid, 1 problem (prediction store, "
                                                  "2 predicted views of 3, split test)")
    res = run("validate", work / "pred.zarr")
    assert "  prediction: views is not a list of distinct view indices in 0..2" in res.output.splitlines()
