"""Surface precision and recall between triangle meshes (docs/spec.md §11.2, paper §5).

Points are sampled uniformly by area on one mesh (``density`` per m², the number of
samples rounded down as in the reference) and their distance to the other mesh is
measured. **Recall** is the fraction of ground-truth samples closer than a threshold to
the prediction, **precision** the fraction of predicted samples closer than it to the
ground truth (strictly closer, as in the reference). An empty prediction has precision 1
and recall 0; an empty ground truth leaves recall undefined (NaN).

Distances come from Open3D's ``RaycastingScene.compute_distance`` (Embree BVH, float32):
coordinates are shifted to the mesh's centre first, so rounding is at the scale of the
mesh and not of its distance from the world origin.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import MissingDependencyError
from ..frustum import triangle_areas
from .depth_mesh import Mesh


def default_thresholds() -> tuple[float, ...]:
    """Match thresholds of the curves: 61 steps from 1 mm to 1 m, evenly in log, plus 5 cm."""
    return tuple(float(t) for t in np.unique(np.r_[np.geomspace(1e-3, 1.0, 61), 0.05]))


@dataclass(frozen=True)
class SurfaceConfig:
    """How surfaces are sampled and compared."""

    #: samples per square metre of surface
    density: float = 10_000.0
    #: match thresholds of the precision/recall curves, metres, ascending
    thresholds: tuple[float, ...] = field(default_factory=default_thresholds)
    #: the threshold of the tables, metres (the paper's 5 cm)
    threshold: float = 0.05

    def __post_init__(self):
        if not self.density > 0:
            raise ValueError(f"density must be > 0 samples/m², got {self.density}")
        t = np.asarray(self.thresholds, dtype=np.float64)
        if t.ndim != 1 or not len(t) or not (t > 0).all() or (np.diff(t) <= 0).any():
            raise ValueError(f"thresholds must be ascending and > 0, got {self.thresholds}")
        if not self.threshold > 0:
            raise ValueError(f"threshold must be > 0 m, got {self.threshold}")


def sample_surface(mesh: Mesh, density: float, rng: np.random.Generator) -> np.ndarray:
    """Points drawn uniformly by area on ``mesh``: ``floor(area × density)`` of them, at
    least one when the mesh has any area.

    Returns (n, 3) float64 world points, grouped by face.
    """
    tris = mesh.triangles
    area = triangle_areas(tris)
    total = float(area.sum())
    if not total > 0:
        return np.zeros((0, 3))
    n = max(int(total * density), 1)
    counts = rng.multinomial(n, area / total)
    corners = np.repeat(tris, counts, axis=0)
    uv = rng.random((n, 2))
    flip = uv.sum(axis=1) > 1
    uv[flip] = 1.0 - uv[flip]
    return (corners[:, 0] + uv[:, :1] * (corners[:, 1] - corners[:, 0])
            + uv[:, 1:] * (corners[:, 2] - corners[:, 0]))


class MeshDistance:
    """Unsigned distance from points to one triangle mesh; build once, query many times.

    mesh : the surface; an empty mesh is infinitely far from everything
    """

    def __init__(self, mesh: Mesh):
        self._scene = None
        if not len(mesh):
            return
        try:
            import open3d as o3d
        except ImportError:
            raise MissingDependencyError(
                "open3d", "surface distances", "pip install 'sceneforge[trace]'"
            ) from None
        self._o3d = o3d
        v = mesh.vertices
        self._shift = 0.5 * (v.min(axis=0) + v.max(axis=0))
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(v - self._shift, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(mesh.faces, dtype=np.uint32)),
        )

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(n,) float64 distance of each (n, 3) world point to the surface."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if self._scene is None:
            return np.full(len(p), np.inf)
        if not len(p):
            return np.zeros(0)
        query = self._o3d.core.Tensor(np.ascontiguousarray(p - self._shift, dtype=np.float32))
        return self._scene.compute_distance(query).numpy().astype(np.float64)


def inlier_fraction(distances: np.ndarray, thresholds) -> np.ndarray:
    """(t,) float64 fraction of ``distances`` (n,) strictly below each of ``thresholds`` (t,)
    (any order); NaN when n = 0. One pass over the distances, no sort: a view has millions."""
    d = np.asarray(distances, dtype=np.float64).ravel()
    t = np.asarray(thresholds, dtype=np.float64).ravel()
    if not len(d):
        return np.full(t.shape, np.nan)
    order = np.argsort(t)
    # d is below sorted threshold k for every k at or after the number of thresholds <= d
    first = np.searchsorted(t[order], d, side="right")
    out = np.empty(len(t))
    out[order] = np.cumsum(np.bincount(first, minlength=len(t) + 1))[:-1] / len(d)
    return out


def precision_recall(
    pred_to_gt: np.ndarray, gt_to_pred: np.ndarray, thresholds
) -> tuple[np.ndarray, np.ndarray]:
    """Precision and recall curves from sample distances.

    pred_to_gt : (n,) float  distance of each predicted sample to the ground truth
    gt_to_pred : (m,) float  distance of each ground-truth sample to the prediction
    thresholds : (t,) float  metres

    Returns precision (t,) and recall (t,) float64. No predicted samples: precision 1
    and recall 0. No ground-truth samples: recall NaN.
    """
    t = np.asarray(thresholds, dtype=np.float64)
    if not len(pred_to_gt):
        recall = np.zeros(t.shape) if len(gt_to_pred) else np.full(t.shape, np.nan)
        return np.ones(t.shape), recall
    return inlier_fraction(pred_to_gt, t), inlier_fraction(gt_to_pred, t)


def surface_precision_recall(
    pred: Mesh, gt: Mesh, rng: np.random.Generator, config: SurfaceConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Precision and recall curves (t,) float64 of ``pred`` against ``gt`` at ``config.thresholds``."""
    config = config or SurfaceConfig()
    pred_samples = sample_surface(pred, config.density, rng)
    gt_samples = sample_surface(gt, config.density, rng)
    return precision_recall(MeshDistance(gt)(pred_samples), MeshDistance(pred)(gt_samples), config.thresholds)
