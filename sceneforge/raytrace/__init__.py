"""Ray tracing a house: every hit of every ray in one traversal (docs/spec.md §4), and first hits.

One interface, three engines (like ``trimesh.ray``):

- ``embree`` (:mod:`.embree_backend`): Embree through sceneforge's compiled extension,
  which collects every hit of a ray in one traversal and writes the hit arrays itself;
  the default wherever the extension was built at install time.
- ``open3d`` (:mod:`.open3d_backend`): Embree through Open3D's ``RaycastingScene``; the
  fallback where the extension is missing.
- ``reference`` (:mod:`.reference`): Möller–Trumbore in numpy over every triangle; slow
  and obviously correct, used by the tests to check the fast engines hit for hit.

An engine only answers *which* triangles a ray crosses, optionally among the envelope
or the object instances only. Everything else is done here, once, for every engine: hit
distances are recomputed in float64 from the triangle's plane (so the engines give
bit-identical distances for the same hit), hits are sorted per ray, and hits of the same
instance within ``tol.same_instance_hit`` of each other (a ray through an edge shared by
two triangles) are merged into the first of them. An engine with ``collect`` and
``first_hit`` methods (the ``embree`` one) does this work itself, operation for operation
the same.

:meth:`HouseTracer.frontal_query` returns only the hits the frontal layers can use (docs/spec.md §4.1),
split the way the rules read them: a first-hit query against the envelope (the
*closing* hit of each ray) and an all-hit query against the objects, cut just behind the
closing hit, replace an all-hit query through every wall of the house (on the bundled
multi-room toy houses a view has 2–6× fewer hits and is traced 1.3–3× faster), with the
same layers. :meth:`HouseTracer.frontal_hits` gives the same hits as one sorted list.

:meth:`HouseTracer.nearest_hits` gives each ray's first k hits over the whole house (the
ray-intersection layers of docs/spec.md §4.7): the Embree extension keeps them as it
traverses and stops where no farther hit can be among them, and
:meth:`HouseTracer.frontal_nearest` takes a view's frontal query from that same traversal.

Where all rays share their origin (a perspective camera) or direction (an orthographic
one), pass it as one row broadcast to (n, 3) (``np.broadcast_to``, as :meth:`Camera.rays`
does): the plane-distance terms are then computed once per face instead of per hit.
"""

from __future__ import annotations

import os
import weakref
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np

from ..conventions import tol
from ..errors import HouseError, SceneforgeError

if TYPE_CHECKING:
    from ..houses.model import House

__all__ = ["BACKENDS", "Backend", "CollectingBackend", "FirstHit", "FrontalHits", "Hits", "HouseTracer", "HouseTriangles", "NearestHits", "NearestSurfaces", "Rays", "default_backend", "nearest_candidates"]

#: Engine names accepted by :class:`HouseTracer`.
BACKENDS = ("embree", "open3d", "reference")
#: environment variable giving :class:`HouseTracer`'s default engine thread count
THREADS_ENV = "SCENEFORGE_TRACE_THREADS"
#: environment variable naming :func:`default_backend`'s engine (one of :data:`BACKENDS`),
#: e.g. ``open3d`` to render with the fallback where the extension is built
ENGINE_ENV = "SCENEFORGE_TRACE_ENGINE"


@dataclass
class Hits:
    """Every intersection of a batch of rays, sorted per ray by distance, CSR layout.

    offsets      : (n_rays + 1,) int64  ray r's hits are ``[offsets[r], offsets[r+1])``
    t            : (k,) float64  distance along the unit ray direction, ascending per ray
    instance     : (k,) int32    house instance index (position in ``house.instances``)
    triangle     : (k,) int64    triangle index within that instance's faces
    front_facing : (k,) bool     the ray meets the triangle's front side (its winding normal
                   points back at the ray origin); back faces are hits too

    Hits at exactly the same distance are ordered by instance, then triangle.
    """

    offsets: np.ndarray
    t: np.ndarray
    instance: np.ndarray
    triangle: np.ndarray
    front_facing: np.ndarray

    @property
    def n_rays(self) -> int:
        return len(self.offsets) - 1

    @property
    def counts(self) -> np.ndarray:
        """(n_rays,) int64 number of hits per ray."""
        return np.diff(self.offsets)

    def ray_ids(self) -> np.ndarray:
        """(k,) int64 the ray of each hit."""
        return np.repeat(np.arange(self.n_rays, dtype=np.int64), self.counts)

    def select(self, keep: np.ndarray) -> "Hits":
        """The hits where ``keep`` (k,) bool is True, still in CSR layout."""
        ray = self.ray_ids()[keep]
        offsets = np.zeros(self.n_rays + 1, dtype=np.int64)
        np.cumsum(np.bincount(ray, minlength=self.n_rays), out=offsets[1:])
        return Hits(offsets, self.t[keep], self.instance[keep], self.triangle[keep], self.front_facing[keep])


@dataclass
class FirstHit:
    """The nearest intersection of each ray.

    t            : (n,) float64  distance along the unit direction; NaN where the ray escapes
    instance     : (n,) int32    house instance index; -1 where the ray escapes
    triangle     : (n,) int64    triangle index within the instance; -1 where the ray escapes
    front_facing : (n,) bool     the ray meets the triangle's front side; False where none
    face         : (n,) int64    index of the triangle in the tracer's ``HouseTriangles.faces``;
                   -1 where the ray escapes
    """

    t: np.ndarray
    instance: np.ndarray
    triangle: np.ndarray
    front_facing: np.ndarray
    face: np.ndarray
    face_normals: np.ndarray = field(repr=False)

    @property
    def hit(self) -> np.ndarray:
        """(n,) bool rays that hit something."""
        return self.instance >= 0

    @property
    def normal(self) -> np.ndarray:
        """(n, 3) float64 unit winding normal of the hit triangle, world; NaN where none
        (looked up on use: the frontal layers only need a few of them)."""
        out = np.full((len(self.t), 3), np.nan)
        hit = self.face >= 0
        out[hit] = self.face_normals[self.face[hit]]
        return out


@dataclass
class NearestHits:
    """The first ``k`` hits of each ray: its :class:`Hits` (every hit, same-instance hits
    merged) in order of float64 distance, exact ties by instance, then triangle, cut after
    the k-th; layer-major, layer j of ray r at ``[j, r]``.

    t            : (k, n) float64  distance along the unit direction; NaN past the ray's last hit
    face         : (k, n) int64    index of the triangle in the tracer's ``HouseTriangles.faces``;
                   -1 past the last hit
    front_facing : (k, n) bool     the ray meets the triangle's front side; False past the last hit
    """

    t: np.ndarray
    face: np.ndarray
    front_facing: np.ndarray

    @property
    def counts(self) -> np.ndarray:
        """(n,) int64 hits kept per ray (at most k)."""
        return (self.face >= 0).sum(axis=0)


@dataclass
class NearestSurfaces:
    """:class:`NearestHits` as a view stores them (:meth:`HouseTracer.nearest_surfaces`);
    layer j of ray r at ``[j, r]`` (normals: ``[j, :, r]``).

    depth        : (k, n) float32     ``t * depth_scale``; NaN past the ray's last hit
    normal       : (k, 3, n) float32  the face's unit winding normal rotated by ``rotation``
                   (not turned to face the ray); NaN past the last hit
    instance     : (k, n) int32       house instance index; -1 past the last hit
    label        : (k, n) uint8       ``labels`` of the instance; 0 past the last hit
    front_facing : (k, n) bool        the ray meets the face's front side; False past the last hit
    """

    depth: np.ndarray
    normal: np.ndarray
    instance: np.ndarray
    label: np.ndarray
    front_facing: np.ndarray


@dataclass
class FrontalHits:
    """The hits the layer rules use (docs/spec.md §4.1), in the form they read them.

    objects : :class:`Hits`  every object hit of each ray, sorted, up to ``tol.envelope_slack``
              behind the ray's closing hit (all of them where there is none)
    closing : :class:`FirstHit`  each ray's first envelope hit (the overhead view: first
              floor hit beyond the clearance); what closes the ray and gives D5
    """

    objects: Hits
    closing: FirstHit


@dataclass(frozen=True)
class HouseTriangles:
    """All triangles of a house in one array, as the engines see them.

    vertices     : (v, 3) float64  every instance's vertices, concatenated; instance i owns
                   ``vertices[first_vertex[i]:first_vertex[i+1]]``
    faces        : (m, 3) int64    indices into ``vertices``; instance i owns faces
                   ``[first_face[i], first_face[i+1])`` in its own order
    first_vertex : (n_instances + 1,) int64
    first_face   : (n_instances + 1,) int64
    instance     : (m,) int32      owning instance of each face
    envelope     : (n_instances,) bool  which instances are room envelope
    normal       : (m, 3) float64  unit winding normal of each face
    normal_xyz   : (3, m) float64  the same, one contiguous row per axis (fast gathers)
    offset       : (m,) float64    ``normal · v0``: the face's plane is ``normal · x = offset``
    """

    vertices: np.ndarray
    faces: np.ndarray
    first_vertex: np.ndarray
    first_face: np.ndarray
    instance: np.ndarray
    envelope: np.ndarray
    normal: np.ndarray
    normal_xyz: np.ndarray
    offset: np.ndarray

    @classmethod
    def from_house(cls, house: "House") -> "HouseTriangles":
        if not house.instances or not house.triangle_count:
            raise HouseError(house.id, house.source_path, "house has no triangles to trace")
        n_vertices = np.cumsum([0] + [len(i.vertices) for i in house.instances])
        n_faces = np.cumsum([0] + [len(i.faces) for i in house.instances])
        vertices = np.concatenate([i.vertices for i in house.instances]).astype(np.float64)
        faces = np.concatenate([i.faces + n_vertices[k] for k, i in enumerate(house.instances)])
        instance = np.repeat(np.arange(len(house.instances), dtype=np.int32), np.diff(n_faces))
        v0, v1, v2 = (vertices[faces[:, c]] for c in range(3))
        normal = np.cross(v1 - v0, v2 - v0)
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        offset = normal[:, 0] * v0[:, 0] + normal[:, 1] * v0[:, 1] + normal[:, 2] * v0[:, 2]
        return cls(
            vertices, faces.astype(np.int64), n_vertices.astype(np.int64), n_faces.astype(np.int64),
            instance, np.array([i.envelope for i in house.instances], dtype=bool),
            normal, np.ascontiguousarray(normal.T), offset,
        )

    @property
    def n_instances(self) -> int:
        return len(self.first_face) - 1

    def global_index(self, instance, triangle) -> np.ndarray:
        """(k,) int64 index into ``faces`` of (instance, triangle-within-instance) pairs."""
        return self.first_face[np.asarray(instance, dtype=np.int64)] + np.asarray(triangle, dtype=np.int64)


@dataclass(frozen=True)
class Rays:
    """A checked batch of rays, as engines receive it.

    origins, directions : (n, 3) float64  unit directions; either may be a read-only
                          broadcast of one row (``np.broadcast_to``): a perspective camera
                          shares its origin, an orthographic one its direction
    origin_xyz          : (3, 1) float64 when every ray starts at the same point, else
                          (3, n) (a view of ``origins``): what distance computations gather
    direction_xyz       : (3, 1) float64 when every ray has the same direction, else (3, n)
    cache               : per-batch values kept between the queries of one
                          :class:`HouseTracer` call (an engine's own form of the rays,
                          per-face terms of the plane distances)
    """

    origins: np.ndarray
    directions: np.ndarray
    origin_xyz: np.ndarray
    direction_xyz: np.ndarray
    cache: dict = field(default_factory=dict)

    @classmethod
    def check(cls, origins, directions) -> "Rays":
        trusted = _CHECKED.get(id(directions)) is directions and not directions.flags.writeable
        o, o_shared = _ray_rows(origins, "origins")
        d, d_shared = _ray_rows(directions, "directions", checked=trusted)
        if d.shape != o.shape:
            raise ValueError(f"origins and directions must both be (n, 3), got {o.shape} and {d.shape}")
        unit = d[:1] if d_shared or trusted else d
        if len(d) and np.abs(np.einsum("ij,ij->i", unit, unit) - 1.0).max() > 2e-6:
            raise ValueError("ray directions must be unit vectors")
        # rows given in full may still all be the same (the last row decides most cases)
        o_shared = o_shared or (len(o) > 0 and bool((o[-1] == o[0]).all()) and bool((o == o[0]).all()))
        origin_xyz = o[:1].T.copy() if o_shared else o.T
        direction_xyz = d[:1].T.copy() if d_shared else d.T
        return cls(o, d, origin_xyz, direction_xyz)

    def __len__(self) -> int:
        return len(self.origins)


#: read-only direction arrays made by :meth:`sceneforge.cameras.Camera.rays` (unit and finite
#: by construction: a validated pose's rotation of cached unit pixel directions), which
#: :meth:`Rays.check` then checks by their first row only; keyed by id, dropped with them
_CHECKED: "weakref.WeakValueDictionary[int, np.ndarray]" = weakref.WeakValueDictionary()


def checked_directions(directions: np.ndarray) -> np.ndarray:
    """Mark ``directions`` (a read-only (n, 3) float64 array of unit vectors that sceneforge
    made) as checked, and return it."""
    if directions.flags.writeable or directions.dtype != np.float64:
        raise ValueError("only read-only float64 directions can be marked checked")
    _CHECKED[id(directions)] = directions
    return directions


def _ray_rows(a, name: str, checked: bool = False) -> tuple[np.ndarray, bool]:
    """``a`` as (n, 3) float64, checked finite, and whether it is one row broadcast (then
    it is kept as the broadcast and only that row is checked; ``checked``: also only that
    row, :func:`checked_directions`)."""
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"ray {name} must be (n, 3), got {a.shape}")
    shared = len(a) > 0 and a.strides[0] == 0
    if not np.isfinite(a[:1] if shared or checked else a).all():
        raise ValueError("ray origins and directions must be finite")
    return (a if shared else np.ascontiguousarray(a)), shared


class Backend(Protocol):
    """What an engine answers. ``instances`` (n_instances,) bool restricts a query to the
    instances it marks (None: every instance)."""

    name: str

    def intersect_all(
        self, rays: Rays, instances: np.ndarray | None = None, t_max: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Every (ray, face) crossing with distance >= 0 in any order: two (k,) int64 arrays,
        faces indexing ``HouseTriangles.faces``. Back faces count. ``t_max`` (n,) float64: the
        caller will drop crossings farther than this along ray r, so an engine may leave out
        those it can tell, from its own distances, are beyond ``t_max[r] + T_MAX_MARGIN``."""

    def intersect_first(self, rays: Rays, instances: np.ndarray | None = None) -> np.ndarray:
        """(n,) int64 face of the nearest crossing of each ray, -1 where none."""

    def closest_distance(self, points: np.ndarray) -> np.ndarray:
        """(n,) float64 distance from each (n, 3) point to the nearest triangle."""


class CollectingBackend(Backend, Protocol):
    """An engine that also does the hit collection itself (distances, sorting, merging);
    :class:`HouseTracer` then calls these instead of building the hits from the engine's
    crossings."""

    def collect(self, rays: Rays, instances: np.ndarray | None = None, cutoff: np.ndarray | None = None) -> "Hits":
        """What :func:`_collect_hits` makes of ``intersect_all(rays, instances, cutoff)``
        with that ``cutoff`` (n,) float64 (None: none), bit for bit."""

    def frontal(self, rays: Rays, objects: np.ndarray, envelope: np.ndarray, envelope_near: float) -> "FrontalHits":
        """What :meth:`HouseTracer.frontal_query` makes of :meth:`intersect_first` and
        :meth:`collect` (closing hits, then object hits up to them + slack), bit for bit."""

    def first_hit(self, rays: Rays, instances: np.ndarray | None = None) -> "FirstHit":
        """What :meth:`HouseTracer.first_hit` makes of :meth:`intersect_first`, bit for bit."""

    def nearest(self, rays: Rays, k: int) -> "NearestHits":
        """What :func:`_nearest_hits` makes of ``intersect_all(rays)``, bit for bit."""

    def nearest_surfaces(self, rays: Rays, k: int, depth_scale: np.ndarray, rotation: np.ndarray,
                         labels: np.ndarray) -> "NearestSurfaces":
        """What :func:`_nearest_surfaces` makes of :meth:`nearest`, bit for bit."""

    def frontal_nearest(self, rays: Rays, objects: np.ndarray, envelope: np.ndarray, k: int, depth_scale: np.ndarray,
                        rotation: np.ndarray, labels: np.ndarray) -> "tuple[FrontalHits, NearestSurfaces]":
        """:meth:`frontal` (``envelope_near`` 0) and :meth:`nearest_surfaces` in one call, bit for bit."""


#: how far (m) past ``t_max`` an engine's own (e.g. float32) distance must be before it
#: may leave a crossing out; generous against rounding, tiny against room sizes
T_MAX_MARGIN = 0.01


def _plane_distance(
    triangles: HouseTriangles, face: np.ndarray, ray: np.ndarray, rays: Rays
) -> tuple[np.ndarray, np.ndarray]:
    """Distance along ray ``ray[i]`` to the plane of face ``face[i]``, and ``normal · direction``.

    face, ray : (k,) int64 (``ray`` None: every ray in order, k = n). Returns two (k,)
    float64 arrays. Every engine's hits go through
    this one computation, so the same (ray, face) pair always gets bit-identical distances:
    ``(offset - normal · origin) / (normal · direction)``, each dot product summed x, y, z.
    """
    numerator = _normal_dot(triangles, face, ray, rays, "origin")
    cos = _normal_dot(triangles, face, ray, rays, "direction")
    with np.errstate(divide="ignore", invalid="ignore"):
        return numerator / cos, cos


def _normal_dot(triangles: HouseTriangles, face: np.ndarray, ray: np.ndarray, rays: Rays, what: str) -> np.ndarray:
    """(k,) ``offset - normal · origin`` (``what="origin"``) or ``normal · direction`` of each
    (face, ray) pair.

    Where every ray shares the vector (a camera's origin, an orthographic direction), the
    value depends on the face only: with at least as many pairs as faces it is computed
    once per face (kept in ``rays.cache``) and gathered, else per pair. The float operations
    are the same either way, so are the results.
    """
    n = triangles.normal_xyz
    xyz = rays.origin_xyz if what == "origin" else rays.direction_xyz
    if xyz.shape[1] == 1:
        x, y, z = xyz[:, 0]
        if len(face) >= len(triangles.offset):
            per_face = rays.cache.get(what)
            if per_face is None:
                per_face = n[0] * x + n[1] * y + n[2] * z
                if what == "origin":
                    per_face = triangles.offset - per_face
                rays.cache[what] = per_face
            return per_face[face]
    elif ray is None:
        x, y, z = xyz
    else:
        x, y, z = xyz[0][ray], xyz[1][ray], xyz[2][ray]
    dot = n[0][face] * x + n[1][face] * y + n[2][face] * z
    return triangles.offset[face] - dot if what == "origin" else dot


def _collect_hits(
    triangles: HouseTriangles, rays: Rays, ray: np.ndarray, face: np.ndarray, cutoff: np.ndarray | None = None
) -> Hits:
    """Turn an engine's unordered (ray, face) crossings into :class:`Hits`.

    Distances come from the face planes in float64; hits are sorted per ray by distance
    (exact ties by face index); a hit is dropped when an earlier hit of the same ray and
    instance lies within ``tol.same_instance_hit`` before it. Rays lying in a face's plane
    (no defined distance) are dropped, and so are hits farther than ``cutoff`` (n,) float,
    when given.
    """
    n_rays = len(rays)
    ray = np.asarray(ray, dtype=np.int64)
    face = np.asarray(face, dtype=np.int64)
    t, cos = _plane_distance(triangles, face, ray, rays)
    valid = np.isfinite(t)
    if cutoff is not None:
        valid &= t <= cutoff[ray]
    if not valid.all():
        ray, face, t, cos = ray[valid], face[valid], t[valid], cos[valid]
    counts = np.bincount(ray, minlength=n_rays)
    order = _order_by_ray_and_distance(ray, t, face)
    ray = np.repeat(np.arange(n_rays, dtype=np.int64), counts)  # == ray[order]
    t = t[order]
    face = face[order]
    instance = triangles.instance[face]

    duplicate = _same_instance_repeats(ray, t, instance)
    if duplicate is not None:
        keep = ~duplicate
        order, t, face, instance = order[keep], t[keep], face[keep], instance[keep]
        counts = np.bincount(ray[keep], minlength=n_rays)

    offsets = np.zeros(n_rays + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    return Hits(
        offsets=offsets,
        t=t,
        instance=instance.astype(np.int32),
        triangle=face - triangles.first_face[instance],
        front_facing=cos[order] < 0,
    )


def _same_instance_repeats(ray: np.ndarray, t: np.ndarray, instance: np.ndarray) -> np.ndarray | None:
    """(k,) bool hits within ``tol.same_instance_hit`` after an earlier hit of the same ray
    and instance (hits sorted by ray, then distance), or None when there is none.

    Each hit is compared with the one ``shift`` places before it. Distances ascend, so a
    hit can only be close to the one two places back if it is close to the one just before,
    and so on: after the first shift, only the (few) hits still in a close run are compared.
    """
    tol_t = tol.same_instance_hit
    close = np.flatnonzero((ray[1:] == ray[:-1]) & (t[1:] - t[:-1] <= tol_t)) + 1
    if not len(close):
        return None
    duplicate = np.zeros(len(t), dtype=bool)
    duplicate[close[instance[close] == instance[close - 1]]] = True
    shift = 2
    while len(close := close[close >= shift]):
        back = close - shift
        close = close[(ray[close] == ray[back]) & (t[close] - t[back] <= tol_t)]
        duplicate[close[instance[close] == instance[close - shift]]] = True
        shift += 1
    return duplicate if duplicate.any() else None


def _nearest_hits(triangles: HouseTriangles, rays: Rays, ray: np.ndarray, face: np.ndarray, k: int) -> NearestHits:
    """The first ``k`` hits of each ray from an engine's unordered (ray, face) crossings.

    As :func:`_collect_hits` (float64 plane distances, crossings without a finite one
    dropped, same-instance repeats merged), but ordered per ray by the exact distance, then
    face, not by :func:`_order_by_ray_and_distance`'s batch-wide key, which may take two
    hits less than ~1e-9 m apart for a tie: the layers of a ray then do not depend on the
    other rays of the batch.
    """
    n = len(rays)
    ray = np.asarray(ray, dtype=np.int64)
    face = np.asarray(face, dtype=np.int64)
    t, cos = _plane_distance(triangles, face, ray, rays)
    valid = np.isfinite(t)
    if not valid.all():
        ray, face, t, cos = ray[valid], face[valid], t[valid], cos[valid]
    order = np.lexsort((face, t, ray))
    ray, face, t, cos = ray[order], face[order], t[order], cos[order]
    duplicate = _same_instance_repeats(ray, t, triangles.instance[face])
    if duplicate is not None:
        keep = ~duplicate
        ray, face, t, cos = ray[keep], face[keep], t[keep], cos[keep]
    first = np.searchsorted(ray, np.arange(n))
    rank = np.arange(len(ray)) - first[ray]
    keep = rank < k
    ray, rank = ray[keep], rank[keep]
    out = NearestHits(np.full((k, n), np.nan), np.full((k, n), -1, dtype=np.int64), np.zeros((k, n), dtype=bool))
    out.t[rank, ray] = t[keep]
    out.face[rank, ray] = face[keep]
    out.front_facing[rank, ray] = cos[keep] < 0
    return out


def _nearest_surfaces(triangles: HouseTriangles, hits: NearestHits, depth_scale: np.ndarray, rotation: np.ndarray,
                      labels: np.ndarray) -> NearestSurfaces:
    """:class:`NearestSurfaces` of ``hits``; each value computed as the extension's
    ``nearest_surfaces`` does (float64 products, sums in the same order, then rounded).

    depth_scale : (n,) float64   rotation : (3, 3) float64   labels : (n_instances,) uint8
    """
    hit = hits.face >= 0
    face = np.where(hit, hits.face, 0)
    depth = np.full(hit.shape, np.nan, dtype=np.float32)
    depth[hit] = (hits.t * depth_scale)[hit]
    x, y, z = (triangles.normal_xyz[a][face] for a in range(3))
    normal = np.full((hit.shape[0], 3, hit.shape[1]), np.nan, dtype=np.float32)
    for a, (ra, rb, rc) in enumerate(rotation):
        normal[:, a][hit] = (ra * x + rb * y + rc * z)[hit]
    instance = np.where(hit, triangles.instance[face], -1).astype(np.int32)
    label = np.where(hit, labels[triangles.instance[face]], 0).astype(np.uint8)
    return NearestSurfaces(depth, normal, instance, label, hits.front_facing)


def _order_by_ray_and_distance(ray: np.ndarray, t: np.ndarray, face: np.ndarray) -> np.ndarray:
    """(k,) int64 permutation sorting hits by ray, then distance, then face (exact ties)."""
    if not len(t):
        return np.zeros(0, dtype=np.int64)
    # One float key orders by ray, then distance: the span keeps rays apart and the key
    # resolves distances to ~1e-16 of its magnitude (1e-9 m for 1e5 rays × 10 m).
    t0 = t.min()
    key = ray * (float(t.max() - t0) + 1.0) + (t - t0)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    tie = ks[1:] == ks[:-1]
    if tie.any():
        # exact ties go by face, so the result does not depend on the engine's hit order;
        # tied positions form short runs, numbered in key order, sorted by (run, face)
        pos = np.flatnonzero(np.r_[tie, False] | np.r_[False, tie])
        sub = order[pos]
        run = np.cumsum(np.r_[True, ~tie[pos[:-1]]])
        order[pos] = sub[np.argsort(run * (int(face.max()) + 1) + face[sub], kind="stable")]
    return order


def nearest_candidates(
    triangles: HouseTriangles, rays: Rays, ray: np.ndarray, face: np.ndarray, t32: np.ndarray
) -> np.ndarray:
    """(n,) int64 each ray's first-hit face (-1: none) from every one of its crossings.

    ray, face : (k,) int64  the crossings (faces index ``triangles.faces``), any order
    t32       : (k,) float32  the engine's distance of each

    The candidates of a ray are its crossings at most ``tol.tie_window`` (relative, in
    float32) beyond its nearest one; the first hit is the candidate of smallest float64
    plane distance (non-finite: last), exact ties by the lower face index, i.e. the lower
    instance, then the lower triangle. Two triangles an edge-on ray passes between, or
    two coincident ones, tie in float32; which one a traversal meets first differs between
    Embree builds and CPUs, this choice does not (the extension's ``nearest_face`` makes
    it the same way).
    """
    out = np.full(len(rays), -1, dtype=np.int64)
    if not len(ray):
        return out
    t32 = np.asarray(t32, dtype=np.float32)
    nearest = np.full(len(rays), np.inf, dtype=np.float32)
    np.minimum.at(nearest, ray, t32)
    limit = nearest * (np.float32(1.0) + np.float32(tol.tie_window))  # float32, as the extension
    candidate = t32 <= limit[ray]
    ray, face = ray[candidate], face[candidate]
    key, _ = _plane_distance(triangles, face, ray, rays)
    key[~np.isfinite(key)] = np.inf
    order = np.lexsort((face, key, ray))
    ray, face = ray[order], face[order]
    first = np.r_[True, ray[1:] != ray[:-1]]
    out[ray[first]] = face[first]
    return out


def _check_k(k) -> None:
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise ValueError(f"k must be an integer >= 1, got {k!r}")


def default_backend() -> str:
    """The engine the ``SCENEFORGE_TRACE_ENGINE`` environment variable names, else
    ``"embree"`` where sceneforge's Embree extension is built, else ``"open3d"``."""
    from .embree_backend import AVAILABLE

    named = os.environ.get(ENGINE_ENV, "")
    if named:
        if named not in BACKENDS:
            raise SceneforgeError(f"{ENGINE_ENV}={named!r} names no ray-tracing engine; choose one of {', '.join(BACKENDS)}")
        return named
    return "embree" if AVAILABLE else "open3d"


class HouseTracer:
    """All-hit and first-hit ray queries against one house; build once, reuse for every view.

    house   : the house; instance ``i`` of the results is ``house.instances[i]``
    backend : ``"embree"`` (fastest; the default where the extension is built),
              ``"open3d"`` (the default elsewhere) or ``"reference"`` (slow numpy, for
              tests); None: :func:`default_backend`. Every engine gives the same hits.
    threads : threads the engine may use per query; 0 (default) = every core, unless the
              ``SCENEFORGE_TRACE_THREADS`` environment variable says otherwise (the render
              pipeline sets it to cores ÷ workers in its worker processes, so that workers
              do not fight over the cores). Results do not depend on it.
    """

    def __init__(self, house: "House", backend: str | None = None, threads: int | None = None):
        backend = default_backend() if backend is None else backend
        if backend not in BACKENDS:
            raise ValueError(f"unknown ray-tracing backend {backend!r}; choose one of {', '.join(BACKENDS)}")
        if threads is None:
            threads = int(os.environ.get(THREADS_ENV, "0") or 0)
        if threads < 0:
            raise ValueError(f"threads must be >= 0 (0: every core), got {threads}")
        self.house_id = house.id
        self.threads = threads
        self.triangles = HouseTriangles.from_house(house)
        if backend == "embree":
            from .embree_backend import EmbreeBackend

            self.backend: Backend = EmbreeBackend(self.triangles, threads)
        elif backend == "open3d":
            from .open3d_backend import Open3DBackend

            self.backend = Open3DBackend(self.triangles, threads)
        else:
            from .reference import ReferenceBackend

            self.backend = ReferenceBackend(self.triangles)

    def all_hits(self, origins, directions, instances=None) -> Hits:
        """Every hit of every ray, back faces included, from one traversal per ray.

        origins, directions : (n, 3) float  ray origins and unit directions, world
        instances           : (n_instances,) bool, optional  trace only these instances
                              (the same hits as tracing all and dropping the others)
        """
        rays = Rays.check(origins, directions)
        return self._hits(rays, self._instance_mask(instances))

    def _hits(self, rays: Rays, instances: np.ndarray | None, cutoff: np.ndarray | None = None) -> Hits:
        """:class:`Hits` of the rays among ``instances``, up to ``cutoff`` (n,) when given:
        collected by the engine where it can, else from its crossings here."""
        collect = getattr(self.backend, "collect", None)
        if collect is not None:
            return collect(rays, instances, cutoff)
        ray, face = self.backend.intersect_all(rays, instances, t_max=cutoff)
        return _collect_hits(self.triangles, rays, ray, face, cutoff)

    def nearest_hits(self, origins, directions, k: int) -> NearestHits:
        """The first ``k`` hits of each ray over the whole house (objects and envelope, back
        faces too): :meth:`all_hits` in exact distance order, cut after the k-th
        (docs/spec.md §4.7). The Embree extension keeps each ray's nearest hits as it
        traverses and stops where no farther hit can be among them; the other engines
        take every hit and cut.

        origins, directions : (n, 3) float  ray origins and unit directions, world
        k                   : hits per ray, >= 1
        """
        _check_k(k)
        rays = Rays.check(origins, directions)
        nearest = getattr(self.backend, "nearest", None)
        if nearest is not None:
            return nearest(rays, int(k))
        ray, face = self.backend.intersect_all(rays)
        return _nearest_hits(self.triangles, rays, ray, face, int(k))

    def nearest_surfaces(self, origins, directions, k: int, depth_scale, rotation, labels) -> NearestSurfaces:
        """:meth:`nearest_hits` as a view stores them: the distance times ``depth_scale``
        (planar depth), the face's winding normal rotated by ``rotation`` (into the camera
        frame), the instance and its entry of ``labels`` (its class). The Embree extension
        writes these as it finishes each ray; the same values as from :meth:`nearest_hits`.

        origins, directions : (n, 3) float  ray origins and unit directions, world
        k                   : hits per ray, >= 1
        depth_scale         : (n,) float  what a hit's distance is multiplied by
        rotation            : (3, 3) float  what a face's normal is multiplied by
        labels              : (n_instances,) uint8  a value per instance
        """
        scale, rotation, labels = self._surface_args(len(np.asarray(directions)), depth_scale, rotation, labels)
        surfaces = getattr(self.backend, "nearest_surfaces", None)
        if surfaces is not None:
            _check_k(k)
            return surfaces(Rays.check(origins, directions), int(k), scale, rotation, labels)
        return _nearest_surfaces(self.triangles, self.nearest_hits(origins, directions, k), scale, rotation, labels)

    def frontal_nearest(self, origins, directions, k: int, depth_scale, rotation, labels
                        ) -> tuple[FrontalHits, NearestSurfaces]:
        """:meth:`frontal_query` (the default objects and envelope) and :meth:`nearest_surfaces`
        of the same rays, from one traversal per ray where the engine can (the Embree
        extension: the object hits up to each ray's closing hit are among the nearest hits
        it keeps); the same results as the two queries. Arguments as for those."""
        fused = getattr(self.backend, "frontal_nearest", None)
        if fused is None:
            return (self.frontal_query(origins, directions),
                    self.nearest_surfaces(origins, directions, k, depth_scale, rotation, labels))
        _check_k(k)
        rays = Rays.check(origins, directions)
        scale, rotation, labels = self._surface_args(len(rays), depth_scale, rotation, labels)
        return fused(rays, *self._frontal_masks(None, None), int(k), scale, rotation, labels)

    def _surface_args(self, n: int, depth_scale, rotation, labels) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`nearest_surfaces`'s ``depth_scale`` (n,), ``rotation`` (3, 3) and ``labels``
        (n_instances,), checked, as float64, float64 and uint8."""
        scale = np.asarray(depth_scale, dtype=np.float64).reshape(-1)
        if len(scale) != n:
            raise ValueError(f"depth_scale has {len(scale)} values for {n} rays")
        rotation = np.ascontiguousarray(rotation, dtype=np.float64)
        if rotation.shape != (3, 3):
            raise ValueError(f"rotation must be (3, 3), got {rotation.shape}")
        labels = np.ascontiguousarray(labels, dtype=np.uint8)
        if labels.shape != (self.triangles.n_instances,):
            raise ValueError(f"labels must be ({self.triangles.n_instances},) uint8, got {labels.shape}")
        return scale, rotation, labels

    def _instance_mask(self, instances) -> np.ndarray | None:
        """``instances`` checked to be (n_instances,) bool, or None."""
        if instances is None:
            return None
        instances = np.asarray(instances, dtype=bool)
        if instances.shape != (self.triangles.n_instances,):
            raise ValueError(f"instances must be ({self.triangles.n_instances},) bool, got {instances.shape}")
        return instances

    def frontal_query(
        self, origins, directions, objects=None, envelope=None, envelope_near: float = 0.0
    ) -> FrontalHits:
        """The hits the layer rules use, split as they read them: each ray's first envelope
        hit (the *closing* hit) and every object hit up to ``tol.envelope_slack`` behind it
        (all object hits where no envelope is hit). :func:`sceneforge.layers.layers_from_frontal`
        gives the same layers from these as :func:`~sceneforge.layers.layers_from_hits` from
        :meth:`all_hits` (docs/spec.md §4.1 ignores the rest), only faster: a first-hit query
        against the envelope replaces tracing through every wall of the house, objects far
        behind the closing hit are dropped before any distance is computed, and the closing
        hits never enter the per-ray sort. Where two envelope surfaces are hit first at the same
        distance (within float32 rounding), the closing hit is the one :func:`nearest_candidates`
        picks; all hits would list both.

        origins, directions : (n, 3) float  ray origins and unit directions, world
        objects             : (n_instances,) bool, optional  the object instances to trace
                              (default: every non-envelope instance)
        envelope            : (n_instances,) bool, optional  the instances that close a ray
                              (default: the house's envelope); the overhead view passes floors
        envelope_near       : envelope hits nearer than this are ignored (metres along the ray)
        """
        frontal = getattr(self.backend, "frontal", None)
        if frontal is not None:  # the engine does both passes itself, ray by ray
            rays = Rays.check(origins, directions)
            return frontal(rays, *self._frontal_masks(objects, envelope), envelope_near)
        rays, objects, closing, cutoff = self._frontal_setup(origins, directions, objects, envelope, envelope_near)
        return FrontalHits(self._hits(rays, objects, cutoff), closing)

    def frontal_hits(self, origins, directions, objects=None, envelope=None, envelope_near: float = 0.0) -> Hits:
        """The hits of :meth:`frontal_query` as one :class:`Hits` (closing hits sorted in
        among the object hits): the subset of :meth:`all_hits` the layer rules use.
        Arguments as for :meth:`frontal_query`."""
        rays, objects, closing, cutoff = self._frontal_setup(origins, directions, objects, envelope, envelope_near)
        ray, face = self.backend.intersect_all(rays, objects, t_max=cutoff)
        walled = np.flatnonzero(closing.face >= 0)
        return _collect_hits(self.triangles, rays, np.r_[ray, walled], np.r_[face, closing.face[walled]], cutoff)

    def _frontal_setup(self, origins, directions, objects, envelope, envelope_near: float):
        """What both frontal queries start from: the checked rays, the object mask, their
        closing hits and the cut-off (n,) (closing distance + slack; inf where nothing
        closes the ray)."""
        rays = Rays.check(origins, directions)
        objects, envelope = self._frontal_masks(objects, envelope)
        closing = self._closing(rays, envelope, envelope_near)
        cutoff = closing.t + tol.envelope_slack
        cutoff[np.isnan(cutoff)] = np.inf
        return rays, objects, closing, cutoff

    def _frontal_masks(self, objects, envelope) -> tuple[np.ndarray, np.ndarray]:
        """The (n_instances,) bool object and closing masks of a frontal query (defaults:
        the non-envelope instances and the envelope)."""
        objects = ~self.triangles.envelope if objects is None else np.asarray(objects, dtype=bool)
        envelope = self.triangles.envelope if envelope is None else np.asarray(envelope, dtype=bool)
        return objects, envelope

    def _closing(self, rays: Rays, envelope: np.ndarray, envelope_near: float) -> FirstHit:
        """Each ray's first hit among the ``envelope`` instances at least ``envelope_near``
        along it."""
        face = self.backend.intersect_first(rays, envelope)
        closing = self._first_hit(rays, face)
        near = np.flatnonzero(closing.t < envelope_near) if envelope_near > 0 else ()
        if len(near):  # rare (a floor right under an overhead camera): look again from past it
            again = Rays.check(rays.origins[near] + envelope_near * rays.directions[near], rays.directions[near])
            face[near] = self.backend.intersect_first(again, envelope)
            closing = self._first_hit(rays, face)
        return closing

    def first_hit(self, origins, directions, instances=None) -> FirstHit:
        """The nearest hit of each ray (origins, directions: (n, 3) float, unit directions),
        among ``instances`` ((n_instances,) bool, optional) only: with ``triangles.envelope``,
        the hits that make D5."""
        rays = Rays.check(origins, directions)
        first_hit = getattr(self.backend, "first_hit", None)
        if first_hit is not None:  # the engine computes the distances itself
            return first_hit(rays, self._instance_mask(instances))
        return self._first_hit(rays, self.backend.intersect_first(rays, self._instance_mask(instances)))

    def _first_hit(self, rays: Rays, face: np.ndarray) -> FirstHit:
        """:class:`FirstHit` of the engine's nearest faces ``face`` (n,) (-1: none)."""
        n = len(rays)
        hit = face >= 0
        everywhere = bool(hit.all())
        f = face if everywhere else face[hit]
        t_hit, cos_hit = _plane_distance(self.triangles, f, None if everywhere else np.flatnonzero(hit), rays)
        if everywhere:
            t, cos = t_hit, cos_hit
        else:
            t = np.full(n, np.nan)
            cos = np.zeros(n)
            t[hit], cos[hit] = t_hit, cos_hit
        instance = np.full(n, -1, dtype=np.int32)
        instance[hit] = self.triangles.instance[f]
        triangle = np.full(n, -1, dtype=np.int64)
        triangle[hit] = f - self.triangles.first_face[instance[hit]]
        return FirstHit(t, instance, triangle, cos < 0, face, self.triangles.normal)

    def closest_distance(self, points) -> np.ndarray:
        """(n,) float64 distance from each (n, 3) world point to the nearest surface."""
        p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        return self.backend.closest_distance(p)

    def face_normals(self, instance, triangle) -> np.ndarray:
        """(k, 3) float64 unit winding normals (world) of (instance, triangle) pairs, e.g. of
        :class:`Hits` entries."""
        return self.triangles.normal[self.triangles.global_index(instance, triangle)]
