"""Everything for one view of one house: ``compute_view(house, camera, config)``, no I/O.

The frontal layers (docs/spec.md §4), the ground-truth mesh (§5), the overhead camera (§6) and the
overhead ground truth (§7), in that order, and the ray-intersection layers when asked for (§4.7),
all from one :class:`HouseTracer` that the caller builds once per house and reuses for every view.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from .frustum import ViewMesh, ViewMeshConfig, view_mesh
from .intersections import Intersections, layers_and_intersections
from .layers import Layers, LayersConfig, frontal_layers
from .overhead import OverheadCamera, OverheadConfig, OverheadTruth, overhead_camera, overhead_truth

if TYPE_CHECKING:
    from .cameras import Camera
    from .houses.model import House
    from .raytrace import HouseTracer


@dataclass(frozen=True)
class ViewConfig:
    """What ground truth to compute for a view and how."""

    #: overhead camera heuristics and overhead ground truth settings
    overhead: OverheadConfig = field(default_factory=OverheadConfig)
    #: the ground-truth mesh: objects clipped to the frustum, the envelope from D5
    mesh: ViewMeshConfig = field(default_factory=ViewMeshConfig)
    #: what the frontal layers carry beyond the paper's: K ray-intersection layers, labels of every layer
    layers: LayersConfig = field(default_factory=LayersConfig)
    #: compute the ground-truth mesh (only the evaluation needs it); a render config sets it
    #: from ``store.gt_mesh``: a view's mesh is computed when the store keeps it
    with_mesh: bool = True


@dataclass(frozen=True, eq=False)
class ViewGroundTruth:
    """Ground truth of one view.

    camera          : the frontal camera (OpenCV axes)
    layers          : D1..D5 (5, H, W), classes, instances, normals
    overhead_camera : the virtual camera with its candidate boxes and parameters
    overhead        : overhead layers (5, Ho, Wo), height map and classes
    mesh            : frustum-clipped objects and the D5 envelope surface, or None when not asked for
    intersections   : the first K surfaces along each pixel's ray (K = ``layers.intersections``
                      of the config, docs/spec.md §4.7), or None when K is 0
    """

    camera: "Camera"
    layers: Layers
    overhead_camera: OverheadCamera
    overhead: OverheadTruth
    mesh: ViewMesh | None
    intersections: Intersections | None = None


def compute_view(
    house: "House", camera: "Camera", config: ViewConfig | None = None, tracer: "HouseTracer | None" = None
) -> ViewGroundTruth:
    """All ground truth of ``house`` seen from ``camera``.

    Pass the same ``tracer`` (``HouseTracer(house)``) for every view of a house: building it
    costs more than a view.
    """
    from .raytrace import HouseTracer

    config = config or ViewConfig()
    tracer = tracer or HouseTracer(house)
    labels, k = config.layers.labels == "all", config.layers.intersections
    if k:  # both from one traversal per ray
        layers, intersections = layers_and_intersections(house, camera, k, tracer, labels=labels)
    else:
        layers, intersections = frontal_layers(house, camera, tracer, labels=labels), None
    top = overhead_camera(house, camera, layers, config.overhead)
    return ViewGroundTruth(
        camera=camera,
        layers=layers,
        overhead_camera=top,
        overhead=overhead_truth(house, top, tracer, config.overhead),
        mesh=view_mesh(house, camera, layers, config.mesh, tracer) if config.with_mesh else None,
        intersections=intersections,
    )
