"""Frontal multi-layer depth: all hits of a view → D1..D5, masks, classes, instances (docs/spec.md §4).

Per pixel, from the ray's hits sorted by distance ``t``:

1. Hits behind the first envelope hit are ignored, except object hits within
   ``tol.envelope_slack`` (1 mm) of it (a rug on the floor).
2. Only *visible* object instances — the first object hit of at least one pixel — may
   fill D1..D4.
3. ``D1`` = first object hit; ``D2`` = last hit of D1's instance; ``D3`` = first hit of
   another visible object instance at or after ``D2 - tol.same_instance_hit``; ``D4`` =
   last hit of D3's instance; ``D5`` = first envelope hit.

Every distance comparison is made along the ray (``t``); depths are then converted to
planar depth. The rules run in sceneforge's compiled extension where it is built (one pass
over each ray's sorted hits, :func:`sceneforge.raytrace._embree.layer_rules`), else on
whole arrays of hits with numpy segment operations, never a Python loop over rays; the
numpy version is the reference, and the tests hold the two equal on every pixel.

Asked for the labels of every layer (docs/spec.md §4.7, ``LayersConfig.labels == "all"``),
both also name the hit that fills each of D1..D4; with the closing hit's face for D5, every
layer has a face, hence a class, an instance and a camera-frame winding normal. Otherwise
nothing of that is computed.
"""

from __future__ import annotations

import typing
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .conventions import CLASS_LAYERS, ENVELOPE_LAYER, MASK_LAYERS, tol

try:
    from .raytrace._embree import layer_rules as _compiled_rules
except ImportError:  # the extension is not built: the numpy rules
    _compiled_rules = None

#: whether the layer rules run compiled (see :func:`apply_rules`)
COMPILED_RULES = _compiled_rules is not None

if TYPE_CHECKING:
    from .cameras import Camera
    from .houses.model import House
    from .raytrace import FrontalHits, Hits, HouseTracer, HouseTriangles


@dataclass(frozen=True)
class LayersConfig:
    """What a view's frontal ground truth carries beyond the paper's five layers (docs/spec.md
    §4.7): both default to what the paper's networks read, so that stores stay lean."""

    #: K: also store the first K surfaces along each pixel's ray, front and back faces alike
    #: (depth, camera-frame normal, instance, NYU40 class, front or back face), for methods that
    #: read layered ray intersections (LaRI, LayeredDepth); 0 = none
    intersections: int = 0
    #: the labels of D1..D5: "paper" (classes of D1, D3 and D5, instances of D1 and D3, as the
    #: paper's networks read them) or "all" (a class, an instance and a camera-frame normal for
    #: each of the five layers, in arrays of their own)
    labels: typing.Literal["paper", "all"] = "paper"

    def __post_init__(self):
        if not 0 <= self.intersections <= 255:
            raise ValueError(f"layers.intersections must be 0..255, got {self.intersections}")


@dataclass
class Layers:
    """Ground truth of one view. Layer order is ``conventions.LAYER_NAMES`` (D1..D5).

    depth    : (5, H, W) float32  planar depth in metres of D1..D5; NaN = no surface
    category : (3, H, W) uint8    NYU40 class of the surface of ``conventions.CLASS_LAYERS``
               (D1, D3, D5); 0 where none
    instance : (2, H, W) int32    house instance index of ``conventions.FRONT_LAYERS`` (D1,
               D3); -1 where none
    normal   : (3, H, W) float32  unit normal of the first surface hit, camera frame (OpenCV
               axes), turned to face the camera; NaN where the ray hits nothing

    The labels of every layer (docs/spec.md §4.7), None unless asked for (``labels``):

    layer_category : (5, H, W) uint8    NYU40 class of the surface of D1..D5 (D2 has D1's, D4
                     D3's); 0 where the layer is empty
    layer_instance : (5, H, W) int32    house instance of the surface of D1..D5 (D5: the closing
                     hit's envelope instance); -1 where empty
    layer_face     : (5, H, W) int64    the face (``HouseTriangles.global_index``) each of D1..D5
                     lies on; -1 where empty
    layer_normal   : (5, 3, H, W) float32  unit winding normal of that face, camera frame, not
                     turned to face the camera; NaN where empty
    """

    depth: np.ndarray
    category: np.ndarray
    instance: np.ndarray
    normal: np.ndarray
    layer_category: np.ndarray | None = None
    layer_instance: np.ndarray | None = None
    layer_face: np.ndarray | None = None
    layer_normal: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.depth.shape[1], self.depth.shape[2]

    @property
    def masks(self) -> np.ndarray:
        """(5, H, W) bool support of each layer: M1 = M2 = finite D1, M3 = M4 = finite D3,
        M5 = finite D5 (docs/spec.md §4.4, ``conventions.MASK_LAYERS``)."""
        return np.isfinite(self.depth)[list(MASK_LAYERS)]

    @property
    def envelope_category(self) -> np.ndarray:
        """(H, W) uint8 NYU40 class of the D5 surface; 0 where none."""
        return self.category[CLASS_LAYERS.index(ENVELOPE_LAYER)]

    @property
    def traditional_depth(self) -> np.ndarray:
        """(H, W) float32 depth of the first surface: D1, or D5 where there is no object."""
        return np.where(np.isfinite(self.depth[0]), self.depth[0], self.depth[ENVELOPE_LAYER])


def instance_labels(house: "House") -> tuple[np.ndarray, np.ndarray]:
    """Per-instance NYU40 class (n,) uint8 and envelope flag (n,) bool, indexed like hits."""
    category = np.array([i.category for i in house.instances], dtype=np.uint8)
    envelope = np.array([i.envelope for i in house.instances], dtype=bool)
    return category, envelope


def _first_per_ray(index: np.ndarray, ray: np.ndarray) -> np.ndarray:
    """The first of ``index`` (ascending hit indices) on each ray that has one."""
    r = ray[index]
    return index[np.r_[True, r[1:] != r[:-1]]] if len(index) else index


def _last_per_ray(index: np.ndarray, ray: np.ndarray) -> np.ndarray:
    """The last of ``index`` (ascending hit indices) on each ray that has one."""
    r = ray[index]
    return index[np.r_[r[1:] != r[:-1], True]] if len(index) else index


def layers_from_hits(
    hits: "Hits",
    depth_scale,
    inst_category,
    inst_envelope,
    shape: tuple[int, int],
    keep=None,
    normals=None,
    triangles: "HouseTriangles | None" = None,
    camera: "Camera | None" = None,
) -> Layers:
    """Apply the layer rules of docs/spec.md §4 to every pixel at once.

    hits          : all hits of the H*W rays of a view, rays in row-major pixel order
    depth_scale   : (H*W,) float   planar depth = ``t * depth_scale`` (1 for orthographic)
    inst_category : (n_instances,) uint8  NYU40 class per instance (see :func:`instance_labels`)
    inst_envelope : (n_instances,) bool   envelope flag per instance
    shape         : (H, W)
    keep          : (k,) bool, optional  hits to use; the others are removed before any rule
                    runs (the overhead view drops ceilings, walls, ... this way, docs/spec.md §7.1)
    normals       : (H*W, 3) float, optional  first-hit normals in the camera frame, NaN
                    where none; copied into ``Layers.normal`` (NaN everywhere when omitted)
    triangles, camera : the tracer's :class:`~sceneforge.raytrace.HouseTriangles` and the
                    view's camera, optional: given both, the labels of every layer
                    (``Layers.layer_*``, docs/spec.md §4.7)
    """
    n = _check_view(hits.n_rays, depth_scale, shape)
    labels = _wants_labels(triangles, camera)
    inst_category = np.asarray(inst_category, dtype=np.uint8)
    inst_envelope = np.asarray(inst_envelope, dtype=bool)
    if inst_category.shape != inst_envelope.shape:
        raise ValueError(f"{len(inst_category)} categories but {len(inst_envelope)} envelope flags")
    if len(hits.instance) and int(hits.instance.max()) >= len(inst_envelope):
        raise ValueError(
            f"hits reference instance {int(hits.instance.max())} "
            f"but only {len(inst_envelope)} instances are labelled"
        )

    ray, t, inst = hits.ray_ids(), hits.t, hits.instance.astype(np.int64)
    face = triangles.global_index(hits.instance, hits.triangle) if labels else None
    if keep is not None:
        keep = np.asarray(keep, dtype=bool)
        if keep.shape != t.shape:
            raise ValueError(f"keep must be ({len(t)},) bool, got shape {keep.shape}")
        ray, t, inst = ray[keep], t[keep], inst[keep]
        face = face[keep] if labels else None
    envelope = inst_envelope[inst]

    # rule 1: the first envelope hit closes the ray (D5), give or take the slack
    e = _first_per_ray(np.flatnonzero(envelope), ray)
    closing_t = np.full(n, np.nan)
    closing_inst = np.full(n, -1, dtype=np.int64)
    closing_t[ray[e]] = t[e]
    closing_inst[ray[e]] = inst[e]
    cutoff = np.where(np.isnan(closing_t), np.inf, closing_t + tol.envelope_slack)
    obj = ~envelope & (t <= cutoff[ray])
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(ray[obj], minlength=n), out=offsets[1:])
    closing_face = None
    if labels:
        closing_face = np.full(n, -1, dtype=np.int64)
        closing_face[ray[e]] = face[e]
        face = face[obj]
    layers = apply_rules(offsets, t[obj], inst[obj], closing_t, closing_inst, depth_scale,
                         inst_category, shape, normals, face=face, closing_face=closing_face)
    return _with_layer_normals(layers, triangles, camera) if labels else layers


def layers_from_frontal(
    hits: "FrontalHits", depth_scale, inst_category, shape: tuple[int, int], normals=None,
    triangles: "HouseTriangles | None" = None, camera: "Camera | None" = None,
) -> Layers:
    """The layers of docs/spec.md §4 from a :meth:`~sceneforge.raytrace.HouseTracer.frontal_query`
    (the same as :func:`layers_from_hits` on every hit, without sorting the closing hits in).

    hits          : the frontal query of the H*W rays of a view, row-major pixel order
    depth_scale, inst_category, shape, normals, triangles, camera : as for :func:`layers_from_hits`
    """
    n = _check_view(hits.objects.n_rays, depth_scale, shape)
    labels = _wants_labels(triangles, camera)
    objects, closing = hits.objects, hits.closing
    if len(closing.t) != n:
        raise ValueError(f"closing hits are for {len(closing.t)} rays, expected {n}")
    # D1..D4 are object hits of the all-hit query; D5 is the closing first hit, which knows its face
    face = triangles.global_index(objects.instance, objects.triangle) if labels else None
    layers = apply_rules(objects.offsets, objects.t, objects.instance, closing.t, closing.instance,
                         depth_scale, np.asarray(inst_category, dtype=np.uint8), shape, normals,
                         face=face, closing_face=closing.face if labels else None)
    return _with_layer_normals(layers, triangles, camera) if labels else layers


def _wants_labels(triangles, camera) -> bool:
    """Whether the labels of every layer are asked for: given both the triangles and the camera."""
    if (triangles is None) != (camera is None):
        raise ValueError("the labels of every layer need both the house's triangles and the camera")
    return triangles is not None


def _with_layer_normals(layers: Layers, triangles: "HouseTriangles", camera: "Camera") -> Layers:
    """``layers`` with ``layer_normal`` (5, 3, H, W) float32: the camera-frame winding normal of
    each layer's face (``layer_face``), not turned to face the camera; NaN where empty."""
    R = camera.cam_to_world[:3, :3]
    face = layers.layer_face
    # rotated normals in a table whose last column, NaN, is what face -1 (none) reads: every
    # face's normal, or, in a house of more faces than the layers have pixels, each pixel's
    if len(triangles.offset) <= face.size:
        normals = triangles.normal_xyz
    else:
        normals = triangles.normal_xyz[:, face.reshape(-1)]
        face = np.where(face >= 0, np.arange(face.size).reshape(face.shape), -1)
    table = np.empty((3, normals.shape[1] + 1), dtype=np.float32)
    table[:, :-1] = R.T @ normals
    table[:, -1] = np.nan
    normal = np.empty((5, 3, *layers.shape), dtype=np.float32)
    for k in range(5):
        np.take(table, face[k], axis=1, out=normal[k])
    layers.layer_normal = normal
    return layers


def _check_view(n_rays: int, depth_scale, shape: tuple[int, int]) -> int:
    """H*W, after checking that the hits and depth scale are for an H×W view."""
    H, W = shape
    n = H * W
    if n_rays != n:
        raise ValueError(f"hits are for {n_rays} rays, expected H×W = {H}×{W} = {n}")
    if np.size(depth_scale) != n:
        raise ValueError(f"depth_scale has {np.size(depth_scale)} values, expected {n}")
    return n


def apply_rules(
    offsets, t, inst, closing_t, closing_inst, depth_scale, inst_category, shape, normals=None,
    compiled: bool | None = None, face=None, closing_face=None,
) -> Layers:
    """The layer rules of docs/spec.md §4.2–§4.3 on the object hits a ray's closing hit lets through.

    offsets, t, inst        : object hits in CSR layout (as :class:`~sceneforge.raytrace.Hits`),
                              sorted per ray by distance; none beyond the closing hit + slack
    closing_t, closing_inst : (H*W,) the closing (first envelope) hit per ray; NaN / -1: none
    depth_scale, inst_category, shape, normals : as for :func:`layers_from_hits`
    compiled                : run the compiled rules (True), the numpy reference (False), or
                              the compiled ones where the extension is built (None); the
                              same layers either way
    face, closing_face      : (k,) and (H*W,) int64, optional: the face of each object hit and
                              of each closing hit (-1: none); given both, the rules also name
                              the hit filling each layer, and the layers carry the labels of
                              every layer (``layer_category``, ``layer_instance``, ``layer_face``;
                              ``layer_normal`` is left to the callers that know the camera)
    """
    n = shape[0] * shape[1]
    if (face is None) != (closing_face is None):
        raise ValueError("the labels of every layer need both face and closing_face")
    # (4, n) int64: the object hit filling each of D1..D4 (-1: none), only when labels are asked for
    hit = None if face is None else np.full((4, n), -1, dtype=np.int64)
    offsets = np.ascontiguousarray(offsets, dtype=np.int64)
    if len(offsets) != n + 1:
        raise ValueError(f"offsets must have {n + 1} entries for a {shape[0]}×{shape[1]} view, got {len(offsets)}")
    scale = np.asarray(depth_scale, dtype=np.float64).reshape(-1)
    compiled = COMPILED_RULES if compiled is None else compiled
    if compiled:
        if _compiled_rules is None:
            raise RuntimeError("the compiled layer rules need sceneforge's Embree extension, which is not built")
        depth = np.full((5, n), np.nan, dtype=np.float32)
        category = np.zeros((3, n), dtype=np.uint8)
        instance = np.full((2, n), -1, dtype=np.int32)
        # a broadcast scale (an orthographic view: all 1) is passed as its one value
        scale = scale[:1] if len(scale) > 1 and scale.strides[0] == 0 else np.ascontiguousarray(scale)
        _compiled_rules(
            offsets, np.ascontiguousarray(t, dtype=np.float64), np.ascontiguousarray(inst, dtype=np.int32),
            np.ascontiguousarray(closing_t, dtype=np.float64), np.ascontiguousarray(closing_inst, dtype=np.int32),
            scale, np.ascontiguousarray(inst_category, dtype=np.uint8), float(tol.same_instance_hit),
            depth, category, instance, *([] if hit is None else [hit]))
    else:
        ray = np.repeat(np.arange(n, dtype=np.int64), np.diff(offsets))
        depth, category, instance = _numpy_rules(ray, np.asarray(t), np.asarray(inst, dtype=np.int64),
                                                 np.asarray(closing_t), np.asarray(closing_inst, dtype=np.int64),
                                                 scale, inst_category, n, hit)
    H, W = shape
    if normals is None:
        normal = np.full((3, n), np.nan, dtype=np.float32)
    else:
        normal = np.asarray(normals, dtype=np.float32).reshape(n, 3).T.copy()
    layers = Layers(
        depth=depth.reshape(5, H, W),
        category=category.reshape(3, H, W),
        instance=instance.reshape(2, H, W),
        normal=normal.reshape(3, H, W),
    )
    if hit is not None:
        _label_layers(layers, hit, face, closing_inst, closing_face)
    return layers


def _label_layers(layers: Layers, hit, face, closing_inst, closing_face) -> None:
    """Set the labels of every layer of ``layers``: classes and instances from its paper ones
    (D2 is a hit of D1's instance, D4 of D3's; D5's instance is the closing hit's), faces from
    the hit filling each of D1..D4 (``hit`` (4, n) int64 into the object hits, whose faces are
    ``face`` (k,); -1: none) and the closing hits' ``closing_face`` (n,)."""
    H, W = layers.shape
    layers.layer_category = layers.category[[0, 0, 1, 1, 2]]
    layers.layer_instance = np.concatenate([layers.instance[[0, 0, 1, 1]],
                                            np.asarray(closing_inst, dtype=np.int32).reshape(1, H, W)])
    layer_face = np.empty((5, H, W), dtype=np.int64)
    # hit -1 (an empty layer) reads the appended -1
    np.take(np.append(np.asarray(face, dtype=np.int64), np.int64(-1)), hit.reshape(4, H, W), out=layer_face[:4])
    layer_face[ENVELOPE_LAYER] = np.asarray(closing_face).reshape(H, W)
    layers.layer_face = layer_face


def _numpy_rules(ray, t, inst, closing_t, closing_inst, depth_scale, inst_category, n, hit=None):
    """The reference rules (:func:`apply_rules`) on whole arrays: (5, n) float32 depths, (3, n)
    uint8 classes and (2, n) int32 instances, from the object hits ``ray, t, inst`` (k,)
    sorted by ray, then distance. ``hit`` (4, n) int64, optional, filled with -1: receives the
    index of the object hit filling each of D1..D4."""
    depth = np.full((5, n), np.nan, dtype=np.float32)
    category = np.zeros((3, n), dtype=np.uint8)
    instance = np.full((2, n), -1, dtype=np.int32)

    def fill(layer: int, index: np.ndarray) -> np.ndarray:
        """Write hits ``index`` (at most one per ray) into depth layer ``layer``; return their rays."""
        r = ray[index]
        depth[layer, r] = t[index] * depth_scale[r]
        if hit is not None:
            hit[layer, r] = index
        return r

    # D5: the closing hit (NaN distance where none: NaN depth; instance -1: the appended 0)
    depth[ENVELOPE_LAYER] = closing_t * depth_scale
    category[CLASS_LAYERS.index(ENVELOPE_LAYER)] = np.append(inst_category, 0)[closing_inst]

    # D1 and rule 2: the first object hit of a ray is visible by definition
    first = _first_per_ray(np.arange(len(ray)), ray)
    r1 = fill(0, first)
    inst1 = np.full(n, -1, dtype=np.int64)
    inst1[r1] = inst[first]
    visible = np.zeros(len(inst_category), dtype=bool)
    visible[inst[first]] = True

    # D2: exit of D1's instance
    d2_t = np.full(n, np.inf)
    same1 = inst == inst1[ray]
    last = _last_per_ray(np.flatnonzero(same1), ray)
    d2_t[fill(1, last)] = t[last]

    # D3: next visible instance at or after D2; D4: its exit
    candidates = ~same1 & visible[inst] & (t >= d2_t[ray] - tol.same_instance_hit)
    third = _first_per_ray(np.flatnonzero(candidates), ray)
    r3 = fill(2, third)
    inst3 = np.full(n, -1, dtype=np.int64)
    inst3[r3] = inst[third]
    fill(3, _last_per_ray(np.flatnonzero(inst == inst3[ray]), ray))

    category[0, r1] = inst_category[inst[first]]
    category[1, r3] = inst_category[inst[third]]
    instance[0, r1] = inst[first]
    instance[1, r3] = inst[third]
    return depth, category, instance


def first_hit_normals(hits: "Hits", tracer: "HouseTracer", camera: "Camera") -> np.ndarray:
    """(H*W, 3) float32 camera-frame normal of each ray's first hit, facing the camera; NaN
    where the ray hits nothing (see :func:`_camera_normals` for the layout)."""
    face = np.full(hits.n_rays, -1, dtype=np.int64)
    front = np.zeros(hits.n_rays, dtype=bool)
    has = hits.counts > 0
    first = hits.offsets[:-1][has]
    face[has] = tracer.triangles.global_index(hits.instance[first], hits.triangle[first])
    front[has] = hits.front_facing[first]
    return _camera_normals(tracer.triangles, face, front, camera)


def frontal_normals(hits: "FrontalHits", tracer: "HouseTracer", camera: "Camera") -> np.ndarray:
    """:func:`first_hit_normals` of a :meth:`~sceneforge.raytrace.HouseTracer.frontal_query`:
    a ray's first hit is its first object hit unless the closing hit is nearer (exact ties:
    lower face index), as in the merged, sorted hits."""
    objects, closing = hits.objects, hits.closing
    tri = tracer.triangles
    has = objects.counts > 0
    rays = np.flatnonzero(has)
    first = objects.offsets[:-1][has]
    face = closing.face.copy()
    front = closing.front_facing.copy()
    obj_face = tri.global_index(objects.instance[first], objects.triangle[first])
    t_obj, t_close = objects.t[first], closing.t[rays]
    # NaN closing distance (no envelope hit) compares False: the object is first
    use = ~((t_close < t_obj) | ((t_close == t_obj) & (face[rays] < obj_face)))
    face[rays[use]] = obj_face[use]
    front[rays[use]] = objects.front_facing[first][use]
    return _camera_normals(tri, face, front, camera)


def _camera_normals(tri, face: np.ndarray, front: np.ndarray | None, camera: "Camera") -> np.ndarray:
    """(n, 3) float32 camera-frame winding normals of faces ``face`` (n,) (-1: none, NaN),
    flipped where ``front`` is False so that they face the camera (``front`` None: none
    flipped, the winding normals themselves). A transposed view of a
    (3, n) array, the layout :class:`Layers` stores. Every face's normal is rotated once
    when there are fewer faces than rays, else each ray's."""
    R = camera.cam_to_world[:3, :3]
    out = np.full((3, len(face)), np.nan, dtype=np.float32)
    hit = face >= 0
    everywhere = bool(hit.all())
    f = face if everywhere else face[hit]
    if len(tri.offset) <= len(f):
        normals = (R.T @ tri.normal_xyz)[:, f]
    else:
        normals = R.T @ tri.normal_xyz[:, f]
    if front is not None:
        normals *= np.where(front if everywhere else front[hit], 1.0, -1.0)
    if everywhere:
        out[:] = normals
    else:
        out[:, hit] = normals
    return out.T


def frontal_layers(
    house: "House", camera: "Camera", tracer: "HouseTracer | None" = None, labels: bool = False,
    hits: "FrontalHits | None" = None,
) -> Layers:
    """D1..D5, classes, instances and first-hit normals of one view of ``house``.

    tracer : a :class:`~sceneforge.raytrace.HouseTracer` of ``house``, reused across views
             (built here when omitted)
    labels : also the labels of every layer (``Layers.layer_*``, docs/spec.md §4.7;
             ``LayersConfig.labels == "all"``)
    hits   : the view's :meth:`~sceneforge.raytrace.HouseTracer.frontal_query`, when the caller
             has it (:func:`sceneforge.intersections.layers_and_intersections`); traced here
             when omitted
    """
    from .raytrace import HouseTracer

    tracer = tracer or HouseTracer(house)
    origins, directions, depth_scale = camera.rays()
    if hits is None:
        hits = tracer.frontal_query(origins, directions)
    category, _ = instance_labels(house)
    return layers_from_frontal(hits, depth_scale, category, camera.shape,
                               normals=frontal_normals(hits, tracer, camera),
                               triangles=tracer.triangles if labels else None, camera=camera if labels else None)
