"""Frontal multi-layer depth: all hits of a view → D1..D5, masks, classes, instances (SPEC §4).

Per pixel, from the ray's hits sorted by distance ``t``:

1. Hits behind the first envelope hit are ignored, except object hits within
   ``tol.envelope_slack`` (1 mm) of it (a rug on the floor).
2. Only *visible* object instances — the first object hit of at least one pixel — may
   fill D1..D4.
3. ``D1`` = first object hit; ``D2`` = last hit of D1's instance; ``D3`` = first hit of
   another visible object instance at or after ``D2 - tol.same_instance_hit``; ``D4`` =
   last hit of D3's instance; ``D5`` = first envelope hit.

Every distance comparison is made along the ray (``t``); depths are then converted to
planar depth. The rules run on whole arrays of hits with segment operations, never a
Python loop over rays.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .conventions import tol

if TYPE_CHECKING:
    from .cameras import Camera
    from .houses.model import House
    from .raytrace import Hits, HouseTracer


@dataclass
class Layers:
    """Ground truth of one view. Layer order is ``conventions.LAYER_NAMES`` (D1..D5).

    depth    : (5, H, W) float32  planar depth in metres of D1..D5; NaN = no surface
    category : (3, H, W) uint8    NYU40 class of the surface of D1, D3 and D5; 0 where none
    instance : (2, H, W) int32    house instance index of D1 and D3; -1 where none
    normal   : (3, H, W) float32  unit normal of the first surface hit, camera frame (OpenCV
               axes), turned to face the camera; NaN where the ray hits nothing
    """

    depth: np.ndarray
    category: np.ndarray
    instance: np.ndarray
    normal: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.depth.shape[1], self.depth.shape[2]

    @property
    def masks(self) -> np.ndarray:
        """(5, H, W) bool support of each layer: M1 = M2 = finite D1, M3 = M4 = finite D3,
        M5 = finite D5 (SPEC §4.4)."""
        finite = np.isfinite(self.depth)
        return np.stack([finite[0], finite[0], finite[2], finite[2], finite[4]])

    @property
    def traditional_depth(self) -> np.ndarray:
        """(H, W) float32 depth of the first surface: D1, or D5 where there is no object."""
        return np.where(np.isfinite(self.depth[0]), self.depth[0], self.depth[4])


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
) -> Layers:
    """Apply the layer rules of SPEC §4 to every pixel at once.

    hits          : all hits of the H*W rays of a view, rays in row-major pixel order
    depth_scale   : (H*W,) float   planar depth = ``t * depth_scale`` (1 for orthographic)
    inst_category : (n_instances,) uint8  NYU40 class per instance (see :func:`instance_labels`)
    inst_envelope : (n_instances,) bool   envelope flag per instance
    shape         : (H, W)
    keep          : (k,) bool, optional  hits to use; the others are removed before any rule
                    runs (the overhead view drops ceilings, walls, ... this way, SPEC §7)
    normals       : (H*W, 3) float, optional  first-hit normals in the camera frame, NaN
                    where none; copied into ``Layers.normal`` (NaN everywhere when omitted)
    """
    H, W = shape
    n = H * W
    if hits.n_rays != n:
        raise ValueError(f"hits are for {hits.n_rays} rays, expected H×W = {H}×{W} = {n}")
    depth_scale = np.asarray(depth_scale, dtype=np.float64).reshape(-1)
    if len(depth_scale) != n:
        raise ValueError(f"depth_scale has {len(depth_scale)} values, expected {n}")
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
    if keep is not None:
        keep = np.asarray(keep, dtype=bool)
        if keep.shape != t.shape:
            raise ValueError(f"keep must be ({len(t)},) bool, got shape {keep.shape}")
        ray, t, inst = ray[keep], t[keep], inst[keep]
    envelope = inst_envelope[inst]

    depth = np.full((5, n), np.nan, dtype=np.float32)
    category = np.zeros((3, n), dtype=np.uint8)
    instance = np.full((2, n), -1, dtype=np.int32)

    def fill(layer: int, index: np.ndarray) -> np.ndarray:
        """Write hits ``index`` (at most one per ray) into depth layer ``layer``; return their rays."""
        r = ray[index]
        depth[layer, r] = t[index] * depth_scale[r]
        return r

    # D5 and rule 1: the first envelope hit closes the ray, give or take the slack
    e = _first_per_ray(np.flatnonzero(envelope), ray)
    r5 = fill(4, e)
    category[2, r5] = inst_category[inst[e]]
    cutoff = np.full(n, np.inf)
    cutoff[r5] = t[e] + tol.envelope_slack
    obj = ~envelope & (t <= cutoff[ray])

    # D1 and rule 2: the first object hit of a ray is visible by definition
    first = _first_per_ray(np.flatnonzero(obj), ray)
    r1 = fill(0, first)
    inst1 = np.full(n, -1, dtype=np.int64)
    inst1[r1] = inst[first]
    visible = np.zeros(len(inst_envelope), dtype=bool)
    visible[inst[first]] = True

    # D2: exit of D1's instance
    d2_t = np.full(n, np.inf)
    last = _last_per_ray(np.flatnonzero(obj & (inst == inst1[ray])), ray)
    d2_t[fill(1, last)] = t[last]

    # D3: next visible instance at or after D2; D4: its exit
    candidates = obj & visible[inst] & (inst != inst1[ray]) & (t >= d2_t[ray] - tol.same_instance_hit)
    third = _first_per_ray(np.flatnonzero(candidates), ray)
    r3 = fill(2, third)
    inst3 = np.full(n, -1, dtype=np.int64)
    inst3[r3] = inst[third]
    fill(3, _last_per_ray(np.flatnonzero(obj & (inst == inst3[ray])), ray))

    category[0, r1] = inst_category[inst[first]]
    category[1, r3] = inst_category[inst[third]]
    instance[0, r1] = inst[first]
    instance[1, r3] = inst[third]

    if normals is None:
        normal = np.full((3, n), np.nan, dtype=np.float32)
    else:
        normal = np.asarray(normals, dtype=np.float32).reshape(n, 3).T.copy()
    return Layers(
        depth=depth.reshape(5, H, W),
        category=category.reshape(3, H, W),
        instance=instance.reshape(2, H, W),
        normal=normal.reshape(3, H, W),
    )


def first_hit_normals(hits: "Hits", tracer: "HouseTracer", camera: "Camera") -> np.ndarray:
    """(H*W, 3) float64 camera-frame normal of each ray's first hit, facing the camera; NaN
    where the ray hits nothing."""
    has = hits.counts > 0
    first = hits.offsets[:-1][has]
    n_world = tracer.face_normals(hits.instance[first], hits.triangle[first])
    n_world *= np.where(hits.front_facing[first], 1.0, -1.0)[:, None]
    out = np.full((hits.n_rays, 3), np.nan)
    out[has] = n_world @ camera.cam_to_world[:3, :3]
    return out


def frontal_layers(house: "House", camera: "Camera", tracer: "HouseTracer | None" = None) -> Layers:
    """D1..D5, classes, instances and first-hit normals of one view of ``house``.

    tracer : a :class:`~sceneforge.raytrace.HouseTracer` of ``house``, reused across views
             (built here when omitted)
    """
    from .raytrace import HouseTracer

    tracer = tracer or HouseTracer(house)
    origins, directions, depth_scale = camera.rays()
    hits = tracer.frontal_hits(origins, directions)
    category, envelope = instance_labels(house)
    return layers_from_hits(
        hits, depth_scale, category, envelope, camera.shape, normals=first_hit_normals(hits, tracer, camera)
    )
