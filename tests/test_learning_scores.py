"""Learning scores of ``evaluate predictions``: the model next to a trivial predictor of the
training houses, against values worked out by hand on 2×2 views (no torch, no renderer)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sceneforge.conventions import NYU40_IDS
from sceneforge.errors import SceneforgeError
from sceneforge.evaluate.learning import learning_scores, seg_targets, training_baselines
from sceneforge.evaluate.stores import check_matching

NAN = np.nan
CHAIR, TABLE, WALL, FLOOR = NYU40_IDS["chair"], NYU40_IDS["table"], NYU40_IDS["wall"], NYU40_IDS["floor"]


class ArrayStore:
    """What the scores read of a store: ``len``, ``names``, ``array(name)``, ``attrs``, ``view(i)``."""

    def __init__(self, **arrays):
        self.arrays = {k: np.asarray(v) for k, v in arrays.items()}
        self.names = tuple(self.arrays)
        self.attrs = {}

    def __len__(self):
        return len(self.arrays["depth"])

    def array(self, name):
        return self.arrays[name]

    def view(self, i):
        return {k: v[i] for k, v in self.arrays.items()}


def views(d1, category1, height, d5=2.0):
    """Views of 2×2 pixels: D1 as given (D2..D4 empty), D5 ``d5`` everywhere but where
    ``d5`` is NaN, layer-1 classes, overhead heights."""
    d1 = np.asarray(d1, np.float32)
    n = len(d1)
    depth = np.full((n, 5, 2, 2), NAN, np.float32)
    depth[:, 0] = d1
    depth[:, 4] = d5
    category = np.zeros((n, 3, 2, 2), np.uint8)
    category[:, 0] = category1
    return dict(depth=depth, category=category, overhead_height=np.asarray(height, np.float32),
                house_id=np.array([f"h{i}" for i in range(n)]), camera_id=np.arange(n),
                cam_to_world=np.tile(np.eye(4), (n, 1, 1)))


def test_baselines_are_the_training_views_statistics():
    gt = ArrayStore(**views(d1=[[[2, NAN], [1, NAN]], [[4, NAN], [NAN, NAN]], [[100, 100], [100, 100]]],
                            category1=[[[CHAIR, 0], [TABLE, 0]], [[CHAIR, 0], [0, 0]], [[TABLE] * 2] * 2],
                            height=[[[0.5, 0.02], [NAN, 1.5]], [[NAN, NAN], [NAN, NAN]], [[9, 9], [9, 9]]]))
    b = training_baselines(gt, [0, 1])  # view 2 is not a training view: it must change nothing
    # per pixel: (2 + 4) / 2 at (0, 0), 1 at (1, 0); pixels no training view has take the layer's mean
    # over every finite pixel, (2 + 1 + 4) / 3
    np.testing.assert_allclose(b.depth[0], [[3, 7 / 3], [1, 7 / 3]])
    # layer 1: chair ×2, table ×1 and background (wall, D5) ×5 of the 8 pixels, plus layer 3's 8
    # background pixels (D3 is empty but D5 is hit): background is the most frequent
    assert b.seg == 0
    assert b.height == pytest.approx((0.5 + 1.5) / 2)  # the 0.02 m pixel is floor (<= 5 cm)
    assert b.views == 2
    with pytest.raises(SceneforgeError, match="no training view"):
        training_baselines(gt, [])


def test_most_frequent_class_counts_only_pixels_where_a_ray_hits():
    d1 = [[[1, 1], [1, NAN]]]
    cats = [[[CHAIR, CHAIR], [CHAIR, WALL]]]
    gt = views(d1=d1, category1=cats, height=[[[NAN] * 2] * 2], d5=NAN)
    target = seg_targets(gt["category"], gt["depth"])
    # layer 1: chair where D1 is hit, nothing (-1) where neither D1 nor D5 is; layer 3 all nothing
    np.testing.assert_array_equal(target[0, 0], [[CHAIR - 1, CHAIR - 1], [CHAIR - 1, -1]])
    assert (target[0, 1] == -1).all()
    assert training_baselines(ArrayStore(**gt), [0]).seg == CHAIR - 1


def test_scores_of_the_model_and_the_baseline_by_hand():
    train = views(d1=[[[2, 2], [NAN, NAN]]], category1=[[[CHAIR, CHAIR], [0, 0]]],
                  height=[[[1.0, 1.0], [NAN, NAN]]])
    test = views(d1=[[[4, 1], [NAN, NAN]]], category1=[[[CHAIR, TABLE], [0, FLOOR]]],
                 height=[[[0.5, 2.0], [NAN, 0.01]]])
    gt = ArrayStore(**{k: np.concatenate([train[k], test[k]]) for k in train})
    # the prediction of view 1: D1 right at (0, 0), 100 % off at (0, 1), and a D1 where truth has none
    pred_depth = np.full((2, 5, 2, 2), NAN, np.float32)
    pred_depth[1, 0] = [[4, 2], [5, NAN]]
    pred_cat = np.zeros((2, 3, 2, 2), np.uint8)
    pred_cat[1, 0] = [[CHAIR, CHAIR], [0, 0]]
    pred_height = np.full((2, 2, 2), NAN, np.float32)
    pred_height[1] = [[0.75, NAN], [3.0, NAN]]
    pred = ArrayStore(**{**gt.arrays, "depth": pred_depth, "category": pred_cat, "overhead_height": pred_height})
    base = training_baselines(gt, [0])
    report = learning_scores(pred, gt, [1], base)
    d = report.scores
    # depth: the model |4-4|/4 and |2-1|/1 → 0.5; the baseline predicts 2: |2-4|/4, |2-1|/1 → 0.75
    assert d["depth_absrel"] == pytest.approx((0.5, 0.75))
    assert report.depth_coverage == 1.0
    # seg over 8 counted pixels (layer 1: 4; layer 3: 4 background where D5 is hit):
    # model: chair {p (0,0),(0,1)} ∩ {t (0,0)} → 1/2; table {p ∅} ∪ {t (0,1)} → 0;
    #        background {p 6} ∩ {t 6} → 6/6: mean (1/2 + 0 + 1) / 3
    # baseline (background everywhere): background 6/8, chair 0, table 0 → (6/8) / 3
    assert d["seg_miou"] == pytest.approx((1.5 / 3, 0.75 / 3))
    # heights above 5 cm: 0.5 and 2.0; the model predicts 0.75 at the first (0.25 off) and
    # removes the second, so both are scored on the first: the baseline 1.0 is 0.5 off there
    assert d["overhead_height_l1"] == pytest.approx((0.25, 0.5))
    assert report.overhead_coverage == 0.5
    out = report.to_dict()
    assert out["depth_absrel"] == {"model": pytest.approx(0.5), "baseline": pytest.approx(0.75), "better": "lower"}
    assert out["seg_miou"]["better"] == "higher" and out["views"] == 1 and out["train_views"] == 1
    assert "depth_absrel" in report.text() and "0.500" in report.text()
    assert out["overhead_coverage"] == 0.5
    assert "overhead heights scored on 50.0% of the object pixels" in report.text()


def test_depth_is_scored_where_the_model_predicted_and_coverage_says_how_much():
    gt = ArrayStore(**views(d1=[[[2, 2], [2, 2]], [[1, 1], [4, 4]]], category1=np.zeros((2, 2, 2)),
                            height=np.zeros((2, 2, 2))))
    pred_depth = np.full((2, 5, 2, 2), NAN, np.float32)
    pred_depth[1, 0, 0] = [1, 1]  # the model left the two 4 m pixels out
    pred = ArrayStore(**{**gt.arrays, "depth": pred_depth})
    report = learning_scores(pred, gt, [1], training_baselines(gt, [0]), stages=("depth",))
    # both on the same 2 pixels: the model exact, the baseline (2 m) 100 % off
    assert report.scores["depth_absrel"] == pytest.approx((0.0, 1.0))
    assert report.depth_coverage == 0.5
    assert report.scores["seg_miou"] is None and report.scores["overhead_height_l1"] is None
    assert report.to_dict()["seg_miou"] is None
    assert "no seg prediction" in report.text()


def test_proposed_overhead_cameras_leave_the_height_score_out():
    gt = ArrayStore(**views(d1=[[[2, 2], [2, 2]]] * 2, category1=np.zeros((2, 2, 2)), height=np.ones((2, 2, 2))))
    report = learning_scores(gt, gt, [1], training_baselines(gt, [0]), same_overhead_cameras=False)
    assert report.scores["overhead_height_l1"] is None
    assert "proposed" in report.text()
    assert report.scores["depth_absrel"] == (0.0, 0.0)  # the truth scored against itself
    assert math.isclose(report.scores["seg_miou"][0], 1.0)


def test_predictions_of_other_views_are_refused_before_scoring():
    gt = ArrayStore(**views(d1=np.ones((3, 2, 2)), category1=np.zeros((3, 2, 2)), height=np.ones((3, 2, 2))))
    check_matching(gt, gt, [0, 2])
    other = ArrayStore(**{**gt.arrays, "house_id": np.array(["h0", "h1", "elsewhere"])})
    with pytest.raises(SceneforgeError, match="view 2: house_id elsewhere in the predictions, h2 in the truth"):
        check_matching(other, gt, [0, 2])
    moved = gt.arrays["cam_to_world"].copy()
    moved[1, 0, 3] = 1.0
    with pytest.raises(SceneforgeError, match="view 1: the predictions come from another camera pose"):
        check_matching(ArrayStore(**{**gt.arrays, "cam_to_world": moved}), gt, [1])
    longer = ArrayStore(**views(d1=np.ones((4, 2, 2)), category1=np.zeros((4, 2, 2)), height=np.ones((4, 2, 2))))
    with pytest.raises(SceneforgeError, match="the predictions have 4 views but the ground truth only 3"):
        check_matching(longer, gt, [0])
