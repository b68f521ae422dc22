"""Depth layers → meshes: the 2×2 triangulation, the edge rule, world coordinates (docs/spec.md §11.1)."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from sceneforge import depth_mesh
from sceneforge.cameras import Camera, default_intrinsics, look_at_camera
from sceneforge.evaluate import EvalView, Mesh, concatenate, grid_mesh, height_map_mesh, perspective_mesh
from sceneforge.evaluate.depth_mesh import MeshingConfig

W, H = 320, 240
K = default_intrinsics(W, H)
F = K[0, 0]
CAMERA = look_at_camera((1.0, 1.5, -2.0), (0.3, -0.2, 1.0), width=W, height=H)


def test_fronto_parallel_plane_triangulates_to_its_area():
    z = 2.5
    mesh = perspective_mesh(np.full((H, W), z), K, CAMERA.cam_to_world)
    # the mesh spans the pixel centres: (W-1) × (H-1) pixels of (z/f)² each, two triangles each
    pixel = z / F
    assert len(mesh) == 2 * (W - 1) * (H - 1)
    assert mesh.area == pytest.approx((W - 1) * (H - 1) * pixel**2, rel=1e-9)
    # and is within 1 % of the plane the camera sees (the whole image at depth z)
    seen = W * H * pixel**2
    assert abs(mesh.area - seen) / seen < 0.01
    # in world coordinates: every vertex projects back onto its pixel centre at depth z
    uv, depth = CAMERA.project(mesh.vertices)
    np.testing.assert_allclose(depth, z, atol=1e-9)
    np.testing.assert_allclose(uv % 1.0, 0.5, atol=1e-6)
    # and every face is wound to face the camera
    tri = mesh.triangles
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert (normal @ CAMERA.view_direction < 0).all()


def test_depth_jump_beyond_the_edge_rule_makes_no_bridge():
    depth = np.full((H, W), 2.0)
    depth[:, W // 2:] = 3.0  # 1 m jump, far above 7 × 2 m / 259 px ≈ 5.4 cm
    mesh = perspective_mesh(depth, K, CAMERA.cam_to_world)
    _, z = CAMERA.project(mesh.vertices)
    near = np.isclose(z, 2.0)[mesh.faces]
    assert (near.all(axis=1) | ~near.any(axis=1)).all(), "a triangle joins the two planes"
    # each side is meshed completely: (W/2 - 1) × (H - 1) blocks of two triangles
    assert len(mesh) == 2 * 2 * (W // 2 - 1) * (H - 1)


@pytest.mark.parametrize("factor, bridged", [(0.95, True), (1.05, False)])
def test_edge_rule_threshold_is_a_times_the_nearer_footprint(factor, bridged):
    z, a = 2.0, 7.0
    depth = np.full((2, 2), z)
    depth[:, 1] = z + factor * a * z / F  # horizontal edges jump just under / over the limit
    mesh = perspective_mesh(depth, K, np.eye(4), a=a)
    assert len(mesh) == (2 if bridged else 0)


@pytest.mark.parametrize("factor, kept", [(1.3, True), (1.5, False)])
def test_diagonal_edges_allow_sqrt2_more(factor, kept):
    # corners 1, 2, 3 valid (corner 0 missing): one triangle with the diagonal 1–2
    z, a = 2.0, 7.0
    jump = factor * a * z / F
    depth = np.array([[np.nan, z], [z + jump, z + jump / 2]])
    mesh = perspective_mesh(depth, K, np.eye(4), a=a)
    assert len(mesh) == (1 if kept else 0)


def test_four_corners_split_along_the_smaller_depth_difference():
    # |d0 - d3| = 0.05 > |d1 - d2| = 0: split along the 1–2 diagonal
    depth = np.array([[2.0, 2.01], [2.01, 2.05]])
    points = np.zeros((2, 2, 3))
    points[..., 0], points[..., 1] = np.meshgrid([0.0, 1.0], [0.0, 1.0])
    mesh = grid_mesh(points, depth, np.full((2, 2), 1.0), a=7.0)
    assert len(mesh) == 2
    corner = {tuple(p[:2]): k for k, p in enumerate(mesh.vertices)}
    diagonal = {corner[(1.0, 0.0)], corner[(0.0, 1.0)]}
    assert all(diagonal <= set(face) for face in mesh.faces.tolist())


def test_nan_pixels_give_no_vertices():
    depth = np.full((4, 4), 2.0)
    depth[1:3, 1:3] = np.nan  # a hole: every block touching it has at most 3 valid corners
    mesh = perspective_mesh(depth, K, np.eye(4))
    assert np.isfinite(mesh.vertices).all()
    # of the 8 blocks around the hole, the 4 corner blocks have 3 valid corners (one
    # triangle each) and the 4 edge blocks only 2 (none)
    assert len(mesh) == 4
    assert perspective_mesh(np.full((4, 4), np.nan), K, np.eye(4)).area == 0


def test_overhead_height_map_mesh_is_metric_and_skips_the_floor():
    res, half, tz = 50, 2.0, 2.4
    pose = np.eye(4)
    pose[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]  # columns: x right, image down +Z, z world down
    pose[:3, 3] = (0.5, 3.0, 1.0)                       # floor at 3.0 - 2.4 = 0.6
    height = np.full((res, res), 0.8, dtype=np.float32)
    height[:, :10] = 0.05   # at the 5 cm limit (in float32, as stored): floor, not meshed
    height[:, 10:12] = 0.06  # just above: meshed
    mesh = height_map_mesh(height, pose, half, tz)
    pixel = 2 * half / res
    # the 6 cm strip (1 block wide) and the 80 cm top (37 blocks) stay apart: the 74 cm
    # step is more than 7 pixels (56 cm)
    assert len(mesh) == 2 * (res - 1) * (1 + 37)
    assert mesh.area == pytest.approx((1 + 37) * (res - 1) * pixel**2, rel=1e-6)
    # world heights: floor (3.0 - 2.4 = 0.6) + height
    ys = np.unique(np.round(mesh.vertices[:, 1], 6))
    np.testing.assert_allclose(ys, [0.6 + 0.06, 0.6 + 0.8], atol=1e-6)
    # the footprint is the pixel size: a step of 6.9 pixel sizes is joined, 7.1 is not
    for step, joined in ((6.9 * pixel, True), (7.1 * pixel, False)):
        h = np.full((res, res), 1.0)
        h[:, res // 2:] += step
        faces = len(height_map_mesh(h, pose, half, tz, MeshingConfig(a=7.0)))
        assert faces == (2 * (res - 1) ** 2 if joined else 2 * 2 * (res // 2 - 1) * (res - 1))


def test_eval_view_meshes_every_part(small_house):
    from sceneforge.raytrace import HouseTracer
    from sceneforge.view import compute_view

    camera = look_at_camera((0.0, 1.5, -1.6), (0.0, -0.2, 1.0), width=80, height=60)
    gt = compute_view(small_house, camera, tracer=HouseTracer(small_house))
    parts = EvalView.from_ground_truth(gt).meshes()
    assert list(parts) == ["D1", "D2", "D3", "D4", "D5", "overhead"]
    assert all(len(parts[p]) for p in ("D1", "D2", "D5", "overhead"))
    # the table top seen from above lies at its world height (0.75 m)
    top = parts["overhead"].vertices[:, 1]
    assert np.isclose(top, 0.75, atol=1e-4).mean() > 0.3
    both = concatenate([parts["D1"], parts["D2"]])
    assert len(both) == len(parts["D1"]) + len(parts["D2"])
    assert both.area == pytest.approx(parts["D1"].area + parts["D2"].area)


def test_mesh_rejects_faces_outside_its_vertices():
    with pytest.raises(ValueError, match="outside"):
        Mesh(np.zeros((3, 3)), [[0, 1, 3]])


def test_camera_with_principal_point_offset_is_respected():
    K2 = K.copy()
    K2[0, 2] += 17.0
    cam = Camera(K2, CAMERA.cam_to_world, W, H)
    mesh = perspective_mesh(np.full((H, W), 3.0), K2, cam.cam_to_world)
    uv, _ = cam.project(mesh.vertices)
    assert uv[:, 0].min() == pytest.approx(0.5) and uv[:, 0].max() == pytest.approx(W - 0.5)


def test_edge_factor_presets_per_layer():
    paper, reference = MeshingConfig(), MeshingConfig(preset="reference")
    assert [paper.edge_factor(p) for p in ("D1", "D4", "D5", "overhead")] == [7.0, 7.0, 7.0, 7.0]
    assert [reference.edge_factor(p) for p in ("D1", "D4", "D5", "overhead")] == [10.0, 10.0, 15.0, 10.0]
    assert MeshingConfig(preset="reference", a=12.0).edge_factor("D5") == 12.0
    with pytest.raises(ValueError, match="preset"):
        MeshingConfig(preset="mine")
    with pytest.raises(ValueError, match="no part"):
        paper.edge_factor("D6")


def test_the_reference_preset_meshes_d5_with_its_own_factor():
    # a depth step of 12 footprints: joined at a = 15 (D5 under the reference preset),
    # cut at a = 7 and at a = 10 (D1 under either preset)
    z = 2.0
    depth = np.full((5, 4, 4), z, dtype=np.float32)
    depth[:, :, 2:] = z + 12 * z / F
    view = EvalView(depth, K, np.eye(4), np.full((4, 4), np.nan), np.eye(4), 1.0, np.zeros(5))
    paper, reference = view.meshes(MeshingConfig()), view.meshes(MeshingConfig(preset="reference"))
    assert len(paper["D5"]) == len(paper["D1"]) == len(reference["D1"]) == 2 * 2 * 3
    assert len(reference["D5"]) == 2 * 3 * 3


def plain_grid_faces(depth, footprint, a):
    """The block rule and the edge rule in their plainest form, block by block: the corners
    (pixel indices) of every triangle, in grid_faces's order (by shape, then block)."""
    h, w = depth.shape
    shapes = [(0, 2, 1), (0, 3, 1), (0, 2, 3), (1, 2, 3)]
    out = []
    for r in range(h - 1):
        for c in range(w - 1):
            pixel = [r * w + c, r * w + c + 1, (r + 1) * w + c, (r + 1) * w + c + 1]
            z = [depth.flat[p] for p in pixel]
            valid = [np.isfinite(x) for x in z]
            if sum(valid) == 4:
                along_03 = abs(z[0] - z[3]) < abs(z[1] - z[2])
                chosen = [1, 2] if along_03 else [0, 3]
            elif sum(valid) == 3:
                chosen = [k for k, s in enumerate(shapes) if all(valid[i] for i in s)]
            else:
                chosen = []
            for k in chosen:
                tri = shapes[k]
                edges = [(tri[e], tri[(e + 1) % 3]) for e in range(3)]
                cut = False
                for i, j in edges:
                    near = footprint.flat[pixel[i]] if z[i] <= z[j] else footprint.flat[pixel[j]]
                    diagonal = {i, j} in ({0, 3}, {1, 2})
                    cut |= abs(z[i] - z[j]) > a * near * (np.sqrt(2.0) if diagonal else 1.0)
                if not cut:
                    out.append((k, r * (w - 1) + c, [pixel[i] for i in tri]))
    out.sort(key=lambda x: (x[0], x[1]))
    return np.array([x[2] for x in out], dtype=np.int64).reshape(-1, 3)


@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=pytest.mark.skipif(
    not depth_mesh.COMPILED, reason="sceneforge's extension is not built"))], ids=["numpy", "compiled"])
@pytest.mark.parametrize("seed", range(6))
def test_grid_faces_match_the_plain_block_by_block_rule(seed, compiled):
    """Both kernels (the numpy reference and the compiled one), on random depths with holes;
    and equal to each other, order and dtype included."""
    rng = np.random.default_rng(seed)
    h, w = rng.integers(2, 24, 2)
    depth = 1.0 + rng.random((h, w)) * rng.choice([0.01, 0.3, 3.0])
    depth[rng.random((h, w)) < 0.2] = np.nan
    footprint = 0.01 + 0.04 * rng.random((h, w))
    for a in (7.0, 10.0, 15.0):
        faces = depth_mesh.grid_faces(depth, footprint, a, compiled=compiled)
        np.testing.assert_array_equal(faces, plain_grid_faces(depth, footprint, a))
        reference = depth_mesh.grid_faces(depth, footprint, a, compiled=False)
        assert faces.dtype == reference.dtype and faces.tobytes() == reference.tobytes()


@pytest.mark.skipif(not depth_mesh.COMPILED, reason="sceneforge's extension is not built")
@pytest.mark.parametrize("seed", range(3))
def test_compiled_compact_equals_the_numpy_one(seed):
    """The pixels the faces use, in pixel order, and the faces renumbered: the same arrays
    from both kernels, unused pixels and repeated corners included."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 400))
    faces = rng.integers(0, n, (int(rng.integers(0, 200)), 3))
    points = rng.normal(size=(n, 3))
    got, want = (depth_mesh.compact(points, faces, compiled=c) for c in (True, False))
    for a, b in zip(got, want):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    # every point used (a D5 surface without holes): the points come back as a copy
    every = np.concatenate([faces, rng.permutation(np.arange(3 * n) % n).reshape(-1, 3)])
    got, want = (depth_mesh.compact(points, every, compiled=c) for c in (True, False))
    for a, b in zip(got, want):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    assert not np.shares_memory(got[0], points)
    with pytest.raises(IndexError):
        depth_mesh.compact(points, np.array([[0, 1, n]]), compiled=True)


COMPILED_ONLY = pytest.mark.skipif(not depth_mesh.COMPILED, reason="sceneforge's extension is not built")


def random_lens(rng, h: int, w: int) -> np.ndarray:
    f = rng.uniform(20.0, 80.0)
    return np.array([[f, rng.choice([0.0, 0.3]), rng.uniform(0, w)], [0.0, f * rng.uniform(0.9, 1.1), rng.uniform(0, h)],
                     [0.0, 0.0, 1.0]])


def random_pose(rng) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    pose[:3, 3] = rng.normal(size=3) * 3
    return pose


def same_surface(t, depth_scale, label, K, pose, shape, a=15.0):
    """depth_surface compiled (on 1 to 3 threads) and in numpy: the same arrays, byte for
    byte (so NaN and -0 count), dtype and shape; returns the numpy one."""
    want = depth_mesh.depth_surface(t, depth_scale, label, K, pose, shape, a, compiled=False)
    for threads in (1, 2, 3):
        got = depth_mesh.depth_surface(t, depth_scale, label, K, pose, shape, a, compiled=True, threads=threads)
        for name, x, y in zip(("vertices", "faces", "label"), got, want):
            assert x.dtype == y.dtype and x.shape == y.shape, name
            assert x.tobytes() == y.tobytes(), name
    assert want[0].dtype == np.float64 and want[1].dtype == want[2].dtype == np.int32
    return want


@COMPILED_ONLY
@pytest.mark.parametrize("seed", range(6))
def test_compiled_depth_surface_equals_the_numpy_steps_bit_for_bit(seed):
    """Random depth maps with holes and depth jumps (steps and noise beyond the edge rule),
    random cameras and labels: the fused kernel's vertices, faces and labels are those of
    perspective_faces, perspective_points and compact, whatever its thread count."""
    rng = np.random.default_rng(seed)
    dropped = 0
    for _ in range(8):
        h, w = (int(x) for x in rng.integers(2, 90, 2))
        t = 1.0 + rng.random((h, w)) * rng.choice([0.001, 0.3, 3.0])
        t[:, int(rng.integers(0, w)):] += rng.choice([0.0, 0.05, 2.0])  # a step
        t[rng.random((h, w)) < rng.choice([0.0, 0.1, 0.5])] = np.nan
        t = t.ravel()
        depth_scale = rng.uniform(0.5, 1.0, h * w)
        label = rng.integers(-1, 40, h * w).astype(np.int32)
        K, pose = random_lens(rng, h, w), random_pose(rng)
        vertices, faces, _ = same_surface(t, depth_scale, label, K, pose, (h, w))
        everything = depth_mesh.depth_surface(t, depth_scale, label, K, pose, (h, w), 1e300, compiled=False)
        dropped += len(everything[1]) - len(faces)
    assert dropped > 0  # the edge rule cut some triangles


@COMPILED_ONLY
@pytest.mark.parametrize("shape, holes", [
    ((1, 1), 0.0), ((1, 9), 0.0), ((9, 1), 0.2), ((2, 2), 0.0), ((2, 2), 0.3), ((2, 9), 0.2), ((9, 2), 0.0),
    ((7, 5), 1.0), ((40, 30), 0.0), ((3, 70_000), 0.1)])
def test_compiled_depth_surface_at_edge_sizes(shape, holes):
    """Rows or columns of one pixel (no blocks), a single block, no NaN, all NaN, and rows of
    more blocks than the kernel's 16-bit shape counters hold."""
    rng = np.random.default_rng(shape[0] * 100 + shape[1])
    n = shape[0] * shape[1]
    t = 2.0 + 0.01 * rng.random(n)
    t[rng.random(n) < holes] = np.nan
    K = np.array([[30.0, 0.0, shape[1] / 2], [0.0, 30.0, shape[0] / 2], [0.0, 0.0, 1.0]])
    vertices, faces, label = same_surface(t, np.full(n, 0.9), np.arange(n, dtype=np.int32), K, random_pose(rng), shape)
    blocks = (shape[0] - 1) * (shape[1] - 1)
    if holes == 0.0:
        assert len(vertices) == (n if blocks else 0) and len(faces) == 2 * blocks
    if holes == 1.0:
        assert len(vertices) == len(faces) == 0


def fma(a: float, b: float, c: float) -> float:
    """a * b + c rounded once (exact rational arithmetic, float() rounds to nearest)."""
    return float(Fraction(a) * Fraction(b) + Fraction(c))


@COMPILED_ONLY
def test_depth_surface_points_round_as_numpy_matmul_does():
    """The points are (rays * depth) @ R.T + T, whose rows numpy's OpenBLAS sums as
    fma(a2, x2, fma(a1, x1, a0 x0)); the kernel repeats that. Checked here on the numpy side
    exactly, and on inputs where plain a0 x0 + a1 x1 + a2 x2 and the reverse fma order round
    differently: a kernel that rounded either way would fail the equality."""
    rng = np.random.default_rng(11)
    h, w = 30, 40
    K, pose = random_lens(rng, h, w), random_pose(rng)
    t = 2.0 + 0.001 * rng.random(h * w)  # smooth: every pixel is a vertex, in pixel order
    depth_scale = rng.uniform(0.9, 0.9001, h * w)
    vertices, _, _ = same_surface(t, depth_scale, np.zeros(h * w, dtype=np.int32), K, pose, (h, w))
    assert len(vertices) == h * w
    x = depth_mesh._pixel_rays(K.tobytes(), h, w).reshape(-1, 3) * (t * depth_scale)[:, None]
    R, T = pose[:3, :3], pose[:3, 3]
    sample = rng.choice(h * w, 300, replace=False)
    forward = [[fma(R[j, 2], x[p, 2], fma(R[j, 1], x[p, 1], R[j, 0] * x[p, 0])) + T[j] for j in range(3)]
               for p in sample]
    reverse = [[fma(R[j, 0], x[p, 0], fma(R[j, 1], x[p, 1], R[j, 2] * x[p, 2])) + T[j] for j in range(3)]
               for p in sample]
    plain = (x[sample, None, 0] * R[:, 0] + x[sample, None, 1] * R[:, 1]) + x[sample, None, 2] * R[:, 2] + T
    np.testing.assert_array_equal(vertices[sample], forward)
    assert (np.array(reverse) != vertices[sample]).sum() > 10
    assert (plain != vertices[sample]).sum() > 10


@COMPILED_ONLY
def test_depth_surface_zeros_keep_the_sign_numpy_matmul_gives():
    """OpenBLAS sums each row from +0, so a zero point coordinate is +0 where a0 x0 first
    could leave -0, which a -0 translation keeps: the camera at -0, rotation entries -0 and
    depth 0, so that every product of some rows is -0."""
    h, w = 4, 5
    K = np.array([[10.0, 0.0, 2.0], [0.0, 10.0, 1.5], [0.0, 0.0, 1.0]])  # rays of either sign
    pose = np.eye(4)
    pose[:3, :3] = [[-1.0, -0.0, -0.0], [-0.0, -1.0, -0.0], [-0.0, -0.0, 1.0]]
    pose[:3, 3] = -0.0
    vertices, faces, _ = same_surface(np.zeros(h * w), np.ones(h * w), np.zeros(h * w, dtype=np.int32), K, pose,
                                      (h, w))
    assert len(vertices) == h * w and not vertices.any()
    x = depth_mesh._pixel_rays(K.tobytes(), h, w).reshape(-1, 3) * 0.0
    R = pose[:3, :3]
    a0_first = (x[:, None, 0] * R[:, 0] + x[:, None, 1] * R[:, 1]) + x[:, None, 2] * R[:, 2] + pose[:3, 3]
    assert (np.signbit(a0_first) != np.signbit(vertices)).any()
