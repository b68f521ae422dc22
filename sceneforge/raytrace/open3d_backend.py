"""The fast engine: Embree through Open3D's ``RaycastingScene`` (float32).

``list_intersections`` reports every crossing of a ray in one traversal (its output is
grouped by ray but not sorted, and a ray through a shared edge may report both faces;
the shared hit collection in :mod:`sceneforge.raytrace` handles both).

Open3D's hit filter skips a hit whose geometry id equals the previous hit's and whose
float32 distance equals it too. With the whole house as one mesh, a bookshelf's back
touching the wall it stands against would lose the wall hit (seen on 23 % of the pixels
of a toy-house view); with one geometry per instance, a ray through an edge two triangles
of one instance share, or through two coincident triangles, would keep only the one the
traversal meets first, and which one that is differs between Embree builds and CPUs. So
each instance is split into as few geometries as keep every two of its triangles that
could ever be crossed at the same distance apart (:func:`tie_free_groups`): the list then
holds every crossing, and the hits depend only on which triangles a ray crosses. First
hits come from the same list: of the crossings within ``tol.tie_window`` of the nearest,
the one of smallest float64 plane distance, exact ties by the lower instance, then the
lower triangle (what the extension's ``nearest_face`` picks).

A query may be restricted to a subset of the instances (the envelope, the objects, the
floors and objects an overhead view sees): each subset gets its own scenes, built on first
use and kept, with envelope and objects always in separate scenes.

Coordinates are shifted to the centre of the house before the float32 conversion, so that
rounding is at the scale of the house, not of its distance from the origin.
"""

from __future__ import annotations

import heapq

import numpy as np

from ..conventions import tol
from ..errors import MissingDependencyError
from . import T_MAX_MARGIN, HouseTriangles, Rays, nearest_candidates


def tie_free_groups(lo: np.ndarray, hi: np.ndarray, pad: float) -> np.ndarray:
    """(m,) int64 a group number per triangle such that two triangles of one group have
    bounding boxes, grown by ``pad``, that are apart along one axis (the same for all):
    they can never be crossed at the same distance. Few groups: along the axis where the
    fewest grown boxes overlap, greedy colouring in order of the boxes' low ends (optimal
    for intervals: as many groups as boxes overlap at one point).

    lo, hi : (m, 3) float64  each triangle's bounding box
    """
    m = len(lo)
    if m == 0:
        return np.zeros(0, dtype=np.int64)
    lo, hi = lo - pad, hi + pad

    def overlap(axis):  # the most grown boxes over one point along ``axis``
        ends = np.r_[lo[:, axis], hi[:, axis]]
        step = np.r_[np.ones(m, np.int64), -np.ones(m, np.int64)]
        order = np.lexsort((-step, ends))  # at equal coordinates a box opens before one closes
        return int(np.cumsum(step[order]).max())

    axis = min(range(3), key=overlap)
    start, end = lo[:, axis].tolist(), hi[:, axis].tolist()
    group = np.empty(m, dtype=np.int64)
    open_boxes: list[tuple[float, int]] = []  # (end, group) of the boxes not yet closed
    free: list[int] = []
    n_groups = 0
    for f in np.argsort(lo[:, axis], kind="stable").tolist():
        while open_boxes and open_boxes[0][0] < start[f]:  # touching boxes overlap
            heapq.heappush(free, heapq.heappop(open_boxes)[1])
        if free:
            g = heapq.heappop(free)
        else:
            g, n_groups = n_groups, n_groups + 1
        group[f] = g
        heapq.heappush(open_boxes, (end[f], g))
    return group


class Open3DBackend:
    name = "open3d"

    def __init__(self, triangles: HouseTriangles, threads: int = 0):
        try:
            import open3d as o3d
        except ImportError:
            raise MissingDependencyError(
                "open3d", "fast ray tracing", "pip install 'sceneforge[trace]'"
            ) from None
        self._o3d = o3d
        self._threads = int(threads)  # Open3D's nthreads: 0 = every core
        self._triangles = triangles
        self._shift = 0.5 * (triangles.vertices.min(axis=0) + triangles.vertices.max(axis=0))
        self._groups: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # instance -> tie_free_groups
        # subset mask bytes -> [(scene, house face of each (geometry, primitive): see _scene)]
        self._scenes: dict[bytes, list[tuple[object, tuple[np.ndarray, np.ndarray]]]] = {}
        for flag in (False, True):
            self._selected(triangles.envelope == flag)

    def _scene(self, members: np.ndarray):
        """One Open3D scene holding the triangles of ``members`` (instance indices), each
        instance as its :func:`tie_free_groups` geometries, and its face map ``(first,
        faces)``: geometry ``g``'s primitive ``p`` is ``HouseTriangles.faces`` row
        ``faces[first[g] + p]``."""
        o3d, tri = self._o3d, self._triangles
        scene = o3d.t.geometry.RaycastingScene()
        first, faces = [0], []
        for i in members:
            for group in self._instance_groups(int(i)):
                # each triangle its own three corners: Embree reads only the coordinates
                corners = tri.vertices[tri.faces[group]].reshape(-1, 3) - self._shift
                scene.add_triangles(
                    o3d.core.Tensor(np.ascontiguousarray(corners, dtype=np.float32)),
                    o3d.core.Tensor(np.arange(len(corners), dtype=np.uint32).reshape(-1, 3)),
                )
                faces.append(group)
                first.append(first[-1] + len(group))
        return scene, (np.array(first[:-1], dtype=np.int64), np.concatenate(faces))

    def _instance_groups(self, i: int) -> list[np.ndarray]:
        """Instance ``i``'s faces (indices into ``HouseTriangles.faces``) split by
        :func:`tie_free_groups`, made once."""
        if i not in self._groups:
            tri = self._triangles
            faces = np.arange(tri.first_face[i], tri.first_face[i + 1])
            corners = tri.vertices[tri.faces[faces]]
            colour = tie_free_groups(corners.min(axis=1), corners.max(axis=1), tol.tie_box_pad)
            order = np.argsort(colour, kind="stable")
            self._groups[i] = np.split(faces[order], np.flatnonzero(np.diff(colour[order])) + 1)
        return self._groups[i]

    def _selected(self, instances: np.ndarray | None):
        """The (scene, face map) pairs a query on the ``instances`` (n,) bool mask (None =
        all) runs on, objects before envelope (see :meth:`_scene`)."""
        if instances is None:
            return self._selected(~self._triangles.envelope) + self._selected(self._triangles.envelope)
        key = np.asarray(instances, dtype=bool).tobytes()
        if key not in self._scenes:
            self._scenes[key] = [
                self._scene(members)
                for flag in (False, True)
                if len(members := np.flatnonzero(instances & (self._triangles.envelope == flag)))
            ]
        return self._scenes[key]

    def _query(self, rays: Rays):
        """The rays as Open3D's (n, 6) float32 tensor, made once per batch (sharing the
        memory of a numpy array kept beside it)."""
        if "open3d" not in rays.cache:
            query = np.empty((len(rays), 6), dtype=np.float32)
            shared = rays.origins.strides[0] == 0
            query[:, :3] = (rays.origins[:1] if shared else rays.origins) - self._shift  # row broadcasts
            query[:, 3:] = rays.directions
            rays.cache["open3d"] = (query, self._o3d.core.Tensor.from_numpy(query))
        return rays.cache["open3d"][1]

    def _crossings(self, rays: Rays, instances: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every crossing of every ray: (k,) int64 rays, (k,) int64 faces, (k,) float32
        Open3D distances, scene by scene."""
        ray_ids, faces, t32 = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)], [np.zeros(0, np.float32)]
        if len(rays):
            for scene, (first, members) in self._selected(instances):
                found = scene.list_intersections(self._query(rays), nthreads=self._threads)
                ray_ids.append(found["ray_ids"].numpy().astype(np.int64))
                faces.append(members[first[found["geometry_ids"].numpy()] + found["primitive_ids"].numpy()])
                t32.append(found["t_hit"].numpy())
        if len(faces) == 2:
            return ray_ids[1], faces[1], t32[1]
        return np.concatenate(ray_ids), np.concatenate(faces), np.concatenate(t32)

    def intersect_all(
        self, rays: Rays, instances: np.ndarray | None = None, t_max: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        ray, face, t32 = self._crossings(rays, instances)
        if t_max is not None:
            # Open3D's float32 distances are within far less than the margin of the exact
            # ones: what is dropped here the caller would drop anyway
            near = t32 <= t_max[ray] + T_MAX_MARGIN
            ray, face = ray[near], face[near]
        return ray, face

    def intersect_first(self, rays: Rays, instances: np.ndarray | None = None) -> np.ndarray:
        ray, face, t32 = self._crossings(rays, instances)
        return nearest_candidates(self._triangles, rays, ray, face, t32)

    def closest_distance(self, points: np.ndarray) -> np.ndarray:
        out = np.full(len(points), np.inf)
        if len(points):
            query = self._o3d.core.Tensor(np.ascontiguousarray(points - self._shift, dtype=np.float32))
            for scene, _ in self._selected(None):
                out = np.minimum(out, scene.compute_distance(query, nthreads=self._threads).numpy().astype(np.float64))
        return out
