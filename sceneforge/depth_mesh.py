"""Depth map → triangles: the 2×2 block rule and the edge rule (SPEC §11, *(ref)*).

The one triangulation kernel of sceneforge. The ground truth uses it to turn the envelope
layer D5 into the envelope's ground-truth surface (SPEC §5, :func:`sceneforge.frustum.envelope_surface`);
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

import numpy as np

# Corners of a 2×2 block: 0 = (row, col), 1 = (row, col + 1), 2 = (row + 1, col),
# 3 = (row + 1, col + 1). The reference's four triangles, all wound the same way (their
# normal faces the camera), and their edges as corner pairs.
_TRIANGLES = np.array([[0, 2, 1], [0, 3, 1], [0, 2, 3], [1, 2, 3]])
_PAIRS = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
_DIAGONALS = frozenset({(0, 3), (1, 2)})
#: (row, column) offset of each block corner
_CORNER_OFFSETS = ((0, 0), (0, 1), (1, 0), (1, 1))


def grid_faces(depth: np.ndarray, footprint: np.ndarray, a: float) -> np.ndarray:
    """The triangles of an image of depths, by the 2×2 block rule and the edge rule.

    depth     : (H, W) float  the depth the edge rule compares; NaN = no vertex
    footprint : (H, W) float  metric size of each pixel at its depth, metres
    a         : float         edge rule factor

    Returns
    -------
    faces : (m, 3) int64  row-major pixel indices (``row * W + col``) of each triangle's
            corners; all triangles of the first of the four block shapes, then the second...,
            blocks in row-major order within each; the first corner is the block's top-left
            pixel except for the shape without it (then the top-right one)
    """
    depth = np.asarray(depth, dtype=np.float64)
    h, w = depth.shape
    if h < 2 or w < 2:
        return np.zeros((0, 3), dtype=np.int64)
    corner_slices = [(slice(dr, h - 1 + dr), slice(dc, w - 1 + dc)) for dr, dc in _CORNER_OFFSETS]
    valid = np.isfinite(depth)
    d = np.stack([depth[s] for s in corner_slices])          # (4, H-1, W-1)
    ok = np.stack([valid[s] for s in corner_slices])
    fp = np.stack([np.asarray(footprint, dtype=np.float64)[s] for s in corner_slices])
    mask = (ok * np.array([1, 2, 4, 8])[:, None, None]).sum(axis=0)

    # The edge rule, per corner pair: the jump against the nearer corner's footprint.
    with np.errstate(invalid="ignore"):
        jump = {}
        for i, j in _PAIRS:
            near = np.where(d[i] <= d[j], fp[i], fp[j])
            limit = a * near * (math.sqrt(2.0) if (i, j) in _DIAGONALS else 1.0)
            jump[i, j] = np.abs(d[i] - d[j]) > limit
        along_03 = np.abs(d[0] - d[3]) < np.abs(d[1] - d[2])
    full = mask == 15
    emit = (
        (mask == 7) | (full & ~along_03),   # 0 2 1
        (mask == 11) | (full & along_03),   # 0 3 1
        (mask == 13) | (full & along_03),   # 0 2 3
        (mask == 14) | (full & ~along_03),  # 1 2 3
    )
    top_left = np.arange(h * w, dtype=np.int64).reshape(h, w)[:-1, :-1].ravel()
    corner_pixel = np.stack([top_left + dr * w + dc for dr, dc in _CORNER_OFFSETS])  # (4, blocks)
    faces = []
    for tri, keep in zip(_TRIANGLES, emit):
        for k in range(3):
            i, j = sorted((tri[k], tri[(k + 1) % 3]))
            keep = keep & ~jump[i, j]
        blocks = np.flatnonzero(keep)
        faces.append(corner_pixel[tri][:, blocks].T)
    return np.concatenate(faces)


def compact(points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An indexed mesh of the pixels ``faces`` use, in pixel order.

    points : (H*W, 3) float  the point of every pixel, row-major
    faces  : (m, 3) int      pixel indices (:func:`grid_faces`)
    Returns vertices (k, 3) float64 and faces (m, 3) int64 indexing them.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
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
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T  # z = 1
    return (rays * depth[..., None]) @ pose[:3, :3].T + pose[:3, 3]


def perspective_faces(depth: np.ndarray, K: np.ndarray, a: float) -> np.ndarray:
    """:func:`grid_faces` of a planar depth map (H, W) of a pinhole camera with intrinsics
    ``K`` (3, 3): a pixel's footprint at depth ``z`` is ``z / fx``."""
    depth = np.asarray(depth, dtype=np.float64)
    return grid_faces(depth, depth / float(np.asarray(K)[0, 0]), a)
