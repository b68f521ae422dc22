"""The overhead camera (docs/spec.md §6) and overhead ground truth (docs/spec.md §7).

Expected boxes are worked out by hand from the formulas of docs/spec.md §6 in the comments.
"""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner
from sceneforge.cli.main import cli

from sceneforge.camera_sampler import CameraSamplerConfig, sample_cameras
from sceneforge.cameras import look_at_camera
from sceneforge.conventions import ENVELOPE_LAYER, FRONT_LAYERS, OBJECT_SEGMENTS, in_classes, tol
from sceneforge.errors import SceneforgeError
from sceneforge.houses import BUNDLED_TOY, discover, load
from sceneforge.houses.formats.native import write_house
from sceneforge.layers import Layers, frontal_layers
from sceneforge.overhead import (
    Box,
    Candidate,
    FrontalPoints,
    GravityFrame,
    OverheadCamera,
    OverheadConfig,
    frontal_points_fast,
    gravity_frame,
    level_floor_y,
    overhead_camera,
    overhead_truth,
    place_overhead_camera,
)
from sceneforge.overhead.heuristics import (
    combine,
    depth_statistics_box,
    envelope_frustum_box,
    majority_room_box,
)
from sceneforge.overhead.points import _frame_rays
from sceneforge.raytrace import HouseTracer

from .conftest import box_instance, box_room
from .hard_houses import rug_room, two_level_house

CONFIG = OverheadConfig()


def frame_looking_down_minus_z(height=1.5):
    """Camera at (0, height, 0) looking along −Z: right = +X, forward = −Z."""
    return GravityFrame(origin=np.array([0.0, height, 0.0]), right=np.array([1.0, 0.0, 0.0]),
                        forward=np.array([0.0, 0.0, -1.0]), theta=1.3734)


def points_at(*groups):
    """(n, 3) frame points ``(right, up, forward)`` from (count, right, forward) groups."""
    return np.concatenate([np.tile([r, 0.0, f], (n, 1)) for n, r, f in groups])


def hand_view():
    """20 points at (right 0, forward 3), 20 at (2, 7), all in room r0; 10 D5 points at z = 5."""
    objects = points_at((20, 0.0, 3.0), (20, 2.0, 7.0))
    return FrontalPoints(
        objects=objects,
        object_room=np.zeros(40, dtype=np.int32),
        object_excluded=np.zeros(40, dtype=bool),
        envelope_z=np.full(10, 5.0),
        room_votes=np.array([30]),
        room_ids=("r0",),
        top=1.2,
    )


def test_overhead_camera_of_hand_made_points_is_the_hand_computed_weighted_box():
    cam = place_overhead_camera(frame_looking_down_minus_z(), hand_view(), tan_half_fov=0.5,
                                floor_y=0.0)
    # 1. depth statistics: mean (1, 5), std (1, 2) → half (1.5, 3):
    #    right [-0.5, 2.5], forward [2, 8]
    # 2. envelope: d = 0.8 × 5 = 4, half = 0.9 × 0.5 × 4 = 1.8 around (0, 4):
    #    right [-1.8, 1.8], forward [2.2, 5.8]
    # 3. room r0: bbox right [0, 2], forward [3, 7]; half (1, 2) × 1.05 around (1, 5):
    #    right [-0.05, 2.05], forward [2.9, 7.1]
    boxes = {c.name: c for c in cam.candidates}
    np.testing.assert_allclose(boxes["depth_statistics"].box.lo, [-0.5, 2.0])
    np.testing.assert_allclose(boxes["depth_statistics"].box.hi, [2.5, 8.0])
    np.testing.assert_allclose(boxes["envelope_frustum"].box.lo, [-1.8, 2.2])
    np.testing.assert_allclose(boxes["envelope_frustum"].box.hi, [1.8, 5.8])
    np.testing.assert_allclose(boxes["majority_room"].box.lo, [-0.05, 2.9])
    np.testing.assert_allclose(boxes["majority_room"].box.hi, [2.05, 7.1])
    assert [c.weight for c in cam.candidates] == [1.0, 1.0, 2.0]
    assert all(c.reason is None for c in cam.candidates)
    # Weighted (1, 1, 2): right (-0.5 - 1.8 - 0.1)/4 = -0.6 .. (2.5 + 1.8 + 4.1)/4 = 2.1,
    # forward (2 + 2.2 + 5.8)/4 = 2.5 .. (8 + 5.8 + 14.2)/4 = 7. Centre (0.75, 4.75),
    # half sizes (1.35, 2.25) → square of half-size 2.25.
    np.testing.assert_allclose(cam.box.lo, [0.75 - 2.25, 2.5])
    np.testing.assert_allclose(cam.box.hi, [0.75 + 2.25, 7.0])
    assert cam.half_extent == pytest.approx(2.25)
    # Height: camera y 1.5 + top 1.2 - 0.05 = 2.65 above a floor at 0.
    tx, ty, tz, theta, sigma = cam.params
    assert (tx, ty, tz) == pytest.approx((0.75, 4.75, 2.65))
    assert theta == pytest.approx(1.3734)
    assert sigma == pytest.approx(2.25 * np.sqrt(2))
    np.testing.assert_allclose(cam.cam_to_world[:3, 3], [0.75, 2.65, -4.75])
    # OpenCV axes: x = right, y (image down) = −forward = +Z, z = straight down.
    np.testing.assert_allclose(cam.cam_to_world[:3, :3], [[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    assert np.linalg.det(cam.cam_to_world[:3, :3]) == pytest.approx(1.0)


def test_overhead_camera_rays_are_parallel_through_pixel_centres():
    cam = place_overhead_camera(frame_looking_down_minus_z(), hand_view(), tan_half_fov=0.5,
                                floor_y=0.0, config=OverheadConfig(resolution=4))
    origins, directions, scale = cam.rays()
    assert origins.shape == (16, 3) and directions.shape == (16, 3) and scale.shape == (16,)
    assert origins.dtype == directions.dtype == scale.dtype == np.float64
    np.testing.assert_array_equal(directions, np.tile([0.0, -1.0, 0.0], (16, 1)))
    np.testing.assert_array_equal(scale, 1.0)
    # Pixel (row 0, col 0) is the far-left corner: half a pixel (2 × 2.25 / 4 / 2) in from
    # the square's right = -1.5 and forward = 7 edges; forward = -Z in the world.
    pix = 2 * 2.25 / 4
    np.testing.assert_allclose(origins[0], [-1.5 + pix / 2, 2.65, -(7.0 - pix / 2)])
    # Row-major: pixel 1 is one step right, pixel 4 one step back towards the camera.
    np.testing.assert_allclose(origins[1] - origins[0], [pix, 0, 0])
    np.testing.assert_allclose(origins[4] - origins[0], [0, 0, pix])
    uv, z = cam.project(origins - [0.0, 1.0, 0.0])
    np.testing.assert_allclose(uv[[0, 1, 4]], [[0.5, 0.5], [1.5, 0.5], [0.5, 1.5]])
    np.testing.assert_allclose(z, 1.0)


def test_depth_statistics_needs_40_points():
    few = depth_statistics_box(points_at((39, 0.0, 3.0)), CONFIG)
    assert few.box is None and few.weight == 0 and "39" in few.reason
    enough = depth_statistics_box(points_at((40, 0.0, 3.0)), CONFIG)
    assert enough.box is not None and enough.reason is None


def test_depth_statistics_half_size_is_at_least_half_a_metre_and_centre_within_9m():
    # All points at one spot: std 0 → half-size 0.5; at forward 12 the centre moves to 9.
    c = depth_statistics_box(points_at((40, 0.0, 12.0)), CONFIG)
    np.testing.assert_allclose(c.box.lo, [-0.5, 8.5])
    np.testing.assert_allclose(c.box.hi, [0.5, 9.5])


def test_envelope_box_distance_rules():
    # Fewer than 10 D5 points: d = 4 whatever their depth; half = 0.9 × 1 × 4 = 3.6.
    c = envelope_frustum_box(np.full(9, 100.0), 1.0, CONFIG)
    np.testing.assert_allclose(c.box.lo, [-3.6, 0.4])
    np.testing.assert_allclose(c.box.hi, [3.6, 7.6])
    # 0.8 × 20 = 16 → clamped to 7; 0.8 × 0.5 = 0.4 → clamped to 1.
    far = envelope_frustum_box(np.full(10, 20.0), 1.0, CONFIG)
    near = envelope_frustum_box(np.full(10, 0.5), 1.0, CONFIG)
    assert far.box.center[1] == pytest.approx(7.0)
    assert near.box.center[1] == pytest.approx(1.0)
    assert near.box.half_size == pytest.approx([0.9, 0.9])


def test_candidates_under_half_a_square_metre_get_weight_zero():
    # tan = 0.05, d = 4: half = 0.18, area 0.36² = 0.1296 m² < 0.5.
    small = envelope_frustum_box(np.full(10, 5.0), 0.05, CONFIG)
    stats = depth_statistics_box(points_at((20, 0.0, 3.0), (20, 2.0, 7.0)), CONFIG)
    missing = Candidate("majority_room", None, 0.0, "no votes")
    weighted, box = combine((stats, small, missing), CONFIG)
    assert [c.weight for c in weighted] == [1.0, 0.0, 0.0]
    assert "0.130 m²" in weighted[1].reason
    np.testing.assert_allclose(box.lo, stats.box.lo)
    np.testing.assert_allclose(box.hi, stats.box.hi)


def test_no_usable_candidate_is_an_error():
    small = envelope_frustum_box(np.full(10, 5.0), 0.05, CONFIG)
    none = Candidate("x", None, 0.0, "too few")
    with pytest.raises(SceneforgeError, match="no overhead box candidate"):
        combine((none, small, none), CONFIG)


def room_inputs(votes, rooms, excluded=None, groups=((20, 0.0, 3.0),)):
    """majority_room_box's inputs from the room name of each voting pixel and of each point
    (None: no room), coded as frontal_points_fast codes them: indices into the sorted names."""
    objects = points_at(*groups)
    room_ids = tuple(sorted({r for r in [*votes, *rooms] if r is not None}))
    code = {r: k for k, r in enumerate(room_ids)}
    return dict(
        objects=objects,
        object_room=np.array([code.get(r, -1) for r in rooms], dtype=np.int32),
        object_excluded=np.zeros(len(objects), bool) if excluded is None else np.array(excluded),
        room_votes=np.array([votes.count(r) for r in room_ids], dtype=np.int64),
        room_ids=room_ids,
    )


def test_majority_room_needs_20_votes_and_15_points():
    rooms = ["r0"] * 20
    few_votes = majority_room_box(**room_inputs(["r0"] * 19 + [None] * 50, rooms), config=CONFIG)
    assert few_votes.box is None and "19 room votes" in few_votes.reason
    ok = majority_room_box(**room_inputs(["r0"] * 20, rooms), config=CONFIG)
    assert ok.box is not None
    # 6 of the 20 points are of an excluded class: 14 < 15.
    excluded = [True] * 6 + [False] * 14
    few_points = majority_room_box(**room_inputs(["r0"] * 20, rooms, excluded), config=CONFIG)
    assert few_points.box is None and "14 points" in few_points.reason


def test_majority_room_uses_only_the_winning_room_and_the_distance_band():
    # r1 wins 15 votes to 10; its points are at forward 3 and 4 (right 0 and 1); r0's
    # points and r1's points closer than 1.5 m or further than 9 m do not count.
    groups = ((10, 0.0, 3.0), (10, 1.0, 4.0), (10, 5.0, 5.0), (5, 0.0, 1.0), (5, 0.0, 9.5))
    rooms = ["r1"] * 20 + ["r0"] * 10 + ["r1"] * 10
    c = majority_room_box(**room_inputs(["r1"] * 15 + ["r0"] * 10, rooms, groups=groups),
                          config=CONFIG)
    assert c.n_points == 20
    # bbox right [0, 1], forward [3, 4]; half 0.5 × 1.05 = 0.525 around (0.5, 3.5).
    np.testing.assert_allclose(c.box.lo, [0.5 - 0.525, 3.5 - 0.525])
    np.testing.assert_allclose(c.box.hi, [0.5 + 0.525, 3.5 + 0.525])


def test_majority_room_ties_go_to_the_smallest_room_id():
    # 20 votes each for "r2" and "r10": "r10" < "r2" as strings, so r10's points are boxed.
    groups = ((20, 0.0, 3.0), (20, 4.0, 6.0))
    rooms = ["r10"] * 20 + ["r2"] * 20
    c = majority_room_box(**room_inputs(["r2"] * 20 + ["r10"] * 20 + [None] * 5, rooms,
                                        groups=groups), config=CONFIG)
    assert c.n_points == 20
    np.testing.assert_allclose(c.box.center, [0.0, 3.0])
    # One more vote for r2 and it wins.
    c = majority_room_box(**room_inputs(["r2"] * 21 + ["r10"] * 20, rooms, groups=groups),
                          config=CONFIG)
    np.testing.assert_allclose(c.box.center, [4.0, 6.0])


def test_box_square_pads_the_short_side():
    sq = Box(np.array([0.0, 1.0]), np.array([4.0, 2.0])).square()
    np.testing.assert_allclose(sq.lo, [0.0, -0.5])
    np.testing.assert_allclose(sq.hi, [4.0, 3.5])


# ------------------------------------------------------------ with a house and a tracer

DOWN_PITCH = (0.0, -0.2, -1.0)  # PBRS pitch: tan = 0.2, looking along −Z


def test_theta_of_the_default_pitch():
    frame = gravity_frame(look_at_camera((0, 1.5, 0), DOWN_PITCH))
    assert frame.theta == pytest.approx(1.3734, abs=5e-5)
    np.testing.assert_allclose(frame.forward, [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(frame.right, [1, 0, 0], atol=1e-12)


def test_gravity_frame_right_is_the_camera_x_axis_for_any_yaw():
    cam = look_at_camera((1, 1.5, 2), (np.sin(0.7), -0.2, np.cos(0.7)))
    frame = gravity_frame(cam)
    np.testing.assert_allclose(frame.right, cam.cam_to_world[:3, 0], atol=1e-12)
    np.testing.assert_allclose(frame.forward, [np.sin(0.7), 0, np.cos(0.7)], atol=1e-12)
    p = np.array([[3.0, 0.5, -1.0]])
    np.testing.assert_allclose(frame.to_world(frame.to_frame(p)), p)


def test_camera_looking_straight_down_has_no_gravity_frame():
    with pytest.raises(SceneforgeError, match="straight up or down"):
        gravity_frame(look_at_camera((0, 1.5, 0), (0, -1, 0), up=(0, 0, -1)))


def room_with_a_box():
    """6 × 2.5 × 6 m room around the origin; a 1 × 0.8 × 1 m box at (0, 0.4, -1.5), a
    chandelier-labelled lamp hanging over it. Floor top at y = 0."""
    h = box_room("box_room", size=6.0, height=2.5, room_type="living")
    box_instance(h, "box", 29, (1.0, 0.8, 1.0), (0, 0.4, -1.5))
    box_instance(h, "lamp", 35, (0.2, 0.1, 0.2), (0.0, 1.3, -1.5), label="chandelier")
    return h


def test_box_height_map_is_its_height_above_the_floor_and_nan_on_bare_floor():
    house = room_with_a_box()
    tracer = HouseTracer(house)
    camera = look_at_camera((0, 1.5, 2.0), DOWN_PITCH, width=80, height=60)
    layers = frontal_layers(house, camera, tracer)
    over = overhead_camera(house, camera, layers, OverheadConfig(resolution=64))
    # The floor seen in the frontal D5 (float32 depths) is the floor top, y = 0.
    assert over.floor_y == pytest.approx(0.0, abs=1e-5)
    assert over.params[2] == pytest.approx(over.cam_to_world[1, 3] - over.floor_y)
    truth = overhead_truth(house, over, tracer, OverheadConfig(resolution=64))
    assert truth.height.shape == (64, 64) and truth.height.dtype == np.float32

    origins, _, _ = over.rays()
    x, z = origins[:, 0].reshape(64, 64), origins[:, 2].reshape(64, 64)
    pixel = 2 * over.half_extent / 64
    on_box = (np.abs(x) < 0.5 - pixel) & (np.abs(z + 1.5) < 0.5 - pixel)
    in_room = (np.abs(x) < 3 - pixel) & (np.abs(z) < 3 - pixel)
    bare = in_room & ~((np.abs(x) < 0.5 + pixel) & (np.abs(z + 1.5) < 0.5 + pixel))
    assert on_box.sum() > 50 and bare.sum() > 500
    # The chandelier above the box is ignored: the box top is 0.8 m above the floor.
    np.testing.assert_allclose(truth.height[on_box], 0.8, atol=1e-5)
    assert (truth.category[on_box] == 29).all()
    assert np.isnan(truth.height[bare]).all()
    assert (truth.category[bare] == 2).all()
    # D5 is the floor (walls and ceiling are ignored), D1..D2 the box top and bottom.
    np.testing.assert_allclose(truth.layers.depth[4][bare], over.params[2], atol=1e-5)
    np.testing.assert_allclose(truth.layers.depth[0][on_box], over.params[2] - 0.8, atol=1e-5)
    np.testing.assert_allclose(truth.layers.depth[1][on_box], over.params[2], atol=1e-5)
    # The height map is tz minus the first overhead depth wherever an object is hit.
    hit = np.isfinite(truth.height)
    np.testing.assert_allclose(truth.height[hit], over.params[2] - truth.layers.depth[0][hit],
                               atol=1e-5)


@pytest.mark.parametrize("holes", [(), (0, 1, 3, 4)])
def test_frontal_points_are_the_pixels_back_projected_into_the_gravity_frame(holes):
    # A rolled camera, a second room, and (second case) random holes in D1, D2, D4 and D5,
    # so that layers do not share pixels and some D1 holes keep a visible instance: the
    # points must still be the rays' points at the planar depths, taken to the frame.
    house = room_with_a_box()
    box_instance(house, "shelf", 10, (0.6, 1.2, 0.4), (1.8, 0.6, -2.0), room_id="r1")
    camera = look_at_camera((0.3, 1.4, 2.2), (0.2, -0.3, -1.0), up=(0.15, 1.0, 0.0),
                            width=80, height=60)
    layers = frontal_layers(house, camera, HouseTracer(house))
    depth = layers.depth.copy()
    rng = np.random.default_rng(0)
    for k in holes:
        depth[k][rng.random(depth[k].shape) < 0.2] = np.nan
    layers = Layers(depth, layers.category, layers.instance, layers.normal)
    frame = gravity_frame(camera)
    points, floor_y, floor_source = frontal_points_fast(house, camera, layers, frame, CONFIG)

    origins, directions, scale = camera.rays()
    finite = [np.isfinite(d.ravel()) for d in depth]
    world = [origins[f] + directions[f] * (d.ravel()[f] / scale[f])[:, None]
             for d, f in zip(depth, finite)]
    np.testing.assert_allclose(points.objects, frame.to_frame(np.concatenate(world[:4])),
                               atol=1e-12)
    np.testing.assert_array_equal(points.envelope_z, depth[4].ravel()[finite[4]])
    top = max(frame.to_frame(world[k])[:, 1].max() for k in (0, 1, 4))
    assert points.top == pytest.approx(top, abs=1e-12)
    # The camera stands over the floor: its height is the floor's top, exactly, not the
    # median of the view's floor pixels (float32 depths: within 1e-5 of it).
    floor = layers.category[2].ravel()[finite[4]] == 2
    assert floor.any()
    assert (floor_y, floor_source) == (0.0, "room floor")
    assert floor_y == pytest.approx(np.median(world[4][floor, 1]), abs=1e-5)
    # Rooms are indices into the sorted room ids; every visible D1 pixel votes.
    assert points.room_ids == ("r0", "r1")
    rooms = np.array([i.room_id for i in house.instances])
    inst = np.concatenate([layers.instance[k // 2].ravel()[finite[k]] for k in range(4)])
    np.testing.assert_array_equal(np.array(points.room_ids)[points.object_room], rooms[inst])
    lamp = np.array([i.label == "chandelier" for i in house.instances])
    np.testing.assert_array_equal(points.object_excluded, lamp[inst])
    visible = layers.instance[0][layers.instance[0] >= 0]
    assert points.room_votes.tolist() == [int((rooms[visible] == r).sum()) for r in ("r0", "r1")]
    assert points.room_votes.min() > 0


# ------------------------------------------------ the fast kernel against the plain version


def plain_frontal_points(house, camera, layers, frame, config):
    """frontal_points_fast as docs/spec.md §6 reads, one layer and one pixel rule at a time.

    A pixel's point at planar depth z is z times its ray's point at depth 1 in the frame
    (``_frame_rays``; the test above pins those rays to the back-projected world points).
    Points of D1, D2 take the D1 instance's room and exclusion, those of D3, D4 the D3
    instance's; D5 gives planar depths and heights; the top is the highest of D1, D2 and
    D5; every pixel showing an instance in D1 votes for its room; the floor and its source
    are :func:`plain_floor`'s.
    """
    rays = _frame_rays(camera, frame)
    offset = frame.to_frame(camera.cam_to_world[None, :3, 3])[0]
    depth = layers.depth.reshape(5, -1)
    instance = layers.instance.reshape(2, -1)
    room_ids = tuple(sorted({i.room_id for i in house.instances if i.room_id is not None}, key=str))

    def room(k):
        rid = house.instances[k].room_id if k >= 0 else None
        return -1 if rid is None else room_ids.index(rid)

    def excluded(k):
        return k >= 0 and in_classes(house.instances[k].category, house.instances[k].label,
                                     frozenset(config.room_excluded))

    objects, rooms, skip, ups = [], [], [], []
    for segment, (front, back) in enumerate(OBJECT_SEGMENTS):
        assert FRONT_LAYERS[segment] == front
        for layer in (front, back):
            pixels = np.flatnonzero(np.isfinite(depth[layer]))
            points = (rays[:, pixels] * depth[layer][pixels]).T + offset
            objects.append(points)
            rooms += [room(k) for k in instance[segment][pixels]]
            skip += [excluded(k) for k in instance[segment][pixels]]
            if segment == 0:
                ups.append(points[:, 1])
    pixels = np.flatnonzero(np.isfinite(depth[ENVELOPE_LAYER]))
    envelope_z = depth[ENVELOPE_LAYER][pixels].astype(np.float64)
    envelope_up = rays[1][pixels] * envelope_z + offset[1]
    ups.append(envelope_up)
    votes = np.zeros(len(room_ids), dtype=np.int64)
    for k in instance[0]:
        if k >= 0 and room(k) >= 0:
            votes[room(k)] += 1
    floor = layers.envelope_category.reshape(-1)[pixels] == 2
    floor_pixels = envelope_up[floor] + float(frame.origin[1])
    return (FrontalPoints(np.concatenate(objects), np.array(rooms), np.array(skip, dtype=bool), envelope_z,
                          votes, room_ids, float(max(u.max() for u in ups if len(u)))),
            *plain_floor(house, camera.position, floor_pixels))


def plain_floor_faces(house):
    """(corners, room, level id) of every walkable floor face, one face at a time: the faces
    of floor instances whose normal points up within tol.floor_face_cos (those pointing
    down, reversed, when none does), on their room's level, else on the highest level at
    most tol.level_floor above their top."""
    room_level = {r.id: r.level for r in house.rooms}
    faces = []
    for inst in house.instances:
        if inst.category != 2:
            continue
        up, down = [], []
        for face in inst.faces:
            a, b, c = inst.vertices[face]
            n = np.cross(b - a, c - a)
            if n[1] > tol.floor_face_cos * np.linalg.norm(n):
                up.append((a, b, c))
            elif -n[1] > tol.floor_face_cos * np.linalg.norm(n):
                down.append((c, b, a))
        for corners in up or down:
            top = max(p[1] for p in corners)
            if inst.room_id in room_level:
                level = room_level[inst.room_id]
            else:
                level = plain_level_at(house, top + tol.level_floor).id
            faces.append((corners, inst.room_id, level))
    return faces


def plain_level_at(house, y):
    """The level with the highest floor_y at or below y, else the lowest."""
    levels = sorted(house.levels, key=lambda lv: lv.floor_y)
    return ([lv for lv in levels if lv.floor_y <= y] or levels[:1])[-1]


def plain_floor(house, eye, floor_pixel_heights):
    """The floor height of a view from a camera at ``eye`` and its source, one rule at a time:
    the highest walkable floor face whose x–z footprint holds the eye and whose plane passes
    at most tol.eye_above_floor above it ("room floor"); else the median height of the view's
    D5 floor pixels; else the area-weighted median top of the faces of the eye's level that
    are not above it; else the level's floor_y."""
    x, y, z = eye
    below = []
    faces = plain_floor_faces(house)
    for (a, b, c), _, _ in faces:
        # inside when on the inner side of all three edges (either winding), edges included
        sides = [(q[0] - p[0]) * (z - p[2]) - (q[2] - p[2]) * (x - p[0]) for p, q in ((a, b), (b, c), (c, a))]
        slack = tol.floor_footprint * abs((b[0] - a[0]) * (c[2] - a[2]) - (b[2] - a[2]) * (c[0] - a[0]))
        if not (all(d >= -slack for d in sides) or all(d <= slack for d in sides)):
            continue
        n = np.cross(b - a, c - a)
        height = a[1] - (n[0] * (x - a[0]) + n[2] * (z - a[2])) / n[1]
        if height <= y + tol.eye_above_floor:
            below.append(height)
    if below:
        return float(max(below)), "room floor"
    if len(floor_pixel_heights):
        return float(np.median(floor_pixel_heights)), "view floor pixels"
    level = plain_level_at(house, y)
    tops = sorted((max(p[1] for p in corners), 0.5 * np.linalg.norm(np.cross(corners[1] - corners[0],
                                                                               corners[2] - corners[0])))
                  for corners, _, lv in faces if lv == level.id)
    tops = [(top, area) for top, area in tops if top <= y + tol.eye_above_floor]
    if tops:
        half, total = 0.5 * sum(area for _, area in tops), 0.0
        for top, area in tops:
            total += area
            if total >= half:
                return float(top), "level floor"
    return float(level.floor_y), "level bbox"


def toy_views():
    """Two views of each bundled toy house at 80 × 60, as traced and with random holes in
    every layer (so that no two layers share their pixels)."""
    rng = np.random.default_rng(0)
    for house in (load(source) for source in discover(BUNDLED_TOY)):
        cameras, _ = sample_cameras(house, 2, np.random.default_rng(0), CameraSamplerConfig())
        tracer = HouseTracer(house)
        for cam in cameras:
            cam = cam.resized(80, 60)
            layers = frontal_layers(house, cam, tracer)
            yield house, cam, layers
            depth = layers.depth.copy()
            depth[rng.random(depth.shape) < 0.1] = np.nan
            yield house, cam, Layers(depth, layers.category, layers.instance, layers.normal)


def test_frontal_points_fast_equals_the_plain_version_on_toy_views():
    n = 0
    for house, camera, layers in toy_views():
        frame = gravity_frame(camera)
        fast, *fast_floor = frontal_points_fast(house, camera, layers, frame, CONFIG)
        plain, *plain_floor = plain_frontal_points(house, camera, layers, frame, CONFIG)
        for field in ("objects", "object_room", "object_excluded", "envelope_z", "room_votes"):
            np.testing.assert_array_equal(getattr(fast, field), getattr(plain, field), err_msg=field)
        assert fast.room_ids == plain.room_ids
        assert fast.top == plain.top and fast_floor == plain_floor
        n += len(fast.objects)
    assert n > 10_000


def overhead_at(height, resolution=16):
    """Hand-made overhead camera over (0, height, -1.5), 2 × 2 m, right = +X, forward = −Z."""
    pose = np.eye(4)
    pose[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
    pose[:3, 3] = (0.0, height, -1.5)
    return OverheadCamera(pose, 1.0, resolution, np.zeros(5), 0.0,
                          Box(np.array([-1.0, 0.5]), np.array([1.0, 2.5])))


def test_floor_hits_within_half_a_metre_of_the_camera_are_ignored():
    house = room_with_a_box()
    tracer = HouseTracer(house)
    # 0.9 m above the floor: the box top is 0.1 m below, the floor 0.9 m: both count.
    high = overhead_truth(house, overhead_at(0.9), tracer)
    assert np.isfinite(high.layers.depth[4]).all()
    np.testing.assert_allclose(high.layers.depth[4], 0.9, atol=1e-6)
    # 0.35 m above the floor: inside the box, whose underside 0.35 m below still counts,
    # but both faces of the 0.1 m floor slab are closer than 0.5 m and are ignored.
    low = overhead_truth(house, overhead_at(0.35), tracer)
    assert np.isnan(low.layers.depth[4]).all()
    assert (low.layers.category[2] == 0).all()
    inside = np.isfinite(low.layers.depth[0])
    assert inside.any() and (low.layers.instance[0][inside] == 6).all()
    np.testing.assert_allclose(low.height[inside], 0.0, atol=1e-6)


def test_cli_prints_candidates_and_parameters_and_plots(small_house, tmp_path):
    write_house(small_house, tmp_path / "small")
    cameras = tmp_path / "cameras.txt"
    cameras.write_text("0 1.5 1.6  0 -0.2 -1  0 1 0  0.5534 0.4339 0\n"
                       "0 1.5 1.6  0 -1 0  0 0 -1  0.5534 0.4339 0\n")
    res = CliRunner().invoke(cli, ["overhead-camera", str(tmp_path / "small"), "--camera-file",
                                   str(cameras), "--view", "0", "--plot", str(tmp_path / "p.png")])
    assert res.exit_code == 0, res.output
    for name in ("depth_statistics", "envelope_frustum", "majority_room", "overhead: tx"):
        assert name in res.output
    assert "theta 1.3734" in res.output
    assert (tmp_path / "p.png").stat().st_size > 1000
    # The second camera looks straight down: one red line, no traceback.
    res = CliRunner().invoke(cli, ["overhead-camera", str(tmp_path / "small"), "--camera-file",
                                   str(cameras), "--view", "1"])
    assert res.exit_code == 1
    assert "straight up or down" in res.output and "Traceback" not in res.output


def test_overhead_config_is_checked():
    with pytest.raises(ValueError, match="weights"):
        OverheadConfig(weights=(1.0, 1.0))
    with pytest.raises(ValueError, match="resolution"):
        OverheadConfig(resolution=0)
    with pytest.raises(ValueError, match="room_distance_range"):
        OverheadConfig(room_distance_range=(9.0, 1.5))


# ------------------------------------------------------- the floor of a view (hard cases)


def open_rug_room(covered):
    """rug_room without its +z wall; a camera outside it (z = 2.8, beyond the floor slab)
    looks in."""
    house = rug_room(covered=covered, walls=(0, 1, 2))
    return house, look_at_camera((0.0, 1.5, 2.8), DOWN_PITCH, width=80, height=60)


def floor_cases():
    """(house, camera, expected floor height, its source) per rule of FLOOR_SOURCES."""
    house = rug_room()
    # Over the rug, looking away from the only bare strip of floor: no floor pixel in view.
    yield "room floor, hidden", house, look_at_camera((0.5, 1.5, 1.0), DOWN_PITCH, width=80, height=60), \
        0.0, "room floor"
    two = two_level_house()
    yield "room floor, upper level", two, look_at_camera((0.5, 4.5, 1.0), DOWN_PITCH, width=80, height=60), \
        3.0, "room floor"
    # Outside the floor, seeing a bare strip along the far wall: the median of its pixels
    # (float32 depths).
    yield "view floor pixels", *open_rug_room((-2.0, 2.5)), 0.0, "view floor pixels"
    # Outside the floor, which the rug hides entirely: the tops of the level's floors.
    yield "level floor", *open_rug_room((-2.5, 2.5)), 0.0, "level floor"
    # No floor at all: the level's floor_y, the bottom of the slab.
    house, camera = open_rug_room((-2.5, 2.5))
    next(i for i in house.instances if i.name == "r0_floor").category = 20
    yield "level bbox", house, camera, -0.1, "level bbox"


@pytest.mark.parametrize("case", [c[0] for c in floor_cases()])
def test_the_floor_of_a_view_is_the_top_of_the_camera_rooms_floor(case):
    _, house, camera, expected, source = next(c for c in floor_cases() if c[0] == case)
    tracer = HouseTracer(house)
    layers = frontal_layers(house, camera, tracer)
    frame = gravity_frame(camera)
    seen = (layers.envelope_category == 2).any()
    assert seen == (case in ("room floor, upper level", "view floor pixels"))
    points, floor_y, floor_source = frontal_points_fast(house, camera, layers, frame, CONFIG)
    plain, *plain_floor = plain_frontal_points(house, camera, layers, frame, CONFIG)
    assert [floor_y, floor_source] == plain_floor
    assert floor_source == source
    if source == "view floor pixels":
        assert floor_y == pytest.approx(expected, abs=1e-5)
    else:
        assert floor_y == expected
    if source == "level bbox":
        assert floor_y == level_floor_y(house, camera.position[1])
    over = overhead_camera(house, camera, layers, OverheadConfig(resolution=64))
    assert (over.floor_y, over.floor_source) == (floor_y, floor_source)
    assert over.params[2] == over.cam_to_world[1, 3] - floor_y


def test_overhead_heights_start_at_the_floor_under_a_rug():
    # Before, a view whose floor the rug hides took the level's slab bottom: every height 0.1 m
    # too high. The table top is 0.75 m above the floor.
    _, house, camera, _, _ = next(floor_cases())
    tracer = HouseTracer(house)
    layers = frontal_layers(house, camera, tracer)
    assert not (layers.envelope_category == 2).any()
    config = OverheadConfig(resolution=64)
    over = overhead_camera(house, camera, layers, config)
    truth = overhead_truth(house, over, tracer, config)
    table = next(i.id for i in house.instances if i.name == "r0_table")
    on_table = truth.layers.instance[0] == table
    assert on_table.sum() > 20
    np.testing.assert_allclose(truth.height[on_table], 0.75, atol=1e-5)
