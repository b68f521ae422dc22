"""The all-hit tracer: the fast engines (sceneforge's Embree extension, Open3D) against the
numpy reference and each other, hit for hit, and the hit rules they share (plane distances,
sorting, merging same-instance hits)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from sceneforge.camera_sampler import CameraSamplerConfig, sample_cameras
from sceneforge.conventions import tol
from sceneforge.errors import HouseError, MissingDependencyError
from sceneforge.houses import BUNDLED_TOY, House, discover, load, make_instance
from sceneforge.raytrace import HouseTracer, Rays, _plane_distance, default_backend
from sceneforge.raytrace import embree_backend as embree
from sceneforge.raytrace.reference import moller_trumbore

NO_EXTENSION = pytest.mark.skipif(not embree.AVAILABLE, reason="sceneforge's Embree extension is not built")
#: the fast engines: the Embree extension (where it is built) and Open3D
FAST = (pytest.param("embree", marks=NO_EXTENSION), "open3d")
BACKENDS = (*FAST, "reference")
HIT_FIELDS = ("offsets", "t", "instance", "triangle", "front_facing")


def assert_same_hits(a, b):
    for name in HIT_FIELDS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def add_box(house: House, name: str, category: int, lo, hi):
    b = trimesh.creation.box(bounds=[lo, hi])
    return make_instance(house, name=name, category=category, label=name, room_id=None,
                         vertices=b.vertices, faces=b.faces)


def add_quad(house: House, name: str, category: int, corners):
    """A single-sided quad; corners (4, 3) counter-clockwise seen from its front."""
    return make_instance(house, name=name, category=category, label=name, room_id=None,
                         vertices=corners, faces=[[0, 1, 2], [0, 2, 3]])


def random_house(seed: int) -> House:
    """Triangle soups (objects and envelope) and closed boxes (some touching) in a 2 m cube."""
    rng = np.random.default_rng(seed)
    h = House(id=f"random{seed}", instances=[])
    for k, category in enumerate((40, 40, 1, 1)):
        v = rng.uniform(0, 2, (30, 3))
        make_instance(h, name=f"soup{k}", category=category, label="soup", room_id=None,
                      vertices=v, faces=rng.integers(0, 30, (20, 3)))
    for k in range(3):
        lo = rng.uniform(0, 1.5, 3)
        add_box(h, f"box{k}", 3, lo, lo + rng.uniform(0.1, 0.5, 3))
    lo = h.instances[-1].vertices.min(0)
    add_box(h, "touching", 3, lo - [0.3, 0, 0], lo + [0, 0.2, 0.2])
    return h


def random_rays(rng, n: int):
    origins = rng.uniform(-0.5, 2.5, (n, 3))
    directions = rng.normal(size=(n, 3))
    return origins, directions / np.linalg.norm(directions, axis=1, keepdims=True)


@pytest.mark.parametrize("backend", FAST)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fast_engine_equals_reference_hit_for_hit(backend, seed):
    house = random_house(seed)
    origins, directions = random_rays(np.random.default_rng(100 + seed), 2000)
    fast = HouseTracer(house, backend=backend).all_hits(origins, directions)
    ref = HouseTracer(house, backend="reference").all_hits(origins, directions)
    assert len(ref.t) > 1000
    np.testing.assert_array_equal(fast.offsets, ref.offsets)
    np.testing.assert_array_equal(fast.instance, ref.instance)
    np.testing.assert_array_equal(fast.triangle, ref.triangle)
    np.testing.assert_array_equal(fast.front_facing, ref.front_facing)
    np.testing.assert_allclose(fast.t, ref.t, rtol=0, atol=1e-12)


@pytest.mark.parametrize("backend", FAST)
@pytest.mark.parametrize("seed", [0, 1])
def test_hits_are_sorted_real_crossings(backend, seed):
    """Every reported hit lies on its triangle, at its distance, in ascending order per ray."""
    house = random_house(seed)
    origins, directions = random_rays(np.random.default_rng(seed), 500)
    tracer = HouseTracer(house, backend=backend)
    hits = tracer.all_hits(origins, directions)
    ray = hits.ray_ids()
    same_ray = ray[1:] == ray[:-1]
    assert (np.diff(hits.t)[same_ray] >= 0).all()
    corners = np.stack([house.instances[i].vertices[house.instances[i].faces[f]]
                        for i, f in zip(hits.instance, hits.triangle)])
    hit, t_mt = moller_trumbore(origins[ray], directions[ray], corners[:, 0], corners[:, 1], corners[:, 2])
    assert hit.all()
    np.testing.assert_allclose(hits.t, t_mt, rtol=1e-9, atol=1e-9)
    normal = tracer.face_normals(hits.instance, hits.triangle)
    np.testing.assert_array_equal(hits.front_facing, np.einsum("ij,ij->i", normal, directions[ray]) < 0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_shared_edge_counts_once_and_back_faces_count(backend):
    """A ray through the diagonal of each face of a box: two hits, entry (front) and exit (back)."""
    h = House(id="box", instances=[])
    add_box(h, "box", 3, (0, 0, 0), (1, 1, 1))
    hits = HouseTracer(h, backend=backend).all_hits([[0.5, 2.0, 0.5]], [[0.0, -1.0, 0.0]])
    np.testing.assert_array_equal(hits.offsets, [0, 2])
    np.testing.assert_allclose(hits.t, [1.0, 2.0], atol=1e-12)
    np.testing.assert_array_equal(hits.front_facing, [True, False])


@pytest.mark.parametrize("backend", BACKENDS)
def test_coincident_hits_of_different_instances_are_all_kept(backend):
    """A cabinet standing on the floor and against a wall: the ray leaving the cabinet through
    its bottom or back also hits the floor or the wall at the same distance. (Open3D's own
    filter drops a hit equal in distance to the previous one of the same geometry, which is
    why each instance is a separate geometry.)"""
    h = House(id="touch", instances=[])
    add_box(h, "floor", 2, (-2, -0.1, -2), (2, 0, 2))
    add_box(h, "wall", 1, (-2, 0, 1), (2, 3, 1.1))
    add_box(h, "cabinet", 3, (-0.5, 0, 0.5), (0.5, 1, 1))
    tracer = HouseTracer(h, backend=backend)
    down = tracer.all_hits([[0.0, 2.0, 0.75]], [[0.0, -1.0, 0.0]])
    # exact ties are ordered by instance index
    np.testing.assert_allclose(down.t, [1.0, 2.0, 2.0, 2.1], atol=1e-12)
    np.testing.assert_array_equal(down.instance, [2, 0, 2, 0])
    forward = tracer.all_hits([[0.0, 0.5, 0.0]], [[0.0, 0.0, 1.0]])
    np.testing.assert_allclose(forward.t, [0.5, 1.0, 1.0, 1.1], atol=1e-12)
    np.testing.assert_array_equal(forward.instance, [2, 1, 2, 1])


@pytest.mark.parametrize("backend", BACKENDS)
def test_same_instance_hits_merge_within_tolerance(backend):
    """Two sheets of one instance 5e-5 m apart count once; 2e-4 m apart they count twice."""
    h = House(id="sheets", instances=[])
    for name, gap in (("close", 5e-5), ("apart", 2e-4)):
        x0 = 0.0 if name == "close" else 2.0
        corners = np.array([[x0, 0, 0], [x0 + 1, 0, 0], [x0 + 1, 0, 1], [x0, 0, 1]], dtype=float)
        make_instance(h, name=name, category=40, label=name, room_id=None,
                      vertices=np.r_[corners, corners + [0, -gap, 0]],
                      faces=[[0, 2, 1], [0, 3, 2], [4, 6, 5], [4, 7, 6]])
    hits = HouseTracer(h, backend=backend).all_hits([[0.3, 1.0, 0.6], [2.3, 1.0, 0.6]], [[0, -1.0, 0]] * 2)
    np.testing.assert_array_equal(hits.counts, [1, 2])
    np.testing.assert_allclose(hits.t, [1.0, 1.0, 1.0002], atol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_frontal_hits_are_all_hits_up_to_the_first_envelope_hit(backend):
    """Every object hit up to 1 mm behind the first envelope hit, and that envelope hit."""
    house = random_house(4)
    assert {i.envelope for i in house.instances} == {True, False}
    origins, directions = random_rays(np.random.default_rng(8), 1000)
    tracer = HouseTracer(house, backend=backend)
    every = tracer.all_hits(origins, directions)
    ray = every.ray_ids()
    envelope = np.array([i.envelope for i in house.instances])[every.instance]
    first_wall = np.full(len(origins), np.inf)
    np.minimum.at(first_wall, ray[envelope], every.t[envelope])
    expected = np.where(envelope, every.t == first_wall[ray], every.t <= first_wall[ray] + tol.envelope_slack)
    assert 0 < expected.sum() < len(expected)
    frontal = tracer.frontal_hits(origins, directions)
    wanted = every.select(expected)
    np.testing.assert_array_equal(frontal.offsets, wanted.offsets)
    np.testing.assert_array_equal(frontal.instance, wanted.instance)
    np.testing.assert_array_equal(frontal.triangle, wanted.triangle)
    np.testing.assert_array_equal(frontal.t, wanted.t)


@pytest.mark.parametrize("backend", BACKENDS)
def test_frontal_query_is_frontal_hits_split_at_the_closing_hit(backend):
    """Objects (sorted, cut 1 mm behind the closing hit) and the closing hit per ray: the
    same hits as :meth:`frontal_hits`, which sorts them together."""
    house = random_house(5)
    origins, directions = random_rays(np.random.default_rng(9), 1000)
    tracer = HouseTracer(house, backend=backend)
    merged = tracer.frontal_hits(origins, directions)
    split = tracer.frontal_query(origins, directions)
    envelope = np.array([i.envelope for i in house.instances])
    is_wall = envelope[merged.instance]
    objects = merged.select(~is_wall)
    for name in ("offsets", "t", "instance", "triangle", "front_facing"):
        np.testing.assert_array_equal(getattr(split.objects, name), getattr(objects, name))
    walls = merged.select(is_wall)
    closed = walls.counts > 0
    assert (walls.counts <= 1).all() and 0 < closed.sum() < len(closed)
    np.testing.assert_array_equal(split.closing.hit, closed)
    np.testing.assert_array_equal(split.closing.t[closed], walls.t)
    np.testing.assert_array_equal(split.closing.instance[closed], walls.instance)
    np.testing.assert_array_equal(split.closing.triangle[closed], walls.triangle)
    np.testing.assert_array_equal(split.closing.front_facing[closed], walls.front_facing)
    assert np.isnan(split.closing.t[~closed]).all() and (split.closing.face[~closed] == -1).all()


@pytest.mark.parametrize("backend", FAST)
def test_shared_origin_or_direction_gives_the_same_hits(backend):
    """A camera passes its origin (an orthographic view its direction) as one broadcast row;
    the distances are computed per face then, and must not change by a bit."""
    house = random_house(6)
    tracer = HouseTracer(house, backend=backend)
    rng = np.random.default_rng(10)
    _, directions = random_rays(rng, 3000)
    origin = np.array([1.0, 1.0, 1.0])
    full = tracer.all_hits(np.tile(origin, (3000, 1)), directions)
    shared = tracer.all_hits(np.broadcast_to(origin, (3000, 3)), directions)
    origins, _ = random_rays(rng, 3000)
    down = np.array([0.0, -1.0, 0.0])
    full_d = tracer.frontal_hits(origins, np.tile(down, (3000, 1)))
    shared_d = tracer.frontal_hits(origins, np.broadcast_to(down, (3000, 3)))
    for a, b in ((full, shared), (full_d, shared_d)):
        assert len(a.t) > len(tracer.triangles.faces)  # more hits than faces: the per-face path
        for name in ("offsets", "t", "instance", "triangle", "front_facing"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    few = tracer.all_hits(np.broadcast_to(origin, (5, 3)), directions[:5])  # per-hit path
    np.testing.assert_array_equal(few.t, tracer.all_hits(np.tile(origin, (5, 1)), directions[:5]).t)


@pytest.mark.parametrize("backend", BACKENDS)
def test_frontal_hits_without_objects_or_without_envelope(backend):
    walls = House(id="walls", instances=[])
    add_box(walls, "wall", 1, (0, 0, 1), (1, 1, 1.1))
    hits = HouseTracer(walls, backend=backend).frontal_hits([[0.5, 0.5, 0]] * 2, [[0, 0, 1.0], [0, 0, -1.0]])
    np.testing.assert_array_equal(hits.offsets, [0, 1, 1])
    np.testing.assert_allclose(hits.t, [1.0])
    boxes = House(id="boxes", instances=[])
    add_box(boxes, "box", 3, (0, 0, 1), (1, 1, 1.1))
    hits = HouseTracer(boxes, backend=backend).frontal_hits([[0.5, 0.5, 0]], [[0, 0, 1.0]])
    np.testing.assert_allclose(hits.t, [1.0, 1.1])


@pytest.mark.parametrize("backend", BACKENDS)
def test_first_hit_is_the_first_of_all_hits(backend):
    house = random_house(3)
    origins, directions = random_rays(np.random.default_rng(7), 1000)
    tracer = HouseTracer(house, backend=backend)
    hits = tracer.all_hits(origins, directions)
    first = tracer.first_hit(origins, directions)
    has = hits.counts > 0
    assert (~has).any() and has.any()
    np.testing.assert_array_equal(first.hit, has)
    i = hits.offsets[:-1][has]
    np.testing.assert_allclose(first.t[has], hits.t[i], atol=1e-12)
    np.testing.assert_array_equal(first.instance[has], hits.instance[i])
    np.testing.assert_array_equal(first.front_facing[has], hits.front_facing[i])
    np.testing.assert_allclose(first.normal[has], tracer.face_normals(hits.instance[i], hits.triangle[i]))
    assert np.isnan(first.t[~has]).all() and (first.instance[~has] == -1).all()
    assert np.isnan(first.normal[~has]).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_closest_distance(backend):
    h = House(id="box", instances=[])
    add_box(h, "box", 3, (0, 0, 0), (1, 2, 3))
    points = [[0.5, 1.0, 1.5], [-0.3, 1.0, 1.0], [2.0, 3.0, 1.0], [0.5, 0.5, -0.25]]
    expected = [0.5, 0.3, np.hypot(1.0, 1.0), 0.25]
    np.testing.assert_allclose(HouseTracer(h, backend=backend).closest_distance(points), expected, atol=1e-6)


def test_hits_select_keeps_csr_layout():
    house = random_house(0)
    origins, directions = random_rays(np.random.default_rng(1), 300)
    hits = HouseTracer(house).all_hits(origins, directions)
    keep = hits.instance % 2 == 0
    sub = hits.select(keep)
    np.testing.assert_array_equal(sub.ray_ids(), hits.ray_ids()[keep])
    np.testing.assert_array_equal(sub.t, hits.t[keep])


def test_bad_input_gives_specific_errors():
    with pytest.raises(HouseError, match="empty.*no triangles"):
        HouseTracer(House(id="empty", instances=[]))
    h = House(id="box", instances=[])
    add_box(h, "box", 3, (0, 0, 0), (1, 1, 1))
    with pytest.raises(ValueError, match="backend 'embree9'.*embree, open3d, reference"):
        HouseTracer(h, backend="embree9")
    tracer = HouseTracer(h)
    with pytest.raises(ValueError, match="unit vectors"):
        tracer.all_hits([[0, 0, 0]], [[0, 0, 2.0]])
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        tracer.all_hits([[0, 0, 0]], [[0, 0, 1.0], [1, 0, 0]])
    with pytest.raises(ValueError, match="finite"):
        tracer.first_hit([[0, np.nan, 0]], [[0, 0, 1.0]])
    empty = tracer.all_hits(np.zeros((0, 3)), np.zeros((0, 3)))
    assert empty.n_rays == 0 and len(empty.t) == 0


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("seed", [0, 1])
def test_instance_subset_equals_dropping_the_other_instances(backend, seed):
    house = random_house(seed)
    rng = np.random.default_rng(seed)
    origins, directions = random_rays(rng, 500)
    tracer = HouseTracer(house, backend)
    subset = rng.random(len(house.instances)) < 0.5
    everything = tracer.all_hits(origins, directions)
    expected = everything.select(subset[everything.instance])
    got = tracer.all_hits(origins, directions, instances=subset)
    for field in ("offsets", "t", "instance", "triangle", "front_facing"):
        np.testing.assert_array_equal(getattr(got, field), getattr(expected, field))
    assert len(got.t) < len(everything.t)
    with pytest.raises(ValueError, match="instances must be"):
        tracer.all_hits(origins, directions, instances=subset[:-1])


@pytest.mark.parametrize("backend", FAST)
def test_engine_threads_do_not_change_the_hits(monkeypatch, backend):
    house = random_house(7)
    origins, directions = random_rays(np.random.default_rng(11), 3000)
    every_core = HouseTracer(house, backend).frontal_query(origins, directions)
    monkeypatch.setenv("SCENEFORGE_TRACE_THREADS", "1")
    one = HouseTracer(house, backend)
    assert one.threads == 1 and HouseTracer(house, backend, threads=2).threads == 2
    single = one.frontal_query(origins, directions)
    three = HouseTracer(house, backend, threads=3).frontal_query(origins, directions)
    for other in (single, three):
        assert_same_hits(other.objects, every_core.objects)
        np.testing.assert_array_equal(other.closing.face, every_core.closing.face)
    with pytest.raises(ValueError, match="threads"):
        HouseTracer(house, threads=-1)


@pytest.mark.parametrize("backend", BACKENDS)
def test_envelope_hits_nearer_than_envelope_near_do_not_close_the_ray(backend):
    """The overhead view ignores floors within 0.5 m below its camera: the ray is closed by
    the next envelope hit beyond, and objects between the two are kept."""
    h = House(id="storeys", instances=[])
    upper = add_box(h, "upper_floor", 2, (0, 2.9, 0), (2, 3.0, 2))
    add_box(h, "table", 7, (0.5, 0.0, 0.5), (1.0, 0.8, 1.0))
    lower = add_box(h, "lower_floor", 2, (0, -0.1, 0), (2, 0.0, 2))
    tracer = HouseTracer(h, backend=backend)
    origins = [[0.75, 3.3, 0.75], [1.5, 3.3, 1.5], [1.5, 3.8, 1.5]]
    down = [[0.0, -1.0, 0.0]] * 3
    query = tracer.frontal_query(origins, down, envelope_near=0.5)
    # rays 0 and 1 start 0.3 m above the upper floor: it is skipped, the lower floor closes
    np.testing.assert_array_equal(query.closing.instance, [lower.id, lower.id, upper.id])
    np.testing.assert_allclose(query.closing.t, [3.3, 3.3, 0.8])
    np.testing.assert_array_equal(query.objects.counts, [2, 0, 0])  # the table's top and bottom
    np.testing.assert_allclose(query.objects.t, [2.5, 3.3])


# ------------------------------------------------------------------ the Embree extension


@NO_EXTENSION
@pytest.mark.parametrize("seed", [4, 5])
def test_embree_engine_equals_open3d_engine_bit_for_bit(seed):
    """Every query of the extension against the Open3D engine it replaces: the same hits to
    the last bit (the extension collects them itself; Open3D's go through numpy)."""
    house = random_house(seed)
    origins, directions = random_rays(np.random.default_rng(20 + seed), 3000)
    ours, theirs = HouseTracer(house, "embree"), HouseTracer(house, "open3d")
    assert_same_hits(ours.all_hits(origins, directions), theirs.all_hits(origins, directions))
    a, b = ours.frontal_query(origins, directions), theirs.frontal_query(origins, directions)
    assert_same_hits(a.objects, b.objects)
    np.testing.assert_array_equal(a.closing.face, b.closing.face)
    np.testing.assert_array_equal(a.closing.t, b.closing.t)
    assert_same_hits(ours.frontal_hits(origins, directions), theirs.frontal_hits(origins, directions))
    # closing hits nearer than envelope_near looked for again past it (the overhead view)
    a, b = (tr.frontal_query(origins, directions, envelope_near=0.8) for tr in (ours, theirs))
    assert_same_hits(a.objects, b.objects)
    for name in ("t", "instance", "triangle", "front_facing", "face"):
        np.testing.assert_array_equal(getattr(a.closing, name), getattr(b.closing, name), err_msg=name)
    assert (np.nan_to_num(a.closing.t, nan=1.0) >= 0.8).all()
    # first hits: the extension computes their distances itself, the Open3D engine's go
    # through numpy; shared origins (a camera) and per-ray ones, among a subset too
    envelope = ours.triangles.envelope
    for o, inst in ((origins, None), (np.broadcast_to(origins[0], origins.shape), None), (origins, envelope)):
        mine, other = ours.first_hit(o, directions, inst), theirs.first_hit(o, directions, inst)
        assert mine.hit.any() and (~mine.hit).any()
        for name in ("t", "instance", "triangle", "front_facing", "face"):
            got, want = getattr(mine, name), getattr(other, name)
            assert got.dtype == want.dtype and got.tobytes() == want.tobytes(), name
    # the engines' raw crossings (the Backend interface), cut like a frontal query's
    rays = Rays.check(origins, directions)
    cutoff = np.where(np.isnan(a.closing.t), np.inf, a.closing.t + tol.envelope_slack)
    crossings = [np.unique(np.c_[tr.backend.intersect_all(rays, None, cutoff)], axis=0) for tr in (ours, theirs)]
    np.testing.assert_array_equal(*crossings)
    points = origins[:50]
    np.testing.assert_allclose(ours.closest_distance(points), theirs.closest_distance(points), rtol=0, atol=1e-5)


@NO_EXTENSION
def test_every_engine_keeps_the_same_one_of_coincident_faces():
    """A toy house has coincident coplanar triangles within one instance (a wall's two
    sides, a shelf's overlapping boards). A traversal meets them in an order that differs
    between Embree builds and CPUs; every engine keeps the one of smallest plane distance,
    then lowest index, whatever that order: the extension, Open3D and the reference give
    the same hits, every field, and the view has such ties (a ray crossing two triangles
    of one instance at the same float64 distance, of which the lower is the one kept)."""
    house = load(discover(BUNDLED_TOY)[0])
    tracer = HouseTracer(house, "embree")
    camera = sample_cameras(house, 1, np.random.default_rng(0), CameraSamplerConfig(width=80, height=60), tracer)[0][0]
    origins, directions, _ = camera.rays()
    ours = tracer.all_hits(origins, directions)
    for other in ("open3d", "reference"):
        assert_same_hits(ours, HouseTracer(house, other).all_hits(origins, directions))
    # the ties: every raw crossing, by (ray, distance, face); a tie is two faces of one
    # instance at one distance on one ray, and the first of them must be the one kept
    rays = Rays.check(origins, directions)
    ray, face = HouseTracer(house, "reference").backend.intersect_all(rays)
    t = _plane_distance(tracer.triangles, face, ray, rays)[0]
    order = np.lexsort((face, t, ray))
    ray, face, t = ray[order], face[order], t[order]
    inst = tracer.triangles.instance[face]
    tie = np.flatnonzero((ray[1:] == ray[:-1]) & (t[1:] == t[:-1]) & (inst[1:] == inst[:-1]))
    tie = tie[np.r_[True, (ray[tie][1:] != ray[tie][:-1]) | (t[tie][1:] != t[tie][:-1])]] if len(tie) else tie
    assert len(tie) >= 10
    kept = tracer.triangles.global_index(ours.instance, ours.triangle)
    for k in tie:
        row = slice(ours.offsets[ray[k]], ours.offsets[ray[k] + 1])
        assert face[k] in kept[row] and face[k + 1] not in kept[row]


@NO_EXTENSION
def test_embree_engine_is_deterministic_over_many_blocks():
    """More rays than one block of the extension, traced on 1..4 threads: the same arrays."""
    house = random_house(8)
    origins, directions = random_rays(np.random.default_rng(12), 20_000)
    results = [HouseTracer(house, "embree", threads=k).all_hits(origins, directions) for k in (1, 2, 4)]
    for other in results[1:]:
        assert_same_hits(other, results[0])


def test_without_the_extension_open3d_is_the_default(monkeypatch):
    house = random_house(0)
    monkeypatch.setattr(embree, "AVAILABLE", False)
    monkeypatch.setattr(embree, "_embree", None)
    assert default_backend() == "open3d"
    assert HouseTracer(house).backend.name == "open3d"
    with pytest.raises(MissingDependencyError, match="Embree extension"):
        HouseTracer(house, backend="embree")


def test_the_environment_names_the_default_engine(monkeypatch):
    from sceneforge.errors import SceneforgeError
    from sceneforge.raytrace import ENGINE_ENV

    house = random_house(0)
    monkeypatch.setenv(ENGINE_ENV, "open3d")
    assert default_backend() == "open3d" and HouseTracer(house).backend.name == "open3d"
    monkeypatch.setenv(ENGINE_ENV, "embree9")
    with pytest.raises(SceneforgeError, match=f"{ENGINE_ENV}='embree9'.*embree, open3d, reference"):
        HouseTracer(house)


@NO_EXTENSION
def test_the_extension_breaks_ties_in_the_same_float32_window():
    assert embree._embree.CANDIDATE_WINDOW == float(np.float32(tol.tie_window))


def test_the_extension_is_the_default_where_it_is_built():
    assert default_backend() == ("embree" if embree.AVAILABLE else "open3d")


@NO_EXTENSION
def test_embree_engine_serves_several_python_threads():
    """Queries release the GIL; threads sharing one tracer, each adding scenes for its own
    instance subsets meanwhile, get what they would alone."""
    from concurrent.futures import ThreadPoolExecutor

    house = random_house(9)
    origins, directions = random_rays(np.random.default_rng(13), 4000)
    masks = [np.random.default_rng(k).random(len(house.instances)) < 0.6 for k in range(8)]
    alone = [HouseTracer(house, "embree").all_hits(origins, directions, instances=m) for m in masks]
    shared = HouseTracer(house, "embree", threads=2)
    with ThreadPoolExecutor(4) as pool:
        together = list(pool.map(lambda m: shared.all_hits(origins, directions, instances=m), masks))
    for a, b in zip(alone, together):
        assert_same_hits(a, b)


def test_camera_directions_skip_the_full_scan_and_nothing_else_does():
    """A camera's directions are unit and finite by construction, so the tracers check
    their first row only; any other array (a copy, or the same array made writeable again
    and changed) is scanned in full."""
    from sceneforge.cameras import look_at_camera
    from sceneforge.raytrace import checked_directions

    camera = look_at_camera([0, 1, 0], [0, 0, 1], width=8, height=6)
    origins, directions, _ = camera.rays()
    Rays.check(origins, directions)
    bad = directions.copy()
    bad[5] = np.nan
    with pytest.raises(ValueError, match="finite"):
        Rays.check(origins, bad)
    bad[5] = [0, 0, 2]
    with pytest.raises(ValueError, match="unit"):
        Rays.check(origins, bad)
    directions.flags.writeable = True
    directions[5] = np.nan
    with pytest.raises(ValueError, match="finite"):
        Rays.check(origins, directions)
    with pytest.raises(ValueError, match="read-only"):
        checked_directions(np.zeros((2, 3)))


# ------------------------------------------------------------------ exact ties


def tied_house(seed: int):
    """Coincident and overlapping triangles at exactly representable coordinates, faces and
    instance order shuffled by ``seed``: two coplanar sheets of different labels at z = 1
    (one split along each diagonal, the first also doubled with the opposite winding, as a
    two-sided sheet), and at z = 3 a wall with a picture lying in its plane. Returns the
    house and the instance names in house order."""
    rng = np.random.default_rng(seed)
    sq = lambda lo, hi, z: np.array([[lo, lo, z], [hi, lo, z], [hi, hi, z], [lo, hi, z]], dtype=float)  # noqa: E731
    parts = {
        "shelf": (3, sq(-0.5, 0.5, 1.0), [[0, 1, 2], [0, 2, 3], [0, 2, 1], [0, 3, 2]]),
        "board": (5, sq(-0.5, 0.5, 1.0), [[0, 1, 3], [1, 2, 3]]),
        "wall": (1, sq(-2.0, 2.0, 3.0), [[0, 1, 2], [0, 2, 3]]),
        "picture": (11, sq(-1.0, 1.0, 3.0), [[0, 1, 2], [0, 2, 3]]),
    }
    names = list(rng.permutation(list(parts)))
    h = House(id=f"ties{seed}", instances=[])
    for name in names:
        category, vertices, faces = parts[name]
        make_instance(h, name=name, category=category, label=name, room_id=None,
                      vertices=vertices, faces=np.array(faces)[rng.permutation(len(faces))])
    return h, names


def _containing(house, x: float, y: float, z: float) -> list[tuple[int, int, bool]]:
    """(instance, triangle, front facing for a ray along +z) of every triangle in the plane
    z that contains (x, y), edges included (exact: the coordinates are dyadic)."""
    out = []
    for i, inst in enumerate(house.instances):
        for k, f in enumerate(inst.faces):
            a, b, c = inst.vertices[f]
            if a[2] != z:
                continue
            cross = [(q[0] - p[0]) * (y - p[1]) - (q[1] - p[1]) * (x - p[0]) for p, q in ((a, b), (b, c), (c, a))]
            if min(cross) >= 0 or max(cross) <= 0:
                area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
                out.append((i, k, area < 0))  # counter-clockwise seen from +z faces +z: a back face
    return sorted(out)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_exact_ties_go_to_the_lower_instance_then_triangle_whatever_the_face_order(backend, seed):
    """Rays along +z through a grid that includes the sheets' diagonals, borders and corners
    (edges shared by two triangles, the same triangle twice with both windings, a picture in
    its wall's plane): each tie of one distance goes to the lower instance, then its lower
    triangle, in every engine and whatever order the faces and instances come in; all hits
    keep one hit per instance and distance, lower instance first. Which of the tied labels
    wins follows the instance order, as the rule says, not the triangles' order."""
    house, names = tied_house(seed)
    tracer = HouseTracer(house, backend)
    g = np.arange(-1.75, 1.76, 0.25)
    xy = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    origins = np.c_[xy, np.zeros(len(xy))]
    directions = np.broadcast_to([0.0, 0.0, 1.0], origins.shape)
    envelope = tracer.triangles.envelope
    first, closing = tracer.first_hit(origins, directions), tracer.first_hit(origins, directions, envelope)
    hits = tracer.all_hits(origins, directions)
    ties = 0
    for r, (x, y) in enumerate(xy):
        on_sheets, on_wall = _containing(house, x, y, 1.0), _containing(house, x, y, 3.0)
        ties += len({i for i, _, _ in on_sheets}) > 1 or len(on_sheets) > 2
        want_first = (on_sheets or on_wall)[0]
        assert (first.instance[r], first.triangle[r], first.front_facing[r]) == want_first, (x, y)
        assert first.t[r] == (1.0 if on_sheets else 3.0)
        assert (closing.instance[r], closing.triangle[r]) == on_wall[0][:2], (x, y)
        # all hits: the first triangle of each instance at each distance, in instance order
        want = [(z, *min(c for c in on if c[0] == i)) for z, on in ((1.0, on_sheets), (3.0, on_wall))
                for i in sorted({c[0] for c in on})]
        row = slice(hits.offsets[r], hits.offsets[r + 1])
        got = list(zip(hits.t[row], hits.instance[row], hits.triangle[row], hits.front_facing[row]))
        assert got == want, (x, y)
    assert ties >= 20  # the grid does meet the ties
    # the label the frontal layers and D5 would take: the lower of the tied instances
    inside = np.flatnonzero((np.abs(xy) <= 0.5).all(axis=1))
    sheet = min(names.index("shelf"), names.index("board"))
    np.testing.assert_array_equal(first.instance[inside], sheet)
    np.testing.assert_array_equal(closing.instance[inside], min(names.index("wall"), names.index("picture")))
