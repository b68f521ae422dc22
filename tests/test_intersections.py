"""K ray-intersection layers (docs/spec.md §4.7): exact on a box room, every engine equal to a
slow reference (all hits of the numpy reference engine, sorted, merged, cut) on every pixel of
small views and on random rays of real scenes, the frontal layers unchanged when they come from
the same traversal, and in a store only with ``--intersections K``."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner
from sceneforge.cli.main import cli

from sceneforge.camera_sampler import CameraSamplerConfig, sample_cameras
from sceneforge.cameras import look_at_camera
from sceneforge.conventions import NYU40_IDS, tol
from sceneforge.houses import BUNDLED_TOY, discover, load
from sceneforge.intersections import layers_and_intersections, ray_intersections
from sceneforge.layers import LayersConfig, frontal_layers, instance_labels
from sceneforge.raytrace import HouseTracer, Rays, _plane_distance
from sceneforge.raytrace import embree_backend as embree
from sceneforge.store import array_digests, open_store, validate_store
from sceneforge.view import ViewConfig, compute_view

from .conftest import BREAKFAST_ROOM, box_instance, box_room, needs_shared
from .test_raytrace import random_house, random_rays

NO_EXTENSION = pytest.mark.skipif(not embree.AVAILABLE, reason="sceneforge's Embree extension is not built")
ENGINES = (pytest.param("embree", marks=NO_EXTENSION), "open3d", "reference")
HIT_FIELDS = ("t", "face", "front_facing")
SURFACE_FIELDS = ("depth", "normal", "instance", "label", "front_facing")
CABINET, OTHER = NYU40_IDS["cabinet"], NYU40_IDS["otherprop"]


def assert_bytes_equal(a, b, fields):
    for name in fields:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), name


def slow_nearest(house, origins, directions, k: int):
    """The reference the tracers are held to, one ray at a time in Python: every crossing the
    numpy reference engine reports, with its float64 plane distance (none: dropped), sorted by
    distance then face (the lower instance, then triangle), a hit dropped when an earlier hit
    of its instance lies within ``tol.same_instance_hit`` before it, the first ``k`` kept:
    (t (k, n) float64, face (k, n) int64, front_facing (k, n) bool)."""
    tracer = HouseTracer(house, "reference")
    rays = Rays.check(origins, directions)
    ray, face = tracer.backend.intersect_all(rays)
    t, cos = _plane_distance(tracer.triangles, face, ray, rays)
    per_ray = [[] for _ in range(len(rays))]
    for r, f, d, c in zip(ray.tolist(), face.tolist(), t.tolist(), cos.tolist()):
        if np.isfinite(d):
            per_ray[r].append((d, f, c < 0))
    instance = tracer.triangles.instance
    out_t = np.full((k, len(rays)), np.nan)
    out_face = np.full((k, len(rays)), -1, dtype=np.int64)
    out_front = np.zeros((k, len(rays)), dtype=bool)
    for r, hits in enumerate(per_ray):
        hits.sort()
        kept = [h for i, h in enumerate(hits)
                if not any(instance[g] == instance[h[1]] and h[0] - s <= tol.same_instance_hit for s, g, _ in hits[:i])]
        for j, (d, f, front) in enumerate(kept[:k]):
            out_t[j, r], out_face[j, r], out_front[j, r] = d, f, front
    return out_t, out_face, out_front


def assert_reference(hits, reference):
    t, face, front = reference
    np.testing.assert_array_equal(hits.face, face)
    np.testing.assert_array_equal(hits.front_facing, front)
    assert hits.t.tobytes() == t.tobytes()  # the same float64 plane distances, NaN where none


def house_views(house, n: int, width: int, height: int):
    sampler = CameraSamplerConfig(width=width, height=height, max_escape_fraction=0.5)
    cameras, _ = sample_cameras(house, n, np.random.default_rng(0), sampler, HouseTracer(house))
    assert len(cameras) == n
    return cameras


def houses():
    yield from (pytest.param(s, id=s.id) for s in discover(BUNDLED_TOY))
    yield pytest.param(BREAKFAST_ROOM, id="breakfast_room", marks=needs_shared(BREAKFAST_ROOM))


def rays_in(house, n: int, seed: int):
    """``n`` random rays from inside the middle of the house's bounding box, every direction."""
    vertices = np.concatenate([i.vertices for i in house.instances])
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    rng = np.random.default_rng(seed)
    origins = rng.uniform(lo + 0.2 * (hi - lo), hi - 0.2 * (hi - lo), (n, 3))
    directions = rng.normal(size=(n, 3))
    return origins, directions / np.linalg.norm(directions, axis=1, keepdims=True)


# ----------------------------------------------------------------------------- a box room


@pytest.fixture(scope="module")
def cabinet_room():
    """A 4 × 2.5 × 4 m room (conftest.box_room: walls 0.1 m boxes, the back one's inner face at
    z = -2), a cabinet (z -1.3..-0.7) in it and a crate outside, behind the back wall (z
    -3.2..-2.8); the camera at z = 1 looks along -z, so every plane z = c is at planar depth
    1 - c: the cabinet's front 1.7, its back 2.3, the wall 3.0 and 3.1, the crate 3.8 and 4.2."""
    house = box_room("intersections_room", 4.0, 2.5)
    cabinet = box_instance(house, "cabinet", CABINET, (0.4, 0.4, 0.6), (0.0, 0.5, -1.0))
    crate = box_instance(house, "crate", OTHER, (1.2, 1.2, 0.4), (0.0, 0.5, -3.0), room_id=None)
    camera = look_at_camera((0.0, 0.5, 1.0), (0.0, 0.0, -1.0), width=33, height=25)
    wall = next(i for i in house.instances if i.name == "wall2")  # the back wall (z < 0)
    return house, camera, {"cabinet": cabinet.id, "crate": crate.id, "wall": wall.id}


def test_box_room_layers_are_exact_through_the_cabinet_and_behind_the_wall(cabinet_room):
    house, camera, ids = cabinet_room
    got = ray_intersections(house, camera, 8)
    assert got.layers == 8 and got.depth.shape == (8, 25, 33) and got.normal.shape == (8, 3, 25, 33)
    # the pixels whose ray leaves the cabinet through its back (at planar depth 2.3, within
    # its 0.4 × 0.4 m face centred on the camera axis), not through a side
    K = camera.K
    u = (np.arange(33) + 0.5 - K[0, 2]) / K[0, 0]
    v = (np.arange(25) + 0.5 - K[1, 2]) / K[1, 1]
    through = (np.abs(2.3 * v)[:, None] < 0.2 - 1e-6) & (np.abs(2.3 * u)[None, :] < 0.2 - 1e-6)
    assert through.sum() >= 9 and through[12, 16]  # the centre pixel and its neighbours
    # front and back of the cabinet, the back wall's inner and outer face, the crate's two
    want = {"depth": [1.7, 2.3, 3.0, 3.1, 3.8, 4.2],
            "instance": [ids["cabinet"]] * 2 + [ids["wall"]] * 2 + [ids["crate"]] * 2,
            "category": [CABINET, CABINET, NYU40_IDS["wall"], NYU40_IDS["wall"], OTHER, OTHER],
            "front_facing": [True, False] * 3}
    for name, values in want.items():
        layers = getattr(got, name)[:, through]
        expected = np.repeat(np.asarray(values)[:, None], through.sum(), axis=1)
        if name == "depth":
            np.testing.assert_allclose(layers[:6], expected, rtol=0, atol=1e-6)
        else:
            np.testing.assert_array_equal(layers[:6], expected)
    # winding normals in the camera frame (z forward = world -z), not turned to the camera:
    # the faces met from the front point back at it (-z), those met from behind away (+z)
    normal = got.normal[:6][:, :, through]
    np.testing.assert_allclose(normal[:, :2], 0.0, atol=1e-7)
    np.testing.assert_allclose(normal[:, 2], np.repeat([[-1.0], [1.0]] * 3, through.sum(), axis=1), atol=1e-7)
    # past the sixth surface nothing
    assert np.isnan(got.depth[6:][:, through]).all() and np.isnan(got.normal[6:][:, :, through]).all()
    assert (got.instance[6:][:, through] == -1).all() and (got.category[6:][:, through] == 0).all()
    assert not got.front_facing[6:][:, through].any()


def test_box_room_pixel_beside_the_cabinet_sees_the_wall_then_the_crate(cabinet_room):
    house, camera, ids = cabinet_room
    got = ray_intersections(house, camera, 3)
    uv, _ = camera.project([(0.45, 0.9, -2.0)])  # on the back wall, clear of the cabinet
    r, c = int(uv[0, 1]), int(uv[0, 0])
    np.testing.assert_allclose(got.depth[:, r, c], [3.0, 3.1, 3.8], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(got.instance[:, r, c], [ids["wall"], ids["wall"], ids["crate"]])


def test_the_first_layer_is_the_first_surface_of_the_paper_layers(cabinet_room):
    house, camera, _ = cabinet_room
    got = ray_intersections(house, camera, 2)
    layers = frontal_layers(house, camera)
    np.testing.assert_array_equal(got.depth[0], np.fmin(layers.depth[0], layers.depth[4]))


def test_more_layers_than_surfaces_are_padded(cabinet_room):
    house, camera, _ = cabinet_room
    tracer = HouseTracer(house)
    got = ray_intersections(house, camera, 40, tracer)
    origins, directions, _ = camera.rays()
    counts = tracer.all_hits(origins, directions).counts.reshape(camera.shape)
    assert counts.max() < 40
    layer = np.arange(40)[:, None, None]
    np.testing.assert_array_equal(np.isfinite(got.depth), layer < counts)
    past = layer >= counts
    assert np.isnan(got.normal.transpose(1, 0, 2, 3)[:, past]).all()
    assert (got.instance[past] == -1).all() and (got.category[past] == 0).all() and not got.front_facing[past].any()


# ----------------------------------------------------------------------------- the reference


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("source", list(houses()))
def test_every_pixel_of_small_views_is_the_reference(engine, source):
    house = load(source)
    tracer = HouseTracer(house, engine)
    for camera in house_views(house, 2, 40, 30):
        origins, directions, _ = camera.rays()
        for k in (3, 12):
            assert_reference(tracer.nearest_hits(origins, directions, k), slow_nearest(house, origins, directions, k))


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("source", list(houses()))
def test_random_rays_of_real_scenes_are_the_reference(engine, source):
    house = load(source)
    origins, directions = rays_in(house, 1500, 7)
    reference = slow_nearest(house, origins, directions, 10)
    assert (reference[1] >= 0).sum() > 1500  # rays through several surfaces
    assert_reference(HouseTracer(house, engine).nearest_hits(origins, directions, 10), reference)


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("seed", [0, 1])
def test_random_soups_are_the_reference_and_all_hits_cut(engine, seed):
    """Triangle soups and touching boxes: many coincident and shared-edge hits. The layers are
    also the tracer's own all hits (:class:`Hits`, in their order) cut after the k-th."""
    house = random_house(seed)
    origins, directions = random_rays(np.random.default_rng(100 + seed), 2000)
    tracer = HouseTracer(house, engine)
    all_hits = tracer.all_hits(origins, directions)
    for k in (1, 2, 5, 30):
        got = tracer.nearest_hits(origins, directions, k)
        assert_reference(got, slow_nearest(house, origins, directions, k))
        rank = np.arange(len(all_hits.t)) - np.repeat(all_hits.offsets[:-1], all_hits.counts)
        cut = rank < k
        face = np.full((k, all_hits.n_rays), -1, dtype=np.int64)
        face[rank[cut], all_hits.ray_ids()[cut]] = tracer.triangles.global_index(all_hits.instance, all_hits.triangle)[cut]
        np.testing.assert_array_equal(got.face, face)
        np.testing.assert_array_equal(got.counts, np.minimum(all_hits.counts, k))


@NO_EXTENSION
@pytest.mark.parametrize("source", list(houses()))
def test_engines_agree_bit_for_bit(source):
    """The extension's layers (its own traversal, written as it finishes each ray) against the
    Open3D engine's and the reference engine's (every hit, cut, then written in numpy)."""
    house = load(source)
    category, _ = instance_labels(house)
    tracers = {engine: HouseTracer(house, engine) for engine in ("embree", "open3d", "reference")}
    for camera in house_views(house, 2, 40, 30):
        origins, directions, scale = camera.rays()
        rotation = camera.cam_to_world[:3, :3].T
        for k, engines in ((1, ("open3d",)), (10, ("open3d", "reference"))):
            ours = tracers["embree"].nearest_surfaces(origins, directions, k, scale, rotation, category)
            for engine in engines:
                theirs = tracers[engine].nearest_surfaces(origins, directions, k, scale, rotation, category)
                assert_bytes_equal(ours, theirs, SURFACE_FIELDS)


@NO_EXTENSION
def test_ray_by_ray_and_every_packet_width_give_the_same_layers():
    """The extension traces in ray packets and decides again ray by ray what lies next to an edge."""
    house = load(discover(BUNDLED_TOY)[1])
    tracer = HouseTracer(house, "embree")
    category, _ = instance_labels(house)
    camera = house_views(house, 1, 96, 72)[0]
    origins, directions, scale = camera.rays()
    rotation = camera.cam_to_world[:3, :3].T
    results = []
    for packet in (1, 4, 8, 16):
        try:
            tracer.backend = embree.EmbreeBackend(tracer.triangles, 0, packet)
        except ValueError:  # not a native width of this CPU
            continue
        results.append(tracer.nearest_surfaces(origins, directions, 6, scale, rotation, category))
    assert len(results) >= 2
    for other in results[1:]:
        assert_bytes_equal(results[0], other, SURFACE_FIELDS)


@NO_EXTENSION
def test_layers_do_not_depend_on_the_thread_count_or_the_batch():
    house = random_house(3)
    origins, directions = random_rays(np.random.default_rng(9), 5000)
    results = [HouseTracer(house, "embree", threads=t).nearest_hits(origins, directions, 4) for t in (1, 2, 3)]
    for other in results[1:]:
        assert_bytes_equal(results[0], other, HIT_FIELDS)
    half = HouseTracer(house, "embree").nearest_hits(origins[2500:], directions[2500:], 4)
    assert half.t.tobytes() == np.ascontiguousarray(results[0].t[:, 2500:]).tobytes()


# ----------------------------------------------------------------------------- one traversal for both


@NO_EXTENSION
@pytest.mark.parametrize("source", list(houses()))
def test_frontal_layers_from_the_same_traversal_are_unchanged(source):
    """compute_view with K layers: the paper's layers and the overhead truth byte for byte
    those without, and the K layers those of ray_intersections (the extension takes the
    object hits up to the closing hit from the nearest hits it keeps; where more surfaces lie
    before it than its list holds, k = 1, it traces them again; the other engines run the
    two queries, which the tests above hold to the same hits)."""
    house = load(source)
    tracer = HouseTracer(house, "embree")
    base = ViewConfig(with_mesh=False)
    for camera in house_views(house, 2, 64, 48):
        plain = compute_view(house, camera, base, tracer)
        assert plain.intersections is None
        for k in (1, 10):
            both = compute_view(house, camera, ViewConfig(with_mesh=False, layers=LayersConfig(intersections=k)), tracer)
            for name in ("depth", "category", "instance", "normal"):
                assert getattr(both.layers, name).tobytes() == getattr(plain.layers, name).tobytes(), name
            assert both.overhead.layers.depth.tobytes() == plain.overhead.layers.depth.tobytes()
            np.testing.assert_array_equal(both.overhead_camera.params, plain.overhead_camera.params)
            alone = ray_intersections(house, camera, k, tracer)
            for name in ("depth", "normal", "instance", "category", "front_facing"):
                assert getattr(both.intersections, name).tobytes() == getattr(alone, name).tobytes(), name


@NO_EXTENSION
@pytest.mark.parametrize("seed", [0, 4])
def test_the_fused_query_is_the_frontal_query_and_the_nearest_surfaces(seed):
    house = random_house(seed)
    origins, directions = random_rays(np.random.default_rng(30 + seed), 4000)
    tracer = HouseTracer(house, "embree")
    category, _ = instance_labels(house)
    scale = np.ones(len(directions))
    for k in (1, 3, 16):
        hits, surfaces = tracer.frontal_nearest(origins, directions, k, scale, np.eye(3), category)
        frontal = tracer.frontal_query(origins, directions)
        assert_bytes_equal(hits.objects, frontal.objects, ("offsets", "t", "instance", "triangle", "front_facing"))
        assert_bytes_equal(hits.closing, frontal.closing, ("t", "instance", "triangle", "front_facing", "face"))
        assert_bytes_equal(surfaces, tracer.nearest_surfaces(origins, directions, k, scale, np.eye(3), category),
                           SURFACE_FIELDS)


def test_layers_and_intersections_with_the_labels_of_every_layer(cabinet_room):
    house, camera, _ = cabinet_room
    layers, got = layers_and_intersections(house, camera, 4, labels=True)
    alone = frontal_layers(house, camera, labels=True)
    for name in ("depth", "category", "instance", "normal", "layer_category", "layer_instance", "layer_normal"):
        assert getattr(layers, name).tobytes() == getattr(alone, name).tobytes(), name
    assert got.depth.tobytes() == ray_intersections(house, camera, 4).depth.tobytes()


def test_bad_arguments_give_specific_errors(cabinet_room):
    house, camera, _ = cabinet_room
    tracer = HouseTracer(house)
    origins, directions, scale = camera.rays()
    for k in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="k must be an integer >= 1"):
            tracer.nearest_hits(origins, directions, k)
    category, _ = instance_labels(house)
    with pytest.raises(ValueError, match=r"labels must be \(8,\) uint8, got \(3,\)"):
        tracer.nearest_surfaces(origins, directions, 2, scale, np.eye(3), category[:3])
    with pytest.raises(ValueError, match="depth_scale has 3 values"):
        tracer.nearest_surfaces(origins, directions, 2, scale[:3], np.eye(3), category)
    with pytest.raises(ValueError, match=r"layers.intersections must be 0..255"):
        LayersConfig(intersections=256)


# ----------------------------------------------------------------------------- the store


def render(out, *options):
    res = CliRunner().invoke(cli, ["render", "bundled:toy", str(out), "--views-per-house", "1",
                                   "--resolution", "32x24", "--overhead-resolution", "16", "--no-rgb",
                                   *map(str, options)])
    assert res.exit_code == 0, res.output
    return out


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    """A default render of the toy houses and one with ``--intersections 10``."""
    root = tmp_path_factory.mktemp("intersections")
    return render(root / "paper.zarr"), render(root / "k10.zarr", "--intersections", 10)


INTERSECTION_ARRAYS = ["intersections/category", "intersections/depth", "intersections/front_facing",
                       "intersections/instance", "intersections/normal"]


def test_render_with_intersections_stores_them_and_validates(stores):
    paper, k10 = stores
    assert validate_store(str(k10)) == []
    res = CliRunner().invoke(cli, ["validate", str(k10)])
    assert res.exit_code == 0 and "valid" in res.output, res.output
    # the paper's arrays are byte for byte the default render's; a default store has no new ones
    before, after = array_digests(str(paper)), array_digests(str(k10))
    assert not any(name.startswith("intersections") for name in before)
    assert {name: after[name] for name in before} == before
    assert sorted(set(after) - set(before)) == INTERSECTION_ARRAYS
    store = open_store(str(k10))
    assert store.config.view.layers.intersections == 10
    for i in range(len(store)):
        view = store.view(i)
        shapes = {name: (view[name].shape, view[name].dtype) for name in INTERSECTION_ARRAYS}
        assert shapes == {"intersections/category": ((10, 24, 32), np.uint8),
                          "intersections/depth": ((10, 24, 32), np.float32),
                          "intersections/front_facing": ((10, 24, 32), np.bool_),
                          "intersections/instance": ((10, 24, 32), np.int32),
                          "intersections/normal": ((10, 3, 24, 32), np.float32)}
        first = np.fmin(view["depth"][0], view["depth"][4])
        np.testing.assert_array_equal(view["intersections/depth"][0], first)
        assert np.isfinite(view["intersections/depth"][1]).any()  # behind the first surface too


def test_validate_reports_intersections_that_break_the_rules(stores, tmp_path):
    import shutil

    import zarr

    out = tmp_path / "broken.zarr"
    shutil.copytree(stores[1], out)
    group = zarr.open_group(str(out), mode="r+")
    depth = group["intersections/depth"][0]
    r, c = np.argwhere(np.isfinite(depth[1]))[0]
    depth[0, r, c], depth[1, r, c] = depth[1, r, c], depth[0, r, c]  # not ascending, layer 0 too deep
    group["intersections/depth"][0] = depth
    instance = group["intersections/instance"][1]
    instance[9] = 3  # set past the last surface
    group["intersections/instance"][1] = instance
    normal = group["intersections/normal"][2]
    normal[0, :, 0, 0] *= 2
    group["intersections/normal"][2] = normal
    problems = validate_store(str(out))
    assert "intersections/depth: not ascending along the layers: 1 view (0)" in problems
    assert "intersections/depth: layer 0 is deeper than D1 or D5: 1 view (0)" in problems
    assert "intersections/instance is not set exactly where its depth is: 1 view (1)" in problems
    assert "intersections/normal is not of unit length: 1 view (2)" in problems


def test_a_prediction_store_holds_no_intersection_layers():
    """No net predicts them: predict writes its store without them, whatever its source has."""
    pytest.importorskip("torch")
    from sceneforge.config import load_config
    from sceneforge.learn.predict import _prediction_config
    from sceneforge.store import array_specs

    source = load_config(None, {"view": {"layers": {"intersections": 4}}})
    assert "intersections/depth" in {s.name for s in array_specs(source)}
    assert not any(s.name.startswith("intersections/") for s in array_specs(_prediction_config(source)))
