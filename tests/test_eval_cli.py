"""``sceneforge evaluate`` on a tiny store of the bundled toy houses."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from sceneforge.cli.main import LazyGroup

# the evaluate group under a top-level group like ``sceneforge``'s, which turns expected
# errors into one red line
CLI = LazyGroup(name="sceneforge", lazy={"evaluate": "evaluate:evaluate"})


def run(*args):
    return CliRunner().invoke(CLI, list(map(str, args)))


@pytest.fixture
def store(tiny_toy_store):
    return tiny_toy_store


def test_coverage_prints_the_table_beside_the_paper_and_plots(store, tmp_path):
    png, js = tmp_path / "cov.png", tmp_path / "cov.json"
    res = run("evaluate", "coverage", store, "--density", 1000, "--plot", png, "--json", js)
    assert res.exit_code == 0, res.output
    rows = {line.split()[0] + (" & overhead" if "overhead" in line else ""): line.split()
            for line in res.output.splitlines() if line.startswith("D1")}
    assert list(rows) == ["D1", "D1-2", "D1-3", "D1-4", "D1-5", "D1-5 & overhead"]
    assert [r[-3] for r in rows.values()] == ["0.237", "0.427", "0.450", "0.480", "0.924", "0.932"]
    recall = [float(r[-4]) for r in rows.values()]
    assert (np.diff(recall) >= 0).all() and recall[-1] > 0.8
    assert "mean over 3 views" in res.output
    assert "meshing: edge factor preset paper: a = 7 for every layer" in res.output
    assert png.stat().st_size > 20_000
    values = json.loads(js.read_text())
    assert values["views"] == 3 and values["density"] == 1000 and values["seed"] == 0
    assert values["preset"] == "paper" and set(values["a"].values()) == {7.0}
    assert values["variants"]["D1-5"]["all"]["recall"] == pytest.approx(recall[4], abs=5e-4)


def test_the_store_records_the_rules_of_its_ground_truth_meshes(store):
    from sceneforge.store import open_store, validate_store

    attrs = open_store(str(store)).attrs
    assert attrs["schema_version"] == "1.1"
    rules = attrs["ground_truth_mesh"]
    assert rules["envelope"]["resolution"] == "96x72" and rules["envelope"]["envelope_a"] == 15.0
    assert rules["envelope"]["rule"].startswith("D5 surface")
    assert rules["objects"]["behind_envelope"] == 0.1
    assert validate_store(str(store)) == []


def test_coverage_with_the_reference_preset_says_so(store, tmp_path):
    js = tmp_path / "cov.json"
    res = run("evaluate", "coverage", store, "--density", 1000, "--preset", "reference", "--plot",
              tmp_path / "cov.png", "--json", js)
    assert res.exit_code == 0, res.output
    assert "edge factor preset reference: a = 10 for D1-D4 and the overhead map, 15 for D5" in res.output
    a = json.loads(js.read_text())["a"]
    assert a == {"D1": 10.0, "D2": 10.0, "D3": 10.0, "D4": 10.0, "D5": 15.0, "overhead": 10.0}
    res = run("evaluate", "coverage", store, "--density", 1000, "--preset", "reference", "--a", 12,
              "--plot", tmp_path / "cov.png")
    assert "a = 12 for every layer (preset reference overridden)" in res.output
    assert run("evaluate", "coverage", store, "--preset", "mine").exit_code == 2


def test_predictions_of_the_ground_truth_itself(store, tmp_path):
    png = tmp_path / "pred.png"
    res = run("evaluate", "predictions", store, store, "--density", 1000, "--plot", png, "--split", "all")
    assert res.exit_code == 0, res.output
    assert res.output.splitlines()[0] == "split: all (3 views of 3 houses)"
    # no split file beside the store: every view is scored, but the baselines need training houses
    assert res.output.splitlines()[1].startswith("learning scores left out: the baselines need the training houses")
    assert res.output.splitlines()[3] == "meshing: edge factor preset paper: a = 7 for every layer"
    lines = {line[:18].strip(): line[18:].split() for line in res.output.splitlines()[5:9]}
    assert list(lines) == ["D1", "D1 & overhead", "D1-4", "D1-4 & overhead"]
    assert lines["D1-4 & overhead"][2:] == ["0.519", "0.457"]
    # ground-truth layers lie on the ground-truth objects, but for triangles the edge rule
    # lets bridge neighbouring objects: at 64×48 pixels it allows jumps of 7 × 5.8 cm at 3 m
    assert float(lines["D1-4"][0]) > 0.8
    assert png.exists()


def test_predictions_from_other_cameras_are_one_red_line(store, tmp_path, monkeypatch):
    import sceneforge.store

    real = sceneforge.store.open_store

    class Moved:
        """The store with every camera 10 cm to the side."""

        def __init__(self, inner):
            self.inner, self.names, self.attrs = inner, inner.names, inner.attrs

        def array(self, name):
            a = self.inner.array(name)
            if name == "cam_to_world":
                a = np.asarray(a[:]).copy()
                a[:, 0, 3] += 0.1
            return a

        def __len__(self):
            return len(self.inner)

        def view(self, i):
            v = self.inner.view(i)
            v["cam_to_world"] = v["cam_to_world"].copy()
            v["cam_to_world"][0, 3] += 0.1
            return v

    def open_store(path):
        return Moved(real(path[:-len("#moved")])) if path.endswith("#moved") else real(path)

    monkeypatch.setattr(sceneforge.store, "open_store", open_store)
    res = run("evaluate", "predictions", f"{store}#moved", store, "--plot", tmp_path / "p.png", "--split", "all")
    assert res.exit_code == 1
    assert res.output.count("\n") == 1 and "another camera pose" in res.output
    assert "Traceback" not in res.output


def test_voxels_per_view_and_histogram(store, tmp_path):
    png = tmp_path / "iou.png"
    res = run("evaluate", "voxels", store, "--resolution", 100, "--size", 10, "--plot", png)
    assert res.exit_code == 0, res.output
    ious = [float(line.split("IoU")[1].split()[0])
            for line in res.output.splitlines() if line.startswith("view")]
    # toy_0_000's sampled view (issue 12's informative sampler) faces the office bookshelf:
    # its (D1, D2) interval spans the open shelves, which the solid mesh does not fill (0.27)
    assert len(ious) == 3 and all(0.25 < x <= 1 for x in ious) and sorted(ious)[1] > 0.6
    mean = float(res.output.split("mean voxel IoU")[1].split()[0])
    assert mean == pytest.approx(np.mean(ious), abs=1e-3)
    assert png.stat().st_size > 5_000


def test_missing_store_is_one_red_line(tmp_path):
    res = run("evaluate", "coverage", tmp_path / "nothing.zarr")
    assert res.exit_code == 1 and "error:" in res.output and "Traceback" not in res.output


def _split_file(path, train, val=(), test=()):
    path.write_text(json.dumps({"version": 1, "val_fraction": 0.34, "test_fraction": 0.34, "seed": 0,
                                "stores": [], "train": list(train), "val": list(val), "test": list(test)}))
    return path


def test_predictions_print_the_learning_scores_beside_the_baselines(store, tmp_path):
    split = _split_file(tmp_path / "split.json", ["toy_0_001", "toy_0_002"], test=["toy_0_000"])
    js = tmp_path / "pred.json"
    res = run("evaluate", "predictions", store, store, "--density", 1000, "--plot", tmp_path / "p.png",
              "--split-file", split, "--json", js)
    assert res.exit_code == 0, res.output
    assert res.output.splitlines()[0] == "split: test (1 view of 1 house)"
    assert "learning: the model next to a trivial predictor of the 2 training views (no image), on 1 view" in res.output
    learning = json.loads(js.read_text())["learning"]
    # the truth scored as a prediction: exact depths and classes, next to a baseline that is not
    assert learning["depth_absrel"]["model"] == 0.0 and learning["depth_absrel"]["baseline"] > 0.05
    assert learning["seg_miou"]["model"] == 1.0 and learning["seg_miou"]["baseline"] < 0.5
    assert learning["overhead_height_l1"]["model"] == 0.0 and learning["overhead_height_l1"]["baseline"] > 0.05
    assert learning["depth_coverage"] == 1.0 and learning["views"] == 1 and learning["train_views"] == 2
    assert learning["overhead_coverage"] == 1.0


def test_a_split_without_training_houses_in_the_truth_is_one_red_line(store, tmp_path):
    split = _split_file(tmp_path / "split.json", ["elsewhere_1"], test=["toy_0_000"])
    res = run("evaluate", "predictions", store, store, "--plot", tmp_path / "p.png", "--split-file", split)
    assert res.exit_code == 1 and res.output.count("\n") == 1, res.output
    assert "holds no view of the 1 training houses" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "p.png").exists()


def test_plots_default_beside_the_store_not_into_the_current_folder(store, tmp_path, monkeypatch):
    import shutil

    copy = tmp_path / "data" / "mine.zarr"
    shutil.copytree(store, copy)
    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    res = run("evaluate", "voxels", copy, "--resolution", 20, "--size", 10, "--limit", 1)
    assert res.exit_code == 0, res.output
    assert (tmp_path / "data" / "mine.voxel_iou.png").stat().st_size > 1000
    assert f"histogram: {tmp_path / 'data' / 'mine.voxel_iou.png'}" in res.output
    assert list(here.iterdir()) == []
