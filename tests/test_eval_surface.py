"""Surface sampling, point-to-mesh distance, precision/recall and the coverage variants (docs/spec.md §11)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from sceneforge.evaluate import (
    COVERAGE_VARIANTS,
    GroundTruthMesh,
    Mesh,
    MeshDistance,
    SurfaceConfig,
    Variant,
    inlier_fraction,
    precision_recall,
    sample_surface,
    score_parts,
    surface_precision_recall,
)

THRESHOLDS = np.array([0.001, 0.05, 0.15, 1.0])


def plane(size=(2.0, 1.5), offset=0.0, centre=(0.3, 0.2, 4.0), normal_axis=1) -> Mesh:
    """A rectangle (two triangles) of ``size`` m, its normal along ``normal_axis``, moved by
    ``offset`` along the normal."""
    a, b = [k for k in range(3) if k != normal_axis]
    corners = np.zeros((4, 3))
    corners[:, a] = [-0.5, 0.5, 0.5, -0.5]
    corners[:, b] = [-0.5, -0.5, 0.5, 0.5]
    corners[:, a] *= size[0]
    corners[:, b] *= size[1]
    corners[:, normal_axis] += offset
    return Mesh(corners + centre, [[0, 1, 2], [0, 2, 3]])


def box(extents=(1.0, 0.6, 0.8), centre=(0.0, 0.5, 3.0)) -> Mesh:
    b = trimesh.creation.box(extents=extents)
    b.apply_translation(centre)
    return Mesh(b.vertices, b.faces)


def test_mesh_against_itself_is_perfect():
    m = box()
    config = SurfaceConfig(thresholds=tuple(THRESHOLDS))
    p, r = surface_precision_recall(m, m, np.random.default_rng(0), config)
    np.testing.assert_array_equal(p, 1.0)
    np.testing.assert_array_equal(r, 1.0)


def test_plane_moved_10cm_along_its_normal():
    config = SurfaceConfig(thresholds=(0.05, 0.15))
    p, r = surface_precision_recall(plane(offset=0.1), plane(), np.random.default_rng(1), config)
    np.testing.assert_array_equal(p, [0.0, 1.0])
    np.testing.assert_array_equal(r, [0.0, 1.0])


def test_empty_prediction_has_precision_1_recall_0():
    p, r = surface_precision_recall(Mesh.empty(), box(), np.random.default_rng(0),
                                    SurfaceConfig(thresholds=tuple(THRESHOLDS)))
    np.testing.assert_array_equal(p, 1.0)
    np.testing.assert_array_equal(r, 0.0)
    # and against an empty ground truth recall is undefined, precision 0 (nothing matches)
    p, r = surface_precision_recall(box(), Mesh.empty(), np.random.default_rng(0),
                                    SurfaceConfig(thresholds=tuple(THRESHOLDS)))
    np.testing.assert_array_equal(p, 0.0)
    assert np.isnan(r).all()


def test_samples_are_uniform_on_the_surface_and_seeded():
    # two rectangles of 1 m² and 3 m²
    m = Mesh(np.concatenate([plane((1, 1)).vertices, plane((3, 1), centre=(5, 0, 0)).vertices]),
             [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    points = sample_surface(m, 10_000, np.random.default_rng(7))
    assert len(points) == 40_000
    np.testing.assert_array_equal(points, sample_surface(m, 10_000, np.random.default_rng(7)))
    assert MeshDistance(m)(points).max() < 1e-5
    big = points[:, 0] > 2
    assert big.mean() == pytest.approx(0.75, abs=0.01)
    # uniform inside a rectangle: each quarter of the 1 m² square gets a quarter
    small = points[~big]
    quadrant = (small[:, 0] > 0.3) * 2 + (small[:, 2] > 4.0)
    np.testing.assert_allclose(np.bincount(quadrant) / len(small), 0.25, atol=0.02)
    # the count is floor(area × density), at least one sample when there is any area
    assert len(sample_surface(plane((0.01, 0.01)), 10_000, np.random.default_rng(0))) == 1
    assert len(sample_surface(Mesh.empty(), 10_000, np.random.default_rng(0))) == 0


def test_distance_to_a_square_is_exact():
    sq = plane((2.0, 2.0), centre=(0, 0, 0))  # y = 0, x and z in [-1, 1]
    points = np.array([[0, 0.3, 0], [2.0, 0, 0], [2.0, 1.0, 2.0], [0.5, -0.25, -0.5]])
    expected = [0.3, 1.0, np.sqrt(1 + 1 + 1), 0.25]
    np.testing.assert_allclose(MeshDistance(sq)(points), expected, atol=1e-6)
    assert np.isinf(MeshDistance(Mesh.empty())(points)).all()


def test_inlier_fraction_is_strict_and_takes_thresholds_in_any_order():
    d = np.array([0.01, 0.05, 0.2, np.inf])
    np.testing.assert_array_equal(inlier_fraction(d, [0.05, 0.01, 1.0, 0.06]), [0.25, 0.0, 0.75, 0.5])
    assert np.isnan(inlier_fraction([], [0.05])).all()
    p, r = precision_recall(np.zeros(0), np.zeros(0), [0.05])
    assert p[0] == 1.0 and np.isnan(r[0])


def test_variants_unite_parts_and_score_objects_and_envelope_apart():
    # ground truth: an object plane of 1 m² and an envelope plane of 3 m²
    obj = plane((1, 1), centre=(0, 0, 2))
    wall = plane((3, 1), centre=(0, 0, 6), normal_axis=2)
    gt = GroundTruthMesh(obj, wall)
    half_left = plane((0.5, 1), centre=(-0.25, 0, 2))
    half_right = plane((0.5, 1), centre=(0.25, 0, 2))
    parts = {"D1": half_left, "D2": half_right, "D3": Mesh.empty(), "D4": Mesh.empty(), "D5": wall,
             "overhead": Mesh.empty()}
    variants = (Variant("left", ("D1",)), Variant("halves", ("D1", "D2")),
                Variant("all", ("D1", "D2", "D5")), Variant("nothing", ("D3",)))
    s = score_parts(parts, gt, variants, np.random.default_rng(3), [0.001, 0.05], density=20_000)
    at1mm, at5cm = np.s_[:, :, 0], np.s_[:, :, 1]
    # recall against objects + envelope: left half of 1 m² among 4 m², both halves, all
    np.testing.assert_allclose(s.recall[at1mm][:, 0], [0.125, 0.25, 1.0, 0.0], atol=0.01)
    # against objects only: half, whole, whole, nothing
    np.testing.assert_allclose(s.recall[at1mm][:, 1], [0.5, 1.0, 1.0, 0.0], atol=0.01)
    # at 5 cm the left half also covers a 5 cm strip of the right half
    np.testing.assert_allclose(s.recall[at5cm][0], [0.55 / 4, 0.55], atol=0.01)
    # precision: every part lies on the ground truth, except the wall against objects only
    np.testing.assert_allclose(s.precision[at5cm][:, 0], [1.0, 1.0, 1.0, 1.0])
    np.testing.assert_allclose(s.precision[at5cm][:, 1], [1.0, 1.0, 0.25, 1.0], atol=0.01)


def test_coverage_of_ground_truth_layers_grows_with_the_layers(small_house):
    from sceneforge.cameras import look_at_camera
    from sceneforge.evaluate import EvalView, score_view
    from sceneforge.raytrace import HouseTracer
    from sceneforge.view import compute_view

    camera = look_at_camera((0.0, 1.5, -1.6), (0.0, -0.2, 1.0), width=160, height=120)
    gt = compute_view(small_house, camera, tracer=HouseTracer(small_house))
    scores = score_view(EvalView.from_ground_truth(gt), GroundTruthMesh.from_ground_truth(gt),
                        COVERAGE_VARIANTS, np.random.default_rng(0), SurfaceConfig(density=2_000))
    recall = scores.recall[:, 0, -1]  # against objects + envelope, at 5 cm
    assert (np.diff(recall) >= 0).all(), recall
    # the envelope layer adds the room: its ground truth is the D5 surface itself (docs/spec.md §5),
    # which D5 covers whole; what stays uncovered are object faces that no layer sees (the
    # object ground truth keeps every face of a visible object in front of D5)
    assert recall[3] < 0.5 and recall[4] > 0.98
    assert scores.recall[4, 1, -1] < scores.recall[4, 0, -1]
    # ground-truth layers lie on the ground-truth mesh
    assert (scores.precision[:5, 0, -1] > 0.97).all()
    # the same seed gives the same numbers
    again = score_view(EvalView.from_ground_truth(gt), GroundTruthMesh.from_ground_truth(gt),
                       COVERAGE_VARIANTS, np.random.default_rng(0), SurfaceConfig(density=2_000))
    np.testing.assert_array_equal(again.recall, scores.recall)
    np.testing.assert_array_equal(again.precision, scores.precision)


def test_the_overhead_mesh_is_cut_to_the_frontal_frustum(small_house):
    """The ground-truth mesh ends at the frustum's side and near planes (docs/spec.md §5), so the
    overhead map's mesh is cut there too: what lies outside can never be near the truth."""
    from dataclasses import replace

    from sceneforge.cameras import Camera, look_at_camera
    from sceneforge.evaluate import EvalView
    from sceneforge.evaluate.depth_mesh import OVERHEAD, height_map_mesh
    from sceneforge.frustum import frustum_planes
    from sceneforge.raytrace import HouseTracer
    from sceneforge.view import compute_view

    camera = look_at_camera((0.0, 1.5, -1.6), (0.0, -0.2, 1.0), width=160, height=120)
    view = EvalView.from_ground_truth(compute_view(small_house, camera, tracer=HouseTracer(small_house)))
    # a table top 0.5 m high over the whole square overhead map, wider than the view
    flat = replace(view, overhead_height=np.full_like(view.overhead_height, 0.5))
    whole = height_map_mesh(flat.overhead_height, flat.overhead_cam_to_world, flat.overhead_extent,
                            float(flat.overhead_params[2]))
    cut = flat.meshes()[OVERHEAD]
    planes = frustum_planes(Camera(view.K, view.cam_to_world, 160, 120))
    inside = lambda p: (p @ planes[:, :3].T + planes[:, 3] >= -1e-6).all(axis=1)  # noqa: E731
    assert inside(cut.vertices).all()
    # the cut keeps exactly the part of the map inside the frustum: its area is the
    # fraction of the map's area that a dense sample of the map finds inside
    points = sample_surface(whole, 20_000, np.random.default_rng(0))
    expected = whole.area * inside(points).mean()
    assert 0.05 * whole.area < expected < 0.95 * whole.area
    assert cut.area == pytest.approx(expected, rel=0.02)
