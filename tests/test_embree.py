"""sceneforge's Embree extension on real houses: every array of a view's ground truth
(layers, overhead truth, mesh) bit-identical to the numpy path over the same engine's raw
answers, packets naming the faces ray-by-ray tracing names, agreement with the Open3D
engine, and the extension built wherever Embree is installed."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sceneforge import depth_mesh, layers
from sceneforge.camera_sampler import CameraSamplerConfig, sample_cameras
from sceneforge.houses import BUNDLED_TOY, discover, load
from sceneforge.raytrace import HouseTracer
from sceneforge.raytrace import embree_backend as embree
from sceneforge.view import ViewConfig, compute_view

from .conftest import BREAKFAST_ROOM, needs_shared

NO_EXTENSION = pytest.mark.skipif(not embree.AVAILABLE, reason="sceneforge's Embree extension is not built")
EMBREE_HEADERS = [Path(root) / "include" / f"embree{major}" / "rtcore.h"
                  for root in ("/usr", "/usr/local") for major in (3, 4)]


def houses():
    yield from (pytest.param(s, id=s.id) for s in discover(BUNDLED_TOY))
    yield pytest.param(BREAKFAST_ROOM, id="breakfast_room", marks=needs_shared(BREAKFAST_ROOM))


def view_arrays(view) -> dict[str, np.ndarray]:
    """Every array of a view's ground truth."""
    out = {f"layers.{k}": getattr(view.layers, k) for k in ("depth", "category", "instance", "normal")}
    out |= {f"overhead.layers.{k}": getattr(view.overhead.layers, k) for k in ("depth", "category", "instance")}
    out |= {"overhead.height": view.overhead.height, "overhead.category": view.overhead.category}
    for part in ("objects", "envelope"):
        mesh = getattr(view.mesh, part)
        out |= {f"mesh.{part}.vertices": mesh.vertices, f"mesh.{part}.faces": mesh.faces}
    return out


class RayByRay:
    """The extension as an engine that only answers the raw queries (every crossing, the
    nearest face), traced ray by ray: what the Open3D engine offers. A tracer over it
    collects hits, closes rays and measures distances in numpy, as it does for Open3D."""

    name = "embree, ray by ray"

    def __init__(self, triangles):
        self._engine = embree.EmbreeBackend(triangles, packet=1)

    def intersect_all(self, rays, instances=None, t_max=None):
        return self._engine.intersect_all(rays, instances, t_max)

    def intersect_first(self, rays, instances=None):
        return self._engine.intersect_first(rays, instances)

    def closest_distance(self, points):
        return self._engine.closest_distance(points)


def ray_by_ray(house) -> HouseTracer:
    tracer = HouseTracer(house, "embree")
    tracer.backend = RayByRay(tracer.triangles)
    return tracer


def sampled_views(house, tracers, n: int = 2):
    """``n`` cameras sampled with each tracer (asserted the same), and the ground truth of
    each view by each tracer, the second with numpy layer rules and triangulation."""
    sampler = CameraSamplerConfig()
    if house.id == "BreakfastRoom":  # window openings: let more of a view escape
        sampler = replace(sampler, max_escape_fraction=0.5)
    cameras = [sample_cameras(house, n, np.random.default_rng(0), sampler, t)[0] for t in tracers]
    assert len(cameras[0]) == n
    for a, b in zip(*cameras):
        np.testing.assert_array_equal(a.cam_to_world, b.cam_to_world)
    return cameras[0]


def views_both_ways(house, ours, theirs, monkeypatch):
    """(``ours``'s, ``theirs``'s) :func:`view_arrays` of each of :func:`sampled_views`, the
    second with numpy layer rules and triangulation (as where the extension is missing)."""
    for camera in sampled_views(house, (ours, theirs)):
        got = view_arrays(compute_view(house, camera, ViewConfig(), ours))
        with monkeypatch.context() as fallback:
            fallback.setattr(layers, "COMPILED_RULES", False)
            fallback.setattr(depth_mesh, "COMPILED", False)
            yield got, view_arrays(compute_view(house, camera, ViewConfig(), theirs))


@NO_EXTENSION
@pytest.mark.parametrize("source", list(houses()))
def test_views_are_bit_identical_to_the_numpy_path_on_the_same_engine(source, monkeypatch):
    """Two sampled 320×240 views of each house: cameras (the sampler's first-hit queries and
    distances), frontal layers, overhead truth and mesh the same to the last bit, whether
    the extension does everything (packets for first hits, hit collection in its filter
    callback, layer rules and triangulation compiled) or only answers the raw queries ray
    by ray and numpy does the rest, as it does for the Open3D engine where the extension
    is missing."""
    house = load(source)
    ours, theirs = HouseTracer(house, "embree"), ray_by_ray(house)
    for got, want in views_both_ways(house, ours, theirs, monkeypatch):
        assert np.isfinite(got["layers.depth"][0]).any()
        for name in want:
            np.testing.assert_array_equal(got[name], want[name], err_msg=name)


@NO_EXTENSION
@pytest.mark.parametrize("source", list(houses()))
def test_views_are_bit_identical_with_the_open3d_engine(source, monkeypatch):
    """The same views by the Open3D engine (numpy rules and triangulation): every array the
    same to the last bit.

    Open3D ships its own Embree (4.x) and sceneforge's extension links the system's (3.x
    or 4.x), whose traversals meet triangles in different orders on some CPUs. Where a
    ray crosses two triangles at the same float32 distance (an edge-on ray at a wall's
    corner, coincident faces) each engine used to name the one it met first: on an
    AVX-512 Xeon one D5 vertex of 518,400 in these views differed by 2.4e-7 m (two faces
    tied at a wall-floor edge). Ties now go by a rule that only reads which triangles a
    ray crosses (``tol.tie_window``)."""
    house = load(source)
    ours, theirs = HouseTracer(house, "embree"), HouseTracer(house, "open3d")
    for got, want in views_both_ways(house, ours, theirs, monkeypatch):
        for name in want:
            np.testing.assert_array_equal(got[name], want[name], err_msg=name)


def _render_with(engine: str, source, out: Path, monkeypatch) -> dict[str, str]:
    from sceneforge.config import load_config
    from sceneforge.pipeline import render_dataset
    from sceneforge.pipeline.worker import Worker
    from sceneforge.raytrace import ENGINE_ENV
    from sceneforge.store import array_digests

    used, tracer_of = set(), Worker.tracer_of

    def spy(self, house):
        tracer = tracer_of(self, house)
        used.add(tracer.backend.name)
        return tracer

    # RGB does not read the ray tracer; the ground-truth meshes do
    overrides = {"rgb": {"enabled": False}, "store": {"gt_mesh": "all"}}
    if source != "bundled:toy":  # the breakfast room's windows: let more of a view escape
        overrides |= {"views_per_house": 2, "sampler": {"max_escape_fraction": 0.5}}
    with monkeypatch.context() as m:
        m.setenv(ENGINE_ENV, engine)
        m.setattr(Worker, "tracer_of", spy)
        render_dataset(str(source), str(out), load_config(None, overrides))
    assert used == {engine}
    return array_digests(str(out))


@NO_EXTENSION
@pytest.mark.slow
@pytest.mark.parametrize("source", [
    "bundled:toy", pytest.param(BREAKFAST_ROOM, id="breakfast_room", marks=needs_shared(BREAKFAST_ROOM))])
def test_stores_are_identical_with_either_engine(source, tmp_path, monkeypatch):
    """A default-resolution store (cameras sampled, layers, overhead, meshes) rendered with
    the extension and with the Open3D engine: every array the same (array digests)."""
    ours = _render_with("embree", source, tmp_path / "embree.zarr", monkeypatch)
    theirs = _render_with("open3d", source, tmp_path / "open3d.zarr", monkeypatch)
    assert len(ours) >= 20 and ours == theirs


def edge_on_rays(house, origin):
    """Rays from ``origin`` through every vertex, edge midpoint and face centroid of the
    house: hits on edges and corners, where packet and ray-by-ray traversal are most
    likely to part."""
    points = []
    for inst in house.instances:
        v = inst.vertices[inst.faces]  # (m, 3, 3)
        points += [inst.vertices, 0.5 * (v + v[:, [1, 2, 0]]).reshape(-1, 3), v.mean(axis=1)]
    d = np.concatenate(points) - origin
    d = d[np.linalg.norm(d, axis=1) > 1e-6]
    return np.broadcast_to(origin, d.shape), d / np.linalg.norm(d, axis=1, keepdims=True)


@NO_EXTENSION
@pytest.mark.parametrize("source", list(houses()))
def test_packets_name_the_faces_ray_by_ray_tracing_names(source):
    """Every packet width the CPU runs natively against rtcIntersect1, on first-hit and
    closing queries of three kinds of rays: the 480×360 D5 rays and the overhead rays of a
    sampled view, and rays through every vertex, edge midpoint and face centroid of the
    house (coincident faces, ties at edges). Each query's faces, distances and flags equal."""
    house = load(source)
    single = HouseTracer(house, "embree")
    single.backend = embree.EmbreeBackend(single.triangles, packet=1)
    widths = [w for w in (4, 8, 16) if _native(single.triangles, w)]
    if not widths:  # an Embree built without ray packets: the engine traces ray by ray
        assert single.backend.packet == 1 and embree.EmbreeBackend(single.triangles).packet == 1
        pytest.skip("this Embree build or CPU runs no ray packets natively")
    camera = sampled_views(house, (single, single), n=1)[0]
    config = ViewConfig()
    view = compute_view(house, camera, config, single)
    o, d, _ = camera.resized(480, 360).rays()
    top_o, top_d, _ = view.overhead_camera.rays()
    queries = [(o, d), (top_o, np.broadcast_to(top_d, top_o.shape)), edge_on_rays(house, camera.cam_to_world[:3, 3])]
    envelope = single.triangles.envelope
    for width in widths:
        packed = HouseTracer(house, "embree")
        packed.backend = embree.EmbreeBackend(packed.triangles, packet=width)
        assert packed.backend._engine.packet == width
        for origins, directions in queries:
            for instances in (None, envelope, ~envelope):
                a, b = packed.first_hit(origins, directions, instances), single.first_hit(origins, directions, instances)
                for field in ("face", "t", "front_facing"):
                    np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=f"{width}: {field}")
            for near in (0.0, config.overhead.floor_clearance):
                a, b = (t.frontal_query(origins, directions, objects=~envelope, envelope=envelope, envelope_near=near)
                        for t in (packed, single))
                np.testing.assert_array_equal(a.closing.face, b.closing.face, err_msg=f"{width}: closing")
                np.testing.assert_array_equal(a.closing.t, b.closing.t, err_msg=f"{width}: closing t")


def _native(triangles, width: int) -> bool:
    try:
        embree.EmbreeBackend(triangles, packet=width)
    except ValueError:
        return False
    return True


@NO_EXTENSION
def test_the_packet_width_is_the_widest_native_one_and_others_are_refused():
    house = load(discover(BUNDLED_TOY)[0])
    triangles = HouseTracer(house, "embree").triangles
    native = [w for w in (16, 8, 4) if _native(triangles, w)]
    assert embree.EmbreeBackend(triangles).packet == (native[0] if native else 1)
    assert embree.EmbreeBackend(triangles, packet=1).packet == 1
    for bad in (2, 3, 32, -1):
        with pytest.raises(ValueError, match="packet must be"):
            embree.EmbreeBackend(triangles, packet=bad)


def test_the_extension_is_built_where_embree_is_installed():
    """``pip install -e .`` leaves the extension out, silently apart from a warning, when it
    cannot build it: fail here rather than fall back to Open3D unnoticed."""
    headers = [h for h in EMBREE_HEADERS if h.is_file()]
    if not headers:
        pytest.skip("Embree's headers are not installed (scripts/system-deps.sh installs them)")
    assert embree.AVAILABLE, (
        f"Embree is installed ({headers[0]}) but sceneforge.raytrace._embree is not built: "
        "run `pip install -e .` again and read its warnings")
