"""The reference engine: Möller–Trumbore in float64 numpy, every ray against every triangle.

Slow and obviously correct; the tests check the fast engine against it hit for hit. The
only shortcut is conservative: faces are grouped into small leaves (consecutive faces of
one instance, sorted along its longest extent) and a ray is tested against the faces of
a leaf only when it crosses the leaf's padded bounding box.
"""

from __future__ import annotations

import numpy as np

from ..conventions import tol
from . import HouseTriangles, Rays, nearest_candidates


def moller_trumbore(origins, directions, v0, v1, v2) -> tuple[np.ndarray, np.ndarray]:
    """Ray/triangle intersection of k (ray, triangle) pairs, both sides of the triangle.

    origins, directions, v0, v1, v2 : (k, 3) float64
    Returns ``hit`` (k,) bool (distance >= 0, inside the triangle edges inclusive) and
    ``t`` (k,) float64 distance in units of the direction's length (meaningful where hit).
    """
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(directions, e2)
    det = np.einsum("ij,ij->i", e1, p)
    area2 = np.linalg.norm(np.cross(e1, e2), axis=1)
    ok = np.abs(det) > tol.ray_parallel * area2 * np.linalg.norm(directions, axis=1)
    inv = np.divide(1.0, det, out=np.zeros_like(det), where=ok)
    s = origins - v0
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = np.einsum("ij,ij->i", directions, q) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= -tol.ray_edge) & (v >= -tol.ray_edge) & (u + v <= 1 + tol.ray_edge) & (t >= 0)
    return hit, t


class ReferenceBackend:
    name = "reference"

    def __init__(self, triangles: HouseTriangles, leaf_size: int = 64, batch: int = 1 << 20):
        self._triangles = triangles
        self._corners = triangles.vertices[triangles.faces]
        self._face_instance = triangles.instance
        self._batch = batch
        order = []
        for i in range(triangles.n_instances):
            faces = np.arange(triangles.first_face[i], triangles.first_face[i + 1])
            centroid = self._corners[faces].mean(axis=1)
            axis = int(np.argmax(np.ptp(centroid, axis=0)))
            faces = faces[np.argsort(centroid[:, axis], kind="stable")]
            order.append(faces)
        self._faces = np.concatenate(order)
        # leaves never straddle two instances
        starts, total = [], 0
        for faces in order:
            starts += list(range(total, total + len(faces), leaf_size))
            total += len(faces)
        self._leaf_lo = np.array(starts, dtype=np.int64)
        self._leaf_hi = np.r_[self._leaf_lo[1:], total]
        c = self._corners[self._faces]
        lo = np.minimum.reduceat(c.min(axis=1), self._leaf_lo)
        hi = np.maximum.reduceat(c.max(axis=1), self._leaf_lo)
        self._box_lo, self._box_hi = lo - tol.leaf_pad, hi + tol.leaf_pad

    def _candidates(self, origins: np.ndarray, directions: np.ndarray):
        """(ray, face) pairs whose ray crosses the face's leaf box: two (p,) int64 arrays."""
        n_leaves = len(self._leaf_lo)
        rows = max(1, self._batch // (3 * n_leaves))
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / directions
        pairs = []
        for start in range(0, len(origins), rows):
            o = origins[start:start + rows, None, :]
            w = inv[start:start + rows, None, :]
            t1 = (self._box_lo[None] - o) * w
            t2 = (self._box_hi[None] - o) * w
            # fmin/fmax skip the NaN of a ray lying in a slab plane: conservative
            near = np.fmax.reduce(np.fmin(t1, t2), axis=2)
            far = np.fmin.reduce(np.fmax(t1, t2), axis=2)
            r, leaf = np.nonzero(far >= np.maximum(near, 0.0))
            sizes = self._leaf_hi[leaf] - self._leaf_lo[leaf]
            first = np.repeat(self._leaf_lo[leaf] - np.cumsum(sizes) + sizes, sizes)
            pairs.append((np.repeat(r + start, sizes), self._faces[first + np.arange(sizes.sum())]))
        if not pairs:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        return np.concatenate([p[0] for p in pairs]), np.concatenate([p[1] for p in pairs])

    def _crossings(self, origins: np.ndarray, directions: np.ndarray, instances: np.ndarray | None):
        """Every (ray, face, t) crossing: (k,) int64, (k,) int64, (k,) float64."""
        ray, face = self._candidates(origins, directions)
        if instances is not None:
            wanted = instances[self._face_instance[face]]
            ray, face = ray[wanted], face[wanted]
        out_r, out_f, out_t = [], [], []
        for s in range(0, len(ray), self._batch):
            r, f = ray[s:s + self._batch], face[s:s + self._batch]
            c = self._corners[f]
            hit, t = moller_trumbore(origins[r], directions[r], c[:, 0], c[:, 1], c[:, 2])
            out_r.append(r[hit])
            out_f.append(f[hit])
            out_t.append(t[hit])
        if not out_r:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
        return np.concatenate(out_r), np.concatenate(out_f), np.concatenate(out_t)

    def intersect_all(
        self, rays: Rays, instances: np.ndarray | None = None, t_max: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        # t_max is ignored: the reference reports every crossing and leaves the cut-off to
        # the caller, so that the fast engine's early cut is checked against it
        ray, face, _ = self._crossings(rays.origins, rays.directions, instances)
        return ray, face

    def intersect_first(self, rays: Rays, instances: np.ndarray | None = None) -> np.ndarray:
        ray, face, t = self._crossings(rays.origins, rays.directions, instances)
        # the fast engines' rule, with its float64 distances rounded as theirs are
        return nearest_candidates(self._triangles, rays, ray, face, t.astype(np.float32))

    def closest_distance(self, points: np.ndarray) -> np.ndarray:
        from trimesh.triangles import closest_point

        m = len(self._corners)
        out = np.empty(len(points))
        for i, p in enumerate(points):
            best = np.inf
            for s in range(0, m, self._batch // 4):
                c = self._corners[s:s + self._batch // 4]
                q = closest_point(c, np.broadcast_to(p, (len(c), 3)))
                best = min(best, float(np.linalg.norm(q - p, axis=1).min()))
            out[i] = best
        return out
