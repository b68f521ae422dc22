"""Cameras: SPEC §1 defaults, rays and projection, OpenCV/OpenGL, PBRS files, the sampler."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from sceneforge.cameras import (
    REJECT_REASONS,
    Camera,
    CameraSamplerConfig,
    camera_from_pbrs,
    default_intrinsics,
    look_at_camera,
    opencv_to_opengl,
    read_pbrs_cameras,
    sample_cameras,
    write_pbrs_cameras,
)
from sceneforge.conventions import NYU40_IDS, tol
from sceneforge.errors import HouseError, SceneforgeError
from sceneforge.houses import House, make_instance
from sceneforge.raytrace import HouseTracer


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
    from sceneforge.store import _rigid_problems

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
