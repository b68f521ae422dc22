"""How the overhead camera is placed and its ground truth traced (:class:`OverheadConfig`),
and how its class lists are read on a house (:func:`class_mask`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..conventions import NYU40_IDS, in_classes

if TYPE_CHECKING:
    from ..houses import House

#: the NYU40 id of floors, which both the view's floor height and the ground truth single out
FLOOR = NYU40_IDS["floor"]


@dataclass(frozen=True)
class OverheadConfig:
    """How the overhead camera is placed and its ground truth traced. Defaults: the reference."""

    #: weights of the (depth statistics, envelope/frustum, majority room) boxes
    weights: tuple[float, float, float] = (1.0, 1.0, 2.0)
    #: candidates covering less floor area than this (m²) get weight 0
    min_area: float = 0.5
    #: overhead image size in pixels (square)
    resolution: int = 300
    #: the camera sits this far (m) below the highest frontal point of D1, D2 and D5,
    #: so that it is under the ceiling
    below_top: float = 0.05

    #: depth statistics: fewest D1–D4 points
    stats_min_points: int = 40
    #: depth statistics: box half-size = this × standard deviation
    stats_std_scale: float = 1.5
    #: depth statistics: smallest half-size (m), per axis
    stats_min_half_size: float = 0.5
    #: depth statistics: the box centre is pulled to within this distance (m) of the camera
    stats_max_distance: float = 9.0

    #: envelope/frustum: centre distance = this × mean camera-z of the D5 points
    envelope_depth_scale: float = 0.8
    #: envelope/frustum: the centre distance is clamped to this range (m)
    envelope_depth_range: tuple[float, float] = (1.0, 7.0)
    #: envelope/frustum: with fewer D5 points than this, the centre distance is the default
    envelope_min_points: int = 10
    #: envelope/frustum: centre distance (m) when D5 has too few points
    envelope_default_depth: float = 4.0
    #: envelope/frustum: half-size = this × tan(horizontal half-FOV) × centre distance
    envelope_zoom: float = 0.9

    #: majority room: fewest visible object pixels voting for a room
    room_min_votes: int = 20
    #: majority room: fewest object points of the winning room
    room_min_points: int = 15
    #: majority room: object points are used between these distances (m) from the camera
    room_distance_range: tuple[float, float] = (1.5, 9.0)
    #: majority room: the box's half-size is multiplied by this
    room_growth: float = 1.05
    #: majority room: classes whose points are ignored (NYU40 names or source labels)
    room_excluded: tuple[str, ...] = ("void", "person", "plant", "chandelier", "decoration")

    #: ground truth: classes ignored when tracing down (NYU40 names or source labels)
    truth_excluded: tuple[str, ...] = (
        "void", "person", "plant", "chandelier", "ceiling_fan", "decoration",
    )
    #: ground truth: floor hits closer than this (m) to the overhead camera are ignored
    floor_clearance: float = 0.5

    def __post_init__(self):
        if len(self.weights) != 3 or min(self.weights) < 0:
            raise ValueError(f"weights must be 3 numbers >= 0, got {self.weights}")
        if self.resolution < 1:
            raise ValueError(f"resolution must be at least 1 pixel, got {self.resolution}")
        for name in ("envelope_depth_range", "room_distance_range"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ValueError(f"{name} must be (low, high) with 0 <= low <= high, got {(lo, hi)}")


def class_mask(house: "House", names) -> np.ndarray:
    """(n_inst,) bool: the instance's NYU40 class or its source label is in ``names``."""
    names = frozenset(names)
    return np.array([in_classes(i.category, i.label, names) for i in house.instances], dtype=bool)
