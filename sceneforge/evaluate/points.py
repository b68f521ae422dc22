"""Layered point metrics the way LaRI scores them (docs/spec.md §11.6).

LaRI (Li et al., 2025, "LaRI: Layered Ray Intersections for Single-view 3D Geometric
Reasoning") scores a view's layers as point sets in the camera frame: the points of the
first layer (**visible**), of the layers behind it (**unseen**) and of all of them
(**all**), each compared with the same set of the ground truth by **Chamfer-L1** (the mean
Euclidean distance from each point to the nearest point of the other set, averaged over
both directions) and by the **F-score** at a threshold (the harmonic mean of precision, the
fraction of predicted points strictly closer than the threshold to the truth, and recall,
the fraction of true points strictly closer than it to the prediction). LaRI scores after
a per-view least-squares **scale and shift**: ``s · p + t · ẑ`` (all coordinates scaled,
the shift along the optical axis only); sceneforge reports the scores before and after it.

A view's layers here are ordered like LaRI's ray intersections: layer 0 the first surface
of each ray, layers 1.. the surfaces behind it. A store's ray-intersection layers
(docs/spec.md §4.7) are that already; the paper's D1..D5 become it with
:func:`ray_layers`. Everything here is pure: arrays in, numbers out
(:func:`sceneforge.evaluate.stores.score_store_points` reads the stores).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..conventions import ENVELOPE_LAYER, OBJECT_SEGMENTS
from ..depth_mesh import perspective_points
from ..errors import MissingDependencyError, plural
from .surface import precision_recall

#: the point sets of a view, in table order: the first surface, the surfaces behind it, both
SPLITS: tuple[str, ...] = ("visible", "unseen", "all")
#: the prediction as predicted, and after the per-view least-squares scale and shift
ALIGNMENTS: tuple[str, ...] = ("none", "scale_shift")
#: where a view's layers come from, and its name in the table: the paper's layers
#: (:func:`ray_layers`) or the store's ray-intersection layers
SOURCES: dict[str, str] = {"layers": "D1-D5", "intersections": "ray intersections"}
#: the store array of the ray-intersection layers (docs/spec.md §4.7), where a store holds them
INTERSECTION_DEPTH = "intersections/depth"


@dataclass(frozen=True)
class PointsConfig:
    """How layered point sets are scored (LaRI's Chamfer-L1 and F-score)."""

    #: points drawn per view from each point set (visible, unseen, all; prediction and truth apart),
    #: without replacement; a set with fewer points is used whole (LaRI's scenes: 100 000)
    samples: int = 100_000
    #: F-score thresholds, metres (LaRI's scenes: 0.1, 0.05, 0.02)
    thresholds: tuple[float, ...] = (0.1, 0.05, 0.02)
    #: read a store's ray-intersection layers (intersections/depth) where it holds them, instead of its D1..D5
    intersections: bool = True

    def __post_init__(self):
        if not self.samples >= 1:
            raise ValueError(f"samples must be >= 1 point per set, got {self.samples}")
        t = np.asarray(self.thresholds, dtype=np.float64)
        if t.ndim != 1 or not len(t) or not (t > 0).all():
            raise ValueError(f"thresholds must be one or more distances > 0 m, got {self.thresholds}")


def ray_layers(depth: np.ndarray) -> np.ndarray:
    """The paper's layers ordered as a ray's surfaces: the first one, then those behind it.

    depth : (5, H, W) float  planar depth of D1..D5, metres; NaN = none

    Returns (5, H, W) float32: layer 0 the first surface (D1, else D5 where D1 is NaN);
    layers 1..4 the others: D2 (NaN where it equals D1: a single-sided sheet, one surface),
    D3, D4 (NaN where it equals D3) and D5 (NaN where it is layer 0). NaN = none.
    """
    depth = np.asarray(depth, dtype=np.float32)
    if depth.ndim != 3 or depth.shape[0] != 5:
        raise ValueError(f"depth must be the five layers D1..D5, (5, H, W), got {depth.shape}")
    out = np.full_like(depth, np.nan)
    no_object = np.isnan(depth[0])
    out[0] = np.where(no_object, depth[ENVELOPE_LAYER], depth[0])
    for entry, exit_ in OBJECT_SEGMENTS:
        if entry:
            out[entry] = depth[entry]
        out[exit_] = np.where(depth[exit_] == depth[entry], np.nan, depth[exit_])
    out[ENVELOPE_LAYER] = np.where(no_object, np.nan, depth[ENVELOPE_LAYER])
    return out


def camera_points(layers: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points of layered planar depth (OpenCV axes, pixel centres at integer + 0.5).

    layers : (L, H, W) float  planar depth, metres; NaN = none
    K      : (3, 3) float     intrinsics

    Returns (L, H, W, 3) float64, NaN where the depth is.
    """
    layers = np.asarray(layers)
    if layers.ndim != 3 or not len(layers):
        raise ValueError(f"layers must be (L, H, W) with L >= 1, got {layers.shape}")
    return np.stack([perspective_points(d, K, np.eye(4)) for d in layers])


def split_points(points: np.ndarray) -> dict[str, np.ndarray]:
    """The point sets of :data:`SPLITS`: (n, 3) float64 each, of (L, H, W, 3) layered points
    (NaN = none): layer 0 is visible, layers 1.. unseen, all both."""
    finite = np.isfinite(points).all(axis=-1)
    visible, unseen = points[:1][finite[:1]], points[1:][finite[1:]]
    return {"visible": visible, "unseen": unseen, "all": np.concatenate([visible, unseen])}


def nearest_distances(points: np.ndarray, to: np.ndarray) -> np.ndarray:
    """(n,) float64 Euclidean distance of each of ``points`` (n, 3) to its nearest neighbour
    in ``to`` (m, 3); inf when ``to`` is empty. Exact (Open3D's KD-tree)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(to, dtype=np.float64).reshape(-1, 3)
    if not len(q):
        return np.full(len(p), np.inf)
    if not len(p):
        return np.zeros(0)
    try:
        import open3d as o3d
    except ImportError:
        raise MissingDependencyError("open3d", "point set distances", "pip install 'sceneforge[trace]'") from None
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(p)))
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(q)))
    return np.asarray(cloud.compute_point_cloud_distance(target), dtype=np.float64)


@dataclass(frozen=True)
class SetScore:
    """One predicted point set against one true set.

    chamfer   : float         Chamfer-L1, metres: (mean pred→truth + mean truth→pred
                nearest-neighbour distance) / 2; NaN when either set is empty
    precision : (t,) float64  fraction of predicted points strictly closer than each
                threshold to the truth (1 when there is no predicted point)
    recall    : (t,) float64  fraction of true points strictly closer than it to the
                prediction (NaN when there is no true point)
    fscore    : (t,) float64  2PR / (P + R), 0 where P + R = 0, NaN where recall is
    """

    chamfer: float
    precision: np.ndarray
    recall: np.ndarray
    fscore: np.ndarray


def fscore(precision: np.ndarray, recall: np.ndarray) -> np.ndarray:
    """(t,) float64 harmonic mean 2PR / (P + R) of (t,) precision and recall; 0 where both
    are 0, NaN where either is."""
    p, r = np.asarray(precision, dtype=np.float64), np.asarray(recall, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(p + r > 0, 2 * p * r / (p + r), np.where(np.isnan(p + r), np.nan, 0.0))


def chamfer_fscore(pred: np.ndarray, gt: np.ndarray, thresholds) -> SetScore:
    """Chamfer-L1 and precision, recall and F-score at ``thresholds`` (t,) metres of the
    predicted points ``pred`` (n, 3) against the true points ``gt`` (m, 3)."""
    pred_to_gt, gt_to_pred = nearest_distances(pred, gt), nearest_distances(gt, pred)
    chamfer = (pred_to_gt.mean() + gt_to_pred.mean()) / 2 if len(pred_to_gt) and len(gt_to_pred) else math.nan
    precision, recall = precision_recall(pred_to_gt, gt_to_pred, thresholds)
    return SetScore(float(chamfer), precision, recall, fscore(precision, recall))


def fit_scale_shift(pred: np.ndarray, gt: np.ndarray) -> tuple[float, float] | None:
    """LaRI's alignment: the ``(s, t)`` minimising ``Σ ‖s · p + t · ẑ − g‖²`` over pairs of
    camera-frame points ``pred`` (n, 3) and ``gt`` (n, 3) (ẑ the optical axis); None when
    the normal equations are singular (their determinant is not > 0, e.g. no pair)."""
    p = np.asarray(pred, dtype=np.float64).reshape(-1, 3)
    g = np.asarray(gt, dtype=np.float64).reshape(-1, 3)
    if p.shape != g.shape:
        raise ValueError(f"pred and gt must be pairs of points, got {p.shape} and {g.shape}")
    a00, a01, a11 = (p * p).sum(), p[:, 2].sum(), float(len(p))
    b0, b1 = (p * g).sum(), g[:, 2].sum()
    det = a00 * a11 - a01 * a01
    if not det > 0:
        return None
    return float((a11 * b0 - a01 * b1) / det), float((a00 * b1 - a01 * b0) / det)


def apply_scale_shift(points: np.ndarray, scale: float, shift: float) -> np.ndarray:
    """(..., 3) float64 ``scale · p + shift · ẑ`` of camera-frame ``points`` (..., 3)."""
    out = np.asarray(points, dtype=np.float64) * scale
    out[..., 2] += shift
    return out


def subsample(points: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` of ``points`` (m, 3) drawn without replacement, or all of them when m <= n."""
    if len(points) <= n:
        return points
    return points[np.sort(rng.choice(len(points), n, replace=False))]


@dataclass(frozen=True)
class LayeredView:
    """One side of a view to score: its layered depth and intrinsics.

    layers : (L, H, W) float32  planar depth, metres; layer 0 each ray's first surface,
             layers 1.. the surfaces behind it (:func:`ray_layers`); NaN = none
    K      : (3, 3) float64     intrinsics, pixel centres at integer + 0.5
    source : ``"layers"`` (the paper's D1..D5) or ``"intersections"`` (:data:`SOURCES`)
    """

    layers: np.ndarray
    K: np.ndarray
    source: str

    def __post_init__(self):
        layers = np.asarray(self.layers, dtype=np.float32)
        if layers.ndim != 3 or not len(layers):
            raise ValueError(f"layers must be (L, H, W) with L >= 1, got {layers.shape}")
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must be (3, 3), got {K.shape}")
        if self.source not in SOURCES:
            raise ValueError(f"source must be one of {', '.join(SOURCES)}, got {self.source!r}")
        object.__setattr__(self, "layers", layers)
        object.__setattr__(self, "K", K)

    @classmethod
    def from_arrays(cls, view: Mapping[str, np.ndarray], intersections: bool = True) -> "LayeredView":
        """From one view's arrays (``depth`` (5, H, W), ``K``, and ``intersections/depth``
        (L, H, W) where the store holds it): its ray-intersection layers when there are
        some and ``intersections`` is set, else its D1..D5 as :func:`ray_layers`."""
        if intersections and INTERSECTION_DEPTH in view:
            return cls(view[INTERSECTION_DEPTH], view["K"], "intersections")
        return cls(ray_layers(view["depth"]), view["K"], "layers")


@dataclass(frozen=True)
class ViewPointScores:
    """The scores of one view.

    chamfer       : (2, 3) float64     Chamfer-L1 by :data:`ALIGNMENTS` × :data:`SPLITS`
    precision, recall, fscore : (2, 3, t) float64  at the config's thresholds
    scale, shift  : the fitted alignment (NaN when it could not be fitted: every
                    scale-shift score is NaN then)
    pred_points, gt_points : (3,) int64  points in each set before subsampling
    """

    chamfer: np.ndarray
    precision: np.ndarray
    recall: np.ndarray
    fscore: np.ndarray
    scale: float
    shift: float
    pred_points: np.ndarray
    gt_points: np.ndarray


def score_view(pred: LayeredView, gt: LayeredView, rng: np.random.Generator,
               config: PointsConfig | None = None) -> ViewPointScores:
    """Score a view's predicted layers against its true ones, before and after the
    scale-shift fit (on the pixels where both first layers are finite; both sides must have
    the same image size).

    Draws from ``rng``, in :data:`SPLITS` order, each set's truth sample and then its
    prediction sample; the aligned prediction is the same sample, scaled and shifted.
    """
    config = config or PointsConfig()
    if pred.layers.shape[1:] != gt.layers.shape[1:]:
        raise ValueError(f"the prediction's image is {pred.layers.shape[1:]} but the truth's "
                         f"{gt.layers.shape[1:]}: the alignment pairs their pixels")
    pred_points, gt_points = camera_points(pred.layers, pred.K), camera_points(gt.layers, gt.K)
    both = np.isfinite(pred_points[0]).all(axis=-1) & np.isfinite(gt_points[0]).all(axis=-1)
    fit = fit_scale_shift(pred_points[0][both], gt_points[0][both])
    pred_sets, gt_sets = split_points(pred_points), split_points(gt_points)
    t = len(config.thresholds)
    chamfer = np.full((len(ALIGNMENTS), len(SPLITS)), np.nan)
    prf = np.full((3, len(ALIGNMENTS), len(SPLITS), t), np.nan)
    for k, split in enumerate(SPLITS):
        g = subsample(gt_sets[split], config.samples, rng)
        p = subsample(pred_sets[split], config.samples, rng)
        for a, points in enumerate((p, None if fit is None else apply_scale_shift(p, *fit))):
            if points is None:
                continue
            s = chamfer_fscore(points, g, config.thresholds)
            chamfer[a, k] = s.chamfer
            prf[:, a, k] = s.precision, s.recall, s.fscore
    scale, shift = (math.nan, math.nan) if fit is None else fit
    return ViewPointScores(chamfer, *prf, scale, shift,
                           np.array([len(pred_sets[s]) for s in SPLITS]), np.array([len(gt_sets[s]) for s in SPLITS]))


def _nanmean(x: np.ndarray) -> np.ndarray:
    """Mean over the first axis, leaving out NaN (NaN where every entry is)."""
    n = np.isfinite(x).sum(axis=0)
    return np.where(n > 0, np.nansum(x, axis=0) / np.maximum(n, 1), np.nan)


@dataclass(frozen=True, eq=False)
class PointsReport:
    """Layered point scores of many views and their means.

    indices : (n,) int64  the views scored
    chamfer : (n, 2, 3) float64; precision, recall, fscore : (n, 2, 3, t) float64, by view,
              :data:`ALIGNMENTS`, :data:`SPLITS` (and threshold)
    scale, shift : (n,) float64  each view's fitted alignment (NaN: not fitted)
    pred_source, gt_source : where the layers came from (:data:`SOURCES`)
    """

    indices: np.ndarray
    chamfer: np.ndarray
    precision: np.ndarray
    recall: np.ndarray
    fscore: np.ndarray
    scale: np.ndarray
    shift: np.ndarray
    config: PointsConfig
    seed: int
    pred_source: str
    gt_source: str

    @classmethod
    def collect(cls, indices: Sequence[int], scores: Sequence[ViewPointScores], config: PointsConfig, seed: int,
                pred_source: str, gt_source: str) -> "PointsReport":
        t = len(config.thresholds)

        def stack(name, shape):
            return np.stack([getattr(s, name) for s in scores]) if scores else np.zeros((0, *shape))

        shape = (len(ALIGNMENTS), len(SPLITS), t)
        return cls(np.asarray(indices, dtype=np.int64), stack("chamfer", shape[:2]), stack("precision", shape),
                   stack("recall", shape), stack("fscore", shape),
                   np.array([s.scale for s in scores]), np.array([s.shift for s in scores]),
                   config, seed, pred_source, gt_source)

    @property
    def n_views(self) -> int:
        return len(self.indices)

    def table(self) -> dict[str, np.ndarray]:
        """Means over the views where each is defined: ``chamfer`` (2, 3), ``precision``,
        ``recall``, ``fscore`` (2, 3, t); ``views`` (2, 3) int64 the views with a defined
        F-score, ``chamfer_views`` (2, 3) those with a defined Chamfer-L1 (neither set empty)."""
        return {"chamfer": _nanmean(self.chamfer), "precision": _nanmean(self.precision),
                "recall": _nanmean(self.recall), "fscore": _nanmean(self.fscore),
                "views": np.isfinite(self.fscore[..., 0]).sum(axis=0),
                "chamfer_views": np.isfinite(self.chamfer).sum(axis=0)}

    def to_dict(self) -> dict:
        """JSON-ready: the config, then per alignment and point set the means (F-score,
        precision and recall by threshold) and the views they are over."""
        table = self.table()
        keys = [f"{t:g}" for t in self.config.thresholds]
        out: dict = {"views": self.n_views, "seed": self.seed, "samples": self.config.samples,
                     "thresholds": list(self.config.thresholds), "prediction": self.pred_source,
                     "truth": self.gt_source, "aligned_views": int(np.isfinite(self.scale).sum())}
        for a, alignment in enumerate(ALIGNMENTS):
            out[alignment] = {
                split: {"chamfer_l1": _json(table["chamfer"][a, k]),
                        **{name: dict(zip(keys, map(_json, table[name][a, k])))
                           for name in ("fscore", "precision", "recall")},
                        "views": int(table["views"][a, k]), "chamfer_views": int(table["chamfer_views"][a, k])}
                for k, split in enumerate(SPLITS)}
        return out

    def text(self) -> str:
        """The table: Chamfer-L1 and F-score at each threshold, by point set and alignment."""
        table = self.table()
        heads = [f"F@{t * 100:g}cm" for t in self.config.thresholds]
        lines = [f"layered points (LaRI): Chamfer-L1 (m) and F-score, mean over {plural(self.n_views, 'view')}, "
                 f"at most {self.config.samples} points per set",
                 f"truth: {SOURCES[self.gt_source]}, prediction: {SOURCES[self.pred_source]}; visible: each ray's "
                 "first surface, unseen: those behind it",
                 f"{'points':<9}{'alignment':<13}{'chamfer':>8}" + "".join(f"{h:>9}" for h in heads) + f"{'views':>7}"]
        for k, split in enumerate(SPLITS):
            for a, alignment in enumerate(ALIGNMENTS):
                lines.append(f"{split:<9}{alignment.replace('_', '-'):<13}{_fmt(table['chamfer'][a, k]):>8}"
                             + "".join(f"{_fmt(f):>9}" for f in table["fscore"][a, k])
                             + f"{table['views'][a, k]:>7}")
        if (table["chamfer_views"] < table["views"]).any():
            lines.append("a view with an empty predicted set has F-score 0 and no Chamfer-L1: the Chamfer "
                         "means are over fewer views (--json: chamfer_views)")
        unaligned = self.n_views - int(np.isfinite(self.scale).sum())
        if unaligned:
            lines.append(f"scale-shift: not fitted on {plural(unaligned, 'view')} (no first-surface pixel "
                         "in both): left out of its rows")
        return "\n".join(lines)


def _fmt(x) -> str:
    return "—" if x is None or not np.isfinite(x) else f"{x:.3f}"


def _json(x) -> float | None:
    return float(x) if np.isfinite(x) else None
