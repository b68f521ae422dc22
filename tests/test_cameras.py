"""Cameras: docs/spec.md §1 defaults, rays and projection, OpenCV/OpenGL, PBRS files, the sampler."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from sceneforge.camera_sampler import (
    REJECT_REASONS,
    SCORE_TERMS,
    CameraSamplerConfig,
    ViewStats,
    sample_cameras,
)
from sceneforge.cameras import (
    Camera,
    camera_from_pbrs,
    default_intrinsics,
    look_at_camera,
    opencv_to_opengl,
    read_pbrs_cameras,
    write_pbrs_cameras,
)
from sceneforge.conventions import NYU40_IDS, tol
from sceneforge.errors import HouseError, SceneforgeError
from sceneforge.houses import House, make_instance
from sceneforge.raytrace import HouseTracer

from .hard_houses import add_box_room, furnish, rug_room, three_room_house, two_level_house


def test_default_intrinsics_match_spec():
    K = default_intrinsics()
    assert K.shape == (3, 3) and K.dtype == np.float64
    assert K[0, 0] == pytest.approx(259.0, abs=0.05)
    assert K[1, 1] == K[0, 0]
    assert (K[0, 2], K[1, 2]) == (160.0, 120.0)
    camera = Camera(K, np.eye(4), 320, 240)
    assert camera.half_fov[0] == pytest.approx(0.5534, abs=1e-12)
    assert camera.half_fov[1] == pytest.approx(0.4339, abs=1e-4)


@pytest.mark.parametrize("yaw", [0.0, 1.0, 2.5, -2.0])
def test_default_pitch_is_11_31_degrees_down(yaw):
    config = CameraSamplerConfig()
    d = config.view_direction(yaw)
    assert np.linalg.norm(d) == pytest.approx(1.0)
    assert d[1] == pytest.approx(-0.196116, abs=1e-6)
    assert -d[1] / np.hypot(d[0], d[2]) == pytest.approx(0.2)
    assert math.degrees(config.pitch) == pytest.approx(11.31, abs=0.005)
    camera = look_at_camera((1, 1.5, 2), d)
    np.testing.assert_allclose(camera.view_direction, d)
    assert camera.cam_to_world[1, 0] == pytest.approx(0.0, abs=1e-12)  # no roll: x stays level
    assert camera.cam_to_world[1, 1] < 0  # image down points down


def test_rays_go_through_pixel_centres_in_row_major_order():
    camera = look_at_camera((0.3, 1.2, -0.7), (0.4, -0.2, 0.9), width=5, height=3)
    origins, directions, scale = camera.rays()
    assert origins.shape == directions.shape == (15, 3) and scale.shape == (15,)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0)
    np.testing.assert_allclose(origins, np.tile(camera.position, (15, 1)))
    t = np.linspace(0.5, 4.0, 15)
    uv, z = camera.project(origins + t[:, None] * directions)
    rows, cols = np.divmod(np.arange(15), 5)
    np.testing.assert_allclose(uv, np.stack([cols + 0.5, rows + 0.5], axis=1), atol=1e-9)
    np.testing.assert_allclose(z, t * scale)
    # the principal ray has scale 1; corner rays are longer than their planar depth
    assert scale.max() <= 1.0 and scale[7] == pytest.approx(1.0)


def test_project_axes_are_opencv():
    camera = look_at_camera((0, 0, 0), (0, 0, 1), width=320, height=240)  # world +Y up
    f = camera.K[0, 0]
    uv, z = camera.project([[0, 0, 5], [1, 1, 2]])
    np.testing.assert_allclose(uv[0], [160, 120])
    # up in the world is up in the image (smaller v); looking along +Z with +Y up, +X is on the left
    np.testing.assert_allclose(uv[1], [160 - 0.5 * f, 120 - 0.5 * f])
    np.testing.assert_allclose(z, [5, 2])


def test_opencv_to_opengl():
    camera = look_at_camera((1, 2, 3), (0.3, -0.2, 0.9))
    gl = opencv_to_opengl(camera.cam_to_world)
    np.testing.assert_allclose(-gl[:3, 2], camera.view_direction)  # OpenGL looks down -z
    np.testing.assert_allclose(gl[:3, 1], -camera.cam_to_world[:3, 1])  # y up
    np.testing.assert_allclose(gl[:3, 0], camera.cam_to_world[:3, 0])
    np.testing.assert_allclose(gl[:3, 3], [1, 2, 3])
    assert gl[1, 1] > 0
    np.testing.assert_allclose(opencv_to_opengl(gl), camera.cam_to_world)
    batch = np.stack([camera.cam_to_world, np.eye(4)])
    np.testing.assert_allclose(opencv_to_opengl(batch)[1], np.diag([1, -1, -1, 1]))


def test_cameras_and_store_validation_share_the_rotation_tolerance():
    # A pose a valid store holds must load as a Camera: both use conventions.tol.rotation.
    from sceneforge.store.validate import _rigid_problems

    def sheared(eps):
        pose = np.eye(4)
        pose[0, 1] = eps  # RᵀR is off the identity by eps
        return pose

    for eps, ok in ((0.1 * tol.rotation, True), (2 * tol.rotation, False), (5e-6, False)):
        assert not _rigid_problems(sheared(eps)[None])[0] == ok
        if ok:
            Camera(default_intrinsics(), sheared(eps), 320, 240)
        else:
            with pytest.raises(ValueError, match="orthonormal"):
                Camera(default_intrinsics(), sheared(eps), 320, 240)


def test_camera_checks_its_inputs():
    with pytest.raises(ValueError, match="orthonormal"):
        Camera(default_intrinsics(), np.diag([2.0, 1, 1, 1]), 320, 240)
    with pytest.raises(ValueError, match="K must be"):
        Camera(np.eye(2), np.eye(4), 320, 240)
    with pytest.raises(ValueError, match="parallel"):
        look_at_camera((0, 0, 0), (0, 2, 0))
    camera = Camera(default_intrinsics(), np.eye(4), 320, 240)
    with pytest.raises(ValueError):
        camera.K[0, 0] = 1.0  # frozen: arrays are read-only


def test_pbrs_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    config = CameraSamplerConfig()
    cameras = [
        look_at_camera(rng.uniform(-5, 5, 3), config.view_direction(rng.uniform(0, 2 * np.pi)))
        for _ in range(4)
    ]
    path = tmp_path / "room_camera.txt"
    write_pbrs_cameras(path, cameras, scores=[0.1, 0.2, 0.3, 0.4])
    lines = path.read_text().splitlines()
    assert len(lines) == 4 and all(len(line.split()) == 12 for line in lines)
    assert [float(line.split()[-1]) for line in lines] == [0.1, 0.2, 0.3, 0.4]
    back = read_pbrs_cameras(path)
    for a, b in zip(cameras, back):
        np.testing.assert_allclose(b.cam_to_world, a.cam_to_world, atol=1e-12)
        np.testing.assert_allclose(b.K, a.K, rtol=1e-12)
        assert (b.width, b.height) == (320, 240)


def test_pbrs_line_as_written_by_pbrs():
    line = "38.5 1.55 41.2  0 -0.196116 0.980581  0 0.980581 0.196116  0.5534 0.4339 0.83"
    camera = camera_from_pbrs(line)
    np.testing.assert_allclose(camera.position, [38.5, 1.55, 41.2])
    np.testing.assert_allclose(camera.view_direction, [0, -0.196116, 0.980581], atol=1e-6)
    np.testing.assert_allclose(camera.cam_to_world[:3, 1], [0, -0.980581, -0.196116], atol=1e-6)
    assert camera.K[0, 0] == pytest.approx(259.0, abs=0.05)
    assert camera.K[1, 1] == pytest.approx(259.0, abs=0.1)
    assert camera_from_pbrs(line, width=64, height=48).K[0, 0] == pytest.approx(259.0 / 5, abs=0.01)


def test_pbrs_errors_name_file_and_line(tmp_path):
    path = tmp_path / "cams.txt"
    path.write_text("# comment\n\n0 1 0 0 0 1 0 1 0 0.55 0.43 1\n0 1 0 0 0 1 0 1 0 0.55\n")
    with pytest.raises(SceneforgeError, match=r"cams.txt:4: expected 12 numbers"):
        read_pbrs_cameras(path)
    path.write_text("0 1 0 0 0 1 0 0 1 0.55 0.43 1\n")
    with pytest.raises(SceneforgeError, match=r"cams.txt:1: .*parallel"):
        read_pbrs_cameras(path)
    path.write_text("0 1 0 0 0 1 0 1 0 0.55 two 1\n")
    with pytest.raises(SceneforgeError, match=r"cams.txt:1: not a list of numbers"):
        read_pbrs_cameras(path)
    with pytest.raises(SceneforgeError, match="cannot read camera file"):
        read_pbrs_cameras(tmp_path / "missing.txt")
    off_centre = Camera(np.array([[200.0, 0, 100], [0, 200, 120], [0, 0, 1]]), np.eye(4), 320, 240)
    with pytest.raises(ValueError, match="principal point"):
        write_pbrs_cameras(tmp_path / "x.txt", [off_centre])


# ---------------------------------------------------------------------------------------
# Sampler


def add_box(house: House, name: str, category: int, lo, hi):
    b = trimesh.creation.box(bounds=[lo, hi])
    return make_instance(house, name=name, category=category, label=name, room_id="r0",
                         vertices=b.vertices, faces=b.faces)


BOXES = [
    ((1.0, 0.0, 1.0), (2.0, 0.8, 2.0)), ((4.0, 0.0, 3.0), (5.5, 1.8, 3.6)), ((2.5, 0.0, 0.0), (3.5, 2.0, 0.5))
]
ROOM = (6.0, 3.0, 4.0)


def box_room(open_top: bool = False) -> House:
    """Interior 6 × 3 × 4 m (x, y, z from 0) with three pieces of furniture; ``open_top``:
    no ceiling and 1.7 m walls, so that the top of every view escapes."""
    X, Y, Z = ROOM
    if open_top:
        Y = 1.7
    h = House(id="room", instances=[])
    add_box(h, "floor", NYU40_IDS["floor"], (-0.1, -0.1, -0.1), (X + 0.1, 0, Z + 0.1))
    if not open_top:
        add_box(h, "ceiling", NYU40_IDS["ceiling"], (-0.1, Y, -0.1), (X + 0.1, Y + 0.1, Z + 0.1))
    for lo, hi in [((-0.1, 0, 0), (0, Y, Z)), ((X, 0, 0), (X + 0.1, Y, Z)),
                   ((0, 0, -0.1), (X, Y, 0)), ((0, 0, Z), (X, Y, Z + 0.1))]:
        add_box(h, "wall", NYU40_IDS["wall"], lo, hi)
    for k, (lo, hi) in enumerate(BOXES):
        add_box(h, f"cabinet{k}", NYU40_IDS["cabinet"], lo, hi)
    return h


def distance_to_box(p, lo, hi) -> float:
    return float(np.linalg.norm(np.maximum(np.maximum(np.asarray(lo) - p, 0), p - np.asarray(hi))))


SMALL = CameraSamplerConfig(width=64, height=48, check_width=32, check_height=24)


def test_sampler_is_deterministic_and_its_cameras_pass_the_checks():
    house = box_room()
    tracer = HouseTracer(house)
    cameras, report = sample_cameras(house, 5, np.random.default_rng(11), SMALL, tracer)
    again, report_again = sample_cameras(house, 5, np.random.default_rng(11), SMALL, tracer)
    assert len(cameras) == 5 and report.accepted == 5 and report == report_again
    assert report.candidates == report.accepted + sum(report.rejected.values())
    for a, b in zip(cameras, again):
        np.testing.assert_array_equal(a.cam_to_world, b.cam_to_world)
    other, _ = sample_cameras(house, 5, np.random.default_rng(12), SMALL, tracer)
    assert not np.array_equal(other[0].cam_to_world, cameras[0].cam_to_world)

    envelope = np.array([i.envelope for i in house.instances])
    for camera in cameras:
        p = camera.position
        assert p[1] == pytest.approx(SMALL.eye_height)
        assert camera.view_direction[1] == pytest.approx(-0.196116, abs=1e-6)
        assert (camera.width, camera.height) == (64, 48)
        # inside the room, away from walls, floor, ceiling and furniture (analytic distances)
        assert all(0 < p[i] < ROOM[i] for i in range(3))
        nearest = min([p[0], ROOM[0] - p[0], p[1], ROOM[1] - p[1], p[2], ROOM[2] - p[2]]
                      + [distance_to_box(p, lo, hi) for lo, hi in BOXES])
        assert nearest >= SMALL.min_surface_distance - 1e-5
        assert not any(np.all((np.array(lo) <= p) & (p <= np.array(hi))) for lo, hi in BOXES)
        origins, directions, _ = camera.resized(SMALL.check_width, SMALL.check_height).rays()
        first = tracer.first_hit(origins, directions)
        assert first.hit.all()  # a closed room: nothing escapes
        assert (~envelope[first.instance]).mean() >= SMALL.min_object_fraction


def test_sampler_counts_rejections_per_reason():
    house = box_room()
    far = CameraSamplerConfig(width=64, height=48, min_surface_distance=5.0, candidates_per_camera=10)
    cameras, report = sample_cameras(house, 2, np.random.default_rng(0), far)
    assert cameras == [] and report.candidates == 20
    assert report.rejected["too_close"] + report.rejected["not_above_floor"] == 20
    assert report.rejected["too_close"] > 0

    crowded = CameraSamplerConfig(width=64, height=48, min_object_fraction=0.99, candidates_per_camera=10)
    _, report = sample_cameras(house, 1, np.random.default_rng(0), crowded)
    assert report.rejected["few_objects"] > 0 and report.accepted == 0

    _, report = sample_cameras(box_room(open_top=True), 1, np.random.default_rng(0), SMALL)
    assert report.rejected["escapes"] > 0
    assert set(report.rejected) == set(REJECT_REASONS)


def test_sampler_stands_on_free_floor_only():
    """Cameras never stand above furniture, even when it is low enough not to be too close."""
    house = box_room()
    cameras, report = sample_cameras(house, 8, np.random.default_rng(5), SMALL)
    assert report.rejected["not_above_floor"] > 0
    for camera in cameras:
        x, _, z = camera.position
        assert not any(lo[0] <= x <= hi[0] and lo[2] <= z <= hi[2] for lo, hi in BOXES)


def test_sampler_needs_a_floor_and_a_generator():
    house = House(id="nofloor", instances=[])
    add_box(house, "wall", NYU40_IDS["wall"], (0, 0, 0), (1, 3, 0.1))
    with pytest.raises(HouseError, match="nofloor.*no horizontal floor"):
        sample_cameras(house, 1, np.random.default_rng(0))
    with pytest.raises(TypeError, match="numpy.random.Generator"):
        sample_cameras(box_room(), 1, 0)
    with pytest.raises(ValueError, match="max_escape_fraction"):
        CameraSamplerConfig(max_escape_fraction=1.5)


# ---------------------------------------------------------------------------------------
# Sampler on the hard cases of real houses (tests/hard_houses.py)

FAST = CameraSamplerConfig(width=64, height=48, check_width=40, check_height=30)


def views_of(house, cameras, tracer):
    from sceneforge.layers import frontal_layers
    from sceneforge.overhead import OverheadConfig, overhead_camera

    for camera in cameras:
        layers = frontal_layers(house, camera, tracer)
        yield layers, overhead_camera(house, camera, layers, OverheadConfig(resolution=32))


def test_a_room_sized_rug_gets_every_camera_and_the_true_floor_in_every_view():
    # 90 % of the floor is under a 1 cm rug: the first surface below most candidates.
    house = rug_room()
    tracer = HouseTracer(house)
    cameras, report = sample_cameras(house, 6, np.random.default_rng(0), FAST, tracer)
    assert len(cameras) == report.accepted == 6
    on_rug, hidden = 0, 0
    for camera, (layers, over) in zip(cameras, views_of(house, cameras, tracer)):
        assert camera.position[1] == 1.5  # over the floor top (y = 0), not the rug top
        on_rug += camera.position[2] < 2.0
        # The floor's top surface, exactly: not the rug's top, not the level's slab bottom
        # (-0.1), with or without floor pixels in view.
        assert (over.floor_y, over.floor_source) == (0.0, "room floor")
        assert over.params[2] == over.cam_to_world[1, 3]
        hidden += not (layers.envelope_category == NYU40_IDS["floor"]).any()
    assert on_rug >= 4 and hidden >= 1


def test_a_rug_on_the_floor_is_stood_on_but_not_one_on_furniture_or_too_thick():
    house = rug_room()
    stand = np.array([[0.0, 1.5, 1.0]])  # over the rug, 1.5 m above the floor
    cameras, report = sample_cameras(house, 2, np.random.default_rng(1), FAST)
    assert report.accepted == 2
    thick = rug_room(thickness=tol.floor_cover + 0.02)
    cameras, report = sample_cameras(thick, 2, np.random.default_rng(1), FAST)
    # only the bare 0.5 m strip is left to stand on
    assert all(c.position[2] > 2.0 for c in cameras)
    assert report.rejected["not_above_floor"] > 0
    first = HouseTracer(house).first_hit(stand, np.array([[0.0, -1.0, 0.0]]))
    assert house.instances[first.instance[0]].label == "rug"


def test_a_two_level_house_gets_cameras_on_both_levels_each_with_its_own_floor():
    house = two_level_house()
    tracer = HouseTracer(house)
    cameras, report = sample_cameras(house, 4, np.random.default_rng(0), FAST, tracer)
    assert [(r.room, r.level, r.share, r.accepted) for r in report.rooms] == [("r0", 0, 2, 2), ("r1", 1, 2, 2)]
    assert [v.level for v in report.views] == [0, 0, 1, 1]
    for camera, view, (_, over) in zip(cameras, report.views, views_of(house, cameras, tracer)):
        floor = 3.0 if view.level == 1 else 0.0
        assert camera.position[1] == floor + 1.5
        assert (over.floor_y, over.floor_source) == (floor, "room floor")


def test_a_house_without_rooms_is_sampled_level_by_level():
    # As glTF/OBJ scenes come: no room records, no room ids; the floors' heights say their level.
    house = two_level_house()
    house.rooms = []
    for inst in house.instances:
        inst.room_id = None
    cameras, report = sample_cameras(house, 4, np.random.default_rng(0), FAST)
    assert [(r.room, r.level, r.share, r.accepted) for r in report.rooms] == [(None, 0, 2, 2), (None, 1, 2, 2)]
    assert sorted(c.position[1] for c in cameras) == [1.5, 1.5, 4.5, 4.5]


@pytest.mark.parametrize("per_room", [1, 2])
def test_cameras_are_spread_over_the_rooms(per_room):
    house = three_room_house()
    cameras, report = sample_cameras(house, 3 * per_room, np.random.default_rng(4), FAST)
    assert [(r.room, r.share, r.accepted) for r in report.rooms] == [(f"r{k}", per_room, per_room) for k in range(3)]
    for k in range(3):  # room k spans x in 5.2 k ± 2.5
        inside = [c for c in cameras if abs(c.position[0] - 5.2 * k) < 2.5]
        assert len(inside) == per_room
        assert [v.room for v in report.views].count(f"r{k}") == per_room


def test_the_remainder_goes_to_the_largest_floors_and_a_room_without_floor_is_skipped():
    house = three_room_house()
    for inst in house.instances:  # r1 loses its floor; r2 gets a larger one
        if inst.name == "r1_floor":
            inst.category = NYU40_IDS["otherprop"]
        if inst.name == "r2_floor":
            inst.vertices = inst.vertices * [1.01, 1.0, 1.0] + [-0.1, 0.0, 0.0]
    house.rooms.append(type(house.rooms[0])("r9", "closet", 0))
    cameras, report = sample_cameras(house, 3, np.random.default_rng(0), FAST)
    assert report.skipped == {"r1": "no floor instance", "r9": "no floor instance"}
    assert [(r.room, r.share) for r in report.rooms] == [("r0", 1), ("r2", 2)]
    assert report.accepted == 3


def test_views_of_mostly_void_or_mostly_envelope_are_rejected_with_their_reason():
    # Walls the name map did not recognise (void, like a glTF "room_skeleton").
    void = House(id="void", instances=[])
    add_box_room(void, "r0", wall_category=0)
    furnish(void, "r0")
    _, report = sample_cameras(void, 2, np.random.default_rng(0), FAST)
    assert report.rejected["mostly_void"] > 0 and report.accepted < 2
    loose = CameraSamplerConfig(width=64, height=48, check_width=40, check_height=30, max_void_fraction=1.0,
                                min_object_fraction=0.0)
    _, report = sample_cameras(void, 2, np.random.default_rng(0), loose)
    assert report.rejected["mostly_void"] == 0 and report.accepted == 2
    # An empty room: every view sees only envelope.
    empty = House(id="empty", instances=[])
    add_box_room(empty, "r0")
    cameras, report = sample_cameras(empty, 2, np.random.default_rng(0), FAST)
    assert cameras == [] and report.rejected["mostly_envelope"] > 0
    assert report.rejected["few_objects"] == 0 and report.rejected["mostly_void"] == 0


def test_the_best_scoring_valid_candidate_is_kept():
    # With pool_per_camera = 1 the first valid candidates are kept, in score order; with a
    # pool of 4 for one camera, the same random stream gives those same 4 candidates, and
    # the best of them is kept.
    house = rug_room()
    tracer = HouseTracer(house)
    first = replace(FAST, pool_per_camera=1, min_separation=0.0)
    four, report4 = sample_cameras(house, 4, np.random.default_rng(3), first, tracer)
    assert report4.rejected["outscored"] == 0
    scores = [v.score for v in report4.views]
    assert scores == sorted(scores, reverse=True) and scores[0] > scores[-1]
    best, report = sample_cameras(house, 1, np.random.default_rng(3), replace(first, pool_per_camera=4), tracer)
    np.testing.assert_array_equal(best[0].cam_to_world, four[0].cam_to_world)
    assert report.rejected["outscored"] == 3 and report.views[0].score == scores[0]
    assert report.views[0].score == pytest.approx(FAST.score(report.views[0].stats))


def test_kept_cameras_of_a_room_stand_apart_while_candidates_allow():
    house = rug_room()
    cameras, _ = sample_cameras(house, 3, np.random.default_rng(0), replace(FAST, min_separation=1.0))
    positions = np.array([c.position for c in cameras])
    gaps = np.linalg.norm(positions[:, None] - positions[None], axis=-1)[np.triu_indices(3, 1)]
    assert gaps.min() >= 1.0


def test_sampling_is_deterministic_and_the_report_is_json():
    house = three_room_house()
    tracer = HouseTracer(house)
    a, ra = sample_cameras(house, 6, np.random.default_rng(21), FAST, tracer)
    b, rb = sample_cameras(house, 6, np.random.default_rng(21), FAST, HouseTracer(house))
    assert [c.cam_to_world.tolist() for c in a] == [c.cam_to_world.tolist() for c in b]
    assert ra == rb and ra.to_dict() == rb.to_dict()
    c, _ = sample_cameras(house, 6, np.random.default_rng(22), FAST, tracer)
    assert [x.cam_to_world.tolist() for x in a] != [x.cam_to_world.tolist() for x in c]
    d = json.loads(json.dumps(ra.to_dict()))
    assert d["accepted"] == 6 and d["candidates"] == ra.candidates == ra.accepted + sum(ra.rejected.values())
    assert set(d["rejected"]) == set(REJECT_REASONS)
    assert [r["room"] for r in d["rooms"]] == ["r0", "r1", "r2"]
    assert len(d["views"]) == 6
    for view in d["views"]:
        assert set(view) == {"room", "level", "score", *SCORE_TERMS, "escape_fraction", "envelope_fraction",
                             "void_fraction", "object_fraction"}
        assert view["objects"] >= 1 and 0 < view["envelope_distance"] < 8


def test_view_stats_of_hand_made_layers():
    from sceneforge.layers import Layers

    nan = np.nan
    depth = np.full((5, 2, 3), nan, dtype=np.float32)
    # pixels: object 3 (labelled), object 4 (labelled), void object 5, envelope, envelope, nothing
    depth[0] = [[1, 1, 1], [nan, nan, nan]]
    depth[2] = [[2, nan, nan], [nan, nan, nan]]
    depth[4] = [[3, 3, 4], [5, 6, nan]]
    category = np.zeros((3, 2, 3), dtype=np.uint8)
    category[0] = [[5, 7, 0], [0, 0, 0]]
    instance = np.full((2, 2, 3), -1, dtype=np.int32)
    instance[0] = [[3, 4, 5], [-1, -1, -1]]
    stats = ViewStats.of(Layers(depth, category, instance, np.zeros((3, 2, 3), np.float32)))
    assert stats == ViewStats(objects=2, d3_fraction=1 / 6, envelope_distance=4.0, escape_fraction=1 / 6,
                              envelope_fraction=2 / 6, void_fraction=1 / 6, object_fraction=2 / 6)
    config = CameraSamplerConfig(score_weights=(1.0, 2.0, 0.5), score_saturation=(4.0, 0.1, 2.0))
    assert config.score(stats) == pytest.approx(2 / 4 + 2 * 1.0 + 0.5 * 1.0)


def test_sampler_config_checks_its_new_fields():
    with pytest.raises(ValueError, match="max_void_fraction"):
        CameraSamplerConfig(max_void_fraction=-0.1)
    with pytest.raises(ValueError, match="pool_per_camera"):
        CameraSamplerConfig(pool_per_camera=0)
    with pytest.raises(ValueError, match="score_weights"):
        CameraSamplerConfig(score_weights=(1.0, 1.0))
    with pytest.raises(ValueError, match="score_saturation"):
        CameraSamplerConfig(score_saturation=(1.0, 0.0, 1.0))


def test_the_plan_record_keeps_the_sampler_report_and_matches_the_store_schema(tmp_path):
    import jsonschema

    from sceneforge import schemas
    from sceneforge.config import DatasetConfig
    from sceneforge.houses import discover
    from sceneforge.houses.formats.native import write_house
    from sceneforge.pipeline import plan_house

    write_house(three_room_house(), tmp_path / "three_rooms")
    (source,) = discover(tmp_path / "three_rooms")
    config = DatasetConfig(width=64, height=48, views_per_house=3,
                           sampler=CameraSamplerConfig(check_width=40, check_height=30))
    record = plan_house(source, config)
    assert "failure" not in record and len(record["cam_to_world"]) == 3
    info = record["cameras"]
    assert info["source"] == "sampled" and info["accepted"] == 3
    assert [(r["room"], r["accepted"]) for r in info["rooms"]] == [("r0", 1), ("r1", 1), ("r2", 1)]
    assert len(info["views"]) == 3 and all(v["objects"] >= 1 for v in info["views"])
    house_schema = {**schemas.load("store")["$defs"]["house"], "$defs": schemas.load("store")["$defs"]}
    jsonschema.validate({**{k: record[k] for k in ("id", "format", "path", "cameras")}, "status": "ok",
                         "views": [0, 3]}, house_schema)
