"""The ground truth an overhead camera sees, traced straight down (docs/spec.md §7)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..layers import Layers, instance_labels, layers_from_frontal
from .camera import OverheadCamera
from .config import FLOOR, OverheadConfig, class_mask

if TYPE_CHECKING:
    from ..houses import House


@dataclass(frozen=True, eq=False)
class OverheadTruth:
    """Ground truth seen by an overhead camera (docs/spec.md §7).

    layers   : Layers                 5 overhead depth layers (planar = distance below the
               camera), classes and instances, same rules as the frontal ones
    height   : (H, W) float32         height above ``floor_y`` of the first object hit;
               NaN where only the floor or nothing is hit
    category : (H, W) uint8           NYU40 class of the first object hit, else of the
               floor below, else 0
    floor_y  : float                  world height of the floor
    """

    layers: Layers
    height: np.ndarray
    category: np.ndarray
    floor_y: float


def overhead_instances(house: "House", config: OverheadConfig | None = None) -> np.ndarray:
    """(n_instances,) bool: the instances an overhead view sees (docs/spec.md §7.1): objects not of the
    ``truth_excluded`` classes, and floors; no other envelope surface."""
    config = config or OverheadConfig()
    category, envelope = instance_labels(house)
    return ~class_mask(house, config.truth_excluded) & (~envelope | (category == FLOOR))


def overhead_truth(
    house: "House", camera: OverheadCamera, tracer, config: OverheadConfig | None = None
) -> OverheadTruth:
    """Trace straight down from ``camera`` and build the overhead layers and height map.

    tracer : a :class:`sceneforge.raytrace.HouseTracer` of ``house``
    """
    config = config or OverheadConfig()
    origins, directions, depth_scale = camera.rays()
    category, envelope = instance_labels(house)
    seen = overhead_instances(house, config)
    # The query itself applies the filters of docs/spec.md §7.1: only the instances an overhead view sees,
    # and the first floor beyond the clearance closes each ray as the envelope does in a
    # frontal view (tests/test_view.py checks this against tracing every hit and filtering).
    hits = tracer.frontal_query(origins, directions, objects=seen & ~envelope, envelope=seen & envelope,
                                envelope_near=config.floor_clearance)
    layers = layers_from_frontal(hits, depth_scale, category, (camera.height, camera.width))
    top = float(camera.cam_to_world[1, 3])
    height = (top - layers.depth[0].astype(np.float64) - camera.floor_y).astype(np.float32)
    first = np.isfinite(layers.depth[0])
    category = np.where(first, layers.category[0], layers.envelope_category).astype(np.uint8)
    return OverheadTruth(layers, height, category, camera.floor_y)
