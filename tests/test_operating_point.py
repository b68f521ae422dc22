"""The operating point chosen on validation houses (sceneforge.learn.operating_point): the
thresholds' scores against analytic scenes, the rule, and the link between the scores and
the nets' masks."""

import numpy as np
import pytest

from sceneforge.evaluate import EvalView, GroundTruthMesh, Mesh, score_parts
from sceneforge.evaluate.coverage import Variant
from sceneforge.learn.operating_point import (
    GRID,
    CandidateView,
    OperatingPoint,
    candidate_views,
    choose,
    evenly,
    score_candidates,
)

W, H, R = 40, 30, 32
#: a frontal camera at the origin looking along +z (OpenCV axes), 30 px focal length
K = np.array([[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]])
WIDE = np.array([[10.0, 0, W / 2], [0, 10.0, H / 2], [0, 0, 1]])
#: the overhead camera: also at the origin looking along +z, 3 m "above the floor", half-extent 1 m
TOP_HEIGHT, EXTENT = 3.0, 1.0


def square(x0, x1, y0, y1, z) -> Mesh:
    """The rectangle [x0, x1] × [y0, y1] of the plane at depth z, two triangles."""
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float64)
    return Mesh(v, np.array([[0, 1, 2], [0, 2, 3]]))


def view(depth: np.ndarray, height: np.ndarray, k=K) -> EvalView:
    return EvalView(depth, k, np.eye(4), height, np.eye(4), EXTENT, np.array([0, 0, TOP_HEIGHT, 0, 1.0]))


def halves(left: float, right: float, shape) -> np.ndarray:
    a = np.full(shape, right, np.float32)
    a[..., : shape[-1] // 2] = left
    return a


def no_layers() -> np.ndarray:
    return np.full((5, H, W), np.nan, np.float32)


def frontal_case():
    """D1: the left half of the image on the plane z = 2 m (surely an object: 0.9), the right
    half 0.5 m behind it (unsure: 0.55); the object is exactly what the left half sees."""
    depth = no_layers()
    depth[0] = halves(2.0, 2.5, (H, W))
    score = np.stack([halves(0.9, 0.55, (H, W))] * 2)
    x = lambda u: (u - W / 2) / 30.0 * 2.0  # noqa: E731  pixel centre u at depth 2
    y = lambda v: (v - H / 2) / 30.0 * 2.0  # noqa: E731
    gt = GroundTruthMesh(square(x(0.5), x(W / 2 - 0.5), y(0.5), y(H - 0.5), 2.0), Mesh.empty())
    top = np.full((R, R), np.nan, np.float32)
    return CandidateView(view(depth, top), score, np.full((R, R), -1.0, np.float32)), gt


def test_a_threshold_that_drops_the_unsure_half_scores_what_the_geometry_says():
    c, gt = frontal_case()
    fronts = (None, 0.5, 0.6, 0.9, 0.95)
    p, r = score_candidates(c, gt, fronts, (None,), np.random.default_rng(0), density=20_000)
    p, r = p[:, 0], r[:, 0]
    # both halves kept: the right one is 0.5 m off and (2.5/2)² as large per pixel
    both = 1 / (1 + 1.25 ** 2)
    assert p[0] == pytest.approx(both, abs=0.03) and p[1] == pytest.approx(both, abs=0.03)
    assert r[0] > 0.97 and r[1] > 0.97
    # 0.6 and 0.9 keep exactly the sure half: every point on the object, the object covered
    assert p[2] > 0.99 and p[3] > 0.99 and r[2] > 0.97 and r[3] > 0.97
    # nothing is that sure: an empty prediction, precision 1 and recall 0 by convention
    assert p[4] == 1.0 and r[4] == 0.0
    assert fronts[choose(p[:, None], r[:, None])[0]] in (0.6, 0.9)


def test_overhead_thresholds_are_scored_with_the_frontal_ones_as_one_union():
    """The overhead map sees a table top (the whole map, at 0.7 m) right on its left half
    (0.9 sure) and 0.8 m too high on its right half (0.55); the frontal layer sees the plane
    of the table top on the image's left half, surely, and nothing on its right half."""
    depth = no_layers()
    d = TOP_HEIGHT - 0.7
    depth[0] = d
    front_score = np.stack([halves(0.9, -1.0, (H, W))] * 2)  # the right half is background
    height = halves(0.7, 1.5, (R, R))
    top_score = halves(0.9, 0.55, (R, R))
    c = CandidateView(view(depth, height, WIDE), front_score, top_score)
    edge = EXTENT * (1 - 1 / R)
    gt = GroundTruthMesh(square(-edge, edge, -edge, edge, d), Mesh.empty())
    fronts, tops = (None, 0.95), (None, 0.6, 0.95)
    p, r = score_candidates(c, gt, fronts, tops, np.random.default_rng(1), density=20_000)
    # the overhead map alone: both halves (P ½, R ½: the unsure half is wrong) or the sure half (P 1, R ½)
    assert p[1, 0] == pytest.approx(0.5, abs=0.04) and r[1, 0] == pytest.approx(0.5, abs=0.04)
    assert p[1, 1] > 0.99 and r[1, 1] == pytest.approx(0.5, abs=0.04)
    # the frontal layer alone: half the table, and far more floor beside it (~2 of 32 m²)
    assert r[0, 2] == pytest.approx(0.5, abs=0.04) and p[0, 2] < 0.1
    # nothing at all
    assert (p[1, 2], r[1, 2]) == (1.0, 0.0)
    # a union recalls at least what each of its parts does, and its precision lies between theirs
    assert r[0, 0] >= max(r[0, 2], r[1, 0]) - 0.02 and r[0, 1] >= max(r[0, 2], r[1, 1]) - 0.02
    assert p[0, 2] - 0.01 <= p[0, 1] <= p[1, 1] + 0.01


def test_the_scores_are_evaluate_predictions_own_at_the_chosen_thresholds():
    """One candidate scored here and by ``score_parts`` (what ``evaluate predictions`` runs)
    on the view masked at its thresholds: the same numbers, up to sampling."""
    depth = no_layers()
    depth[0] = halves(2.0, 2.3, (H, W))
    depth[2] = 2.6
    score = np.stack([halves(0.9, 0.55, (H, W)), halves(0.4, 0.8, (H, W))])
    c = CandidateView(view(depth, np.full((R, R), np.nan, np.float32)), score, np.full((R, R), -1.0, np.float32))
    gt = GroundTruthMesh(square(-0.8, 0.6, -0.9, 0.9, 2.0), square(-3, 3, -3, 3, 4.0))
    for t in (None, 0.5, 0.7):
        p, r = score_candidates(c, gt, (t,), (None,), np.random.default_rng(3), density=40_000)
        (masked,), _ = candidate_views(c, (t,), ())
        scores = score_parts(masked.meshes(), gt, [Variant("D1-4 & overhead", ("D1", "D2", "D3", "D4", "overhead"))],
                             np.random.default_rng(4), [0.05], 40_000)
        assert p[0, 0] == pytest.approx(scores.precision[0, 1, 0], abs=0.01), t
        assert r[0, 0] == pytest.approx(scores.recall[0, 1, 0], abs=0.01), t


def test_candidates_mask_d3_d4_by_their_own_score_and_leave_d5_out():
    depth = np.ones((5, H, W), np.float32)
    score = np.stack([np.full((H, W), 0.9, np.float32), np.full((H, W), 0.6, np.float32)])
    c = CandidateView(view(depth, np.ones((R, R), np.float32)), score, np.full((R, R), 0.7, np.float32))
    (loose, strict), (top_loose, top_strict) = candidate_views(c, (None, 0.8), (0.5, 0.8))
    assert np.isfinite(loose.depth[:4]).all() and np.isnan(loose.depth[4]).all()
    assert np.isfinite(strict.depth[:2]).all() and np.isnan(strict.depth[2:]).all()
    assert np.isnan(loose.overhead_height).all()  # the frontal candidates carry no overhead part
    assert np.isnan(top_loose.depth).all() and np.isfinite(top_loose.overhead_height).all()
    assert np.isnan(top_strict.overhead_height).all()


def test_the_rule_is_where_precision_meets_recall_ties_to_the_lower_thresholds():
    precision = np.array([[0.2, 0.3], [0.4, 0.5], [0.6, 0.9]])
    recall = np.array([[0.9, 0.8], [0.5, 0.4], [0.3, 0.1]])
    assert choose(precision, recall) == (1, 0)  # min 0.4 beats 0.3 and 0.2 elsewhere
    tied = np.array([[0.5, 0.5], [0.5, 0.5]])
    assert choose(tied, tied) == (0, 0)
    assert choose(np.array([[np.nan, 0.4]]), np.array([[0.9, 0.6]])) == (0, 1)
    assert choose(np.full((2, 2), np.nan), np.full((2, 2), np.nan)) == (0, 0)


def test_the_chosen_point_reads_back_and_says_how_it_was_chosen():
    rng = np.random.default_rng(0)
    p, r = rng.random((3, len(GRID), 2)), rng.random((3, len(GRID), 2))
    r[1, 0, 0] = np.nan  # a view without objects: no recall, left out of the mean
    point = OperatingPoint.chosen(p, r, GRID, (None, 0.7), views=3, houses=2)
    mean_p, mean_r = p.mean(axis=0), np.nanmean(r, axis=0)
    i, j = choose(mean_p, mean_r)
    assert (point.min_object_probability, point.min_overhead_object_probability) == (GRID[i], (None, 0.7)[j])
    assert point.scores == pytest.approx((mean_p[i, j], mean_r[i, j]))
    data = point.to_dict()
    assert data["rule"] == "validation" and data["views"] == 3 and len(data["precision_table"]) == len(GRID)
    again = OperatingPoint.from_dict(data)
    assert again == point and again.scores == pytest.approx(point.scores)
    assert "chosen on 3 views of 2 validation houses where precision meets recall" in point.describe()
    given = OperatingPoint.from_dict({"min_object_probability": 0.85, "min_overhead_object_probability": None})
    assert given.describe() == ("operating point: least object probability 0.85 (frontal), arg-max (overhead), "
                                "as given")
    assert given.to_dict() == {"rule": "given", "min_object_probability": 0.85,
                               "min_overhead_object_probability": None}


def test_evenly_spreads_the_views_it_keeps():
    assert evenly(range(5), 10) == [0, 1, 2, 3, 4]
    assert evenly(range(100), 3) == [0, 50, 99]
    assert len(set(evenly(range(128), 48))) == 48


def test_object_scores_are_the_least_thresholds_object_pixels_keeps_at():
    torch = pytest.importorskip("torch")
    from sceneforge.learn.networks import object_pixels, object_scores

    logits = torch.randn(2, 40, 6, 7, generator=torch.Generator().manual_seed(0)) * 3
    scores = object_scores(logits)
    for t in (None, 0.0, 0.3, 0.5, 0.9, 1.0):
        expected = object_pixels(logits, t)
        assert torch.equal(scores >= (0.0 if t is None else t), expected), t
    assert (scores[~object_pixels(logits)] == -1).all()
