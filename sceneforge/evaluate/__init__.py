"""Evaluation of multi-layer depth reconstructions (docs/spec.md §11).

- :mod:`.depth_mesh`: depth layers and overhead height maps → world-space meshes
  (2×2 block triangulation with the edge rule, the kernel in :mod:`sceneforge.depth_mesh`
  that the ground-truth envelope is made with too), the edge factor presets.
- :mod:`.surface`: uniform surface samples, point-to-mesh distance, precision and recall.
- :mod:`.coverage`: unions of a view's layer meshes scored against its ground-truth
  mesh; the coverage table (paper Table 1) and the predictions table (paper §5).
- :mod:`.voxels`: voxel IoU of the layer intervals against the solid object mesh.
- :mod:`.points`: layered point sets the way LaRI scores them: Chamfer-L1 and F-score of the
  visible, unseen and all points, as predicted and after a per-view scale and shift.
- :mod:`.inputs`: what all of them read of a view, from a store or from ``compute_view``.
- :mod:`.stores`: the views of opened stores to score, predictions checked against their
  truth view by view, and the per-view voxel and layered point loops.
- :mod:`.config`: the configs of all of them in one file, ``sceneforge evaluate --config``.

Everything but :mod:`.stores` is pure: arrays in, numbers out; ``sceneforge evaluate``
opens the stores.
"""

from .config import EvaluateConfig
from .coverage import (
    COVERAGE_VARIANTS,
    GT_KINDS,
    PAPER_COVERAGE,
    PAPER_PREDICTIONS,
    PREDICTION_VARIANTS,
    SurfaceReport,
    Variant,
    ViewScores,
    evaluate_views,
    score_parts,
    score_view,
)
from .depth_mesh import (
    EDGE_FACTORS,
    Mesh,
    MeshingConfig,
    concatenate,
    grid_mesh,
    height_map_mesh,
    orthographic_mesh,
    perspective_mesh,
)
from .inputs import OVERHEAD, PART_NAMES, EvalView, GroundTruthMesh
from .points import LayeredView, PointsConfig, PointsReport, ray_layers
from .stores import (
    ViewVoxelScore,
    VoxelReport,
    coverage_views,
    matching_view,
    prediction_views,
    score_store_points,
    score_store_voxels,
    views_to_score,
)
from .surface import (
    MeshDistance,
    SurfaceConfig,
    default_thresholds,
    inlier_fraction,
    precision_recall,
    sample_surface,
    surface_precision_recall,
)
from .voxels import (
    VoxelConfig,
    VoxelScore,
    frustum_mask,
    layer_occupancy,
    mesh_occupancy,
    plot_iou_histogram,
    score_voxels,
    voxel_iou,
)

__all__ = [
    "COVERAGE_VARIANTS", "EDGE_FACTORS", "GT_KINDS", "OVERHEAD", "PAPER_COVERAGE", "PAPER_PREDICTIONS", "PART_NAMES",
    "PREDICTION_VARIANTS", "EvalView", "EvaluateConfig", "GroundTruthMesh", "LayeredView", "Mesh", "MeshDistance",
    "MeshingConfig", "PointsConfig", "PointsReport", "SurfaceConfig", "SurfaceReport", "Variant", "ViewScores", "ViewVoxelScore", "VoxelConfig",
    "VoxelReport", "VoxelScore", "concatenate", "coverage_views", "default_thresholds", "evaluate_views",
    "frustum_mask", "grid_mesh", "height_map_mesh", "inlier_fraction", "layer_occupancy", "matching_view",
    "mesh_occupancy", "orthographic_mesh", "perspective_mesh", "plot_iou_histogram", "precision_recall",
    "prediction_views", "ray_layers", "sample_surface", "score_parts", "score_store_points", "score_store_voxels", "score_view", "score_voxels",
    "surface_precision_recall", "views_to_score", "voxel_iou",
]
