"""Surface precision/recall of layer reconstructions: the coverage table and the predictions table.

A view's reconstruction is the union, in world coordinates, of the meshes of some of its
parts (:data:`~sceneforge.evaluate.inputs.PART_NAMES`: D1..D5 from the frontal camera and
the overhead height map). A **variant** names the parts it unites, e.g. ``D1-4 &
overhead``. Every variant is scored against two ground truths: the objects and the room
envelope together (``all``), and the objects alone (``objects``).

Each part is sampled and measured once per view and the variants are assembled from
those: the samples of a union are the union of its parts' samples (same density), and a
point's distance to a union is the smallest of its distances to the parts.

- **Coverage** (paper Table 1): the variants D1, D1-2, D1-3, D1-4, D1-5 and D1-5 &
  overhead built from *ground-truth* layers; the table is their recall at 5 cm against
  ``all``, averaged over views.
- **Predictions** (the precision/recall table of paper §5): D1, D1 & overhead, D1-4 and
  D1-4 & overhead built from *predicted* layers; the table is their precision and recall
  at 5 cm against ``objects``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Iterable, Sequence

import numpy as np

from ..errors import MissingDependencyError
from .depth_mesh import Mesh, MeshingConfig
from .inputs import OVERHEAD, PART_NAMES, EvalView, GroundTruthMesh
from .surface import MeshDistance, SurfaceConfig, precision_recall, sample_surface

if TYPE_CHECKING:
    import matplotlib.figure

#: The ground truths a variant is scored against: objects + envelope, objects only.
GT_KINDS: tuple[str, ...] = ("all", "objects")


@dataclass(frozen=True)
class Variant:
    """A reconstruction made of some parts of a view (names from ``PART_NAMES``)."""

    name: str
    parts: tuple[str, ...]

    def __post_init__(self):
        unknown = set(self.parts) - set(PART_NAMES)
        if unknown or not self.parts:
            raise ValueError(f"variant {self.name!r}: parts must be among {PART_NAMES}, got {self.parts}")


COVERAGE_VARIANTS: tuple[Variant, ...] = (
    Variant("D1", ("D1",)),
    Variant("D1-2", ("D1", "D2")),
    Variant("D1-3", ("D1", "D2", "D3")),
    Variant("D1-4", ("D1", "D2", "D3", "D4")),
    Variant("D1-5", ("D1", "D2", "D3", "D4", "D5")),
    Variant("D1-5 & overhead", ("D1", "D2", "D3", "D4", "D5", OVERHEAD)),
)
#: Paper Table 1: recall at 5 cm of ground-truth layers against objects + envelope, SUNCG.
PAPER_COVERAGE: dict[str, float] = {
    "D1": 0.237, "D1-2": 0.427, "D1-3": 0.450, "D1-4": 0.480, "D1-5": 0.924, "D1-5 & overhead": 0.932,
}

PREDICTION_VARIANTS: tuple[Variant, ...] = (
    Variant("D1", ("D1",)),
    Variant("D1 & overhead", ("D1", OVERHEAD)),
    Variant("D1-4", ("D1", "D2", "D3", "D4")),
    Variant("D1-4 & overhead", ("D1", "D2", "D3", "D4", OVERHEAD)),
)
#: The precision/recall table of paper §5: (precision, recall) at 5 cm of predicted layers
#: against objects, SUNCG.
PAPER_PREDICTIONS: dict[str, tuple[float, float]] = {
    "D1": (0.525, 0.212), "D1 & overhead": (0.553, 0.275),
    "D1-4": (0.499, 0.417), "D1-4 & overhead": (0.519, 0.457),
}


@dataclass(frozen=True, eq=False)
class ViewScores:
    """Precision and recall of every variant of one view.

    precision, recall : (n_variants, 2, t) float64  against ``GT_KINDS`` (all, objects) at
                        the thresholds; NaN recall where that ground truth is empty
    """

    precision: np.ndarray
    recall: np.ndarray


def score_parts(
    parts: dict[str, Mesh],
    gt: GroundTruthMesh,
    variants: Sequence[Variant],
    rng: np.random.Generator,
    thresholds,
    density: float = SurfaceConfig.density,
) -> ViewScores:
    """Precision and recall of unions of ``parts`` (name → world mesh) against ``gt``.

    Draws, in this order, the ground-truth object samples, the envelope samples, then each
    used part's samples in ``PART_NAMES`` order, all from ``rng``.
    """
    thresholds = np.asarray(thresholds, dtype=np.float64)
    gt_objects = sample_surface(gt.objects, density, rng)
    gt_all = np.concatenate([gt_objects, sample_surface(gt.envelope, density, rng)])
    n_objects = len(gt_objects)
    to_objects, to_envelope = MeshDistance(gt.objects), MeshDistance(gt.envelope)

    used = [p for p in PART_NAMES if any(p in v.parts for v in variants)]
    pred_to_objects, pred_to_all, gt_to_part = {}, {}, {}
    for name in used:
        samples = sample_surface(parts[name], density, rng)
        pred_to_objects[name] = to_objects(samples)
        pred_to_all[name] = np.minimum(pred_to_objects[name], to_envelope(samples))
        gt_to_part[name] = MeshDistance(parts[name])(gt_all)

    precision = np.empty((len(variants), len(GT_KINDS), len(thresholds)))
    recall = np.empty_like(precision)
    for i, variant in enumerate(variants):
        gt_to_pred = np.minimum.reduce([gt_to_part[p] for p in variant.parts])
        # GT_KINDS order: objects + envelope, then objects (the first n_objects GT samples)
        for k, (to_gt, gt_dist) in enumerate(((pred_to_all, gt_to_pred),
                                              (pred_to_objects, gt_to_pred[:n_objects]))):
            pred_dist = np.concatenate([to_gt[p] for p in variant.parts])
            precision[i, k], recall[i, k] = precision_recall(pred_dist, gt_dist, thresholds)
    return ViewScores(precision, recall)


def score_view(
    view: EvalView,
    gt: GroundTruthMesh,
    variants: Sequence[Variant],
    rng: np.random.Generator,
    config: SurfaceConfig | None = None,
    meshing: MeshingConfig | None = None,
) -> ViewScores:
    """Mesh a view's layers and score ``variants`` at ``config.thresholds`` followed by
    ``config.threshold`` (the last entry of the threshold axis)."""
    config = config or SurfaceConfig()
    parts = view.meshes(meshing)
    return score_parts(parts, gt, variants, rng, np.r_[config.thresholds, config.threshold], config.density)


def evaluate_views(
    views: Iterable[tuple[int, EvalView, GroundTruthMesh]],
    variants: Sequence[Variant],
    seed: int,
    config: SurfaceConfig | None = None,
    meshing: MeshingConfig | None = None,
) -> SurfaceReport:
    """Score ``variants`` on every ``(index, view, ground-truth mesh)``.

    View ``index`` draws its samples from ``np.random.default_rng((seed, index))``, so its
    scores do not depend on which other views are evaluated.
    """
    config, meshing = config or SurfaceConfig(), meshing or MeshingConfig()
    scores = [score_view(view, gt, variants, np.random.default_rng((seed, index)), config, meshing)
              for index, view, gt in views]
    return SurfaceReport.collect(scores, variants, config, meshing, seed)


@dataclass(frozen=True, eq=False)
class SurfaceReport:
    """Precision/recall of variants over many views.

    variants   : the variants, in table order
    thresholds : (t,) float64  curve thresholds, metres
    threshold  : the table threshold, metres
    precision, recall : (n_views, n_variants, 2, t + 1) float64; the last threshold entry is
                 ``threshold``; the axis of size 2 is ``GT_KINDS``
    config, meshing, seed : how it was computed
    """

    variants: tuple[Variant, ...]
    precision: np.ndarray
    recall: np.ndarray
    config: SurfaceConfig = field(default_factory=SurfaceConfig)
    meshing: MeshingConfig = field(default_factory=MeshingConfig)
    seed: int | None = None

    @classmethod
    def collect(cls, scores: Sequence[ViewScores], variants, config: SurfaceConfig,
                meshing: MeshingConfig, seed: int | None) -> "SurfaceReport":
        t = len(config.thresholds) + 1
        shape = (0, len(variants), len(GT_KINDS), t)
        p = np.stack([s.precision for s in scores]) if scores else np.zeros(shape)
        r = np.stack([s.recall for s in scores]) if scores else np.zeros(shape)
        return cls(tuple(variants), p, r, config, meshing, seed)

    @property
    def n_views(self) -> int:
        return len(self.precision)

    def table(self, kind: str) -> tuple[np.ndarray, np.ndarray]:
        """Mean precision and recall (n_variants,) at the table threshold over views with
        that ground truth (``kind`` in ``GT_KINDS``)."""
        k = GT_KINDS.index(kind)
        return _nanmean(self.precision[:, :, k, -1]), _nanmean(self.recall[:, :, k, -1])

    def curves(self, kind: str) -> tuple[np.ndarray, np.ndarray]:
        """Mean precision and recall curves (n_variants, t) against ``kind``."""
        k = GT_KINDS.index(kind)
        return _nanmean(self.precision[:, :, k, :-1]), _nanmean(self.recall[:, :, k, :-1])

    def to_dict(self) -> dict:
        """JSON-ready summary: config, seed, per-variant table values and mean curves."""
        out = {"views": self.n_views, "seed": self.seed, "density": self.config.density,
               "threshold": self.config.threshold, "preset": self.meshing.preset,
               "a": {part: self.meshing.edge_factor(part) for part in PART_NAMES},
               "min_height": self.meshing.min_height, "thresholds": list(self.config.thresholds),
               "variants": {}}
        for i, v in enumerate(self.variants):
            entry = out["variants"][v.name] = {"parts": list(v.parts)}
            for kind in GT_KINDS:
                p, r = self.table(kind)
                cp, cr = self.curves(kind)
                entry[kind] = {"precision": _json(p[i]), "recall": _json(r[i]),
                               "precision_curve": [_json(x) for x in cp[i]],
                               "recall_curve": [_json(x) for x in cr[i]]}
        return out

    def coverage_text(self) -> str:
        """The coverage table (paper Table 1) beside the paper's SUNCG numbers."""
        p_all, r_all = self.table("all")
        _, r_obj = self.table("objects")
        cm = f"{self.config.threshold * 100:g} cm"
        lines = [f"coverage: recall at {cm} of meshes from ground-truth layers, "
                 f"mean over {self.n_views} views",
                 f"meshing: {self.meshing.describe()}",
                 f"{'layers':<18}{'recall':>8}{'paper':>8}{'objects':>10}{'precision':>11}",
                 f"{'':<18}{'all':>8}{'SUNCG':>8}{'recall':>10}{'all':>11}"]
        for i, v in enumerate(self.variants):
            paper = PAPER_COVERAGE.get(v.name)
            lines.append(f"{v.name:<18}{_fmt(r_all[i]):>8}{_fmt(paper):>8}{_fmt(r_obj[i]):>10}{_fmt(p_all[i]):>11}")
        return "\n".join(lines)

    def predictions_text(self) -> str:
        """The predictions table (objects only) beside the paper's SUNCG numbers (paper §5)."""
        p, r = self.table("objects")
        cm = f"{self.config.threshold * 100:g} cm"
        lines = [f"predictions: precision and recall at {cm} against objects, mean over {self.n_views} views",
                 f"meshing: {self.meshing.describe()}",
                 f"{'layers':<18}{'precision':>10}{'recall':>8}{'paper P':>9}{'paper R':>9}"]
        for i, v in enumerate(self.variants):
            pp, pr = PAPER_PREDICTIONS.get(v.name, (None, None))
            lines.append(f"{v.name:<18}{_fmt(p[i]):>10}{_fmt(r[i]):>8}{_fmt(pp):>9}{_fmt(pr):>9}")
        return "\n".join(lines)

    def plot(self, title: str = "") -> "matplotlib.figure.Figure":
        """Precision and recall against the threshold (log scale), one line per variant,
        against objects + envelope (top) and objects (bottom). Needs matplotlib."""
        try:
            from matplotlib.figure import Figure
        except ImportError as e:
            raise MissingDependencyError("matplotlib", "plotting", "pip install 'sceneforge[plot]'") from e
        fig = Figure(figsize=(10, 8), layout="constrained")
        axes = fig.subplots(2, 2, sharex=True, sharey=True)
        t = np.asarray(self.config.thresholds)
        for row, kind in enumerate(GT_KINDS):
            p, r = self.curves(kind)
            for col, (name, values) in enumerate((("precision", p), ("recall", r))):
                ax = axes[row, col]
                for i, v in enumerate(self.variants):
                    ax.plot(t, values[i], label=v.name)
                ax.axvline(self.config.threshold, color="0.6", lw=0.8, ls="--")
                ax.set_xscale("log")
                ax.set_ylim(0, 1.02)
                ax.grid(True, which="both", alpha=0.3)
                ax.set_title(f"{name} — {'objects + envelope' if kind == 'all' else 'objects'}")
                if row == 1:
                    ax.set_xlabel("match threshold (m)")
        axes[0, 0].legend(loc="lower right", fontsize="small")
        fig.suptitle(title or f"{self.n_views} views, {self.config.density:g} samples/m²")
        return fig


def _nanmean(a: np.ndarray) -> np.ndarray:
    """Mean over the first axis ignoring NaN, NaN (without a warning) where all are NaN."""
    finite = np.isfinite(a)
    n = finite.sum(axis=0)
    total = np.where(finite, a, 0.0).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, total / np.maximum(n, 1), np.nan)


def _fmt(x) -> str:
    return "—" if x is None or not np.isfinite(x) else f"{x:.3f}"


def _json(x) -> float | None:
    return float(x) if np.isfinite(x) else None
