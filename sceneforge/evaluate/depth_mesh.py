"""Depth layers → triangle meshes in world coordinates (SPEC §11, *(ref)*).

Every pixel with a finite depth becomes a vertex: the point at that depth on the ray
through the pixel centre. Each 2×2 block of pixels with at least three vertices gives
triangles: with three, the one triangle they make; with four, two triangles split along
the diagonal whose corners differ less in depth. A triangle is dropped when one of its
edges spans a depth jump larger than ``a`` times the metric footprint of the nearer
pixel (× √2 on a diagonal): the footprint at depth ``z`` is ``z / fx`` for a perspective
camera and the pixel size for an orthographic one. With four valid corners the diagonal
is chosen before the edge rule, so a block may keep one triangle, as in the reference
(MVE's ``depthmap_triangulate``).

Overhead height maps are triangulated in the orthographic overhead camera; pixels at or
below ``min_height`` above the floor are left out, since the floor belongs to the
envelope that the overhead view does not predict (paper §5).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..frustum import triangle_areas


@dataclass(frozen=True)
class MeshingConfig:
    """How depth maps are turned into meshes."""

    #: edge rule: no edge across a depth jump larger than this × the pixel footprint
    a: float = 7.0
    #: overhead pixels at or below this height above the floor (m) are not meshed
    min_height: float = 0.05

    def __post_init__(self):
        if not self.a > 0:
            raise ValueError(f"a must be > 0, got {self.a}")
        if not self.min_height >= 0:
            raise ValueError(f"min_height must be >= 0 m, got {self.min_height}")


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh in world coordinates.

    vertices : (n, 3) float64  metres
    faces    : (m, 3) int32    indices into ``vertices``
    """

    vertices: np.ndarray
    faces: np.ndarray

    def __post_init__(self):
        vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(self.faces, dtype=np.int32).reshape(-1, 3)
        if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
            raise ValueError(f"faces index outside the {len(vertices)} vertices")
        object.__setattr__(self, "vertices", vertices)
        object.__setattr__(self, "faces", faces)

    @classmethod
    def empty(cls) -> "Mesh":
        return cls(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32))

    @property
    def triangles(self) -> np.ndarray:
        """(m, 3, 3) float64 corners of every face."""
        return self.vertices[self.faces]

    @property
    def area(self) -> float:
        """Total surface area, m²."""
        return float(triangle_areas(self.triangles).sum())

    def __len__(self) -> int:
        return len(self.faces)


def concatenate(meshes) -> Mesh:
    """One mesh holding every face of ``meshes`` (an iterable of :class:`Mesh`)."""
    meshes = list(meshes)
    if not meshes:
        return Mesh.empty()
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return Mesh(np.concatenate([m.vertices for m in meshes]),
                np.concatenate([m.faces + o for m, o in zip(meshes, offsets)]))


# Corners of a 2×2 block: 0 = (row, col), 1 = (row, col + 1), 2 = (row + 1, col),
# 3 = (row + 1, col + 1). The reference's four triangles, all wound the same way (their
# normal faces the camera), and their edges as corner pairs.
_TRIANGLES = np.array([[0, 2, 1], [0, 3, 1], [0, 2, 3], [1, 2, 3]])
_PAIRS = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
_DIAGONALS = frozenset({(0, 3), (1, 2)})


def grid_mesh(points: np.ndarray, depth: np.ndarray, footprint: np.ndarray, a: float) -> Mesh:
    """Triangulate an image of points with the 2×2 block rule and the edge rule.

    points    : (H, W, 3) float  the world point of every pixel
    depth     : (H, W) float     the depth the edge rule compares; NaN = no vertex
    footprint : (H, W) float     metric size of each pixel at its depth, metres
    a         : float            edge rule factor
    """
    depth = np.asarray(depth, dtype=np.float64)
    h, w = depth.shape
    if h < 2 or w < 2:
        return Mesh.empty()
    valid = np.isfinite(depth)
    corner_slices = ((slice(0, -1), slice(0, -1)), (slice(0, -1), slice(1, None)),
                     (slice(1, None), slice(0, -1)), (slice(1, None), slice(1, None)))
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
    index = np.full((h, w), -1, dtype=np.int64)
    index[valid] = np.arange(int(valid.sum()))
    corner_index = np.stack([index[s] for s in corner_slices]).reshape(4, -1)
    faces = []
    for tri, keep in zip(_TRIANGLES, emit):
        for k in range(3):
            i, j = sorted((tri[k], tri[(k + 1) % 3]))
            keep = keep & ~jump[i, j]
        blocks = np.flatnonzero(keep)
        faces.append(corner_index[tri][:, blocks].T)
    faces = np.concatenate(faces)
    # Keep only vertices some face uses.
    used = np.zeros(int(valid.sum()), dtype=bool)
    used[faces.ravel()] = True
    renumber = np.cumsum(used) - 1
    vertices = np.asarray(points, dtype=np.float64).reshape(h, w, 3)[valid][used]
    return Mesh(vertices, renumber[faces])


def perspective_mesh(depth: np.ndarray, K: np.ndarray, cam_to_world: np.ndarray, a: float = 7.0) -> Mesh:
    """Mesh of one planar depth map of a pinhole camera.

    depth        : (H, W) float  planar depth, metres; NaN = no surface
    K            : (3, 3) float  intrinsics, pixel centres at integer + 0.5
    cam_to_world : (4, 4) float  OpenCV axes
    """
    depth = np.asarray(depth, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    pose = np.asarray(cam_to_world, dtype=np.float64)
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T  # z = 1
    points = (rays * depth[..., None]) @ pose[:3, :3].T + pose[:3, 3]
    return grid_mesh(points, depth, depth / K[0, 0], a)


def orthographic_mesh(
    depth: np.ndarray, cam_to_world: np.ndarray, half_extent: float, a: float = 7.0
) -> Mesh:
    """Mesh of one depth map of a square orthographic camera (the overhead camera).

    depth        : (R, R) float  distance along the camera's z axis, metres; NaN = none
    cam_to_world : (4, 4) float  OpenCV axes (z = viewing direction)
    half_extent  : float         half the side of the square the camera sees, metres
    """
    depth = np.asarray(depth, dtype=np.float64)
    pose = np.asarray(cam_to_world, dtype=np.float64)
    res = depth.shape[0]
    if depth.shape != (res, res):
        raise ValueError(f"an overhead depth map is square, got {depth.shape}")
    c = ((np.arange(res) + 0.5) / res * 2.0 - 1.0) * half_extent
    y, x = np.meshgrid(c, c, indexing="ij")
    local = np.stack([x, y, depth], axis=-1)
    points = local @ pose[:3, :3].T + pose[:3, 3]
    return grid_mesh(points, depth, np.full(depth.shape, 2.0 * half_extent / res), a)


def height_map_mesh(
    height: np.ndarray, cam_to_world: np.ndarray, half_extent: float, camera_height: float,
    config: MeshingConfig | None = None,
) -> Mesh:
    """Mesh of an overhead height map: pixels more than ``min_height`` above the floor.

    height        : (R, R) float  height above the floor, metres; NaN = floor or nothing
    cam_to_world  : (4, 4) float  the overhead camera, looking straight down
    half_extent   : float         its orthographic half-extent, metres
    camera_height : float         its height above the floor (``tz`` of the overhead
                    parameters), so that depth below it = camera_height - height
    """
    config = config or MeshingConfig()
    height = np.asarray(height)
    if not np.issubdtype(height.dtype, np.floating):
        height = height.astype(np.float64)
    # compared in the map's own precision, so that a float32 5 cm is "at 5 cm"
    with np.errstate(invalid="ignore"):
        floor = ~(height > height.dtype.type(config.min_height))
    depth = np.where(floor, np.nan, camera_height - height.astype(np.float64))
    return orthographic_mesh(depth, cam_to_world, half_extent, config.a)
