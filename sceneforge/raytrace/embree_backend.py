"""The default engine: Embree through sceneforge's own extension, :mod:`._embree` (float32).

Open3D's ``list_intersections`` traverses every ray twice (a count pass to size its output,
then a list pass), takes no far limit, and leaves distances, sorting and the merging of
same-instance hits to numpy. The extension traverses each ray once, stops at the cut-off,
and does the rest in its filter callback and per-ray pass, multi-threaded, writing the
:class:`~sceneforge.raytrace.Hits` arrays directly (:meth:`EmbreeBackend.collect`).

Its hits are bit-identical to the Open3D engine's: it builds the same float32 triangles
(robust scenes, envelope and objects apart, coordinates shifted to the house centre before
the float32 conversion; one geometry per instance, where Open3D needs more, see
:mod:`.open3d_backend`), keeps every crossing, breaks first-hit ties by the rule of
:func:`~sceneforge.raytrace.nearest_candidates` and repeats the shared hit collection of
:mod:`sceneforge.raytrace` operation for operation (see the comment atop ``_embree.cpp``).

The extension is built at install time where a C++ compiler and Embree's headers are
present (``setup.py``); :data:`AVAILABLE` says whether it was.
"""

from __future__ import annotations

import os

import numpy as np

from ..conventions import tol
from ..errors import MissingDependencyError
from . import T_MAX_MARGIN, FirstHit, FrontalHits, Hits, HouseTriangles, NearestHits, NearestSurfaces, Rays

try:
    from . import _embree
except ImportError:  # not built (no compiler or no Embree headers at install time)
    _embree = None

#: whether the compiled extension is importable (the default engine then)
AVAILABLE = _embree is not None
#: room for same-instance repeats in :meth:`EmbreeBackend.nearest`'s per-ray list beyond the
#: k hits asked for: a ray whose repeats use it up is traced again with a longer list
NEAREST_SPARE = 4


def every_core() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


class EmbreeBackend:
    name = "embree"

    def __init__(self, triangles: HouseTriangles, threads: int = 0, packet: int = 0):
        """``packet``: rays per first-hit packet (16, 8, 4; 1 traces ray by ray); 0, the
        widest the CPU runs natively. The results do not depend on it."""
        if _embree is None:
            raise MissingDependencyError(
                "sceneforge's Embree extension", "the embree ray-tracing engine",
                "apt-get install libembree-dev g++, then pip install -e . again (see docs/install.md)")
        self._triangles = triangles
        shift = 0.5 * (triangles.vertices.min(axis=0) + triangles.vertices.max(axis=0))
        self._engine = _embree.Engine(
            int(threads) or every_core(),
            np.ascontiguousarray(triangles.vertices, dtype=np.float64),
            np.ascontiguousarray(triangles.faces, dtype=np.int64),
            np.ascontiguousarray(triangles.instance, dtype=np.int32),
            np.ascontiguousarray(triangles.first_face, dtype=np.int64),
            np.ascontiguousarray(triangles.normal_xyz, dtype=np.float64),
            np.ascontiguousarray(triangles.offset, dtype=np.float64),
            np.ascontiguousarray(shift, dtype=np.float64),
            int(packet),
        )
        #: rays per first-hit packet (1: ray by ray)
        self.packet = self._engine.packet
        # subset mask bytes -> scene ids, objects before envelope (as the Open3D engine)
        self._scenes: dict[bytes, tuple[int, ...]] = {}
        for flag in (False, True):
            self._selected(triangles.envelope == flag)

    def _selected(self, instances: np.ndarray | None) -> tuple[int, ...]:
        """The scenes a query on the ``instances`` (n,) bool mask (None = all) runs on."""
        if instances is None:
            return self._selected(~self._triangles.envelope) + self._selected(self._triangles.envelope)
        instances = np.asarray(instances, dtype=bool)
        key = instances.tobytes()
        if key not in self._scenes:
            envelope = self._triangles.envelope
            self._scenes[key] = tuple(
                self._engine.add_scene(members, self._triangles.first_vertex)
                for flag in (False, True)
                if len(members := np.flatnonzero(instances & (envelope == flag)).astype(np.int64))
            )
        return self._scenes[key]

    @staticmethod
    def _rows(rays: Rays) -> tuple[np.ndarray, np.ndarray]:
        """Origins and directions as the extension reads them: (1, 3) where shared, else (n, 3)."""
        def rows(a):
            return np.ascontiguousarray(a[:1] if len(a) and a.strides[0] == 0 else a)

        return rows(rays.origins), rows(rays.directions)

    def collect(self, rays: Rays, instances: np.ndarray | None = None, cutoff: np.ndarray | None = None) -> Hits:
        """:class:`~sceneforge.raytrace.Hits` of the rays among ``instances`` (None: all),
        up to ``cutoff`` (n,) float64 along each ray (None: no limit): what
        ``_collect_hits`` makes of :meth:`intersect_all`, in one traversal per ray."""
        n = len(rays)
        if not n:
            return _empty_hits(0)
        o, d = self._rows(rays)
        c = None if cutoff is None else np.ascontiguousarray(cutoff, dtype=np.float64)
        offsets, t, instance, triangle, front = self._engine.collect(
            self._selected(instances), n, o, d, c, T_MAX_MARGIN, tol.same_instance_hit, False)
        return _hits_of(offsets, t, instance, triangle, front)

    def frontal(self, rays: Rays, objects: np.ndarray, envelope: np.ndarray, envelope_near: float) -> FrontalHits:
        """:meth:`HouseTracer.frontal_query <sceneforge.raytrace.HouseTracer.frontal_query>`
        in one call: each ray's closing hit (first-hit pass) and then its object hits up
        to that hit + ``tol.envelope_slack``, ray by ray, bit for bit what the tracer makes
        of :meth:`intersect_first` and :meth:`collect`."""
        n = len(rays)
        if not n:
            empty = FirstHit(np.zeros(0), np.zeros(0, np.int32), np.zeros(0, np.int64), np.zeros(0, bool),
                             np.zeros(0, np.int64), self._triangles.normal)
            return FrontalHits(_empty_hits(0), empty)
        o, d = self._rows(rays)
        out = self._engine.collect(self._selected(objects), n, o, d, None, T_MAX_MARGIN, tol.same_instance_hit,
                                   False, self._selected(envelope), float(envelope_near), tol.envelope_slack)
        offsets, t, instance, triangle, front, c_face, c_t, c_instance, c_triangle, c_front = out
        hits = _hits_of(offsets, t, instance, triangle, front)
        return FrontalHits(hits, self._first_hits(c_face, c_t, c_instance, c_triangle, c_front))

    def first_hit(self, rays: Rays, instances: np.ndarray | None = None) -> FirstHit:
        """:meth:`HouseTracer.first_hit <sceneforge.raytrace.HouseTracer.first_hit>` in one
        call: the nearest faces and their float64 plane distances, bit for bit what the
        tracer makes of :meth:`intersect_first`."""
        n = len(rays)
        if not n:
            return FirstHit(np.zeros(0), np.zeros(0, np.int32), np.zeros(0, np.int64), np.zeros(0, bool),
                            np.zeros(0, np.int64), self._triangles.normal)
        o, d = self._rows(rays)
        return self._first_hits(*self._engine.closing(self._selected(instances), n, o, d, 0.0))

    def nearest(self, rays: Rays, k: int) -> NearestHits:
        """:meth:`HouseTracer.nearest_hits <sceneforge.raytrace.HouseTracer.nearest_hits>` in
        one traversal per ray and scene that keeps the ray's nearest hits and stops where no
        farther one can be among them (see ``engine_nearest`` in ``_embree.cpp``), bit for bit
        what the tracer makes of :meth:`intersect_all`."""
        n = len(rays)
        out = NearestHits(np.empty((k, n)), np.empty((k, n), dtype=np.int64), np.empty((k, n), dtype=bool))
        if n:
            o, d = self._rows(rays)
            self._engine.nearest(self._selected(None), n, o, d, k, NEAREST_SPARE, T_MAX_MARGIN, tol.same_instance_hit,
                                 out.t, out.face, out.front_facing)
        return out

    def nearest_surfaces(self, rays: Rays, k: int, depth_scale: np.ndarray, rotation: np.ndarray,
                         labels: np.ndarray) -> NearestSurfaces:
        """:meth:`HouseTracer.nearest_surfaces <sceneforge.raytrace.HouseTracer.nearest_surfaces>`:
        :meth:`nearest`'s traversal, each ray's hits written as the view's layers as soon as
        the ray is done (no hit arrays in between), bit for bit what the tracer makes of
        :meth:`nearest`."""
        n = len(rays)
        out = NearestSurfaces(np.empty((k, n), dtype=np.float32), np.empty((k, 3, n), dtype=np.float32),
                              np.empty((k, n), dtype=np.int32), np.empty((k, n), dtype=np.uint8),
                              np.empty((k, n), dtype=bool))
        if n:
            o, d = self._rows(rays)
            # a broadcast scale (an orthographic view: all 1) is passed as its one value
            scale = depth_scale[:1] if depth_scale.strides[0] == 0 else np.ascontiguousarray(depth_scale)
            self._engine.nearest_surfaces(self._selected(None), n, o, d, k, NEAREST_SPARE, T_MAX_MARGIN,
                                          tol.same_instance_hit, scale, rotation, labels, out.depth, out.normal,
                                          out.instance, out.label, out.front_facing)
        return out

    def frontal_nearest(self, rays: Rays, objects: np.ndarray, envelope: np.ndarray, k: int, depth_scale: np.ndarray,
                        rotation: np.ndarray, labels: np.ndarray) -> tuple[FrontalHits, NearestSurfaces]:
        """:meth:`frontal` and :meth:`nearest_surfaces` from one traversal per ray: each ray's
        object hits up to its closing hit are taken from the nearest hits the K-nearest
        traversal keeps (traced again as :meth:`frontal` traces them only where more surfaces
        lie before the closing hit than that list holds), bit for bit the same arrays as the
        two queries give."""
        n = len(rays)
        surfaces = NearestSurfaces(np.empty((k, n), dtype=np.float32), np.empty((k, 3, n), dtype=np.float32),
                                   np.empty((k, n), dtype=np.int32), np.empty((k, n), dtype=np.uint8),
                                   np.empty((k, n), dtype=bool))
        if not n:
            return self.frontal(rays, objects, envelope, 0.0), surfaces
        o, d = self._rows(rays)
        scale = depth_scale[:1] if depth_scale.strides[0] == 0 else np.ascontiguousarray(depth_scale)
        out = self._engine.frontal_nearest(
            self._selected(objects), self._selected(envelope), np.ascontiguousarray(objects, dtype=bool), n, o, d,
            T_MAX_MARGIN, tol.same_instance_hit, tol.envelope_slack, k, NEAREST_SPARE, scale, rotation, labels,
            surfaces.depth, surfaces.normal, surfaces.instance, surfaces.label, surfaces.front_facing)
        (offsets, t, instance, triangle, front), c_face, c_t, c_instance, c_triangle, c_front, _ = out
        hits = _hits_of(offsets, t, instance, triangle, front)
        return FrontalHits(hits, self._first_hits(c_face, c_t, c_instance, c_triangle, c_front)), surfaces

    def _first_hits(self, face, t, instance, triangle, front) -> FirstHit:
        """The :class:`FirstHit` over the extension's result buffers (no copies)."""
        return FirstHit(
            t=np.frombuffer(t, dtype=np.float64),
            instance=np.frombuffer(instance, dtype=np.int32),
            triangle=np.frombuffer(triangle, dtype=np.int64),
            front_facing=np.frombuffer(front, dtype=bool),
            face=np.frombuffer(face, dtype=np.int64),
            face_normals=self._triangles.normal,
        )

    def intersect_all(
        self, rays: Rays, instances: np.ndarray | None = None, t_max: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        if not len(rays):
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        o, d = self._rows(rays)
        c = None if t_max is None else np.ascontiguousarray(t_max, dtype=np.float64)
        ray, face = self._engine.collect(self._selected(instances), len(rays), o, d, c, T_MAX_MARGIN, 0.0, True)
        return np.frombuffer(ray, dtype=np.int64), np.frombuffer(face, dtype=np.int64)

    def intersect_first(self, rays: Rays, instances: np.ndarray | None = None) -> np.ndarray:
        if not len(rays):
            return np.full(0, -1, dtype=np.int64)
        o, d = self._rows(rays)
        return np.frombuffer(self._engine.first(self._selected(instances), len(rays), o, d), dtype=np.int64)

    def closest_distance(self, points: np.ndarray) -> np.ndarray:
        p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        return np.frombuffer(self._engine.closest(self._selected(None), p), dtype=np.float64)


def _hits_of(offsets, t, instance, triangle, front) -> Hits:
    """:class:`Hits` over the extension's output bytearrays (no copies): offsets int64, t
    float64, instance int32, triangle int64, front_facing bool."""
    return Hits(offsets=np.frombuffer(offsets, dtype=np.int64), t=np.frombuffer(t, dtype=np.float64),
                instance=np.frombuffer(instance, dtype=np.int32), triangle=np.frombuffer(triangle, dtype=np.int64),
                front_facing=np.frombuffer(front, dtype=bool))


def _empty_hits(n_rays: int) -> Hits:
    return Hits(np.zeros(n_rays + 1, np.int64), np.zeros(0), np.zeros(0, np.int32), np.zeros(0, np.int64),
                np.zeros(0, bool))
