"""Voxel IoU of layer intervals against the ground-truth object mesh (docs/spec.md §11.4, paper supplement).

The grid is fixed in the frontal camera's frame (OpenCV axes): ``resolution``³ voxels over
x, y in [-size/2, size/2] and z in [0, size] — the paper's 400³ voxels of 2.5 cm over a
10 m box in front of the camera. Occupancy arrays are (R, R, R) bool indexed
``[z, y, x]``; voxel ``k`` along an axis has its centre at ``lo + (k + 0.5) * size / R``.
Both occupancies are depth intervals along camera rays, voxelised by one function
(:func:`interval_occupancy`): a voxel is occupied when its centre lies strictly inside an
interval of the ray (pixel) it projects to.

- **Layers** (:func:`layer_occupancy`): the intervals (D1, D2) and (D3, D4) of every pixel.
- **Ground truth** (:func:`mesh_occupancy`): the inside of the object mesh, by parity along
  rays from the camera, each connected component on its own (:func:`mesh_intervals`), on
  rays dense enough to be at most ``ray_spacing`` voxels apart at the far end of the grid
  (a voxel takes the answer of its nearest ray, so only centres within about a third of a
  voxel of the surface can come out wrong). Per-component parity keeps the union right
  where closed parts interpenetrate (a cushion sunk into a sofa), which parity over the
  whole mesh gets wrong. Rays from the camera matter: the ground-truth mesh is clipped
  to the frustum (docs/spec.md §5.1) and its cuts are open; a ray from the camera never crosses the
  side planes, while parity along any other direction pairs crossings with missing cuts.
- **IoU** (:func:`voxel_iou`) counts the voxels whose centre projects into the image:
  outside the frustum nothing is predicted and the ground-truth mesh is cut away.

The paper voxelised its ground truth with binvox (z-buffer carving and parity voting);
this is parity along camera rays, per component: an open component (a lamp shade) has
no inside and a crossing left unpaired fills nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..conventions import tol
from ..errors import MissingDependencyError
from .depth_mesh import Mesh

if TYPE_CHECKING:
    import matplotlib.figure


@dataclass(frozen=True)
class VoxelConfig:
    """The voxel grid in front of the camera and how the ground truth is traced."""

    #: voxels along each axis
    resolution: int = 400
    #: side of the cube, metres: x, y in [-size/2, size/2], z in [0, size], camera frame
    size: float = 10.0
    #: ground-truth rays are at most this many voxels apart at the far end of the grid
    ray_spacing: float = 0.5

    def __post_init__(self):
        if self.resolution < 1:
            raise ValueError(f"resolution must be >= 1, got {self.resolution}")
        if not self.size > 0:
            raise ValueError(f"size must be > 0 m, got {self.size}")
        if not self.ray_spacing > 0:
            raise ValueError(f"ray_spacing must be > 0 voxels, got {self.ray_spacing}")

    @property
    def voxel(self) -> float:
        """Voxel side, metres."""
        return self.size / self.resolution

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Voxel centre coordinates (R,) float64 along x (= along y) and along z."""
        k = (np.arange(self.resolution) + 0.5) * self.voxel
        return k - 0.5 * self.size, k

    def supersampling(self, K: np.ndarray) -> int:
        """Rays per pixel side for the ground truth of a camera with intrinsics ``K``."""
        footprint = self.size / min(K[0, 0], K[1, 1])  # one pixel at the far end, metres
        return max(1, math.ceil(footprint / (self.ray_spacing * self.voxel)))


def _check_K(K) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or K[0, 1] != 0 or K[1, 0] != 0 or not np.array_equal(K[2], [0, 0, 1]):
        raise ValueError(f"voxel IoU needs an unskewed pinhole K (no skew, last row 0 0 1), got {K.tolist()}")
    return K


def _slice_pixels(
    K: np.ndarray, shape: tuple[int, int], config: VoxelConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Image row of every voxel row and image column of every voxel column, per z-slice.

    Every voxel of a slice has the same planar depth, and with an unskewed ``K`` its column
    depends only on its x and its row only on its y: a slice needs 2R projections, not R².
    Returns rows (R, R) and cols (R, R) int64 indexed [slice, voxel row/column], -1 where
    it falls outside the (H, W) image.
    """
    xy, zs = config.centres()
    col = np.floor(K[0, 0] * xy / zs[:, None] + K[0, 2])
    row = np.floor(K[1, 1] * xy / zs[:, None] + K[1, 2])
    h, w = shape
    return (np.where((row >= 0) & (row < h), row, -1).astype(np.int64),
            np.where((col >= 0) & (col < w), col, -1).astype(np.int64))


def frustum_mask(K: np.ndarray, shape: tuple[int, int], config: VoxelConfig | None = None) -> np.ndarray:
    """(R, R, R) bool ``[z, y, x]``: the voxel centre projects into the (H, W) image of ``K``."""
    config = config or VoxelConfig()
    rows, cols = _slice_pixels(_check_K(K), shape, config)
    return (rows >= 0)[:, :, None] & (cols >= 0)[:, None, :]


def interval_occupancy(
    pixel: np.ndarray, near: np.ndarray, far: np.ndarray, K: np.ndarray, shape: tuple[int, int],
    config: VoxelConfig | None = None,
) -> np.ndarray:
    """Voxels whose centre lies strictly inside a depth interval of the pixel it projects to.

    pixel     : (k,) int  flat index (row * W + column) of each interval's pixel
    near, far : (k,) float  planar depth interval, metres
    K, shape  : (3, 3) unskewed intrinsics and (H, W) of the image the pixels belong to
    Returns (R, R, R) bool ``[z, y, x]``.

    Slices are swept near to far keeping a count of the open intervals of every pixel, so
    each interval is touched twice and each slice costs one pass over the pixels.
    """
    config = config or VoxelConfig()
    rows, cols = _slice_pixels(_check_K(K), shape, config)
    zs = config.centres()[1]
    r, (h, w) = config.resolution, shape
    out = np.zeros((r, r, r), dtype=bool)
    pixel = np.asarray(pixel, dtype=np.int64)
    first = np.searchsorted(zs, near, side="right")   # first slice deeper than near
    stop = np.searchsorted(zs, far, side="left")      # first slice at or beyond far
    span = stop > first
    pixel, first, stop = pixel[span], first[span], stop[span]
    if not len(pixel):
        return out
    opening = np.argsort(first, kind="stable")
    closing = np.argsort(stop, kind="stable")
    open_at = np.searchsorted(first[opening], np.arange(r + 1))
    close_at = np.searchsorted(stop[closing], np.arange(r + 1))
    count = np.zeros(h * w, dtype=np.int32)
    # one row and column of padding that is never inside: where the voxel misses the image
    inside = np.zeros((h + 1, w + 1), dtype=bool)
    for k in range(int(first.min()), int(stop.max())):
        np.add.at(count, pixel[opening[open_at[k]:open_at[k + 1]]], 1)
        np.subtract.at(count, pixel[closing[close_at[k]:close_at[k + 1]]], 1)
        np.greater(count.reshape(h, w), 0, out=inside[:h, :w])
        out[k] = inside[np.ix_(rows[k], cols[k])]
    return out


def layer_occupancy(depth: np.ndarray, K: np.ndarray, config: VoxelConfig | None = None) -> np.ndarray:
    """Voxels inside the layer intervals (D1, D2) or (D3, D4) (paper supplement).

    depth : (4 or 5, H, W) float  planar D1..D4(, D5), metres, NaN = none
    K     : (3, 3) float          unskewed intrinsics of the camera the grid is in front of
    Returns (R, R, R) bool ``[z, y, x]``.
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 3 or depth.shape[0] < 4:
        raise ValueError(f"depth must be (>= 4, H, W), got {depth.shape}")
    near = np.concatenate([depth[0].ravel(), depth[2].ravel()])
    far = np.concatenate([depth[1].ravel(), depth[3].ravel()])
    pixel = np.tile(np.arange(depth[0].size), 2)
    finite = np.isfinite(near) & np.isfinite(far)
    return interval_occupancy(pixel[finite], near[finite], far[finite], K, depth.shape[1:], config)


def _vertex_components(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(n,) int64 connected component of each vertex (vertices of a face are connected), by
    vectorised union-find: hook every edge's larger root onto its smaller, then shorten
    paths, until no edge joins two roots."""
    parent = np.arange(n_vertices)
    a = np.concatenate([faces[:, 0], faces[:, 1]])
    b = np.concatenate([faces[:, 1], faces[:, 2]])
    while True:
        ra, rb = parent[a], parent[b]
        differ = ra != rb
        if not differ.any():
            return parent
        np.minimum.at(parent, np.maximum(ra, rb)[differ], np.minimum(ra, rb)[differ])
        while True:
            grand = parent[parent]
            if np.array_equal(grand, parent):
                break
            parent = grand


def _component_scene(o3d, vertices: np.ndarray, faces: np.ndarray):
    """An Open3D scene with one geometry per connected component of the mesh.

    Required, not a convenience: Open3D drops a hit whose geometry and distance equal the
    previous hit's, so two components of one geometry touching where a ray leaves one and
    meets the other would lose a crossing and break the parity of the rest of the ray.
    Returns the scene and, per geometry id, the index of its first face in ``order``, the
    permutation of ``faces`` that groups them by component.
    """
    label = _vertex_components(faces, len(vertices))
    vertex_order = np.argsort(label, kind="stable")
    renumber = np.empty(len(vertices), dtype=np.int64)
    renumber[vertex_order] = np.arange(len(vertices))
    roots, vertex_start, vertex_count = np.unique(label[vertex_order], return_index=True, return_counts=True)
    face_label = label[faces[:, 0]]
    order = np.argsort(face_label, kind="stable")
    labels, face_start = np.unique(face_label[order], return_index=True)
    face_start = np.r_[face_start, len(faces)]
    block = np.searchsorted(roots, labels)
    grouped = renumber[faces[order]]
    scene = o3d.t.geometry.RaycastingScene()
    for k, b in enumerate(block):
        v0, v1 = vertex_start[b], vertex_start[b] + vertex_count[b]
        f = grouped[face_start[k]:face_start[k + 1]] - v0
        scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(vertices[vertex_order[v0:v1]], dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(f, dtype=np.uint32)),
        )
    return scene, order, face_start[:-1]


def mesh_intervals(mesh: Mesh, K: np.ndarray, cam_to_world: np.ndarray, shape: tuple[int, int],
                   supersampling: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth intervals inside the solid of ``mesh`` along the rays of a camera.

    Rays start at the camera centre and pass through the centres of an image of
    ``shape`` (H, W) pixels, each pixel split into ``supersampling``² rays. Per ray and per
    connected component of the mesh, the crossings are paired near to far (entry, exit,
    ...); crossings of one side of a component within ``tol.same_instance_hit`` of each
    other are one (a ray through an edge shared by two faces), and an unpaired last
    crossing (an open surface) starts nothing.

    Returns ray (k,) int64 flat index into the (H·s, W·s) ray image, near (k,) and far (k,)
    float64 planar depths.
    """
    empty = np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
    if not len(mesh):
        return empty
    try:
        import open3d as o3d
    except ImportError:
        raise MissingDependencyError("open3d", "voxel IoU", "pip install 'sceneforge[trace]'") from None
    pose = np.asarray(cam_to_world, dtype=np.float64)
    v = (mesh.vertices - pose[:3, 3]) @ pose[:3, :3]
    s = int(supersampling)
    h, w = shape[0] * s, shape[1] * s
    Ks = np.diag([s, s, 1.0]) @ np.asarray(K, dtype=np.float64)
    # only the rays through the image box of the vertices in front of the camera
    used = np.unique(mesh.faces)
    front = v[used][v[used, 2] > 0]
    if not len(front):
        return empty
    uv = front[:, :2] / front[:, 2:] @ Ks[:2, :2].T + Ks[:2, 2]
    c0, r0 = np.clip(np.floor(uv.min(axis=0)).astype(int), 0, [w, h])
    c1, r1 = np.clip(np.floor(uv.max(axis=0)).astype(int) + 1, 0, [w, h])
    rr, cc = np.meshgrid(np.arange(r0, r1), np.arange(c0, c1), indexing="ij")
    ray_pixel = (rr * w + cc).ravel()
    # camera-frame directions with z = 1, so that Open3D's ray parameter is planar depth
    directions = np.column_stack([cc.ravel() + 0.5, rr.ravel() + 0.5, np.ones(cc.size)]) @ np.linalg.inv(Ks).T
    rays = np.zeros((len(directions), 6), dtype=np.float32)
    rays[:, 3:] = directions
    scene, face_order, first_face = _component_scene(o3d, v, mesh.faces)
    hits = scene.list_intersections(o3d.core.Tensor(rays))
    ray = hits["ray_ids"].numpy().astype(np.int64)
    depth = hits["t_hit"].numpy().astype(np.float64)
    comp = hits["geometry_ids"].numpy().astype(np.int64)
    face = face_order[first_face[comp] + hits["primitive_ids"].numpy().astype(np.int64)]
    tri = v[mesh.faces[face]]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    facing = np.einsum("ij,ij->i", normal, directions[ray]) < 0

    order = np.lexsort((depth, comp, ray))
    ray, comp, depth, facing = ray[order], comp[order], depth[order], facing[order]
    group_start = np.r_[True, (ray[1:] != ray[:-1]) | (comp[1:] != comp[:-1])]
    repeat = ~group_start & np.r_[False, (depth[1:] - depth[:-1] <= tol.same_instance_hit)
                                  & (facing[1:] == facing[:-1])]
    ray, depth, group_start = ray[~repeat], depth[~repeat], group_start[~repeat]
    group = np.cumsum(group_start) - 1
    rank = np.arange(len(depth)) - np.flatnonzero(group_start)[group]
    entry = np.flatnonzero((rank[:-1] % 2 == 0) & (group[1:] == group[:-1]))
    return ray_pixel[ray[entry]], depth[entry], depth[entry + 1]


def mesh_occupancy(mesh: Mesh, K: np.ndarray, cam_to_world: np.ndarray, shape: tuple[int, int],
                   config: VoxelConfig | None = None) -> np.ndarray:
    """Solid occupancy of a world-space mesh in the voxel grid of a camera.

    The mesh is traced with :func:`mesh_intervals` on rays ``config.supersampling(K)``
    times denser than the (H, W) image, and each voxel takes the answer of the ray nearest
    to it. Rays start at the camera and never cross the frustum's side planes, so a mesh
    clipped to the frustum (docs/spec.md §5.1) gives the same intervals as the whole house there.
    Returns (R, R, R) bool ``[z, y, x]``.
    """
    config = config or VoxelConfig()
    K = _check_K(K)
    s = config.supersampling(K)
    ray, near, far = mesh_intervals(mesh, K, cam_to_world, shape, s)
    return interval_occupancy(ray, near, far, np.diag([s, s, 1.0]) @ K, (shape[0] * s, shape[1] * s), config)


@dataclass(frozen=True)
class VoxelScore:
    """Voxel counts of one view inside the frustum and their IoU (NaN when both are empty)."""

    intersection: int
    union: int
    predicted: int
    truth: int

    @property
    def iou(self) -> float:
        return self.intersection / self.union if self.union else float("nan")


def voxel_iou(predicted: np.ndarray, truth: np.ndarray, frustum: np.ndarray) -> VoxelScore:
    """IoU of two (R, R, R) bool occupancies over the voxels where ``frustum`` is True."""
    p, t = predicted & frustum, truth & frustum
    return VoxelScore(int(np.count_nonzero(p & t)), int(np.count_nonzero(p | t)),
                      int(np.count_nonzero(p)), int(np.count_nonzero(t)))


def score_voxels(depth: np.ndarray, K: np.ndarray, cam_to_world: np.ndarray, objects: Mesh,
                 config: VoxelConfig | None = None) -> VoxelScore:
    """Voxel IoU of one view: layer intervals of ``depth`` (4 or 5, H, W) against the solid
    ground-truth ``objects`` mesh (world), in the grid of the camera (K, cam_to_world)."""
    config = config or VoxelConfig()
    shape = np.shape(depth)[1:]
    return voxel_iou(layer_occupancy(depth, K, config),
                     mesh_occupancy(objects, K, cam_to_world, shape, config),
                     frustum_mask(K, shape, config))


def plot_iou_histogram(ious, title: str = "") -> "matplotlib.figure.Figure":
    """Histogram of per-view voxel IoU (views with an undefined IoU left out). Needs matplotlib."""
    try:
        from matplotlib.figure import Figure
    except ImportError as e:
        raise MissingDependencyError("matplotlib", "plotting", "pip install 'sceneforge[plot]'") from e
    values = np.asarray(ious, dtype=np.float64)
    values = values[np.isfinite(values)]
    fig = Figure(figsize=(6, 4), layout="constrained")
    ax = fig.add_subplot()
    ax.hist(values, bins=np.linspace(0, 1, 21), color="tab:blue", edgecolor="white")
    if len(values):
        ax.axvline(values.mean(), color="k", ls="--", label=f"mean {values.mean():.3f}")
        ax.legend()
    ax.set_xlabel("voxel IoU (objects)")
    ax.set_ylabel("views")
    ax.set_xlim(0, 1)
    ax.set_title(title or f"{len(values)} views")
    return fig
