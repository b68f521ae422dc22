"""The overhead camera (:class:`OverheadCamera`) and its placement from a frontal view (docs/spec.md §6)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..conventions import overhead_pixel, overhead_pixel_centre
from ..layers import Layers
from .config import OverheadConfig
from .frame import Box, GravityFrame, gravity_frame
from .heuristics import (
    Candidate,
    FrontalPoints,
    combine,
    depth_statistics_box,
    envelope_frustum_box,
    majority_room_box,
)
from .points import frontal_points_fast

if TYPE_CHECKING:
    from ..cameras import Camera
    from ..houses import House


@dataclass(frozen=True, eq=False)
class OverheadCamera:
    """An orthographic camera looking straight down (OpenCV axes: z = world −Y).

    cam_to_world : (4, 4) float64  pose; column 1 (image down) is −forward of the frontal
                   view, so the frontal view direction points to the top of the image
    half_extent  : float           half the side of the square it sees, metres
    resolution   : int             image width = height, pixels; pixel centres at integer + 0.5
    params       : (5,) float64    ``tx, ty`` box centre (right, forward of the frontal
                   camera), ``tz`` camera height above the floor, ``theta`` angle between
                   the frontal view direction and gravity, ``sigma`` half-diagonal of the box
    floor_y      : float           world height of the floor the heights refer to
    box          : Box             the square it sees, in the frontal gravity-aligned frame
    candidates   : the three heuristic boxes with their weights and rejection reasons
    floor_source : where ``floor_y`` came from, one of :data:`FLOOR_SOURCES` (None: given
                   by the caller)
    """

    cam_to_world: np.ndarray
    half_extent: float
    resolution: int
    params: np.ndarray
    floor_y: float
    box: Box
    candidates: tuple[Candidate, ...] = field(default=())
    floor_source: str | None = None

    @property
    def width(self) -> int:
        return self.resolution

    @property
    def height(self) -> int:
        return self.resolution

    def _pixel_centres(self) -> np.ndarray:
        """(resolution,) float64 camera-plane coordinate of the pixel centres along either
        image axis (x along a row, y down a column)."""
        return overhead_pixel_centre(np.arange(self.resolution), self.half_extent, self.resolution)

    def rays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Parallel rays through the pixel centres, row-major.

        Returns origins (H*W, 3) float64 on the camera plane, directions (H*W, 3) float64
        (all world −Y) and depth_scale (H*W,) float64 (all 1: ray length = planar depth).
        ``directions`` and ``depth_scale`` are read-only broadcasts of one value (the
        tracer takes a broadcast direction as shared), and origins are one pass over the
        output: the sum of a per-column and a per-row term.
        """
        c = self._pixel_centres()
        R, t = self.cam_to_world[:3, :3], self.cam_to_world[:3, 3]
        n = self.resolution
        origins = np.empty((n, n, 3))
        # (t + x·R₀) + y·R₁ per pixel: column x, row y, summed in that order.
        np.add((t + c[:, None] * R[:, 0])[None, :, :], (c[:, None] * R[:, 1])[:, None, :], out=origins)
        origins = origins.reshape(n * n, 3)
        directions = np.broadcast_to(R[:, 2].copy(), origins.shape)
        depth_scale = np.broadcast_to(np.float64(1.0), (n * n,))
        return origins, directions, depth_scale

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (n, 3) → pixel coordinates uv (n, 2) (:func:`~sceneforge.conventions.overhead_pixel`)
        and depth below the camera z (n,)."""
        R, t = self.cam_to_world[:3, :3], self.cam_to_world[:3, 3]
        p = (np.asarray(points_world, dtype=np.float64) - t) @ R
        return overhead_pixel(p[:, :2], self.half_extent, self.resolution), p[:, 2]


def place_overhead_camera(
    frame: GravityFrame,
    points: FrontalPoints,
    tan_half_fov: float,
    floor_y: float,
    config: OverheadConfig | None = None,
    floor_source: str | None = None,
) -> OverheadCamera:
    """The overhead camera from a frontal view's points (docs/spec.md §6).

    tan_half_fov : tan of the frontal camera's horizontal half field of view
    floor_y      : world height of the floor (``tz`` is the camera height above it)
    floor_source : where ``floor_y`` came from (:data:`FLOOR_SOURCES`), kept with the camera
    """
    config = config or OverheadConfig()
    candidates = (
        depth_statistics_box(points.objects, config),
        envelope_frustum_box(points.envelope_z, tan_half_fov, config),
        majority_room_box(points.objects, points.object_room, points.object_excluded,
                          points.room_votes, points.room_ids, config),
    )
    candidates, box = combine(candidates, config)
    square = box.square()
    half = float(square.half_size[0])
    up = points.top - config.below_top
    tx, ty = square.center
    position = frame.to_world(np.array([[tx, up, ty]]))[0]
    pose = np.eye(4)
    pose[:3, 0] = frame.right
    pose[:3, 1] = -frame.forward
    pose[:3, 2] = (0.0, -1.0, 0.0)
    pose[:3, 3] = position
    params = np.array([tx, ty, position[1] - floor_y, frame.theta, half * np.sqrt(2.0)])
    return OverheadCamera(pose, half, int(config.resolution), params, float(floor_y), square,
                          candidates, floor_source)


def overhead_camera_and_points(
    house: "House", camera: "Camera", layers: Layers, config: OverheadConfig | None = None
) -> tuple[OverheadCamera, FrontalPoints]:
    """The overhead camera of a frontal view and the frontal points it was chosen from."""
    config = config or OverheadConfig()
    frame = gravity_frame(camera)
    points, floor_y, source = frontal_points_fast(house, camera, layers, frame, config)
    tan_half_fov = float(np.tan(camera.half_fov[0]))
    return place_overhead_camera(frame, points, tan_half_fov, floor_y, config, source), points


def overhead_camera(
    house: "House", camera: "Camera", layers: Layers, config: OverheadConfig | None = None
) -> OverheadCamera:
    """The overhead camera of a frontal view (docs/spec.md §6)."""
    return overhead_camera_and_points(house, camera, layers, config)[0]
