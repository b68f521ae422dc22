"""compute_view on real houses: fast and reference engines agree on every overhead pixel,
the overhead query loses nothing against tracing every hit, and results are deterministic."""

from __future__ import annotations

import numpy as np
import pytest

from sceneforge.camera_sampler import CameraSamplerConfig, sample_cameras
from sceneforge.houses import BUNDLED_TOY, discover, load
from sceneforge.layers import instance_labels, layers_from_hits
from sceneforge.overhead import FLOOR, OverheadConfig, overhead_instances, overhead_truth
from sceneforge.raytrace import HouseTracer
from sceneforge.view import ViewConfig, compute_view

from .conftest import BREAKFAST_ROOM, needs_shared

SMALL = CameraSamplerConfig(width=64, height=48)
TOP = OverheadConfig(resolution=40)


def houses():
    yield from (pytest.param(s, id=s.id) for s in discover(BUNDLED_TOY))
    yield pytest.param(BREAKFAST_ROOM, id="breakfast_room", marks=needs_shared(BREAKFAST_ROOM))


def first_view(house, tracer):
    cams, _ = sample_cameras(house, 1, np.random.default_rng(0), SMALL, tracer)
    if not cams:  # the breakfast room has window openings: let more of the view escape
        loose = CameraSamplerConfig(width=64, height=48, max_escape_fraction=0.5)
        cams, _ = sample_cameras(house, 1, np.random.default_rng(0), loose, tracer)
    assert cams, f"no camera could be sampled in {house.id}"
    return cams[0]


def overhead_keep(house, hits, config):
    """The slow reference of the filters of docs/spec.md §7.1 on every hit of straight-down rays: drop the
    instances an overhead view does not see, and floor hits within the clearance."""
    floor = instance_labels(house)[0] == FLOOR
    inst = np.asarray(hits.instance, dtype=np.int64)
    return overhead_instances(house, config)[inst] & ~(floor[inst] & (hits.t < config.floor_clearance))


def same(a, b):
    np.testing.assert_array_equal(a, b)  # NaN == NaN for assert_array_equal


@pytest.mark.parametrize("source", list(houses()))
def test_overhead_fast_equals_reference_and_equals_all_hits(source):
    house = load(source)
    fast, ref = HouseTracer(house), HouseTracer(house, backend="reference")
    config = ViewConfig(overhead=TOP, with_mesh=False)
    view = compute_view(house, first_view(house, fast), config, fast)
    top = view.overhead_camera
    slow = overhead_truth(house, top, ref, TOP)
    for name in ("depth", "category", "instance"):
        same(getattr(view.overhead.layers, name), getattr(slow.layers, name))
    same(view.overhead.height, slow.height)
    same(view.overhead.category, slow.category)
    # the overhead query (objects + first floor beyond the clearance) drops only hits the
    # rules ignore: tracing every hit and filtering gives the same layers
    o, d, s = top.rays()
    hits = fast.all_hits(o, d)
    category, envelope = instance_labels(house)
    full = layers_from_hits(hits, s, category, envelope, (top.height, top.width), keep=overhead_keep(house, hits, TOP))
    same(view.overhead.layers.depth, full.depth)
    same(view.overhead.layers.category, full.category)
    assert np.isfinite(view.overhead.height).any(), "the overhead view should see some object"


def test_compute_view_is_deterministic_and_shaped():
    house = load(discover(BUNDLED_TOY)[1])
    cam = first_view(house, HouseTracer(house))
    a = compute_view(house, cam)
    b = compute_view(house, cam, tracer=HouseTracer(house))
    assert a.layers.depth.shape == (5, 48, 64) and a.layers.depth.dtype == np.float32
    assert a.overhead.layers.depth.shape == (5, 300, 300)
    for x, y in [(a.layers.depth, b.layers.depth), (a.overhead.height, b.overhead.height),
                 (a.mesh.objects.vertices, b.mesh.objects.vertices), (a.mesh.envelope.faces, b.mesh.envelope.faces),
                 (a.overhead_camera.params, b.overhead_camera.params)]:
        assert x.tobytes() == y.tobytes()
    # the overhead camera looks straight down from below the highest frontal point
    assert np.allclose(a.overhead_camera.cam_to_world[:3, 2], [0, -1, 0])
