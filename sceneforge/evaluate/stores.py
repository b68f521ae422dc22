"""Scoring whole stores: which views, checked pairs of prediction and truth, per-view loops.

A store here is anything :func:`sceneforge.store.open_store` returns (``len``, ``names``,
``array``, ``view(i)``, ``mesh(i)``); this module reads views from it and never opens one.
The ground-truth meshes come from ``meshes`` where given (anything with ``mesh(i)``, e.g.
:class:`sceneforge.pipeline.gt_mesh.GroundTruthMeshes`, which makes them from the houses
of a store that keeps none), else from the truth store itself.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from ..errors import SceneforgeError, plural
from .inputs import EvalView, GroundTruthMesh
from .points import INTERSECTION_DEPTH, LayeredView, PointsConfig, PointsReport, score_view
from .voxels import VoxelConfig, VoxelScore, score_voxels


def views_to_score(store, limit: int | None = None, houses: Collection[str] | None = None) -> list[int]:
    """Indices of the views to score: those among the first ``limit`` whose ground truth
    did not fail (a failed view is blank in the store), of ``houses`` (None: any house),
    and, in a store of predictions, that were predicted (its ``prediction`` attribute's
    ``views``; the others are blank)."""
    n = len(store) if limit is None else min(limit, len(store))
    keep = np.ones(n, dtype=bool)
    if "valid" in store.names:
        keep &= np.asarray(store.array("valid")[:n], dtype=bool)
    predicted = predicted_views(store)
    if predicted is not None:
        keep &= np.isin(np.arange(n), predicted)
    if houses is not None:
        ids = np.array([str(h) for h in store.array("house_id")[:n]])
        keep &= np.isin(ids, np.array(sorted(houses), dtype=str))
    return np.flatnonzero(keep).tolist()


def predicted_views(store) -> np.ndarray | None:
    """(k,) int64 the views that a store of predictions predicted (its ``prediction``
    attribute's ``views``; the others are blank), or None for a store of ground truth."""
    predicted = (getattr(store, "attrs", None) or {}).get("prediction", {}).get("views")
    return None if predicted is None else np.asarray(predicted, dtype=np.int64)


def check_predicted(store, i: int) -> None:
    """Raise :class:`SceneforgeError` when ``store`` holds predictions and view ``i`` is not
    one of them (its arrays are blank), naming the views that are."""
    predicted = predicted_views(store)
    if predicted is None or i in predicted:
        return
    split = store.attrs["prediction"].get("split")
    of = f" of the {split} split" if split and split != "all" else ""
    raise SceneforgeError(f"view {i} was not predicted: the store predicts views {_runs(predicted, i)} "
                          f"({plural(len(predicted), 'view')}{of})")


def _runs(views: np.ndarray, near: int, most: int = 8) -> str:
    """``views`` as runs of consecutive indices, ``"0-3, 8, 12-15"``; of many runs the
    ``most`` around ``near``, the others as ``...``."""
    views = np.unique(views)
    if not len(views):
        return "none"
    starts = np.flatnonzero(np.diff(views, prepend=views[0] - 2) != 1)  # the first view starts a run
    runs = [(int(views[a]), int(views[b - 1])) for a, b in zip(starts, [*starts[1:], len(views)])]
    first = min(max(0, int(np.searchsorted([a for a, _ in runs], near)) - most // 2), max(0, len(runs) - most))
    shown = [f"{a}" if a == b else f"{a}-{b}" for a, b in runs[first:first + most]]
    return ", ".join(["..."] * (first > 0) + shown + ["..."] * (first + most < len(runs)))


def empty_views(store, indices: Collection[int]) -> list[int]:
    """Those of ``indices`` whose layers D1..D4 and overhead heights hold no finite value:
    an empty prediction (scored precision 1, recall 0 by convention)."""
    empty = []
    for i in indices:
        depth = np.asarray(store.array("depth")[i][:4])
        height = np.asarray(store.array("overhead_height")[i]) if "overhead_height" in store.names else None
        if not np.isfinite(depth).any() and (height is None or not np.isfinite(height).any()):
            empty.append(int(i))
    return empty


def matching_view(pred, gt, i: int) -> dict:
    """View ``i`` of ``pred``, after checking that it is view ``i`` of ``gt``.

    Raises :class:`SceneforgeError` when ``pred`` has more views than ``gt`` or view ``i``
    shows another house, camera or camera pose.
    """
    if len(pred) > len(gt):
        raise SceneforgeError(f"the predictions have {len(pred)} views but the ground truth only {len(gt)}")
    p, g = pred.view(i), gt.view(i)
    for key in ("house_id", "camera_id"):
        if str(p[key]) != str(g[key]):
            raise SceneforgeError(f"view {i}: {key} {p[key]} in the predictions, {g[key]} in the truth")
    if not np.allclose(p["cam_to_world"], g["cam_to_world"], atol=1e-6):
        raise SceneforgeError(f"view {i}: the predictions come from another camera pose than the truth")
    return p


def check_matching(pred, gt, indices: Collection[int]) -> None:
    """Check that views ``indices`` of ``pred`` are the same views of ``gt`` (house, camera
    and pose), all at once, before anything is scored: :func:`matching_view`'s errors, for
    the first view that differs."""
    if len(pred) > len(gt):
        matching_view(pred, gt, 0)
    rows = np.asarray(sorted(indices), dtype=np.int64)
    if not len(rows):
        return
    for key in ("house_id", "camera_id"):
        p = np.array([str(x) for x in np.asarray(pred.array(key)[:])[rows]])
        g = np.array([str(x) for x in np.asarray(gt.array(key)[:])[rows]])
        if (p != g).any():
            matching_view(pred, gt, int(rows[np.flatnonzero(p != g)[0]]))
    p, g = np.asarray(pred.array("cam_to_world")[:])[rows], np.asarray(gt.array("cam_to_world")[:])[rows]
    far = ~np.isclose(p, g, atol=1e-6).all(axis=(1, 2))
    if far.any():
        matching_view(pred, gt, int(rows[np.flatnonzero(far)[0]]))


def coverage_views(store, limit: int | None = None,
                   meshes=None) -> Iterator[tuple[int, EvalView, GroundTruthMesh]]:
    """``(index, view, ground-truth mesh)`` of every view of ``store`` to score, read lazily
    (what :func:`~sceneforge.evaluate.evaluate_views` takes); the meshes from ``meshes``
    (default: ``store``)."""
    meshes = store if meshes is None else meshes
    for i in views_to_score(store, limit):
        yield i, EvalView.from_arrays(store.view(i)), GroundTruthMesh.from_arrays(meshes.mesh(i))


def prediction_views(pred, gt, limit: int | None = None, houses: Collection[str] | None = None,
                     indices: Collection[int] | None = None,
                     meshes=None) -> Iterator[tuple[int, EvalView, GroundTruthMesh]]:
    """``(index, predicted view, ground-truth mesh)``: the layers and cameras of ``pred``
    against the meshes of ``gt`` (from ``meshes``, default ``gt``), view ``i`` of one checked
    to be view ``i`` of the other; the views of ``houses`` (None: all), or exactly
    ``indices`` when given."""
    meshes = gt if meshes is None else meshes
    for i in (views_to_score(pred, limit, houses) if indices is None else indices):
        yield i, EvalView.from_arrays(matching_view(pred, gt, i)), GroundTruthMesh.from_arrays(meshes.mesh(i))


@dataclass(frozen=True)
class ViewVoxelScore:
    """The voxel score of view ``index`` (house, camera) of a store."""

    index: int
    house_id: str
    camera_id: int
    score: VoxelScore


@dataclass(frozen=True, eq=False)
class VoxelReport:
    """Per-view voxel scores of a store and their mean."""

    views: tuple[ViewVoxelScore, ...]

    @property
    def ious(self) -> np.ndarray:
        """(n,) float64 per-view IoU, NaN for a view without objects in its frustum."""
        return np.asarray([v.score.iou for v in self.views], dtype=np.float64)

    @property
    def scored(self) -> int:
        """Views with a defined IoU."""
        return int(np.isfinite(self.ious).sum())

    @property
    def mean(self) -> float:
        """Mean IoU over the scored views (NaN when none)."""
        ious = self.ious[np.isfinite(self.ious)]
        return float(ious.mean()) if len(ious) else float("nan")


def score_store_voxels(layers, truth=None, config: VoxelConfig | None = None, limit: int | None = None,
                       on_view: Callable[[ViewVoxelScore], None] | None = None, meshes=None) -> VoxelReport:
    """Voxel IoU of the layers of every view of ``layers`` against the solid object mesh of
    the same view of ``truth`` (default: ``layers`` itself, i.e. the ground-truth layers),
    from ``meshes`` (default: the truth store).

    on_view : called with each view's score as soon as it is known
    """
    config = config or VoxelConfig()
    meshes = (layers if truth is None else truth) if meshes is None else meshes
    views = []
    for i in views_to_score(layers, limit):
        view = layers.view(i) if truth is None else matching_view(layers, truth, i)
        mesh = meshes.mesh(i)
        score = ViewVoxelScore(i, str(view["house_id"]), int(view["camera_id"]),
                               score_voxels(view["depth"], view["K"], view["cam_to_world"],
                                            GroundTruthMesh.from_arrays(mesh).objects, config))
        views.append(score)
        if on_view:
            on_view(score)
    return VoxelReport(tuple(views))


def layered_view(store, i: int, intersections: bool = True) -> LayeredView:
    """The layers of view ``i`` of ``store`` to score as points (:class:`~sceneforge.evaluate.points.LayeredView`):
    its ray-intersection layers where it holds them and ``intersections`` is set, else its
    D1..D5; only the arrays needed are read."""
    names = ("depth", "K", *((INTERSECTION_DEPTH,) if intersections and INTERSECTION_DEPTH in store.names else ()))
    return LayeredView.from_arrays({name: np.asarray(store.array(name)[i]) for name in names}, intersections)


def score_store_points(pred, gt, indices: Iterable[int], config: PointsConfig | None = None,
                       seed: int = 0) -> PointsReport:
    """LaRI's layered point scores (docs/spec.md §11.6) of views ``indices`` of the
    predictions ``pred`` against the same views of ``gt`` (the caller checks that they are
    the same views: :func:`check_matching`); each side's layers from :func:`layered_view`.
    View ``i`` draws its samples from ``np.random.default_rng((seed, i))``."""
    config = config or PointsConfig()
    done, scores = [], []
    for i in indices:
        p, g = layered_view(pred, i, config.intersections), layered_view(gt, i, config.intersections)
        if p.layers.shape[1:] != g.layers.shape[1:]:
            raise SceneforgeError(f"view {i}: the prediction's image is {p.layers.shape[2]}x{p.layers.shape[1]} but "
                                  f"the truth's {g.layers.shape[2]}x{g.layers.shape[1]}: the scale-shift fit pairs "
                                  "their pixels")
        scores.append(score_view(p, g, np.random.default_rng((seed, i)), config))
        done.append(i)
    sources = ["intersections" if config.intersections and INTERSECTION_DEPTH in s.names else "layers"
               for s in (pred, gt)]
    return PointsReport.collect(done, scores, config, seed, *sources)
