"""Depth map → triangles: the 2×2 block rule and the edge rule (docs/spec.md §11.1, *(ref)*).

The one triangulation kernel of sceneforge. The ground truth uses it to turn the envelope
layer D5 into the envelope's ground-truth surface (docs/spec.md §5.2, :func:`sceneforge.frustum.envelope_surface`);
the evaluation uses it to turn every layer it scores into a mesh
(:mod:`sceneforge.evaluate.depth_mesh`).

Every pixel with a finite depth is a vertex. Each 2×2 block of pixels with at least three
vertices gives triangles: with three, the one triangle they make; with four, two
triangles split along the diagonal whose corners differ less in depth. A triangle is
dropped when one of its edges spans a depth jump larger than ``a`` times the metric
footprint of the nearer pixel (× √2 on a diagonal). With four valid corners the diagonal
is chosen before the edge rule, so a block may keep one triangle, as in the reference
(MVE's ``depthmap_triangulate``).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

try:
    from .raytrace._embree import compact_faces as _compiled_compact
    from .raytrace._embree import depth_surface as _compiled_depth_surface
    from .raytrace._embree import grid_faces as _compiled_grid_faces
except ImportError:  # the extension is not built: numpy only
    _compiled_grid_faces = _compiled_compact = _compiled_depth_surface = None

#: whether :func:`grid_faces`, :func:`compact` and :func:`depth_surface` run compiled (a
#: few passes over the blocks and faces in sceneforge's extension; the numpy versions are
#: the reference, and the tests hold the two equal)
COMPILED = _compiled_grid_faces is not None

# Corners of a 2×2 block: 0 = (row, col), 1 = (row, col + 1), 2 = (row + 1, col),
# 3 = (row + 1, col + 1). The reference's four triangles, all wound the same way (their
# normal faces the camera), and their edges as corner pairs.
_TRIANGLES = np.array([[0, 2, 1], [0, 3, 1], [0, 2, 3], [1, 2, 3]])
_PAIRS = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
_DIAGONALS = frozenset({(0, 3), (1, 2)})
#: (row, column) offset of each block corner
_CORNER_OFFSETS = ((0, 0), (0, 1), (1, 0), (1, 1))


def grid_faces(depth: np.ndarray, footprint: np.ndarray, a: float, compiled: bool | None = None) -> np.ndarray:
    """The triangles of an image of depths, by the 2×2 block rule and the edge rule.

    depth     : (H, W) float  the depth the edge rule compares; NaN = no vertex
    footprint : (H, W) float  metric size of each pixel at its depth, metres
    a         : float         edge rule factor
    compiled  : the compiled kernel (True), the numpy reference (False), or the compiled one
                where the extension is built (None); the same triangles either way

    Returns
    -------
    faces : (m, 3) int64  row-major pixel indices (``row * W + col``) of each triangle's
            corners; all triangles of the first of the four block shapes, then the second...,
            blocks in row-major order within each; the first corner is the block's top-left
            pixel except for the shape without it (then the top-right one)
    """
    depth = np.asarray(depth, dtype=np.float64)
    footprint = np.asarray(footprint, dtype=np.float64)
    if depth.ndim != 2 or footprint.shape != depth.shape:
        raise ValueError(f"depth and footprint must be the same (H, W), got {depth.shape} and {footprint.shape}")
    h, w = depth.shape
    if h < 2 or w < 2:
        return np.zeros((0, 3), dtype=np.int64)
    if COMPILED if compiled is None else compiled:
        if _compiled_grid_faces is None:
            raise RuntimeError("the compiled grid_faces needs sceneforge's Embree extension, which is not built")
        faces = _compiled_grid_faces(np.ascontiguousarray(depth), np.ascontiguousarray(footprint), h, w,
                                     float(a), float(a) * math.sqrt(2.0))
        return np.frombuffer(faces, dtype=np.int64).reshape(-1, 3)
    return _numpy_grid_faces(depth, footprint, a)


def _numpy_grid_faces(depth: np.ndarray, footprint: np.ndarray, a: float) -> np.ndarray:
    """:func:`grid_faces` with whole-image numpy operations: the reference."""
    h, w = depth.shape
    valid = np.isfinite(depth)
    with np.errstate(invalid="ignore"):
        # The edge rule, per pixel pair: the jump against the nearer pixel's footprint. Each
        # horizontal and vertical pair is shared by two blocks: test it once for the image.
        across = _jumps(depth[:, :-1], depth[:, 1:], footprint[:, :-1], footprint[:, 1:], a)  # (H, W-1)
        down = _jumps(depth[:-1], depth[1:], footprint[:-1], footprint[1:], a)              # (H-1, W)
        d = [depth[dr:h - 1 + dr, dc:w - 1 + dc] for dr, dc in _CORNER_OFFSETS]
        fp = [footprint[dr:h - 1 + dr, dc:w - 1 + dc] for dr, dc in _CORNER_OFFSETS]
        diagonal = a * math.sqrt(2.0)
        jump = {(0, 1): across[:-1], (2, 3): across[1:], (0, 2): down[:, :-1], (1, 3): down[:, 1:],
                (0, 3): _jumps(d[0], d[3], fp[0], fp[3], diagonal), (1, 2): _jumps(d[1], d[2], fp[1], fp[2], diagonal)}
        along_03 = np.abs(d[0] - d[3]) < np.abs(d[1] - d[2])
    ok = [valid[dr:h - 1 + dr, dc:w - 1 + dc] for dr, dc in _CORNER_OFFSETS]
    full = ok[0] & ok[1] & ok[2] & ok[3]
    split_12 = full & ~along_03
    split_03 = full & along_03
    # A block with exactly three valid corners gives the triangle of those three.
    emit = (
        (ok[0] & ok[1] & ok[2] & ~ok[3]) | split_12,  # 0 2 1
        (ok[0] & ok[1] & ~ok[2] & ok[3]) | split_03,  # 0 3 1
        (ok[0] & ~ok[1] & ok[2] & ok[3]) | split_03,  # 0 2 3
        (~ok[0] & ok[1] & ok[2] & ok[3]) | split_12,  # 1 2 3
    )
    corner_offset = np.array([dr * w + dc for dr, dc in _CORNER_OFFSETS])
    faces = []
    for tri, keep in zip(_TRIANGLES, emit):
        for k in range(3):
            keep &= ~jump[tuple(sorted((tri[k], tri[(k + 1) % 3])))]
        blocks = np.flatnonzero(keep)
        # block b = row r, column c of the (H-1) × (W-1) blocks: its top-left pixel is b + r
        top_left = blocks + blocks // (w - 1)
        faces.append(top_left[:, None] + corner_offset[tri])
    return np.concatenate(faces)


def _jumps(d_i, d_j, f_i, f_j, a: float) -> np.ndarray:
    """(...) bool: ``|d_i - d_j|`` exceeds ``a`` × the footprint of the nearer of the two."""
    near = np.where(d_i <= d_j, f_i, f_j)
    near *= a
    return np.abs(d_i - d_j) > near


def compact(points: np.ndarray, faces: np.ndarray, compiled: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
    """An indexed mesh of the pixels ``faces`` use, in pixel order.

    points   : (H*W, 3) float  the point of every pixel, row-major
    faces    : (m, 3) int      pixel indices (:func:`grid_faces`)
    compiled : as for :func:`grid_faces`
    Returns vertices (k, 3) float64 and faces (m, 3) int64 indexing them.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if COMPILED if compiled is None else compiled:
        if _compiled_compact is None:
            raise RuntimeError("the compiled compact needs sceneforge's Embree extension, which is not built")
        used, renumbered = _compiled_compact(np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3), len(points))
        used = np.frombuffer(used, dtype=np.int64)
        # (a view's D5 surface often uses every pixel: then the points are copied as they are;
        # take is several times faster than fancy indexing)
        vertices = points.copy() if len(used) == len(points) else points.take(used, axis=0)
        return vertices, np.frombuffer(renumbered, dtype=np.int64).reshape(-1, 3)
    used = np.zeros(len(points), dtype=bool)
    used[faces.ravel()] = True
    renumber = np.cumsum(used) - 1
    return points[used], renumber[faces]


def perspective_points(depth: np.ndarray, K: np.ndarray, cam_to_world: np.ndarray) -> np.ndarray:
    """(H, W, 3) float64 world point at planar ``depth`` (H, W) on the ray through each pixel
    centre of a pinhole camera (K (3, 3), pixel centres at integer + 0.5; cam_to_world (4, 4),
    OpenCV axes); NaN where the depth is."""
    depth = np.asarray(depth, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    pose = np.asarray(cam_to_world, dtype=np.float64)
    h, w = depth.shape
    rays = _pixel_rays(K.tobytes(), h, w)  # z = 1
    return (rays * depth[..., None]) @ pose[:3, :3].T + pose[:3, 3]


@lru_cache(maxsize=8)
def _pixel_rays(K_bytes: bytes, h: int, w: int) -> np.ndarray:
    """(h, w, 3) float64 camera-frame point at planar depth 1 of each pixel centre of
    intrinsics ``K`` (its float64 bytes); read-only, shared by every view with these
    intrinsics (a render's views differ only in pose)."""
    K = np.frombuffer(K_bytes, dtype=np.float64).reshape(3, 3)
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T
    rays.flags.writeable = False
    return rays


def perspective_faces(depth: np.ndarray, K: np.ndarray, a: float, compiled: bool | None = None) -> np.ndarray:
    """:func:`grid_faces` of a planar depth map (H, W) of a pinhole camera with intrinsics
    ``K`` (3, 3): a pixel's footprint at depth ``z`` is ``z / fx``."""
    depth = np.asarray(depth, dtype=np.float64)
    return grid_faces(depth, depth / float(np.asarray(K)[0, 0]), a, compiled)


def depth_surface(t: np.ndarray, depth_scale: np.ndarray, label: np.ndarray, K: np.ndarray, cam_to_world: np.ndarray,
                  shape: tuple[int, int], a: float, compiled: bool | None = None,
                  threads: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mesh of the ray hits of a pinhole camera's pixels (row-major): their planar depth
    ``t * depth_scale`` triangulated (:func:`perspective_faces`), the points of the pixels
    the faces use (:func:`perspective_points`, :func:`compact`) and a label per face.

    t, depth_scale : (H*W,) float  distance along each pixel's ray (NaN = no vertex) and
                                   planar depth per unit distance (:meth:`Camera.rays`)
    label          : (H*W,) int32  per pixel; each face gets its first corner pixel's
    shape          : (H, W)
    compiled       : as for :func:`grid_faces`. Compiled, it is one kernel that writes each
                     output once, several times faster than these steps (their glue over
                     fresh whole-image arrays cost more than the steps); the steps in numpy
                     (False) are the reference, and the tests hold the two equal bit for bit
    threads        : threads the compiled kernel may use (the arrays do not depend on it)

    Returns vertices (k, 3) float64, faces (m, 3) int32 and label (m,) int32.
    """
    h, w = shape
    t = np.asarray(t, dtype=np.float64)
    depth_scale = np.asarray(depth_scale, dtype=np.float64)
    label = np.asarray(label, dtype=np.int32)
    K = np.asarray(K, dtype=np.float64)
    pose = np.asarray(cam_to_world, dtype=np.float64)
    if COMPILED if compiled is None else compiled:
        if _compiled_depth_surface is None:
            raise RuntimeError("the compiled depth_surface needs sceneforge's Embree extension, which is not built")
        vertices, faces, face_label = _compiled_depth_surface(
            np.ascontiguousarray(t), np.ascontiguousarray(depth_scale), np.ascontiguousarray(label),
            _pixel_rays(K.tobytes(), h, w), np.ascontiguousarray(pose[:3, :3]), np.ascontiguousarray(pose[:3, 3]),
            h, w, float(K[0, 0]), float(a), float(a) * math.sqrt(2.0), int(threads))
        return (np.frombuffer(vertices, dtype=np.float64).reshape(-1, 3),
                np.frombuffer(faces, dtype=np.int32).reshape(-1, 3), np.frombuffer(face_label, dtype=np.int32))
    depth = (t * depth_scale).reshape(shape)
    pixels = perspective_faces(depth, K, a, compiled)
    vertices, faces = compact(perspective_points(depth, K, pose).reshape(-1, 3), pixels, compiled)
    return vertices, faces.astype(np.int32), label[pixels[:, 0]]
