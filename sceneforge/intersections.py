"""K ray-intersection layers: the first K surfaces along each pixel's ray (docs/spec.md §4.7).

Beyond the paper's five layers, for methods that read layered ray intersections (LaRI,
LayeredDepth): per pixel, every surface its ray crosses over the whole house — objects
and envelope, front and back faces, behind the first wall too — after the same-instance
merge of docs/spec.md §4, in order of distance (exact ties: instance, then triangle), the
first K kept, each as its planar depth, camera-frame normal, instance, class and side.

The tracer finds and measures them (:meth:`~sceneforge.raytrace.HouseTracer.nearest_surfaces`):
the Embree extension keeps each ray's nearest hits as it traverses, stops where no farther
one can be among them, and writes them as the view's layers; the other engines take every
hit of the ray and cut. The tests hold them equal, and to all hits of the numpy reference
engine sorted and cut, on every pixel. A view that needs the paper's layers too
(:func:`layers_and_intersections`, what ``compute_view`` calls) gets both from one traversal
per ray (:meth:`~sceneforge.raytrace.HouseTracer.frontal_nearest`): a ray's object hits up to
its closing hit are among its nearest hits.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .layers import Layers, frontal_layers, instance_labels

if TYPE_CHECKING:
    from .cameras import Camera
    from .houses.model import House
    from .raytrace import HouseTracer, NearestSurfaces


@dataclass
class Intersections:
    """The first K surfaces along each pixel's ray; layer k of pixel (i, j) is at ``[k, ..., i, j]``.

    depth        : (K, H, W) float32     planar depth of the k-th surface, metres; NaN past
                   the ray's last surface
    normal       : (K, 3, H, W) float32  the face's unit winding normal, camera frame (OpenCV
                   axes), not turned to face the camera; NaN past the last surface
    instance     : (K, H, W) int32       house instance index; -1 past the last surface
    category     : (K, H, W) uint8       NYU40 class of the instance; 0 past the last surface
                   (and for void objects)
    front_facing : (K, H, W) bool        the ray meets the face's front side (its winding
                   normal points back at the camera); False past the last surface
    """

    depth: np.ndarray
    normal: np.ndarray
    instance: np.ndarray
    category: np.ndarray
    front_facing: np.ndarray

    @property
    def layers(self) -> int:
        """K."""
        return self.depth.shape[0]


def ray_intersections(house: "House", camera: "Camera", k: int, tracer: "HouseTracer | None" = None) -> Intersections:
    """The first ``k`` (>= 1) surfaces along each pixel's ray of ``camera`` in ``house``.

    tracer : a :class:`~sceneforge.raytrace.HouseTracer` of ``house``, reused across views
             (built here when omitted)
    """
    from .raytrace import HouseTracer

    tracer = tracer or HouseTracer(house)
    origins, directions, depth_scale = camera.rays()
    category, _ = instance_labels(house)
    # the camera-frame normal is R.T @ the world normal, R the camera-to-world rotation
    surfaces = tracer.nearest_surfaces(origins, directions, k, depth_scale, camera.cam_to_world[:3, :3].T, category)
    return _as_view(surfaces, camera)


def layers_and_intersections(house: "House", camera: "Camera", k: int, tracer: "HouseTracer | None" = None,
                             labels: bool = False) -> tuple[Layers, Intersections]:
    """:func:`~sceneforge.layers.frontal_layers` and :func:`ray_intersections` of one view, the
    same arrays, from one traversal per ray. ``labels`` as for ``frontal_layers``."""
    from .raytrace import HouseTracer

    tracer = tracer or HouseTracer(house)
    origins, directions, depth_scale = camera.rays()
    category, _ = instance_labels(house)
    hits, surfaces = tracer.frontal_nearest(origins, directions, k, depth_scale, camera.cam_to_world[:3, :3].T,
                                            category)
    return frontal_layers(house, camera, tracer, labels=labels, hits=hits), _as_view(surfaces, camera)


def _as_view(surfaces: "NearestSurfaces", camera: "Camera") -> Intersections:
    """The tracer's (k, n) surfaces of a camera's rays as the view's (K, H, W) layers."""
    k = surfaces.depth.shape[0]
    H, W = camera.shape
    return Intersections(
        depth=surfaces.depth.reshape(k, H, W),
        normal=surfaces.normal.reshape(k, 3, H, W),
        instance=surfaces.instance.reshape(k, H, W),
        category=surfaces.label.reshape(k, H, W),
        front_facing=surfaces.front_facing.reshape(k, H, W),
    )
