"""The virtual overhead camera of a frontal view and its ground truth (docs/spec.md §6, §7).

Frames used here:

- **World**: metres, +Y up (docs/spec.md §1).
- **Gravity-aligned frame** of a frontal camera (:class:`GravityFrame`): origin at the
  camera centre, coordinates ``(right, up, forward)`` where ``forward`` is the view
  direction flattened onto the floor plane, ``up`` is world +Y and ``right`` is
  ``forward × up``. The overhead box lives on its floor plane as ``(right, forward)``.
- **Overhead camera** (:class:`OverheadCamera`): orthographic, OpenCV axes like every
  camera of the project — z forward = straight down, image y (down) = −forward, so the
  top of the overhead image is where the frontal camera looks, and image x = right.

Three heuristics *(ref)* each propose a box on the floor plane (:class:`Candidate`, kept
with its weight and the reason it was rejected); their weighted average, padded to a
square, is the overhead camera's extent. Ground truth is traced straight down with the
frontal multi-hit rules (:func:`sceneforge.layers.layers_from_hits`) on a reduced set of
surfaces (:func:`overhead_truth`).

The modules follow the steps: :mod:`.config` (the settings), :mod:`.frame` (the gravity
frame, floor-plane boxes), :mod:`.points` (a frontal view's points in that frame and its
floor height), :mod:`.heuristics` (the three boxes and their average), :mod:`.camera` (the
camera placed from them), :mod:`.truth` (what it sees). How one view's camera was chosen,
for ``sceneforge overhead-camera``, is :mod:`sceneforge.pipeline.explain`'s.
"""

from __future__ import annotations

from .camera import OverheadCamera, overhead_camera, overhead_camera_and_points, place_overhead_camera
from .config import FLOOR, OverheadConfig
from .frame import Box, GravityFrame, gravity_frame
from .heuristics import CANDIDATE_NAMES, Candidate, FrontalPoints
from .points import FLOOR_SOURCES, frontal_points_fast, level_floor_y
from .truth import OverheadTruth, overhead_instances, overhead_truth

__all__ = ["CANDIDATE_NAMES", "FLOOR", "FLOOR_SOURCES", "Box", "Candidate", "FrontalPoints", "GravityFrame",
           "OverheadCamera", "OverheadConfig", "OverheadTruth", "frontal_points_fast", "gravity_frame",
           "level_floor_y", "overhead_camera", "overhead_camera_and_points", "overhead_instances", "overhead_truth",
           "place_overhead_camera"]
