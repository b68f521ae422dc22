"""Frustum planes, triangle clipping and the ground-truth mesh of a view (docs/spec.md §5)."""

from __future__ import annotations

import numpy as np
import pytest

from sceneforge import depth_mesh, frustum
from sceneforge.camera_sampler import CameraSamplerConfig, sample_cameras
from sceneforge.cameras import look_at_camera
from sceneforge.conventions import tol
from sceneforge.frustum import (
    ViewMeshConfig,
    _clipped_meshes,
    _envelope_limit,
    _lens,
    _settle_fast,
    _unique_rows,
    _vertex_codes,
    clip_triangles,
    clip_triangles_by_plane,
    drop_behind_envelope,
    envelope_surface,
    frustum_planes,
    triangle_areas,
    view_mesh,
    weld,
)
from sceneforge.houses import BUNDLED_TOY, House, Room, discover, load, make_instance
from sceneforge.layers import Layers, frontal_layers
from sceneforge.raytrace import HouseTracer

from .conftest import BREAKFAST_ROOM, box_instance, needs_shared

# Plane z >= 0 (unit normal +Z pointing inside).
Z_PLANE = np.array([0.0, 0.0, 1.0, 0.0])


def normals(tris):
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_triangle_with_one_vertex_inside_keeps_its_tip():
    # Apex at z = 2, base at z = -2 and 4 m wide: the part at z >= 0 is a triangle with a
    # 2 m base (x in [-1, 1]) and 2 m height, area 2 of the original 8.
    tri = np.array([[[0, 0, 2], [2, 0, -2], [-2, 0, -2]]], dtype=float)
    kept, src = clip_triangles_by_plane(tri, Z_PLANE)
    cut, _ = clip_triangles_by_plane(tri, -Z_PLANE)
    assert len(kept) == 1 and src.tolist() == [0]
    assert triangle_areas(kept).sum() == pytest.approx(2.0)
    assert triangle_areas(cut).sum() == pytest.approx(6.0)
    assert len(cut) == 2  # the cut-away quad is split into two triangles
    assert triangle_areas(kept).sum() + triangle_areas(cut).sum() == pytest.approx(8.0)
    assert (kept[..., 2] >= -tol.clip).all()
    assert (cut[..., 2] <= tol.clip).all()
    np.testing.assert_allclose(sorted(kept[0, :, 0]), [-1, 0, 1])
    # Winding (and so the facing direction) is kept.
    np.testing.assert_allclose(normals(kept), normals(tri))
    np.testing.assert_allclose(normals(cut), np.repeat(normals(tri), 2, axis=0))


def test_triangle_with_two_vertices_inside_becomes_a_quad():
    # Right triangle (0,0)-(4,0)-(0,4) in x/z, cut at z <= 1 (plane z' = 1 - z >= 0):
    # kept trapezoid = 8 - area of the tip (3×3/2 = 4.5) = 3.5.
    tri = np.array([[[0, 0, 0], [4, 0, 0], [0, 0, 4]]], dtype=float)
    plane = np.array([0.0, 0.0, -1.0, 1.0])
    kept, src = clip_triangles_by_plane(tri, plane)
    cut, _ = clip_triangles_by_plane(tri, -plane)
    assert len(kept) == 2 and src.tolist() == [0, 0]
    assert triangle_areas(kept).sum() == pytest.approx(3.5)
    assert triangle_areas(cut).sum() == pytest.approx(4.5)
    assert (kept[..., 2] <= 1 + tol.clip).all()
    np.testing.assert_allclose(normals(kept), np.repeat(normals(tri), 2, axis=0))


def test_whole_triangles_are_kept_or_dropped_and_the_tolerance_prevents_slivers():
    inside = [[0, 0, 1], [1, 0, 1], [0, 1, 2]]
    outside = [[0, 0, -1], [1, 0, -1], [0, 1, -2]]
    # One vertex only half a tolerance behind the plane: counts as inside, not cut.
    grazing = [[0, 0, -0.5 * tol.clip], [1, 0, 1], [0, 1, 1]]
    tris = np.array([inside, outside, grazing], dtype=float)
    kept, src = clip_triangles_by_plane(tris, Z_PLANE)
    assert src.tolist() == [0, 2]
    np.testing.assert_array_equal(kept, tris[[0, 2]])


def test_triangle_touching_the_plane_from_outside_is_dropped():
    # One vertex on the plane, two outside: the inside part has no area.
    tri = np.array([[[0, 0, 0], [1, 0, -1], [-1, 0, -1]]], dtype=float)
    kept, src = clip_triangles_by_plane(tri, Z_PLANE)
    assert len(kept) == 0 and len(src) == 0


def test_shared_edges_are_cut_at_the_same_point_and_weld():
    # Square [0,2]² (x, z) as two triangles, clipped at x <= 1: rectangle of area 2 whose
    # corners plus the diagonal's cut point (1, 1) are 5 distinct vertices.
    v = np.array([[0, 0, 0], [2, 0, 0], [2, 0, 2], [0, 0, 2]], dtype=float)
    tris = v[[[0, 1, 2], [0, 2, 3]]]
    kept, src = clip_triangles_by_plane(tris, np.array([-1.0, 0, 0, 1.0]))
    vertices, faces = weld(kept)
    assert triangle_areas(vertices[faces]).sum() == pytest.approx(2.0)
    assert len(vertices) == 5
    assert faces.dtype == np.int32
    assert sorted(set(src.tolist())) == [0, 1]


def test_clipping_against_several_planes_keeps_their_intersection():
    # A 4×4 square clipped to the slab |x| <= 1, |z| <= 0.5 leaves a 2×1 rectangle.
    v = np.array([[-2, 0, -2], [2, 0, -2], [2, 0, 2], [-2, 0, 2]], dtype=float)
    tris = v[[[0, 1, 2], [0, 2, 3]]]
    planes = np.array([[1, 0, 0, 1], [-1, 0, 0, 1], [0, 0, 1, 0.5], [0, 0, -1, 0.5]], dtype=float)
    kept, src = clip_triangles(tris, planes)
    assert triangle_areas(kept).sum() == pytest.approx(2.0)
    assert (np.abs(kept[..., 0]) <= 1 + tol.clip).all()
    assert (np.abs(kept[..., 2]) <= 0.5 + tol.clip).all()
    assert set(src.tolist()) == {0, 1}


def test_random_triangles_area_is_conserved_across_a_plane():
    rng = np.random.default_rng(0)
    tris = rng.uniform(-1, 1, size=(200, 3, 3))
    plane = np.array([0.3, -0.5, 0.8, 0.1])
    plane[:3] /= np.linalg.norm(plane[:3])
    kept, _ = clip_triangles_by_plane(tris, plane)
    cut, _ = clip_triangles_by_plane(tris, -plane)
    total = triangle_areas(kept).sum() + triangle_areas(cut).sum()
    assert total == pytest.approx(triangle_areas(tris).sum(), rel=1e-9)
    assert (kept.reshape(-1, 3) @ plane[:3] + plane[3] >= -tol.clip).all()


# --------------------------------------------------------------------- with a camera

# 40×30 pixels, fx = fy = 50, principal point at the centre: at depth z the view covers
# 40 z / 50 = 0.8 z m across and 30 z / 50 = 0.6 z m down.
K = np.array([[50.0, 0, 20], [0, 50.0, 15], [0, 0, 1]])


def camera_looking_down_minus_z(height=1.0):
    return look_at_camera((0.0, height, 0.0), (0.0, 0.0, -1.0), K=K, width=40, height=30)


def quad(x0, x1, y0, y1, z):
    """Two triangles of an axis-aligned rectangle at world z, facing +Z."""
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=float)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def test_frustum_planes_cut_a_large_quad_to_the_image_footprint():
    cam = camera_looking_down_minus_z()
    planes = frustum_planes(cam, near=0.01)
    assert planes.shape == (5, 4)
    np.testing.assert_allclose(np.linalg.norm(planes[:, :3], axis=1), 1.0)
    # The camera centre is on the four side planes and 1 cm behind the near plane.
    centre = np.array([0.0, 1.0, 0.0])
    np.testing.assert_allclose(planes[:4, :3] @ centre + planes[:4, 3], 0.0, atol=1e-12)
    assert planes[4, :3] @ centre + planes[4, 3] == pytest.approx(-0.01)
    v, f = quad(-10, 10, -10, 10, -2.0)
    kept, _ = clip_triangles(v[f], planes)
    # At depth 2: 1.6 m × 1.2 m, centred on the camera axis (x = 0, y = 1).
    assert triangle_areas(kept).sum() == pytest.approx(1.6 * 1.2)
    np.testing.assert_allclose(kept[..., 0].min(), -0.8)
    np.testing.assert_allclose(kept[..., 0].max(), 0.8)
    np.testing.assert_allclose(kept[..., 1].min(), 1.0 - 0.6)
    np.testing.assert_allclose(kept[..., 1].max(), 1.0 + 0.6)
    uv, z = cam.project(kept.reshape(-1, 3))
    assert (uv >= -1e-6).all() and (uv[:, 0] <= 40 + 1e-6).all() and (uv[:, 1] <= 30 + 1e-6).all()


def test_near_plane_cuts_what_reaches_behind_the_camera():
    cam = camera_looking_down_minus_z()
    planes = frustum_planes(cam, near=0.5)
    # A horizontal strip through the camera height from z = +1 (behind) to z = -1.
    v = np.array([[-0.01, 1.0, 1.0], [0.01, 1.0, 1.0], [0.01, 1.0, -1.0], [-0.01, 1.0, -1.0]])
    kept, _ = clip_triangles(v[[[0, 1, 2], [0, 2, 3]]], planes)
    assert kept[..., 2].max() == pytest.approx(-0.5)
    assert triangle_areas(kept).sum() == pytest.approx(0.02 * 0.5)


def layers_like(d5, object_ids):
    """Stand-in frontal layers: D5 (H, W) and the object instance ids that fill a layer."""
    h, w = d5.shape
    instance = np.full((2, h, w), -1, dtype=np.int32)
    instance[0].flat[: len(object_ids)] = object_ids
    depth = np.full((5, h, w), np.nan, dtype=np.float32)
    depth[4] = d5
    return Layers(depth=depth, category=np.zeros((3, h, w), np.uint8), instance=instance,
                  normal=np.full((3, h, w), np.nan, np.float32))


def wall_house():
    """Camera at (0, 1, 0) looking at a wall 3 m ahead; a box in front of it, a box, a
    panel 5 cm and a second wall 3 m behind it."""
    h = House(id="walls", instances=[], rooms=[Room("r0", "room", 0)])
    for name, (v, f) in [("wall", quad(-5, 5, -5, 5, -3.0)), ("panel", quad(-0.1, 0.1, 0.9, 1.1, -3.05)),
                         ("far_wall", quad(-9, 9, -9, 9, -6.0))]:
        make_instance(h, name=name, category=1, label="wall", room_id="r0", vertices=v, faces=f)
    box_instance(h, "front", 29, (0.4, 0.4, 0.4), (0.0, 1.0, -2.0))
    box_instance(h, "hidden", 29, (0.4, 0.4, 0.4), (0.0, 1.0, -4.5))
    return h


def fine_area(camera, upscale, area):
    """``area`` of a plane filling the view, as the D5 surface covers it: the triangulated
    grid of the traced D5 spans from the first to the last pixel centre."""
    w, h = round(camera.width * upscale), round(camera.height * upscale)
    return area * (w - 1) / w * (h - 1) / h


def test_view_mesh_keeps_layer_objects_and_the_d5_surface_as_envelope():
    house = wall_house()
    cam = camera_looking_down_minus_z()
    layers = frontal_layers(house, cam, HouseTracer(house))
    np.testing.assert_allclose(layers.depth[4], 3.0, rtol=1e-6)
    mesh = view_mesh(house, cam, layers)
    # Objects: only the visible box, whole (6 faces of 0.4 × 0.4 m).
    assert set(mesh.objects.instance.tolist()) == {3}
    assert mesh.objects.area == pytest.approx(6 * 0.16)
    # Envelope: the D5 surface, the wall in its 2.4 × 1.8 m footprint at depth 3. The panel
    # 5 cm behind it and the far wall are hidden by the wall and are not ground truth.
    assert set(mesh.envelope.instance.tolist()) == {0}
    assert mesh.envelope.area == pytest.approx(fine_area(cam, 1.5, 2.4 * 1.8))
    np.testing.assert_allclose(mesh.envelope.vertices[:, 2], -3.0, atol=1e-9)
    assert mesh.envelope.faces.dtype == np.int32 and mesh.envelope.vertices.dtype == np.float64
    assert len(mesh.envelope.faces) == len(mesh.envelope.instance)
    # Traced at 1.5 × 40 × 30 pixels: every pixel is a vertex, every block two triangles.
    assert len(mesh.envelope.vertices) == 60 * 45 and len(mesh.envelope.faces) == 2 * 59 * 44


def test_view_mesh_drops_objects_behind_d5_and_keeps_faces_where_d5_is_nan():
    house = wall_house()
    cam = camera_looking_down_minus_z()
    # Pretend the hidden box filled a layer: it is 2.3 m behind D5 = 3 and goes.
    mesh = view_mesh(house, cam, layers_like(np.full((30, 40), 3.0, np.float32), [3, 4]))
    assert set(mesh.objects.instance.tolist()) == {3}
    # Where D5 is NaN the ray left the house: nothing is behind the envelope there.
    mesh = view_mesh(house, cam, layers_like(np.full((30, 40), np.nan, np.float32), [3, 4]))
    assert set(mesh.objects.instance.tolist()) == {3, 4}
    assert mesh.objects.area == pytest.approx(2 * 6 * 0.16)
    # The envelope is traced from the house, whatever D5 the layers hold.
    assert mesh.envelope.area == pytest.approx(fine_area(cam, 1.5, 2.4 * 1.8))


def one_triangle_house(corners):
    """An object triangle (world corners (3, 3)) and nothing else."""
    h = House(id="triangle", instances=[], rooms=[Room("r0", "room", 0)])
    make_instance(h, name="board", category=29, label="board", room_id="r0",
                  vertices=np.asarray(corners, dtype=float), faces=np.array([[0, 1, 2]]))
    return h


@pytest.mark.parametrize("max_edge", [None, 4.0])
def test_an_object_vertex_outside_the_image_or_over_a_nan_d5_pixel_does_not_count(max_edge):
    cam = camera_looking_down_minus_z()  # 40 × 30 px, f = 50: at depth 2, 1.6 × 1.2 m
    config = ViewMeshConfig(max_edge_pixels=max_edge)
    # A triangle at depth 2 reaching 4 m out of the image to the left and up. D5 = 1.5 m
    # everywhere would hide it; here D5 is 3 m except at the top-left pixel, so the face is
    # in front of D5 wherever it is in the image, and only a vertex projected outside the
    # image and clamped onto the border would find the 1.5 m there.
    far = one_triangle_house([[-4.0, 5.0, -2.0], [0.4, 0.8, -2.0], [0.6, 1.2, -2.0]])
    d5 = np.full((30, 40), 3.0, np.float32)
    d5[0, 0] = 1.5
    board = view_mesh(far, cam, layers_like(d5, [0]), config).objects
    inside, _ = clip_triangles(far.instances[0].vertices[None], frustum_planes(cam))
    assert board.area == pytest.approx(triangle_areas(inside).sum()) and board.area > 0.05
    # A triangle at depth 2 with one corner 3 m behind D5 = 2.5 m: that corner drops the face,
    # unless D5 is NaN at its pixel (the ray there left the house).
    deep = one_triangle_house([[-0.2, 0.8, -2.0], [0.2, 0.8, -2.0], [0.0, 1.0, -5.5]])
    d5 = np.full((30, 40), 2.5, np.float32)
    uv, _ = cam.project([[0.0, 1.0, -5.5]])
    u, v = uv[0]
    assert view_mesh(deep, cam, layers_like(d5, [0]), config).objects.area < 0.5 * triangle_areas(
        deep.instances[0].vertices[None])[0]
    d5[int(v), int(u)] = np.nan
    kept = view_mesh(deep, cam, layers_like(d5, [0]), config).objects
    assert kept.area == pytest.approx(triangle_areas(deep.instances[0].vertices[None])[0])


def test_view_mesh_rejects_layers_of_another_size():
    house = wall_house()
    with pytest.raises(ValueError, match="40×30"):
        view_mesh(house, camera_looking_down_minus_z(), layers_like(np.ones((10, 10)), []))


def test_object_faces_half_hidden_behind_the_envelope_keep_their_visible_part():
    # A wall 2 m ahead covers the left half of the view (x < 0); a board (an object) at
    # 2.9 m in front of the wall at 3 m is seen only for x in [0, 1.16] (1.74 m high).
    h = House(id="occluded", instances=[], rooms=[Room("r0", "room", 0)])
    for name, (v, f) in [("near", quad(-5, 0, -5, 5, -2.0)), ("back", quad(-5, 5, -5, 5, -3.0))]:
        make_instance(h, name=name, category=1, label="wall", room_id="r0", vertices=v, faces=f)
    v, f = quad(-5, 5, -5, 5, -2.9)
    make_instance(h, name="board", category=29, label="board", room_id="r0", vertices=v, faces=f)
    cam = camera_looking_down_minus_z()
    layers = frontal_layers(h, cam, HouseTracer(h))
    visible = 1.16 * 1.74
    fine = view_mesh(h, cam, layers, ViewMeshConfig(max_edge_pixels=1.0)).objects
    kept = fine.vertices[fine.faces]
    # Pieces are kept whole or dropped: at most a one-pixel strip (0.058 m at 2.9 m) is lost.
    assert visible - 0.058 * 1.74 <= fine.area <= visible + 1e-9
    assert kept[..., 0].min() >= -1e-9
    # Dropping whole faces (the reference rule) loses more of the board.
    coarse = view_mesh(h, cam, layers, ViewMeshConfig(max_edge_pixels=None)).objects
    assert coarse.area < fine.area - 0.1


# ---------------------------------------- the envelope: the D5 surface, not its polygons


def rectangle(axis, value, lo, hi):
    """Two triangles of the axis-aligned rectangle ``axis = value``, the other two
    coordinates from ``lo`` to ``hi`` (2,)."""
    others = [k for k in range(3) if k != axis]
    corners = np.zeros((4, 3))
    corners[:, axis] = value
    corners[:, others[0]] = [lo[0], hi[0], hi[0], lo[0]]
    corners[:, others[1]] = [lo[1], lo[1], hi[1], hi[1]]
    return corners[[[0, 1, 2], [0, 2, 3]]]


def pixel_centre_frustum(camera, upscale):
    """The frustum planes through the outermost pixel centres of ``camera`` resized by
    ``upscale``: what the triangulated D5 grid spans."""
    from sceneforge.cameras import Camera

    w, h = round(camera.width * upscale), round(camera.height * upscale)
    fine = camera.resized(w, h)
    K = fine.K.copy()
    K[:2, 2] -= 0.5
    return frustum_planes(Camera(K, fine.cam_to_world, w - 1, h - 1))


def test_a_box_room_has_its_inner_faces_in_the_frustum_as_envelope_ground_truth(small_house):
    # small_house: a 4 × 3 × 4 m room of 0.1 m thick boxes, a table, a chair and a cup.
    cam = look_at_camera((0.6, 1.4, 1.3), (-0.3, -0.35, -1.0), width=160, height=120)
    mesh = view_mesh(small_house, cam, frontal_layers(small_house, cam, HouseTracer(small_house)))
    inner = np.concatenate([rectangle(1, 0.0, (-2, -2), (2, 2)), rectangle(1, 3.0, (-2, -2), (2, 2)),
                            *(rectangle(0, x, (0, -2), (3, 2)) for x in (-2.0, 2.0)),
                            *(rectangle(2, z, (-2, 0), (2, 3)) for z in (-2.0, 2.0))])
    seen, _ = clip_triangles(inner, pixel_centre_frustum(cam, 1.5))
    # D5 looks through the furniture: every inner face in the frustum, and nothing else.
    assert mesh.envelope.area == pytest.approx(triangle_areas(seen).sum(), rel=0.01)
    v = mesh.envelope.vertices
    assert (v[:, 1] >= -1e-9).all() and (v[:, 1] <= 3 + 1e-9).all()
    assert (np.abs(v[:, [0, 2]]) <= 2 + 1e-9).all()
    assert {"table", "chair"} <= {small_house.instances[i].name for i in mesh.objects.instance}


def partition_house():
    """Room A (x in [-2, 2], z in [-3, 1], 2.8 m high) as real houses build it: its wall
    at z = -3 is a 5 cm partition, the next room's wall skin is 6 cm behind the partition's
    face (SUNCG's per-room walls), and the floor is a 5 cm slab with an underside."""
    h = House(id="partition", instances=[], rooms=[Room("a", "room", 0), Room("b", "room", 0)])
    box_instance(h, "partition", 1, (4.0, 2.8, 0.05), (0.0, 1.4, -3.025), room_id="a", label="wall")
    box_instance(h, "next_wall", 1, (4.0, 2.8, 0.05), (0.0, 1.4, -3.085), room_id="b", label="wall")
    box_instance(h, "floor", 2, (4.2, 0.05, 4.2), (0.0, -0.025, -1.0), room_id="a", label="floor")
    box_instance(h, "ceiling", 22, (4.2, 0.05, 4.2), (0.0, 2.825, -1.0), room_id="a", label="ceiling")
    for x in (-2.025, 2.025):
        box_instance(h, f"wall_{x}", 1, (0.05, 2.8, 4.0), (x, 1.4, -1.0), room_id="a", label="wall")
    box_instance(h, "sofa", 6, (1.6, 0.8, 0.8), (0.0, 0.4, -2.5), room_id="a", label="sofa")
    return h


def test_a_thin_partition_gives_only_its_facing_side_and_nothing_behind_it():
    house = partition_house()
    tracer = HouseTracer(house)
    cam = look_at_camera((0.3, 1.5, 0.5), (-0.1, -0.3, -1.0), width=160, height=120)
    layers = frontal_layers(house, cam, tracer)
    mesh = view_mesh(house, cam, layers, tracer=tracer)
    env = mesh.envelope
    v = env.vertices
    # Nothing behind the partition's face (its back face, the next room's skin) and nothing
    # below the floor (the slab underside): every vertex is on the room's inner faces.
    assert v[:, 2].min() >= -3.0 - 1e-9 and v[:, 1].min() >= -1e-9
    names = [house.instances[i].name for i in env.instance]
    assert set(names) <= {"partition", "floor", "ceiling", "wall_-2.025", "wall_2.025"}
    # The partition contributes its facing side, in the frustum, behind the sofa too.
    facing, _ = clip_triangles(rectangle(2, -3.0, (-2, 0), (2, 2.8)), pixel_centre_frustum(cam, 1.5))
    on_partition = (np.abs(v[env.faces][..., 2] + 3.0) < 1e-9).all(axis=1)
    area = triangle_areas(v[env.faces[on_partition]]).sum()
    assert area == pytest.approx(triangle_areas(facing).sum(), rel=0.01)
    assert set(np.asarray(names)[on_partition]) == {"partition"}
    # The envelope polygons would have kept those hidden faces: they lie within the 0.1 m
    # margin behind D5 that the object rule allows.
    envelope_ids = [k for k, inst in enumerate(house.instances) if inst.envelope]
    d5 = np.asarray(layers.depth[4])
    (polygons,) = _clipped_meshes(house, [envelope_ids], cam, frustum_planes(cam), d5,
                                  _envelope_limit(d5, tol.behind_envelope), ViewMeshConfig())
    tris = polygons.vertices[polygons.faces]
    hidden = (tris[..., 2] < -3.0 - 1e-6).all(axis=1) | (tris[..., 1] < -1e-6).all(axis=1)
    assert triangle_areas(tris[hidden]).sum() > 0.5 * area


def test_every_envelope_vertex_is_the_first_envelope_hit_on_its_ray():
    # On the bundled toy houses (0.1 m partitions, 5 cm floor slabs): no back face, no
    # skin behind a partition, no slab underside, only what D5 sees.
    for house, cam, layers in toy_house_views():
        tracer = HouseTracer(house)
        env = view_mesh(house, cam, layers, tracer=tracer).envelope
        assert len(env.faces) > 0
        centre = cam.cam_to_world[:3, 3]
        to = env.vertices - centre
        dist = np.linalg.norm(to, axis=1)
        first = tracer.first_hit(np.broadcast_to(centre, to.shape), to / dist[:, None],
                                 instances=tracer.triangles.envelope)
        np.testing.assert_allclose(first.t, dist, rtol=1e-6, atol=1e-6)
        ids = np.flatnonzero([i.envelope for i in house.instances])
        assert set(env.instance.tolist()) <= set(ids.tolist())


def test_envelope_surface_leaves_out_rays_that_leave_the_house():
    # Only the wall of wall_house's left half: the right half of the view sees nothing.
    house = House(id="half", instances=[], rooms=[Room("r0", "room", 0)])
    v, f = quad(-5, 0, -5, 5, -3.0)
    make_instance(house, name="wall", category=1, label="wall", room_id="r0", vertices=v, faces=f)
    cam = camera_looking_down_minus_z()
    env = envelope_surface(HouseTracer(house), cam, ViewMeshConfig(envelope_upscale=2.0))
    # 80 × 60 pixels; the wall fills columns 0..39 (x < 0 at depth 3 is u < 40 of 80).
    assert len(env.vertices) == 40 * 60 and env.vertices[:, 0].max() < 0
    assert env.area == pytest.approx(1.2 * 39 / 40 * 1.8 * 59 / 60)


def assert_same_envelope(tracer, cam, config=None):
    """envelope_surface by the fused kernel and by the numpy steps: the same arrays, byte
    for byte (so NaN and -0 count), dtype and shape."""
    got = envelope_surface(tracer, cam, config, compiled=True)
    want = envelope_surface(tracer, cam, config, compiled=False)
    for name in ("vertices", "faces", "instance"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), name
    assert len(want.faces) > 0
    return want


@pytest.mark.skipif(not depth_mesh.COMPILED, reason="sceneforge's extension is not built")
def test_compiled_envelope_surface_of_toy_houses_equals_the_numpy_steps():
    # The small views of the tests above and four sampled 320×240 views of each toy house
    # (its D5 traced at 480×360, as a render's; the kernel on two threads, which
    # tests/test_eval_mesh.py shows makes no difference).
    for house, cam, _ in toy_house_views():
        assert_same_envelope(HouseTracer(house), cam)
    for house in (load(source) for source in discover(BUNDLED_TOY)):
        tracer = HouseTracer(house, threads=2)
        cameras, _ = sample_cameras(house, 4, np.random.default_rng(0), CameraSamplerConfig(), tracer)
        assert len(cameras) == 4
        for cam in cameras:
            assert_same_envelope(tracer, cam)


@pytest.mark.skipif(not depth_mesh.COMPILED, reason="sceneforge's extension is not built")
@needs_shared(BREAKFAST_ROOM)
def test_compiled_envelope_surface_of_the_breakfast_room_equals_the_numpy_steps():
    # Window openings: rays that leave the house, holes in D5.
    house = load(BREAKFAST_ROOM)
    tracer = HouseTracer(house)
    sampler = CameraSamplerConfig(max_escape_fraction=0.5)
    cameras, _ = sample_cameras(house, 3, np.random.default_rng(0), sampler, tracer)
    assert len(cameras) == 3
    for cam in cameras:
        assert_same_envelope(tracer, cam)


def test_view_mesh_config_is_checked():
    with pytest.raises(ValueError, match="near"):
        ViewMeshConfig(near=0.0)
    with pytest.raises(ValueError, match="max_edge_pixels"):
        ViewMeshConfig(max_edge_pixels=0.0)
    with pytest.raises(ValueError, match="envelope_upscale"):
        ViewMeshConfig(envelope_upscale=0.0)
    with pytest.raises(ValueError, match="envelope_a"):
        ViewMeshConfig(envelope_a=-1.0)


# ------------------------------------------------ the fast paths against plain versions


def plain_unique_rows(points):
    """np.unique(points, axis=0, return_inverse=True) by lexsort, first of equal rows."""
    order = np.lexsort(points.T[::-1])
    rows = points[order]
    new = np.ones(len(points), dtype=bool)
    new[1:] = (rows[1:] != rows[:-1]).any(axis=1)
    inverse = np.empty(len(points), dtype=np.int32)
    inverse[order] = np.cumsum(new) - 1
    return rows[new], inverse


@pytest.mark.parametrize("n", [1, 7, 999, 1000, 5000])
def test_unique_rows_sorts_rows_and_keeps_the_first_of_equal_ones(n):
    rng = np.random.default_rng(n)
    points = np.round(rng.normal(size=(n // 3 + 1, 3)), 1)[rng.integers(0, n // 3 + 1, n)]
    points[rng.random(n) < 0.3, 1] *= -1  # -0.0 next to 0.0: equal, kept as first seen
    vertices, inverse = _unique_rows(points)
    expected, expected_inverse = plain_unique_rows(points)
    np.testing.assert_array_equal(vertices, expected)
    np.testing.assert_array_equal(np.signbit(vertices), np.signbit(expected))
    np.testing.assert_array_equal(inverse, expected_inverse)
    assert inverse.dtype == np.int32


def test_unique_rows_of_no_points_is_empty():
    vertices, inverse = _unique_rows(np.zeros((0, 3)))
    assert vertices.shape == (0, 3) and inverse.shape == (0,)


def plain_drop_behind_envelope(triangles, camera, d5, config):
    """drop_behind_envelope in its plainest form: every corner, sample and half is
    projected anew each round."""
    world = np.asarray(triangles, dtype=np.float64)
    rot, centre = camera.cam_to_world[:3, :3], camera.cam_to_world[:3, 3]
    cam = (world - centre) @ rot
    src = np.arange(len(world))
    kept, kept_src = [np.zeros((0, 3, 3))], [np.zeros(0, dtype=np.int64)]
    (fx, skew, cx), (fy, cy) = camera.K[0], camera.K[1, 1:]
    h, w = d5.shape

    def front(points):
        z = points[..., 2]
        uv = np.stack([(fx * points[..., 0] + skew * points[..., 1]) / z + cx, fy * points[..., 1] / z + cy], -1)
        col = np.clip(uv[..., 0], 0, w - 1).astype(np.int64)
        row = np.clip(uv[..., 1], 0, h - 1).astype(np.int64)
        limit = d5[row, col].astype(np.float64) + config.behind_envelope
        return ~(np.isfinite(limit) & (z > limit)), uv

    def bisect(t, k):
        t = t[np.arange(len(t))[:, None], (k[:, None] + np.arange(3)) % 3]
        m = 0.5 * (t[:, 0] + t[:, 1])
        return np.concatenate([np.stack([t[:, 0], m, t[:, 2]], 1), np.stack([m, t[:, 1], t[:, 2]], 1)])

    while len(world):
        vertex_ok, uv = front(cam)
        ok = vertex_ok.all(axis=1)
        kept.append(world[ok])
        kept_src.append(src[ok])
        if config.max_edge_pixels is None or ok.all():
            break
        world, cam, src, uv, vertex_ok = world[~ok], cam[~ok], src[~ok], uv[~ok], vertex_ok[~ok]
        samples = np.concatenate([0.5 * (cam + cam[:, [1, 2, 0]]), cam.mean(axis=1, keepdims=True)], axis=1)
        partly = vertex_ok.any(axis=1) | front(samples)[0].any(axis=1)
        edge = np.linalg.norm(uv[:, [1, 2, 0]] - uv, axis=2)
        split = partly & (edge.max(axis=1) > config.max_edge_pixels)
        k = np.argmax(edge[split], axis=1)
        world, cam, src = bisect(world[split], k), bisect(cam[split], k), np.tile(src[split], 2)
    return np.concatenate(kept), np.concatenate(kept_src)


def half_occluded_view():
    """A near wall over the left half of the view, a wall behind, two boxes."""
    h = House(id="occluded", instances=[], rooms=[Room("r0", "room", 0)])
    for name, (v, f) in [("near", quad(-5, 0, -5, 5, -2.0)), ("back", quad(-5, 5, -5, 5, -3.0))]:
        make_instance(h, name=name, category=1, label="wall", room_id="r0", vertices=v, faces=f)
    box_instance(h, "front", 29, (0.4, 0.4, 0.4), (0.3, 1.0, -2.5))
    box_instance(h, "behind", 29, (0.6, 0.6, 0.6), (-0.5, 1.1, -2.6))
    cam = camera_looking_down_minus_z()
    return h, cam, frontal_layers(h, cam, HouseTracer(h))


@pytest.mark.parametrize("max_edge", [None, 1.0, 4.0])
def test_drop_behind_envelope_matches_the_plain_refinement_bit_for_bit(max_edge):
    house, cam, layers = half_occluded_view()
    planes = frustum_planes(cam)
    tris = np.concatenate([inst.vertices[inst.faces] for inst in house.instances])
    tris, _ = clip_triangles(tris, planes)
    # An occluder 1 m ahead with a window onto the walls, a hole (NaN: nothing behind) and
    # scattered gaps: faces with every corner hidden that are partly seen through a gap,
    # and wholly hidden ones.
    d5 = np.full_like(layers.depth[4], 1.0)
    d5[9:21, 12:28] = layers.depth[4][9:21, 12:28]
    d5[2:6, 30:36] = np.nan
    gaps = np.random.default_rng(1).random(d5.shape) < 0.05
    d5[gaps] = layers.depth[4][gaps]
    config = ViewMeshConfig(max_edge_pixels=max_edge)
    kept, src = drop_behind_envelope(tris, cam, d5, config)
    expected, expected_src = plain_drop_behind_envelope(tris, cam, d5, config)
    np.testing.assert_array_equal(kept, expected)
    np.testing.assert_array_equal(src, expected_src)
    # The limit may be passed in, computed once per view.
    again = drop_behind_envelope(tris, cam, d5, config, _envelope_limit(d5, config.behind_envelope))
    np.testing.assert_array_equal(again[0], expected)


def test_the_meshes_of_a_view_come_out_as_each_would_alone():
    # Several lists of instances are clipped and refined in one batch.
    house, cam, layers = half_occluded_view()
    planes, config = frustum_planes(cam), ViewMeshConfig(max_edge_pixels=1.0)
    d5 = np.asarray(layers.depth[4])
    limit = _envelope_limit(d5, config.behind_envelope)
    ids = [[2, 3], [0, 1]]
    together = _clipped_meshes(house, ids, cam, planes, d5, limit, config)
    for mesh, one in zip(together, ids):
        (alone,) = _clipped_meshes(house, [one], cam, planes, d5, limit, config)
        for field in ("vertices", "faces", "instance"):
            np.testing.assert_array_equal(getattr(mesh, field), getattr(alone, field))
    assert len(together[1].faces) > 2  # the back wall was refined


def plain_clipped_mesh(house, ids, cam, planes, d5, config):
    """A mesh of _clipped_meshes in its plainest form: every face of the instances clipped
    (clip_triangles) and tested against the envelope (plain_drop_behind_envelope), then welded
    by comparing coordinates: a piece's corner that equals a corner of its face is that
    vertex, the other points are new vertices, unique and sorted after the instances'."""
    instances = [house.instances[i] for i in ids]
    if not instances:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32), np.zeros(0, dtype=np.int32)
    vertices = np.concatenate([inst.vertices for inst in instances])
    base = np.cumsum([0] + [len(inst.vertices) for inst in instances[:-1]])
    corners = np.concatenate([inst.faces + b for inst, b in zip(instances, base)])
    owner = np.concatenate([np.full(len(inst.faces), i, dtype=np.int32) for i, inst in zip(ids, instances)])
    cut, source = clip_triangles(vertices[corners], planes, config.clip_tolerance)
    pieces, kept = plain_drop_behind_envelope(cut, cam, d5, config)
    source = source[kept]
    parent = vertices[corners[source]]
    equal = (pieces[:, :, None] == parent[:, None]).all(axis=3)  # (piece, its corner, face corner)
    index = np.take_along_axis(corners[source], equal.argmax(axis=2), axis=1)
    uncut = (pieces == parent).all(axis=(1, 2))
    index[uncut] = corners[source[uncut]]
    fresh = ~equal.any(axis=2)
    new_vertices, new_index = plain_unique_rows(pieces[fresh])
    index[fresh] = len(vertices) + new_index
    used, faces = np.unique(index, return_inverse=True)
    table = np.concatenate([vertices, new_vertices])
    return table[used], faces.reshape(-1, 3).astype(np.int32), owner[source]


def toy_house_views():
    """Two views of each bundled toy house, small enough to trace at once."""
    for house in (load(source) for source in discover(BUNDLED_TOY)):
        cameras, _ = sample_cameras(house, 2, np.random.default_rng(0), CameraSamplerConfig())
        tracer = HouseTracer(house)
        for cam in cameras:
            cam = cam.resized(80, 60)
            yield house, cam, frontal_layers(house, cam, tracer)


#: the frustum's per-vertex and per-face tests in numpy (the reference) and compiled
SETTLE = pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=pytest.mark.skipif(
    not frustum.COMPILED, reason="sceneforge's extension is not built"))], ids=["numpy", "compiled"])


def assert_plain_meshes(house, cam, d5, id_lists, config, compiled=None):
    planes = frustum_planes(cam, config.near)
    limit = _envelope_limit(d5, config.behind_envelope)
    meshes = _clipped_meshes(house, id_lists, cam, planes, d5, limit, config, compiled)
    for mesh, ids in zip(meshes, id_lists):
        vertices, faces, instance = plain_clipped_mesh(house, ids, cam, planes, d5, config)
        np.testing.assert_array_equal(mesh.vertices, vertices)
        np.testing.assert_array_equal(mesh.faces, faces)
        np.testing.assert_array_equal(mesh.instance, instance)
        assert mesh.vertices.dtype == np.float64
        assert mesh.faces.dtype == mesh.instance.dtype == np.int32
    return meshes


def settled(house, cam, d5, ids, config, compiled=None):
    """How many faces _settle_fast keeps, passes on as having a corner behind D5 and as crossing
    a plane, and the instances it skips as outside."""
    limit = _envelope_limit(d5, config.behind_envelope)
    soup = _settle_fast(house, ids, frustum_planes(cam, config.near), cam, _lens(cam, d5.shape), limit,
                        config.clip_tolerance, compiled)
    return np.array([len(soup.kept), len(soup.hidden), len(soup.cross)]), sorted(set(ids) - set(soup.ids.tolist()))


@SETTLE
@pytest.mark.parametrize("max_edge", [None, 1.0, 4.0])
def test_clipped_meshes_settle_faces_by_vertex_as_the_plain_pipeline_does(max_edge, compiled):
    # _clipped_meshes keeps faces wholly inside and in front of D5, and drops faces wholly
    # outside a plane, from tests on their vertices: bit for bit what clipping and testing
    # every face gives. The occluded view with the windowed occluder of the test above:
    # faces kept, hidden, partly hidden, cut and wholly hidden.
    config = ViewMeshConfig(max_edge_pixels=max_edge)
    house, cam, layers = half_occluded_view()
    d5 = np.full_like(layers.depth[4], 1.0)
    d5[9:21, 12:28] = layers.depth[4][9:21, 12:28]
    d5[2:6, 30:36] = np.nan
    gaps = np.random.default_rng(1).random(d5.shape) < 0.05
    d5[gaps] = layers.depth[4][gaps]
    # An instance behind the camera is skipped; one outside a plane by half the tolerance
    # is not; no instances, no faces.
    v, f = quad(-10, 10, -10, 10, 1.0)
    make_instance(house, name="behind", category=1, label="wall", room_id="r0", vertices=v, faces=f)
    v, f = quad(-2, -0.8 - 0.5 * tol.clip, -1, 1, -2.0)  # the left plane is at x = -0.8
    make_instance(house, name="edge", category=1, label="wall", room_id="r0", vertices=v, faces=f)
    counts, skipped = settled(house, cam, d5, [0, 1, 2, 3, 4, 5], config, compiled)
    assert (counts > 0).all() and skipped == [4]
    objects, _, empty = assert_plain_meshes(house, cam, d5, [[2, 3], [0, 1, 4, 5], []], config, compiled)
    assert len(objects.faces) and not len(empty.faces)


@SETTLE
def test_clipped_meshes_of_toy_houses_match_the_plain_pipeline(compiled):
    config = ViewMeshConfig()
    counts = np.zeros(3, dtype=np.int64)
    for house, cam, layers in toy_house_views():
        inst = np.asarray(layers.instance)
        ids = [np.unique(inst[inst >= 0]).tolist(), [k for k, i in enumerate(house.instances) if i.envelope]]
        d5 = np.asarray(layers.depth[4])
        assert_plain_meshes(house, cam, d5, ids, config, compiled)
        counts += sum(settled(house, cam, d5, one, config, compiled)[0] for one in ids)
    assert (counts > 0).all()


@pytest.mark.skipif(not frustum.COMPILED, reason="sceneforge's extension is not built")
def test_compiled_vertex_codes_and_face_classes_equal_numpy_bit_for_bit():
    # Vertices all around a skewed camera, many within float64 rounding of a frustum plane
    # or of the envelope limit at their pixel, some behind the camera and on its plane.
    rng = np.random.default_rng(7)
    where, view = np.array([0.3, 1.2, -0.4]), np.array([2.0, 0.9, 3.0])
    K = np.array(look_at_camera(where, view, width=40, height=30).K, dtype=np.float64)
    K[0, 1] = 0.7
    cam = look_at_camera(where, view, K=K, width=40, height=30)
    planes = frustum_planes(cam, 0.01)
    points = rng.normal(size=(60_000, 3)) * 3 + cam.cam_to_world[:3, 3]
    # project a third onto a random plane, then nudge by a few ulps (and the tolerance)
    on = rng.integers(0, 5, 20_000)
    p = points[:20_000]
    p -= (np.einsum("ij,ij->i", p, planes[on, :3]) + planes[on, 3])[:, None] * planes[on, :3]
    p += planes[on, :3] * (tol.clip * rng.integers(-1, 2, 20_000) + 1e-15 * rng.integers(-4, 5, 20_000))[:, None]
    points[-10:] = cam.cam_to_world[:3, 3]  # z = 0
    d5 = 1.0 + 4.0 * rng.random((30, 40))
    d5[rng.random(d5.shape) < 0.1] = np.nan
    config = ViewMeshConfig()
    limit = _envelope_limit(d5, config.behind_envelope)
    lens = _lens(cam, d5.shape)
    # a third exactly at the limit of their pixel (depth within an ulp or two)
    cam_frame = (points[20_000:40_000] - cam.cam_to_world[:3, 3]) @ cam.cam_to_world[:3, :3]
    px = np.floor(rng.random((20_000, 2)) * [40, 30]) + 0.5
    z = np.nan_to_num(limit[(px[:, 1].astype(int) * 40 + px[:, 0].astype(int))], posinf=2.0)
    z = z * (1 + 2.2e-16 * rng.integers(-2, 3, 20_000))
    cam_frame = np.linalg.solve(K, np.column_stack([px, np.ones(20_000)]).T).T * z[:, None]
    points[20_000:40_000] = cam_frame @ cam.cam_to_world[:3, :3].T + cam.cam_to_world[:3, 3]
    numpy_codes = _vertex_codes(points, planes, cam, lens, limit, tol.clip, False)
    codes = _vertex_codes(points, planes, cam, lens, limit, tol.clip, True)
    np.testing.assert_array_equal(codes, numpy_codes)
    assert len(np.unique(numpy_codes)) > 10  # many combinations of bits, both envelope sides
    corners = rng.integers(0, len(points), (50_000, 3))
    for got, want in zip(frustum._face_classes(codes, corners, True), frustum._face_classes(codes, corners, False)):
        np.testing.assert_array_equal(got, want)
        assert len(want)
    with pytest.raises(IndexError):
        frustum._face_classes(codes, np.array([[0, 1, len(points)]]), True)
    with pytest.raises(IndexError):
        frustum._compiled_weld_faces(corners, np.array([0]), np.array([[0, 1, len(points)]]), len(points))
