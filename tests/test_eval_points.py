"""Layered point metrics the way LaRI scores them (docs/spec.md §11.6): hand-computed point
sets, the scale-shift fit, the visible/unseen split of a tiny view, and the CLI on a store
predicting itself."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner
from sceneforge.cli.main import LazyGroup

from sceneforge.evaluate.points import (
    LayeredView,
    PointsConfig,
    PointsReport,
    apply_scale_shift,
    camera_points,
    chamfer_fscore,
    fit_scale_shift,
    nearest_distances,
    ray_layers,
    score_view,
    split_points,
)

pytest.importorskip("open3d", reason="point distances need open3d (the trace extra)")

CLI = LazyGroup(name="sceneforge", lazy={"evaluate": "evaluate:evaluate"})
T = (0.1, 0.05, 0.02)
NaN = np.nan


def grid(n: int = 4, spacing: float = 1.0) -> np.ndarray:
    """(n², 3) points of a square grid in the plane z = 2, ``spacing`` apart."""
    i, j = np.meshgrid(np.arange(n), np.arange(n))
    return np.stack([i.ravel() * spacing, j.ravel() * spacing, np.full(n * n, 2.0)], axis=1)


def brute_force_nearest(points: np.ndarray, to: np.ndarray) -> np.ndarray:
    """The slow reference: every pair's distance."""
    return np.sqrt(((points[:, None, :] - to[None, :, :]) ** 2).sum(axis=-1)).min(axis=1)


def test_nearest_distances_match_the_brute_force_reference():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(300, 3)), rng.normal(size=(200, 3)) + 0.1
    np.testing.assert_allclose(nearest_distances(a, b), brute_force_nearest(a, b), rtol=0, atol=1e-12)
    assert np.isinf(nearest_distances(a, np.zeros((0, 3)))).all()
    assert nearest_distances(np.zeros((0, 3)), b).shape == (0,)


def test_a_set_offset_by_3_cm_has_chamfer_3_cm_and_full_fscore_above_it():
    gt = grid()
    s = chamfer_fscore(gt + [0.0, 0.0, 0.03], gt, T)  # neighbours 1 m apart: the nearest is the shifted twin
    assert s.chamfer == pytest.approx(0.03, abs=1e-12)
    np.testing.assert_array_equal(s.precision, [1, 1, 0])
    np.testing.assert_array_equal(s.recall, [1, 1, 0])
    np.testing.assert_array_equal(s.fscore, [1, 1, 0])


def test_a_subset_is_precise_but_recalls_only_itself():
    square = np.array([[0, 0, 2], [1, 0, 2], [0, 1, 2], [1, 1, 2]], dtype=float)
    s = chamfer_fscore(square[:2], square, (0.5,))
    # pred → truth: 0, 0; truth → pred: 0, 0, 1, 1 (the far corners' nearest kept corner)
    assert s.chamfer == pytest.approx((0 + 0.5) / 2)
    assert (s.precision[0], s.recall[0]) == (1.0, 0.5)
    assert s.fscore[0] == pytest.approx(2 * 1 * 0.5 / 1.5)
    # the other way round: every true point is recalled, half the predicted ones are near it
    s = chamfer_fscore(square, square[:2], (0.5,))
    assert (s.precision[0], s.recall[0], s.chamfer) == (0.5, 1.0, 0.25)


def test_empty_sets():
    gt = grid(2)
    s = chamfer_fscore(np.zeros((0, 3)), gt, T)  # nothing predicted: precision 1, recall 0
    assert math.isnan(s.chamfer)
    np.testing.assert_array_equal(np.c_[s.precision, s.recall, s.fscore], [[1, 0, 0]] * 3)
    s = chamfer_fscore(gt, np.zeros((0, 3)), T)  # no truth: recall and F-score undefined
    assert math.isnan(s.chamfer) and np.isnan(s.recall).all() and np.isnan(s.fscore).all()
    assert (s.precision == 0).all()
    s = chamfer_fscore(np.zeros((0, 3)), np.zeros((0, 3)), T)
    assert math.isnan(s.chamfer) and np.isnan(s.fscore).all()


def test_the_fit_recovers_a_known_scale_and_shift_exactly():
    rng = np.random.default_rng(1)
    gt = rng.uniform([-2, -1, 1], [2, 1, 6], size=(500, 3))
    scale, shift = 1.7, -0.35
    pred = apply_scale_shift(gt, 1 / scale, -shift / scale)  # gt = scale · pred + shift · ẑ
    s, t = fit_scale_shift(pred, gt)
    assert s == pytest.approx(scale, rel=1e-12) and t == pytest.approx(shift, abs=1e-12)
    np.testing.assert_allclose(apply_scale_shift(pred, s, t), gt, atol=1e-12)
    assert fit_scale_shift(np.zeros((0, 3)), np.zeros((0, 3))) is None
    with pytest.raises(ValueError, match="pairs"):
        fit_scale_shift(pred[:3], gt[:4])


def test_the_fit_is_least_squares_on_noisy_pairs():
    rng = np.random.default_rng(2)
    pred = rng.uniform([-2, -1, 1], [2, 1, 6], size=(200, 3))
    gt = apply_scale_shift(pred, 0.8, 0.2) + rng.normal(scale=0.01, size=pred.shape)
    s, t = fit_scale_shift(pred, gt)
    # the normal equations of the stacked 3n × 2 system [p | ẑ] (s, t) = g
    A = np.stack([pred.ravel(), np.tile([0.0, 0.0, 1.0], len(pred))], axis=1)
    np.testing.assert_allclose((s, t), np.linalg.lstsq(A, gt.ravel(), rcond=None)[0], rtol=1e-10)


#: a 1 × 3 view: a single-sided sheet (D2 = D1) before a wall, a box behind a box before the
#: wall on the optical axis, and the bare wall
D = np.array([[[1.0, 1.0, NaN]], [[1.0, 1.5, NaN]], [[NaN, 2.0, NaN]], [[NaN, 2.5, NaN]], [[4.0, 4.0, 3.0]]],
             dtype=np.float32)
K = np.array([[1.0, 0, 1.5], [0, 1.0, 0.5], [0, 0, 1]])  # pixel j's centre at x = (j - 1) · z


def test_the_paper_layers_become_the_first_surface_and_the_ones_behind_it():
    layers = ray_layers(D)
    np.testing.assert_array_equal(layers[:, 0].T, [[1, NaN, NaN, NaN, 4], [1, 1.5, 2, 2.5, 4], [3, NaN, NaN, NaN, NaN]])
    sets = split_points(camera_points(layers, K))
    np.testing.assert_allclose(sets["visible"], [[-1, 0, 1], [0, 0, 1], [3, 0, 3]])
    np.testing.assert_allclose(sets["unseen"], [[0, 0, 1.5], [0, 0, 2], [0, 0, 2.5], [-4, 0, 4], [0, 0, 4]])
    assert len(sets["all"]) == 8
    with pytest.raises(ValueError, match="D1..D5"):
        ray_layers(D[:4])


def test_a_view_predicting_its_truth_at_half_scale_is_perfect_once_aligned():
    gt = LayeredView(ray_layers(D), K, "layers")
    pred = LayeredView(ray_layers(D / 2), K, "layers")
    v = score_view(pred, gt, np.random.default_rng(0), PointsConfig(thresholds=T))
    assert (v.scale, v.shift) == (pytest.approx(2.0), pytest.approx(0.0, abs=1e-12))
    np.testing.assert_allclose(v.chamfer[1], 0, atol=1e-12)
    np.testing.assert_array_equal(v.fscore[1], 1)
    assert (v.chamfer[0] > 0.1).all() and (v.fscore[0] < 1).all()
    np.testing.assert_array_equal(v.pred_points, [3, 5, 8])
    np.testing.assert_array_equal(v.gt_points, [3, 5, 8])


def test_unseen_points_the_prediction_lacks_leave_recall():
    gt = LayeredView(ray_layers(D), K, "layers")
    front = ray_layers(D)
    front[1:] = np.nan  # only the first surface predicted
    v = score_view(LayeredView(front, K, "layers"), gt, np.random.default_rng(0), PointsConfig(thresholds=T))
    np.testing.assert_array_equal(v.fscore[:, 0], 1)  # visible: exact
    np.testing.assert_array_equal(v.fscore[:, 1], 0)  # unseen: nothing predicted
    assert np.isnan(v.chamfer[:, 1]).all()
    # all: the 3 visible of 8 true points are recalled, every predicted point is exact
    np.testing.assert_allclose(v.recall[:, 2], 3 / 8)
    np.testing.assert_allclose(v.fscore[:, 2], 2 * (3 / 8) / (1 + 3 / 8))


def test_sets_larger_than_the_samples_are_subsampled_without_replacement():
    rng = np.random.default_rng(3)
    depth = rng.uniform(1, 3, size=(2, 8, 8)).astype(np.float32)
    view = LayeredView(depth, np.array([[8.0, 0, 4], [0, 8, 4], [0, 0, 1]]), "intersections")
    v = score_view(view, view, np.random.default_rng(0), PointsConfig(samples=10, thresholds=T))
    assert (v.chamfer > 0).all()  # two different samples of the same set
    full = score_view(view, view, np.random.default_rng(0), PointsConfig(samples=128, thresholds=T))
    np.testing.assert_array_equal(full.chamfer, 0)


def test_the_report_averages_over_the_views_where_a_score_is_defined():
    gt = LayeredView(ray_layers(D), K, "layers")
    wall_only = D.copy()
    wall_only[:4] = np.nan  # no object: nothing behind the first surface
    bare = LayeredView(ray_layers(wall_only), K, "layers")
    config = PointsConfig(thresholds=(0.05,))
    scores = [score_view(gt, gt, np.random.default_rng(0), config), score_view(bare, bare, np.random.default_rng(1),
                                                                               config)]
    report = PointsReport.collect([0, 1], scores, config, 0, "layers", "layers")
    table = report.table()
    np.testing.assert_array_equal(table["views"], [[2, 1, 2], [2, 1, 2]])
    np.testing.assert_array_equal(table["fscore"][..., 0], 1)
    out = report.to_dict()
    assert out["views"] == 2 and out["aligned_views"] == 2 and out["truth"] == "layers"
    assert out["scale_shift"]["unseen"] == {"chamfer_l1": 0.0, "fscore": {"0.05": 1.0}, "precision": {"0.05": 1.0},
                                            "recall": {"0.05": 1.0}, "views": 1, "chamfer_views": 1}
    text = report.text().splitlines()
    assert text[2].split() == ["points", "alignment", "chamfer", "F@5cm", "views"]
    assert text[5].split() == ["unseen", "none", "0.000", "1.000", "1"]


class FakeStore:
    """The arrays of one view, as a store holds them (``names``, ``array(name)[i]``)."""

    def __init__(self, **arrays):
        self.arrays = {k.replace("__", "/"): v[None] for k, v in arrays.items()}
        self.names = tuple(self.arrays)

    def array(self, name):
        return self.arrays[name]


def test_a_store_with_ray_intersections_is_scored_on_them():
    from sceneforge.evaluate.stores import score_store_points

    hits = np.array([[[1.0, 1.0, 3.0]], [[1.2, 1.5, NaN]], [[4.0, 2.0, NaN]]], dtype=np.float32)
    gt = FakeStore(depth=D, K=K, intersections__depth=hits)
    pred = FakeStore(depth=D, K=K)
    report = score_store_points(pred, gt, [0], PointsConfig(thresholds=T))
    assert (report.pred_source, report.gt_source) == ("layers", "intersections")
    assert report.text().splitlines()[1].startswith("truth: ray intersections, prediction: D1-D5; visible: each ")
    np.testing.assert_array_equal(report.fscore[0, :, 0], 1)  # the same first surfaces
    assert (report.fscore[0, :, 1] < 1).all()
    off = score_store_points(pred, gt, [0], PointsConfig(thresholds=T, intersections=False))
    assert off.gt_source == "layers" and (off.fscore == 1).all()
    assert score_store_points(gt, gt, [0]).chamfer.max() == 0


def test_a_prediction_of_another_image_size_is_one_clear_error():
    from sceneforge.errors import SceneforgeError
    from sceneforge.evaluate.stores import score_store_points

    small = FakeStore(depth=D, K=K)
    large = FakeStore(depth=np.repeat(D, 2, axis=1), K=K)
    with pytest.raises(SceneforgeError, match=r"^view 0: the prediction's image is 3x2 but the truth's 3x1: "):
        score_store_points(large, small, [0])


def run(*args):
    return CliRunner().invoke(CLI, list(map(str, args)))


def test_points_of_a_store_predicting_itself_are_perfect(tiny_toy_store, tmp_path):
    js = tmp_path / "points.json"
    res = run("evaluate", "points", tiny_toy_store, tiny_toy_store, "--json", js)
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert lines[0] == ("layered points (LaRI): Chamfer-L1 (m) and F-score, mean over 3 views, "
                        "at most 100000 points per set")
    assert lines[2].split() == ["points", "alignment", "chamfer", "F@10cm", "F@5cm", "F@2cm", "views"]
    rows = [line.split() for line in lines[3:9]]
    assert [r[:2] for r in rows] == [[s, a] for s in ("visible", "unseen", "all") for a in ("none", "scale-shift")]
    assert all(r[2:] == ["0.000", "1.000", "1.000", "1.000", "3"] for r in rows), res.output
    values = json.loads(js.read_text())
    assert values["views"] == 3 and values["aligned_views"] == 3 and values["truth"] == "layers"
    assert values["none"]["all"]["chamfer_l1"] == 0 and values["scale_shift"]["unseen"]["fscore"]["0.02"] == 1


def test_predictions_write_the_layered_points_beside_the_paper_table(tiny_toy_store, tmp_path):
    js = tmp_path / "pred.json"
    res = run("evaluate", "predictions", tiny_toy_store, tiny_toy_store, "--split", "all", "--limit", 1,
              "--density", 100, "--fscore-threshold", 0.05, "--plot", tmp_path / "p.png", "--json", js)
    assert res.exit_code == 0, res.output
    assert "layered points (LaRI): Chamfer-L1 (m) and F-score, mean over 1 view, at most" in res.output
    points = json.loads(js.read_text())["layered_points"]
    assert points["views"] == 1 and points["thresholds"] == [0.05]
    assert points["none"]["visible"]["fscore"] == {"0.05": 1.0}
