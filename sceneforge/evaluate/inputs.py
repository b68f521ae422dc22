"""What the evaluation reads of one view, from a store or from :func:`sceneforge.view.compute_view`.

The same arrays describe ground truth (the layers a store holds) and predictions (the
layers ``sceneforge predict`` writes in the store layout), so every metric is one
function of an :class:`EvalView` and the view's ground-truth mesh.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..cameras import Camera
from ..conventions import LAYER_NAMES
from ..frustum import clip_triangles, frustum_planes, weld
from .depth_mesh import OVERHEAD, Mesh, MeshingConfig, height_map_mesh, perspective_mesh

if TYPE_CHECKING:
    from ..view import ViewGroundTruth

#: Every part a view's reconstruction is made of, in order.
PART_NAMES: tuple[str, ...] = (*LAYER_NAMES, OVERHEAD)


@dataclass(frozen=True, eq=False)
class EvalView:
    """The layers and cameras of one view.

    depth                 : (5, H, W) float32  planar depth of D1..D5, metres; NaN = none
    K                     : (3, 3) float64     frontal intrinsics
    cam_to_world          : (4, 4) float64     frontal pose, OpenCV axes
    overhead_height       : (R, R) float32     height above the floor, NaN = floor/nothing
    overhead_cam_to_world : (4, 4) float64     overhead pose (z straight down)
    overhead_extent       : float              overhead orthographic half-extent, metres
    overhead_params       : (5,) float64       tx, ty, tz, theta, sigma (tz: camera height
                            above the floor)
    """

    depth: np.ndarray
    K: np.ndarray
    cam_to_world: np.ndarray
    overhead_height: np.ndarray
    overhead_cam_to_world: np.ndarray
    overhead_extent: float
    overhead_params: np.ndarray

    def __post_init__(self):
        depth = np.asarray(self.depth, dtype=np.float32)
        if depth.ndim != 3 or depth.shape[0] != len(LAYER_NAMES):
            raise ValueError(f"depth must be (5, H, W), got {depth.shape}")
        height = np.asarray(self.overhead_height, dtype=np.float32)
        if height.ndim != 2 or height.shape[0] != height.shape[1]:
            raise ValueError(f"overhead_height must be square (R, R), got {height.shape}")
        for name, shape in (("K", (3, 3)), ("cam_to_world", (4, 4)), ("overhead_cam_to_world", (4, 4)),
                            ("overhead_params", (5,))):
            value = np.asarray(getattr(self, name), dtype=np.float64)
            if value.shape != shape:
                raise ValueError(f"{name} must be {shape}, got {value.shape}")
            object.__setattr__(self, name, value)
        object.__setattr__(self, "depth", depth)
        object.__setattr__(self, "overhead_height", height)
        object.__setattr__(self, "overhead_extent", float(self.overhead_extent))

    @classmethod
    def from_arrays(cls, view: Mapping[str, np.ndarray]) -> "EvalView":
        """From one view of a store (``store.view(i)``: depth, K, cam_to_world, overhead_*)."""
        missing = [k for k in ("depth", "K", "cam_to_world", "overhead_height", "overhead_cam_to_world",
                               "overhead_extent", "overhead_params") if k not in view]
        if missing:
            raise KeyError(f"the view lacks {', '.join(missing)}")
        return cls(view["depth"], view["K"], view["cam_to_world"], view["overhead_height"],
                   view["overhead_cam_to_world"], float(np.asarray(view["overhead_extent"])),
                   view["overhead_params"])

    @classmethod
    def from_ground_truth(cls, gt: "ViewGroundTruth") -> "EvalView":
        """From :func:`sceneforge.view.compute_view`'s output."""
        top = gt.overhead_camera
        return cls(gt.layers.depth, gt.camera.K, gt.camera.cam_to_world, gt.overhead.height,
                   top.cam_to_world, top.half_extent, top.params)

    def meshes(self, config: MeshingConfig | None = None) -> dict[str, Mesh]:
        """World-space mesh of every part: D1..D5 and the overhead height map (:data:`PART_NAMES`).

        The overhead map's mesh is cut to the frontal camera's frustum (its left, right, top,
        bottom and near planes), as the ground-truth mesh is (docs/spec.md §5.1): the paper measures
        surfaces "within the viewing frustum", and a square overhead map also reaches beside
        the view, where the truth is cut away and nothing it holds can be near it.
        """
        config = config or MeshingConfig()
        parts = {name: perspective_mesh(d, self.K, self.cam_to_world, config.edge_factor(name))
                 for name, d in zip(LAYER_NAMES, self.depth)}
        top = height_map_mesh(self.overhead_height, self.overhead_cam_to_world,
                              self.overhead_extent, float(self.overhead_params[2]), config)
        parts[OVERHEAD] = self._in_frustum(top)
        return parts

    def _in_frustum(self, mesh: Mesh) -> Mesh:
        """``mesh`` cut to the frontal camera's frustum (:func:`~sceneforge.frustum.frustum_planes`)."""
        if not len(mesh.faces):
            return mesh
        H, W = self.depth.shape[1:]
        planes = frustum_planes(Camera(self.K, self.cam_to_world, W, H))
        pieces, _ = clip_triangles(mesh.vertices[mesh.faces], planes)
        return Mesh(*weld(pieces))


@dataclass(frozen=True, eq=False)
class GroundTruthMesh:
    """The ground-truth mesh of a view (docs/spec.md §5): objects and room envelope apart."""

    objects: Mesh
    envelope: Mesh

    @classmethod
    def from_arrays(cls, mesh: Mapping) -> "GroundTruthMesh":
        """From ``store.mesh(i)``: ``{"objects": (vertices, faces), "envelope": (vertices, faces)}``."""
        return cls(Mesh(*mesh["objects"]), Mesh(*mesh["envelope"]))

    @classmethod
    def from_ground_truth(cls, gt: "ViewGroundTruth") -> "GroundTruthMesh":
        """From :func:`sceneforge.view.compute_view`'s output (computed with its mesh)."""
        if gt.mesh is None:
            raise ValueError("the view was computed without its mesh (ViewConfig.with_mesh=False)")
        return cls(Mesh(gt.mesh.objects.vertices, gt.mesh.objects.faces),
                   Mesh(gt.mesh.envelope.vertices, gt.mesh.envelope.faces))
