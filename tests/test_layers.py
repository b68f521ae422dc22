"""D1..D5 on tiny box scenes with exact answers (docs/spec.md §4), and fast vs reference engines on
every pixel of every layer."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from sceneforge import layers as layers_module
from sceneforge.camera_sampler import CameraSamplerConfig, sample_cameras
from sceneforge.cameras import look_at_camera
from sceneforge.conventions import NYU40_IDS, tol
from sceneforge.houses import BUNDLED_TOY, House, discover, load, make_instance
from sceneforge.layers import (
    first_hit_normals,
    frontal_layers,
    frontal_normals,
    instance_labels,
    layers_from_hits,
)
from sceneforge.raytrace import Hits, HouseTracer

from .conftest import BREAKFAST_ROOM, needs_shared

WALL, FLOOR, CEILING = NYU40_IDS["wall"], NYU40_IDS["floor"], NYU40_IDS["ceiling"]
CABINET, TABLE, PROP = NYU40_IDS["cabinet"], NYU40_IDS["table"], NYU40_IDS["otherprop"]
W, H = 64, 48


def add_box(house: House, name: str, category: int, lo, hi):
    b = trimesh.creation.box(bounds=[lo, hi])
    return make_instance(house, name=name, category=category, label=name, room_id="r0",
                         vertices=b.vertices, faces=b.faces)


def add_quad(house: House, name: str, category: int, corners):
    """Single-sided quad, corners (4, 3) counter-clockwise seen from its front."""
    return make_instance(house, name=name, category=category, label=name, room_id="r0",
                         vertices=corners, faces=[[0, 1, 2], [0, 2, 3]])


def room(far_wall_hole=None) -> House:
    """Interior x 0..4, y 0..3, z 0..6 m; 0.1 m slabs for floor, ceiling and walls. The far
    wall (z = 6) can have a rectangular opening ``((x0, y0), (x1, y1))``."""
    h = House(id="room", instances=[])
    add_box(h, "floor", FLOOR, (-0.1, -0.1, -0.1), (4.1, 0, 6.1))
    add_box(h, "ceiling", CEILING, (-0.1, 3, -0.1), (4.1, 3.1, 6.1))
    add_box(h, "wall_left", WALL, (-0.1, 0, 0), (0, 3, 6))
    add_box(h, "wall_right", WALL, (4, 0, 0), (4.1, 3, 6))
    add_box(h, "wall_back", WALL, (0, 0, -0.1), (4, 3, 0))
    if far_wall_hole is None:
        add_box(h, "wall_far", WALL, (0, 0, 6), (4, 3, 6.1))
    else:
        (x0, y0), (x1, y1) = far_wall_hole
        add_box(h, "wall_far_left", WALL, (0, 0, 6), (x0, 3, 6.1))
        add_box(h, "wall_far_right", WALL, (x1, 0, 6), (4, 3, 6.1))
        add_box(h, "wall_far_below", WALL, (x0, 0, 6), (x1, y0, 6.1))
        add_box(h, "wall_far_above", WALL, (x0, y1, 6), (x1, 3, 6.1))
    return h


def forward_camera(position=(2.0, 0.5, 1.0)):
    """Level camera looking along +Z: planes z = c are at planar depth c - position z."""
    return look_at_camera(position, (0, 0, 1), width=W, height=H)


def down_camera(position):
    """Camera looking straight down: planes y = c are at planar depth position y - c."""
    return look_at_camera(position, (0, -1, 0), up=(0, 0, 1), width=W, height=H)


def pixel(camera, point):
    """(row, column) of the pixel that sees world ``point``."""
    uv, _ = camera.project([point])
    return int(uv[0, 1]), int(uv[0, 0])


def layers_from_all_hits(house, camera, tracer):
    """The layers computed from every hit of every ray (what frontal_layers shortcuts)."""
    origins, directions, scale = camera.rays()
    hits = tracer.all_hits(origins, directions)
    return layers_from_hits(hits, scale, *instance_labels(house), camera.shape,
                            normals=first_hit_normals(hits, tracer, camera))


def both_engines(house, camera):
    """Layers from the fast engine, after checking that the reference engine, tracing every
    hit of every ray, gives the same."""
    fast = frontal_layers(house, camera, HouseTracer(house))
    assert_same_layers(fast, layers_from_all_hits(house, camera, HouseTracer(house, backend="reference")))
    return fast


def assert_same_layers(a, b):
    np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(a.category, b.category)
    np.testing.assert_array_equal(a.instance, b.instance)
    np.testing.assert_allclose(a.normal, b.normal, atol=1e-6)


def at(layers, rc):
    """(depth (5,), category (3,), instance (2,)) at a pixel."""
    r, c = rc
    return layers.depth[:, r, c], layers.category[:, r, c], layers.instance[:, r, c]


NAN = np.nan


# ---------------------------------------------------------------------------------------
# A box room with a cabinet B, a crate D hidden behind it and a shelf C further back.


@pytest.fixture(scope="module")
def furnished():
    h = room()
    b = add_box(h, "B", CABINET, (1.5, 0, 3), (2.5, 1, 4))
    d = add_box(h, "D_hidden", PROP, (1.8, 0.2, 4.1), (2.2, 0.8, 4.4))
    c = add_box(h, "C", NYU40_IDS["shelves"], (1.0, 0, 4.5), (3.0, 2, 5.0))
    camera = forward_camera()
    return h, camera, both_engines(h, camera), (b.id, d.id, c.id)


def test_box_room_exact_layers_at_the_centre(furnished):
    h, camera, layers, (b, d, c) = furnished
    depth, category, instance = at(layers, pixel(camera, (2.0, 0.5, 3.0)))
    # B from 3 to 4, hidden D skipped (3.1..3.4), C from 4.5 to 5, far wall at 6; camera z = 1
    np.testing.assert_allclose(depth, [2.0, 3.0, 3.5, 4.0, 5.0], rtol=1e-6)
    np.testing.assert_array_equal(category, [CABINET, NYU40_IDS["shelves"], WALL])
    np.testing.assert_array_equal(instance, [b, c])


def test_instance_never_first_hit_is_excluded(furnished):
    _, _, layers, (_, d, _) = furnished
    assert not (layers.instance == d).any()
    assert np.isfinite(layers.depth[2]).any()


def test_box_on_floor_keeps_floor_as_d5(furnished):
    """Leaving B through its bottom face, the ray meets the floor at the same distance."""
    _, camera, layers, (b, _, _) = furnished
    # 10.5 px below the centre row: the ray enters B's front at y = 0.09 and meets y = 0
    # before B's back, so it leaves through B's bottom, where the floor is
    row, col = 34, W // 2
    y_cam = (row + 0.5 - camera.K[1, 2]) / camera.K[1, 1]
    floor = 0.5 / y_cam
    assert 0.5 - 2.0 * y_cam > 0 and 2.0 < floor < 3.0
    depth, category, instance = at(layers, (row, col))
    np.testing.assert_allclose(depth, [2.0, floor, NAN, NAN, floor], rtol=1e-6)
    np.testing.assert_array_equal(category, [CABINET, 0, FLOOR])
    np.testing.assert_array_equal(instance, [b, -1])


def test_floor_only_and_object_above_box_pixels(furnished):
    _, camera, layers, (_, _, c) = furnished
    depth, category, instance = at(layers, (H - 1, 5))
    y_cam = (H - 0.5 - camera.K[1, 2]) / camera.K[1, 1]
    np.testing.assert_allclose(depth, [NAN, NAN, NAN, NAN, 0.5 / y_cam], rtol=1e-6)
    np.testing.assert_array_equal(category, [0, 0, FLOOR])
    np.testing.assert_array_equal(instance, [-1, -1])
    depth, _, instance = at(layers, pixel(camera, (2.0, 1.6, 4.5)))  # C, above B
    np.testing.assert_allclose(depth, [3.5, 4.0, NAN, NAN, 5.0], rtol=1e-6)
    np.testing.assert_array_equal(instance, [c, -1])


def test_masks_and_traditional_depth(furnished):
    _, _, layers, _ = furnished
    m = layers.masks
    assert m.shape == (5, H, W) and m.dtype == bool
    np.testing.assert_array_equal(m[0], np.isfinite(layers.depth[0]))
    np.testing.assert_array_equal(m[1], m[0])
    np.testing.assert_array_equal(m[3], np.isfinite(layers.depth[2]))
    assert m[4].all()  # closed room
    # wherever D2 or D4 exist, so do D1 or D3, and depths never decrease from D1 to D4
    assert not (np.isfinite(layers.depth[1]) & ~m[0]).any()
    assert not (np.isfinite(layers.depth[3]) & ~m[2]).any()
    d = layers.depth
    assert (d[1][m[0]] >= d[0][m[0]]).all() and (d[3][m[2]] >= d[2][m[2]]).all()
    assert (d[2][m[2]] >= d[1][m[2]] - tol.same_instance_hit).all()
    trad = layers.traditional_depth
    np.testing.assert_array_equal(trad[m[0]], d[0][m[0]])
    np.testing.assert_array_equal(trad[~m[0]], d[4][~m[0]])


def test_first_hit_normals_face_the_camera(furnished):
    _, camera, layers, _ = furnished
    r, c = pixel(camera, (2.0, 0.5, 3.0))
    np.testing.assert_allclose(layers.normal[:, r, c], [0, 0, -1], atol=1e-6)  # B's front, camera frame
    r, c = H - 1, 5  # floor: world +Y is camera -y
    np.testing.assert_allclose(layers.normal[:, r, c], [0, -1, 0], atol=1e-6)
    n = layers.normal.reshape(3, -1)
    np.testing.assert_allclose(np.linalg.norm(n, axis=0), 1, atol=1e-6)


def test_frontal_normals_are_the_first_hit_normals_of_the_merged_hits():
    """The split query picks each ray's first hit from the objects and the closing hit the
    same way the merged, sorted hits do, ties included (a shelf touching the wall behind it)."""
    h = room()
    add_box(h, "shelf", PROP, (1.0, 0.0, 5.7), (2.0, 2.0, 6.0))  # its back is the far wall's plane
    add_box(h, "chair", PROP, (2.5, 0.0, 2.0), (3.0, 1.0, 2.5))
    camera = look_at_camera((2.0, 1.5, 0.5), (0.3, -0.2, 1.0), width=W, height=H)
    tracer = HouseTracer(h)
    origins, directions, _ = camera.rays()
    split = frontal_normals(tracer.frontal_query(origins, directions), tracer, camera)
    merged = first_hit_normals(tracer.frontal_hits(origins, directions), tracer, camera)
    assert np.isfinite(split).all() and split.dtype == np.float32
    np.testing.assert_array_equal(split, merged)


def test_keep_drops_hits_before_the_rules(furnished):
    """Without B's hits, D is the first hit at the centre and becomes visible."""
    h, camera, _, (b, d, c) = furnished
    origins, directions, scale = camera.rays()
    hits = HouseTracer(h).all_hits(origins, directions)
    category, envelope = instance_labels(h)
    layers = layers_from_hits(hits, scale, category, envelope, (H, W), keep=hits.instance != b)
    depth, _, instance = at(layers, pixel(camera, (2.0, 0.5, 3.0)))
    np.testing.assert_allclose(depth, [3.1, 3.4, 3.5, 4.0, 5.0], rtol=1e-6)
    np.testing.assert_array_equal(instance, [d, c])
    assert np.isnan(layers.normal).all()


# ---------------------------------------------------------------------------------------
# Special surfaces


def test_single_sided_sheet_gives_d2_equal_d1():
    h = room()
    front = add_quad(h, "facing", PROP, np.array([[2.5, 0.2, 3], [1.5, 0.2, 3], [1.5, 0.8, 3], [2.5, 0.8, 3]],
                                                 dtype=float))
    back = add_quad(h, "turned", PROP, np.array([[0.5, 1.2, 4], [1.5, 1.2, 4], [1.5, 1.8, 4], [0.5, 1.8, 4]],
                                                dtype=float))
    camera = forward_camera()
    layers = both_engines(h, camera)
    assert h.instances[front.id].faces.shape == (2, 3)
    for sheet, point, d in ((front, (2.0, 0.5, 3.0), 2.0), (back, (1.0, 1.5, 4.0), 3.0)):
        depth, _, instance = at(layers, pixel(camera, point))
        np.testing.assert_allclose(depth, [d, d, NAN, NAN, 5.0], rtol=1e-6)
        np.testing.assert_array_equal(instance, [sheet.id, -1])


def test_interpenetrating_objects_d3_counts_only_hits_after_d2():
    """A (z 3..4) and a taller B (z 3.5..4.5) overlap: B's entry at 3.5 lies before A's exit
    and does not count, so D3 = D4 = B's exit."""
    h = room()
    a = add_box(h, "A", CABINET, (1.5, 0, 3), (2.5, 1, 4))
    b = add_box(h, "B", PROP, (1.7, 0, 3.5), (2.3, 1.5, 4.5))
    camera = forward_camera()
    layers = both_engines(h, camera)
    depth, _, instance = at(layers, pixel(camera, (2.0, 0.5, 3.0)))
    np.testing.assert_allclose(depth, [2.0, 3.0, 3.5, 3.5, 5.0], rtol=1e-6)
    np.testing.assert_array_equal(instance, [a.id, b.id])
    depth, _, instance = at(layers, pixel(camera, (2.0, 1.175, 3.5)))  # B, over A, out at its back
    np.testing.assert_allclose(depth[[0, 1, 4]], [2.5, 3.5, 5.0], rtol=1e-6)
    np.testing.assert_array_equal(instance, [b.id, -1])


def test_rugs_within_a_millimetre_of_the_floor():
    """A thin rug on the floor is an object with D2 = D5 = floor; a rug 0.2 mm *under* the
    floor's top (z-fighting) still shows as an object; one 3 mm under it does not."""
    h = room()
    on = add_box(h, "rug_on", PROP, (0.8, 0, 2.5), (1.6, 0.0008, 3.5))
    under = add_quad(h, "rug_under", PROP, np.array([[2.2, -2e-4, 2.5], [2.2, -2e-4, 3.5],
                                                     [2.8, -2e-4, 3.5], [2.8, -2e-4, 2.5]]))
    deep = add_quad(h, "rug_deep", PROP, np.array([[3.0, -3e-3, 2.5], [3.0, -3e-3, 3.5],
                                                   [3.6, -3e-3, 3.5], [3.6, -3e-3, 2.5]]))
    camera = down_camera((2.2, 2.5, 3.0))
    layers = both_engines(h, camera)

    depth, category, instance = at(layers, pixel(camera, (1.2, 0, 3.0)))
    np.testing.assert_allclose(depth, [2.5 - 0.0008, 2.5, NAN, NAN, 2.5], rtol=1e-6)
    np.testing.assert_array_equal(category, [PROP, 0, FLOOR])
    np.testing.assert_array_equal(instance, [on.id, -1])

    depth, category, instance = at(layers, pixel(camera, (2.5, 0, 3.0)))
    np.testing.assert_allclose(depth, [2.5002, 2.5002, NAN, NAN, 2.5], rtol=1e-6)
    np.testing.assert_array_equal(category, [PROP, 0, FLOOR])
    np.testing.assert_array_equal(instance, [under.id, -1])

    depth, category, instance = at(layers, pixel(camera, (3.3, 0, 3.0)))
    np.testing.assert_allclose(depth, [NAN, NAN, NAN, NAN, 2.5], rtol=1e-6)
    assert not (layers.instance == deep.id).any()


def test_window_opening_lets_rays_escape():
    h = room(far_wall_hole=((1.5, 1.0), (2.5, 2.0)))
    outside = add_box(h, "tree", PROP, (1.0, 1.0, 7.0), (1.6, 2.0, 7.5))  # partly behind the opening
    behind = add_box(h, "shed", PROP, (3.0, 0.0, 7.0), (3.8, 3.0, 8.0))  # wholly behind the wall
    camera = forward_camera((2.0, 1.5, 1.0))
    layers = both_engines(h, camera)
    depth, category, instance = at(layers, pixel(camera, (2.2, 1.5, 6.0)))  # through the opening
    assert np.isnan(depth).all()
    np.testing.assert_array_equal(category, [0, 0, 0])
    np.testing.assert_array_equal(instance, [-1, -1])
    depth, _, instance = at(layers, pixel(camera, (1.55, 1.5, 6.0)))  # the tree through the opening
    np.testing.assert_allclose(depth, [6.0, 6.5, NAN, NAN, NAN], rtol=1e-6)
    np.testing.assert_array_equal(instance, [outside.id, -1])
    depth, category, _ = at(layers, pixel(camera, (3.4, 1.5, 6.0)))  # wall in front of the shed
    np.testing.assert_allclose(depth, [NAN, NAN, NAN, NAN, 5.0], rtol=1e-6)
    assert category[2] == WALL
    assert not (layers.instance == behind.id).any()
    assert 0 < (~layers.masks[4]).mean() < 0.2


def test_cup_standing_on_a_table():
    h = room()
    table = add_box(h, "table", TABLE, (1.2, 0.7, 2.2), (2.8, 0.75, 3.8))
    cup = add_box(h, "cup", PROP, (1.9, 0.75, 2.9), (2.1, 0.85, 3.1))
    camera = down_camera((2.0, 1.75, 3.0))
    layers = both_engines(h, camera)
    depth, category, instance = at(layers, pixel(camera, (2.03, 0.85, 3.04)))
    np.testing.assert_allclose(depth, [0.9, 1.0, 1.0, 1.05, 1.75], rtol=1e-6)
    assert abs(float(depth[2]) - float(depth[1])) <= 1e-4
    np.testing.assert_array_equal(category, [PROP, TABLE, FLOOR])
    np.testing.assert_array_equal(instance, [cup.id, table.id])


# ---------------------------------------------------------------------------------------
# The rules on hand-made hits (no geometry): one ray per case


def hand_hits(rays):
    """Hits from per-ray lists of (t, instance)."""
    t = [hit[0] for ray in rays for hit in ray]
    inst = [hit[1] for ray in rays for hit in ray]
    return Hits(
        offsets=np.r_[0, np.cumsum([len(r) for r in rays])].astype(np.int64),
        t=np.array(t, dtype=np.float64),
        instance=np.array(inst, dtype=np.int32),
        triangle=np.zeros(len(t), dtype=np.int64),
        front_facing=np.ones(len(t), dtype=bool),
    )


def test_rules_on_hand_made_hits():
    # instances: 0 floor (envelope), 1 chair, 2 table, 3 lamp (never first), 4 wall (envelope)
    category = np.array([FLOOR, 5, TABLE, 35, WALL], dtype=np.uint8)
    envelope = np.array([True, False, False, False, True])
    slack = tol.envelope_slack
    rays = [
        [(1.0, 1), (2.0, 1), (2.2, 3), (2.5, 2), (3.0, 2), (4.0, 0)],   # the lamp is skipped
        [(2.0, 0), (2.0 + 0.9 * slack, 2), (2.0 + 1.1 * slack, 1)],      # rule 1 slack
        [(1.0, 2), (2.0 - 0.5e-4, 1), (2.0, 2), (2.2, 1), (3.0, 4)],     # D3 within 1e-4 before D2
        [(1.0, 2), (1.5, 1), (2.0, 2), (2.5, 1), (3.0, 4), (3.5, 3)],   # interpenetrating
        [(1.0, 4), (2.0, 3)],                                            # lamp behind a wall
        [],                                                              # escapes
    ]
    layers = layers_from_hits(hand_hits(rays), np.full(6, 0.5), category, envelope, (1, 6))
    d = layers.depth[:, 0, :] / 0.5
    expected = np.array([
        [1.0, 2.0, 2.5, 3.0, 4.0],
        [2.0 + 0.9 * slack, 2.0 + 0.9 * slack, NAN, NAN, 2.0],
        [1.0, 2.0, 2.0 - 0.5e-4, 2.2, 3.0],
        [1.0, 2.0, 2.5, 2.5, 3.0],
        [NAN, NAN, NAN, NAN, 1.0],
        [NAN] * 5,
    ]).T
    np.testing.assert_allclose(d, expected, rtol=1e-6)
    np.testing.assert_array_equal(layers.instance[:, 0, :], [[1, 2, 2, 2, -1, -1], [2, -1, 1, 1, -1, -1]])
    np.testing.assert_array_equal(layers.category[:, 0, :],
                                  [[5, TABLE, TABLE, TABLE, 0, 0], [TABLE, 0, 5, 5, 0, 0],
                                   [FLOOR, FLOOR, WALL, WALL, WALL, 0]])


def test_layers_from_hits_checks_its_inputs():
    hits = hand_hits([[(1.0, 0)], []])
    labels = np.array([WALL], dtype=np.uint8), np.array([True])
    with pytest.raises(ValueError, match="2 rays, expected H×W = 1×3"):
        layers_from_hits(hits, np.ones(3), *labels, (1, 3))
    with pytest.raises(ValueError, match="depth_scale has 3"):
        layers_from_hits(hits, np.ones(3), *labels, (1, 2))
    with pytest.raises(ValueError, match="keep"):
        layers_from_hits(hits, np.ones(2), *labels, (1, 2), keep=np.ones(2, bool))
    with pytest.raises(ValueError, match="instance 1 but only 1 instances"):
        layers_from_hits(hand_hits([[(1.0, 1)]]), np.ones(1), *labels, (1, 1))


# ---------------------------------------------------------------------------------------
# Fast vs reference engines on real houses


def toy_houses():
    houses = [load(s) for s in discover(BUNDLED_TOY)]
    assert len(houses) == 3
    return houses


def test_engines_agree_on_every_pixel_of_bundled_toy_houses():
    for house in toy_houses():
        tracer = HouseTracer(house)
        config = CameraSamplerConfig(width=W, height=H)
        cameras, _ = sample_cameras(house, 2, np.random.default_rng(0), config, tracer)
        assert cameras, house.id
        reference = HouseTracer(house, backend="reference")
        for camera in cameras:
            fast = frontal_layers(house, camera, tracer)
            assert np.isfinite(fast.depth[0]).any()
            assert_same_layers(fast, layers_from_all_hits(house, camera, reference))
            assert_same_layers(fast, layers_from_all_hits(house, camera, tracer))


@needs_shared(BREAKFAST_ROOM)
def test_engines_agree_on_every_pixel_of_the_breakfast_room():
    house = load(BREAKFAST_ROOM)
    # in the room, looking at the table and chairs and out of a window
    camera = look_at_camera((0.5, 1.5, 1.5), (-0.35, -0.196, -0.92), width=W, height=H)
    fast = frontal_layers(house, camera, HouseTracer(house))
    assert np.isfinite(fast.depth[2]).mean() > 0.01 and np.isfinite(fast.depth[0]).mean() > 0.1
    assert_same_layers(fast, layers_from_all_hits(house, camera, HouseTracer(house, backend="reference")))


# ------------------------------------------------------------- compiled rules vs numpy rules

COMPILED = pytest.mark.skipif(not layers_module.COMPILED_RULES, reason="sceneforge's Embree extension is not built")


def random_object_hits(rng, n_rays: int, n_instances: int):
    """CSR object hits built to test the rules' edge cases: few instances (repeats, D3
    candidates that are not visible), exact distance ties, steps of exactly and just over
    ``tol.same_instance_hit`` (D3's ``t >= D2 - tol`` test), rays without hits, rays with
    and without a closing hit."""
    counts = rng.integers(0, 9, n_rays) * (rng.random(n_rays) < 0.9)
    k = int(counts.sum())
    steps = rng.choice([0.0, tol.same_instance_hit, 1.5 * tol.same_instance_hit, 0.01, 0.3], size=k)
    starts = np.repeat(rng.uniform(0.2, 3.0, n_rays), counts)
    ray = np.repeat(np.arange(n_rays), counts)
    offsets = np.r_[0, np.cumsum(counts)].astype(np.int64)
    t = np.empty(k)
    for r in range(n_rays):  # small: a loop keeps the construction obvious
        lo, hi = offsets[r], offsets[r + 1]
        t[lo:hi] = starts[lo:hi] + np.cumsum(steps[lo:hi]) if hi > lo else 0
    inst = rng.integers(0, n_instances, k).astype(np.int32)
    closes = rng.random(n_rays) < 0.8
    last_t = np.zeros(n_rays)
    np.maximum.at(last_t, ray, t)
    closing_t = np.where(closes, last_t + rng.uniform(0, tol.envelope_slack, n_rays), np.nan)
    closing_inst = np.where(closes, n_instances, -1).astype(np.int32)  # the envelope: the last instance
    return offsets, t, inst, closing_t, closing_inst


@COMPILED
@pytest.mark.parametrize("seed", range(4))
def test_compiled_rules_equal_the_numpy_rules_on_random_hits(seed):
    rng = np.random.default_rng(seed)
    H_, W_ = 30, 40
    n_instances = (2, 3, 6, 40)[seed]
    offsets, t, inst, closing_t, closing_inst = random_object_hits(rng, H_ * W_, n_instances)
    category = rng.integers(1, 41, n_instances + 1).astype(np.uint8)
    for scale in (rng.uniform(0.7, 1.0, H_ * W_), np.broadcast_to(np.float64(1.0), (H_ * W_,))):
        got, want = (layers_module.apply_rules(offsets, t, inst, closing_t, closing_inst, scale, category,
                                               (H_, W_), compiled=c) for c in (True, False))
        assert np.isfinite(want.depth[2]).sum() > 50  # D3 is exercised
        for name in ("depth", "category", "instance", "normal"):
            a, b = getattr(got, name), getattr(want, name)
            assert a.dtype == b.dtype and a.shape == b.shape, name
            assert a.tobytes() == b.tobytes(), name


@COMPILED
@pytest.mark.parametrize("source", [pytest.param(s, id=s.id) for s in discover(BUNDLED_TOY)] + [
    pytest.param(BREAKFAST_ROOM, id="breakfast_room", marks=needs_shared(BREAKFAST_ROOM))])
def test_compiled_rules_equal_the_numpy_rules_on_house_views(source):
    """Every pixel of the frontal and overhead layers of two views of each house."""
    from sceneforge.overhead import OverheadConfig, overhead_camera, overhead_instances

    house = load(source)
    tracer = HouseTracer(house)
    sampler = CameraSamplerConfig(max_escape_fraction=0.5)
    cameras, _ = sample_cameras(house, 2, np.random.default_rng(3), sampler, tracer)
    category, envelope = instance_labels(house)
    seen = overhead_instances(house, OverheadConfig())
    for camera in cameras:
        top = overhead_camera(house, camera, frontal_layers(house, camera, tracer))
        queries = [(camera, {}), (top, dict(objects=seen & ~envelope, envelope=seen & envelope,
                                           envelope_near=OverheadConfig().floor_clearance))]
        for cam, masks in queries:
            origins, directions, scale = cam.rays()
            hits = tracer.frontal_query(origins, directions, **masks)
            got, want = (layers_module.apply_rules(hits.objects.offsets, hits.objects.t, hits.objects.instance,
                                                   hits.closing.t, hits.closing.instance, scale, category,
                                                   (cam.height, cam.width), compiled=c) for c in (True, False))
            assert np.isfinite(want.depth[0]).any()
            for name in ("depth", "category", "instance"):
                assert getattr(got, name).tobytes() == getattr(want, name).tobytes(), name


@COMPILED
def test_compiled_rules_reject_instances_without_labels():
    offsets = np.array([0, 1], np.int64)
    with pytest.raises(ValueError, match="instance index"):
        layers_module.apply_rules(offsets, np.ones(1), np.array([5], np.int32), np.full(1, np.nan),
                                  np.full(1, -1, np.int32), np.ones(1), np.zeros(2, np.uint8), (1, 1), compiled=True)
