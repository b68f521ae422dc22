"""The fast engine: Embree through Open3D's ``RaycastingScene`` (float32).

``list_intersections`` reports every crossing of a ray in one traversal (its output is
grouped by ray but not sorted, and a ray through a shared edge may report both faces;
the shared hit collection in :mod:`sceneforge.raytrace` handles both).

Each instance is its own Open3D geometry. This is required, not a convenience: Open3D's
hit filter skips a hit whose geometry id equals the previous hit's and whose distance
equals it too. With the whole house as one mesh, a bookshelf's back touching the wall it
stands against would lose the wall hit (seen on 23 % of the pixels of a toy-house view).
A query may be restricted to a subset of the instances (the envelope, the objects, the
floors and objects an overhead view sees): each subset gets its own scenes, built on first
use and kept, with envelope and objects always in separate scenes.

Coordinates are shifted to the centre of the house before the float32 conversion, so that
rounding is at the scale of the house, not of its distance from the origin.
"""

from __future__ import annotations

import numpy as np

from ..errors import MissingDependencyError
from . import T_MAX_MARGIN, HouseTriangles, Rays

#: Open3D's id for "no hit" (uint32 max)
_INVALID_ID = np.iinfo(np.uint32).max


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
        self._first_face = triangles.first_face
        # subset mask bytes -> [(scene, instance index of each of its geometry ids)]
        self._scenes: dict[bytes, list[tuple[object, np.ndarray]]] = {}
        for flag in (False, True):
            self._selected(triangles.envelope == flag)

    def _scene(self, members: np.ndarray):
        """One Open3D scene holding ``members`` (instance indices), one geometry each."""
        o3d, tri = self._o3d, self._triangles
        fv, ff = tri.first_vertex, tri.first_face
        scene = o3d.t.geometry.RaycastingScene()
        for i in members:
            vertices = tri.vertices[fv[i]:fv[i + 1]] - self._shift
            faces = tri.faces[ff[i]:ff[i + 1]] - fv[i]
            scene.add_triangles(
                o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
                o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)),
            )
        return scene

    def _selected(self, instances: np.ndarray | None):
        """The (scene, base) pairs a query on the ``instances`` (n,) bool mask (None = all)
        runs on, objects before envelope; ``base[g]`` is the index in ``HouseTriangles.faces``
        of the first face of the scene's geometry ``g``."""
        if instances is None:
            return self._selected(~self._triangles.envelope) + self._selected(self._triangles.envelope)
        key = np.asarray(instances, dtype=bool).tobytes()
        if key not in self._scenes:
            self._scenes[key] = [
                (self._scene(members), self._first_face[members])
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

    def intersect_all(
        self, rays: Rays, instances: np.ndarray | None = None, t_max: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        ray_ids, faces = [], []
        if len(rays):
            for scene, base in self._selected(instances):
                found = scene.list_intersections(self._query(rays), nthreads=self._threads)
                ray = found["ray_ids"].numpy()
                geometry = found["geometry_ids"].numpy()
                primitive = found["primitive_ids"].numpy()
                if t_max is not None:
                    # Open3D's float32 distances are within far less than the margin of the
                    # exact ones: what is dropped here the caller would drop anyway
                    near = found["t_hit"].numpy() <= t_max[ray] + T_MAX_MARGIN
                    ray, geometry, primitive = ray[near], geometry[near], primitive[near]
                ray_ids.append(ray.astype(np.int64))
                faces.append(base[geometry] + primitive)
        if len(faces) == 1:
            return ray_ids[0], faces[0]
        return np.concatenate([np.zeros(0, np.int64)] + ray_ids), np.concatenate([np.zeros(0, np.int64)] + faces)

    def intersect_first(self, rays: Rays, instances: np.ndarray | None = None) -> np.ndarray:
        face = np.full(len(rays), -1, dtype=np.int64)
        if not len(rays):
            return face
        query = self._query(rays)
        nearest = np.full(len(rays), np.inf, dtype=np.float32)
        for scene, base in self._selected(instances):
            found = scene.cast_rays(query, nthreads=self._threads)
            t = found["t_hit"].numpy()
            geometry = found["geometry_ids"].numpy()
            # strict: at equal distances the object, queried first, stays
            better = (geometry != _INVALID_ID) & (t < nearest)
            primitive = found["primitive_ids"].numpy()[better]
            face[better] = base[geometry[better]] + primitive
            nearest[better] = t[better]
        return face

    def closest_distance(self, points: np.ndarray) -> np.ndarray:
        out = np.full(len(points), np.inf)
        if len(points):
            query = self._o3d.core.Tensor(np.ascontiguousarray(points - self._shift, dtype=np.float32))
            for scene, _ in self._selected(None):
                out = np.minimum(out, scene.compute_distance(query, nthreads=self._threads).numpy().astype(np.float64))
        return out
