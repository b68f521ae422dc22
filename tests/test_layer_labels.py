"""The labels of every layer (docs/spec.md §4.7): a class, an instance and a winding normal for
each of D1..D5, exact on a box room, the compiled rules equal to the numpy ones and the fast
engine to the reference on every pixel, and in a store only with ``--labels all``."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner
from sceneforge.cli.main import cli

from sceneforge import layers as layers_module
from sceneforge.camera_sampler import CameraSamplerConfig, sample_cameras
from sceneforge.conventions import NYU40_IDS, tol
from sceneforge.houses import BUNDLED_TOY, House, discover, load
from sceneforge.layers import first_hit_normals, frontal_layers, instance_labels, layers_from_hits
from sceneforge.raytrace import HouseTracer
from sceneforge.store import array_digests, open_store, validate_store

from .conftest import BREAKFAST_ROOM, needs_shared
from .test_layers import (
    CABINET,
    FLOOR,
    WALL,
    H,
    W,
    add_box,
    add_quad,
    forward_camera,
    pixel,
    random_object_hits,
)

SHELVES = NYU40_IDS["shelves"]
NAN3 = [np.nan] * 3
LABELS = ("layer_category", "layer_instance", "layer_face", "layer_normal")


def open_room() -> House:
    """Interior x 0..4, y 0..3, z 0..6 m: 0.1 m slabs for floor, ceiling and three walls
    (``trimesh`` boxes: outward winding), and a far wall at z = 6 that is one single-sided
    quad whose winding normal is +z: away from the room, so that a camera looking along +z
    sees its back."""
    h = House(id="labels_room", instances=[])
    add_box(h, "floor", FLOOR, (-0.1, -0.1, -0.1), (4.1, 0, 6.1))
    add_box(h, "ceiling", NYU40_IDS["ceiling"], (-0.1, 3, -0.1), (4.1, 3.1, 6.1))
    add_box(h, "wall_left", WALL, (-0.1, 0, 0), (0, 3, 6))
    add_box(h, "wall_right", WALL, (4, 0, 0), (4.1, 3, 6))
    add_box(h, "wall_back", WALL, (0, 0, -0.1), (4, 3, 0))
    add_quad(h, "wall_far", WALL, np.array([[0, 0, 6], [4, 0, 6], [4, 3, 6], [0, 3, 6]], dtype=float))
    return h


@pytest.fixture(scope="module")
def box_room():
    """The room with a cabinet B (z 3..4) and shelves C behind it (z 4.5..5); the camera at
    z = 1 looks along +z (camera z = world z, camera y = -world y)."""
    h = open_room()
    b = add_box(h, "B", CABINET, (1.5, 0, 3), (2.5, 1, 4))
    c = add_box(h, "C", SHELVES, (1.0, 0, 4.5), (3.0, 2, 5.0))
    camera = forward_camera()
    tracer = HouseTracer(h)
    layers = frontal_layers(h, camera, tracer, labels=True)
    ids = {i.name: i.id for i in h.instances}
    return h, camera, tracer, layers, (b.id, c.id, ids["floor"], ids["wall_far"])


def labels_at(layers, rc):
    r, c = rc
    return (layers.depth[:, r, c], layers.layer_category[:, r, c], layers.layer_instance[:, r, c],
            layers.layer_normal[:, :, r, c])


def test_box_room_labels_of_every_layer_at_the_centre(box_room):
    h, camera, _, layers, (b, c, _, far) = box_room
    depth, category, instance, normal = labels_at(layers, pixel(camera, (2.0, 0.5, 3.0)))
    np.testing.assert_allclose(depth, [2.0, 3.0, 3.5, 4.0, 5.0], rtol=1e-6)
    np.testing.assert_array_equal(category, [CABINET, CABINET, SHELVES, SHELVES, WALL])
    np.testing.assert_array_equal(instance, [b, b, c, c, far])
    # B's front, B's back, C's front, C's back (outward), the far wall's winding normal (+z):
    # seen from behind and, unlike the first-hit normal, not turned to face the camera
    np.testing.assert_array_equal(normal, [[0, 0, -1], [0, 0, 1], [0, 0, -1], [0, 0, 1], [0, 0, 1]])


def test_box_room_labels_where_b_is_left_through_its_bottom_onto_the_floor(box_room):
    """10.5 px below the centre row the ray leaves B through its bottom face (outward world
    -y, camera +y) where the floor's top (world +y, camera -y) closes it, at one distance."""
    _, camera, _, layers, (b, _, floor, _) = box_room
    row, col = 34, W // 2
    y_cam = (row + 0.5 - camera.K[1, 2]) / camera.K[1, 1]
    depth, category, instance, normal = labels_at(layers, (row, col))
    np.testing.assert_allclose(depth, [2.0, 0.5 / y_cam, np.nan, np.nan, 0.5 / y_cam], rtol=1e-6)
    np.testing.assert_array_equal(category, [CABINET, CABINET, 0, 0, FLOOR])
    np.testing.assert_array_equal(instance, [b, b, -1, -1, floor])
    np.testing.assert_array_equal(normal, [[0, 0, -1], [0, 1, 0], NAN3, NAN3, [0, -1, 0]])


def test_box_room_labels_of_a_floor_only_pixel(box_room):
    _, _, _, layers, (_, _, floor, _) = box_room
    _, category, instance, normal = labels_at(layers, (H - 1, 5))
    np.testing.assert_array_equal(category, [0, 0, 0, 0, FLOOR])
    np.testing.assert_array_equal(instance, [-1, -1, -1, -1, floor])
    np.testing.assert_array_equal(normal, [NAN3] * 4 + [[0, -1, 0]])


def assert_labels_follow_the_rules(layers, tracer):
    """What the labels of every layer must hold beside the paper's arrays (as ``sceneforge
    validate`` checks them), and that each layer's face is of the layer's instance."""
    for name, dtype, shape in (("layer_category", np.uint8, (5, *layers.shape)),
                               ("layer_instance", np.int32, (5, *layers.shape)),
                               ("layer_face", np.int64, (5, *layers.shape)),
                               ("layer_normal", np.float32, (5, 3, *layers.shape))):
        a = getattr(layers, name)
        assert a.dtype == dtype and a.shape == shape, name
    f = np.isfinite(layers.depth)
    np.testing.assert_array_equal(layers.layer_category[[0, 2, 4]], layers.category)
    np.testing.assert_array_equal(layers.layer_instance[[0, 2]], layers.instance)
    np.testing.assert_array_equal(layers.layer_instance >= 0, f)
    np.testing.assert_array_equal(layers.layer_face >= 0, f)
    assert (layers.layer_category[~f] == 0).all()
    face = layers.layer_face
    np.testing.assert_array_equal(tracer.triangles.instance[face[f]], layers.layer_instance[f])
    normal = layers.layer_normal
    np.testing.assert_array_equal(np.isfinite(normal).all(axis=1), f)
    np.testing.assert_array_equal(np.isfinite(normal).any(axis=1), f)
    np.testing.assert_allclose(np.linalg.norm(normal.transpose(1, 0, 2, 3)[:, f], axis=0), 1, atol=tol.stored_normal)
    # where D1 is nearer than D5 its face is the first hit: the first-hit normal up to facing
    first = f[0] & ~(layers.depth[4] <= layers.depth[0])
    cos = np.abs((normal[0] * layers.normal).sum(axis=0))[first]
    np.testing.assert_allclose(cos, 1, atol=tol.stored_normal)


def test_box_room_labels_follow_the_rules_and_the_reference_engine(box_room):
    h, camera, tracer, layers, _ = box_room
    assert_labels_follow_the_rules(layers, tracer)
    assert_same_labels(layers, all_hit_layers(h, camera, HouseTracer(h, backend="reference")))


def all_hit_layers(house, camera, tracer):
    """The layers with labels from every hit of every ray (what the frontal query shortcuts)."""
    origins, directions, scale = camera.rays()
    hits = tracer.all_hits(origins, directions)
    return layers_from_hits(hits, scale, *instance_labels(house), camera.shape,
                            normals=first_hit_normals(hits, tracer, camera),
                            triangles=tracer.triangles, camera=camera)


def assert_same_labels(a, b):
    for name in ("depth", "category", "instance", "layer_category", "layer_instance", "layer_face"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    np.testing.assert_allclose(a.layer_normal, b.layer_normal, atol=1e-6)


def test_default_layers_carry_no_labels_and_the_same_paper_arrays(box_room):
    h, camera, tracer, labelled, _ = box_room
    plain = frontal_layers(h, camera, tracer)
    assert all(getattr(plain, name) is None for name in LABELS)
    for name in ("depth", "category", "instance", "normal"):
        assert getattr(plain, name).tobytes() == getattr(labelled, name).tobytes(), name


def test_labels_need_both_the_triangles_and_the_camera(box_room):
    h, camera, tracer, _, _ = box_room
    origins, directions, scale = camera.rays()
    hits = tracer.frontal_query(origins, directions)
    category, _ = instance_labels(h)
    with pytest.raises(ValueError, match="both the house's triangles and the camera"):
        layers_module.layers_from_frontal(hits, scale, category, camera.shape, triangles=tracer.triangles)
    o = hits.objects
    with pytest.raises(ValueError, match="both face and closing_face"):
        layers_module.apply_rules(o.offsets, o.t, o.instance, hits.closing.t, hits.closing.instance, scale,
                                  category, camera.shape, face=np.zeros(len(o.t), np.int64))


# ------------------------------------------------------------- compiled rules vs numpy rules

COMPILED = pytest.mark.skipif(not layers_module.COMPILED_RULES, reason="sceneforge's Embree extension is not built")


def rules_both_ways(*args, **kwargs):
    return [layers_module.apply_rules(*args, **kwargs, compiled=c) for c in (True, False)]


@COMPILED
@pytest.mark.parametrize("seed", range(4))
def test_compiled_rules_name_the_same_hits_as_the_numpy_rules_on_random_hits(seed):
    rng = np.random.default_rng(seed)
    H_, W_ = 30, 40
    n_instances = (2, 3, 6, 40)[seed]
    offsets, t, inst, closing_t, closing_inst = random_object_hits(rng, H_ * W_, n_instances)
    category = rng.integers(1, 41, n_instances + 1).astype(np.uint8)
    face = np.arange(len(t), dtype=np.int64) + 1000  # each hit its own face: the layers name hits
    closing_face = np.where(closing_inst >= 0, np.arange(H_ * W_), -1)
    scale = rng.uniform(0.7, 1.0, H_ * W_)
    got, want = rules_both_ways(offsets, t, inst, closing_t, closing_inst, scale, category, (H_, W_),
                                face=face, closing_face=closing_face)
    assert np.isfinite(want.depth[2]).sum() > 50  # D3 is exercised
    for name in ("depth", "category", "instance", "layer_category", "layer_instance", "layer_face"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        assert a.tobytes() == b.tobytes(), name
    # the named hits are the layers' hits: of the layers' instances, at the layers' depths
    hit = want.layer_face[:4].reshape(4, -1) - 1000
    f = hit >= 0
    np.testing.assert_array_equal(f, np.isfinite(want.depth[:4].reshape(4, -1)))
    np.testing.assert_array_equal(inst[hit[f]], want.layer_instance[:4].reshape(4, -1)[f])
    pixel_scale = np.broadcast_to(scale, (4, H_ * W_))[f]
    np.testing.assert_array_equal((t[hit[f]] * pixel_scale).astype(np.float32), want.depth[:4].reshape(4, -1)[f])
    np.testing.assert_array_equal(want.layer_face[4].reshape(-1), closing_face)


@COMPILED
@pytest.mark.parametrize("source", [pytest.param(s, id=s.id) for s in discover(BUNDLED_TOY)] + [
    pytest.param(BREAKFAST_ROOM, id="breakfast_room", marks=needs_shared(BREAKFAST_ROOM))])
def test_labels_of_house_views_compiled_equal_numpy_and_fast_equal_reference(source):
    """Every pixel of the labels of two views of each house: compiled rules against the numpy
    rules, the frontal query against every hit of the fast engine (and, on the toy houses,
    of the reference engine), and the rules the validator checks."""
    house = load(source)
    tracer = HouseTracer(house)
    sampler = CameraSamplerConfig(width=W, height=H, max_escape_fraction=0.5)
    cameras, _ = sample_cameras(house, 2, np.random.default_rng(3), sampler, tracer)
    assert cameras
    category, _ = instance_labels(house)
    engines = [tracer] + ([HouseTracer(house, backend="reference")] if source != BREAKFAST_ROOM else [])
    for camera in cameras:
        origins, directions, scale = camera.rays()
        hits = tracer.frontal_query(origins, directions)
        o = hits.objects
        face = tracer.triangles.global_index(o.instance, o.triangle)
        got, want = rules_both_ways(o.offsets, o.t, o.instance, hits.closing.t, hits.closing.instance, scale,
                                    category, camera.shape, face=face, closing_face=hits.closing.face)
        assert np.isfinite(want.depth[0]).any()
        for name in ("depth", "category", "instance", "layer_category", "layer_instance", "layer_face"):
            assert getattr(got, name).tobytes() == getattr(want, name).tobytes(), name
        layers = frontal_layers(house, camera, tracer, labels=True)
        assert_labels_follow_the_rules(layers, tracer)
        for engine in engines:
            assert_same_labels(layers, all_hit_layers(house, camera, engine))


# ----------------------------------------------------------------------------- the store


def render(out, *options):
    res = CliRunner().invoke(cli, ["render", "bundled:toy", str(out), "--views-per-house", "1",
                                   "--resolution", "32x24", "--overhead-resolution", "16", "--no-rgb",
                                   *map(str, options)])
    assert res.exit_code == 0, res.output
    return out


def test_render_with_labels_all_stores_them_and_validates(tmp_path):
    config = tmp_path / "normals.json"  # with the first-hit normals, which D1's is checked against
    config.write_text('{"store": {"normals": true}}')
    paper = render(tmp_path / "paper.zarr", "--config", config)
    labelled = render(tmp_path / "all.zarr", "--config", config, "--labels", "all")
    assert validate_store(str(labelled)) == []
    res = CliRunner().invoke(cli, ["validate", str(labelled)])
    assert res.exit_code == 0 and "valid" in res.output, res.output
    # the paper's arrays are byte for byte the default render's; only the labels are new
    before, after = array_digests(str(paper)), array_digests(str(labelled))
    assert {name: after[name] for name in before} == before
    assert sorted(set(after) - set(before)) == ["layers/category", "layers/instance", "layers/normal"]
    store = open_store(str(labelled))
    view = store.view(0)
    assert view["layers/category"].shape == (5, 24, 32) and view["layers/category"].dtype == np.uint8
    assert view["layers/instance"].shape == (5, 24, 32) and view["layers/instance"].dtype == np.int32
    assert view["layers/normal"].shape == (5, 3, 24, 32) and view["layers/normal"].dtype == np.float32
    np.testing.assert_array_equal(view["layers/category"][[0, 2, 4]], view["category"])
    assert np.isfinite(view["layers/normal"][4]).all()


def test_validate_reports_labels_that_break_the_rules(tmp_path):
    import zarr

    config = tmp_path / "normals.json"
    config.write_text('{"store": {"normals": true}}')
    out = render(tmp_path / "all.zarr", "--config", config, "--labels", "all")
    group = zarr.open_group(str(out), mode="r+")
    inst = group["layers/instance"][0]
    d1 = np.argwhere(inst[0] >= 0)[0]
    inst[1][tuple(d1)] = inst[0][tuple(d1)] + 1  # D2 of another instance than D1
    group["layers/instance"][0] = inst
    normal = group["layers/normal"][1]
    normal[4, :, 0, 0] *= 2  # D5's normal not of unit length
    group["layers/normal"][1] = normal
    category = group["layers/category"][2]
    category[4] = 0  # D5 without its class
    group["layers/category"][2] = category
    normal = group["layers/normal"][2]
    r, c = np.argwhere(np.isfinite(group["depth"][2][0]))[0]
    normal[0, :, r, c] = np.roll(normal[0, :, r, c], 1)  # unit, but not D1's face's
    group["layers/normal"][2] = normal
    problems = validate_store(str(out))
    assert "layers/category, layers/instance: D2 is not labelled as D1, or D4 as D3: 1 view (0)" in problems
    assert "layers/normal is not of unit length: 1 view (1)" in problems
    assert "layers/category of D1, D3, D5 is not the category array: 1 view (2)" in problems
    assert ("layers/normal of D1 is not the first-hit normal (up to its facing) where D1 is the first hit: "
            "1 view (2)") in problems


def test_a_prediction_store_holds_no_labels_of_every_layer():
    """No net predicts them: predict writes its store without them, whatever its source has."""
    pytest.importorskip("torch")
    from sceneforge.config import load_config
    from sceneforge.learn.predict import _prediction_config
    from sceneforge.store import array_specs

    source = load_config(None, {"view": {"layers": {"labels": "all"}}})
    assert "layers/normal" in {s.name for s in array_specs(source)}
    assert not any(s.name.startswith("layers/") for s in array_specs(_prediction_config(source)))
