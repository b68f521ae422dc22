"""The operating point of a prediction: how sure the segmentation nets must be for a pixel to
be kept, chosen on the run's own validation houses (docs/learning.md, "Operating point").

The nets keep a frontal pixel of D1..D4 (an overhead height) where the segmentation's
arg-max is an object, and, with a threshold, where its object probability (1 − P(background))
is at least that (:func:`~.networks.object_pixels`). A higher threshold keeps fewer, surer
pixels: precision for recall. A threshold tuned on one seed's test houses does not carry to
another seed, so ``sceneforge predict --operating-point validation`` chooses it per run:

1. the views of the run's **validation** houses (never trained on, never tested on; at most
   ``views`` of them, evenly spread) are predicted once, keeping each pixel's object
   probability;
2. every pair of thresholds of :data:`GRID` (frontal × overhead) is scored the way
   ``sceneforge evaluate predictions`` scores predictions: precision and recall at 5 cm of
   the meshes of D1-4 & overhead against the objects, mean over the views;
3. **the rule**: the pair where precision meets recall — the largest min(precision, recall);
   ties go to the lower thresholds (more recall).

Each threshold pair is scored from one set of samples per view: the ground-truth object
samples are drawn once, and a candidate's D1-4 samples and overhead samples are measured
apart, so a pair's union costs no new distance query.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Iterable, Sequence

import numpy as np

from ..conventions import LAYER_NAMES
from ..evaluate.coverage import _nanmean

if TYPE_CHECKING:
    from ..evaluate import EvalView, GroundTruthMesh, MeshingConfig

#: the candidate thresholds, of the frontal and of the overhead segmentation; None = the
#: arg-max alone (the paper's rule)
GRID: tuple[float | None, ...] = (None, 0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.95)
#: the reconstruction whose precision and recall choose the point
VARIANT = "D1-4 & overhead"
#: the rule, as reports state it
RULE = ("largest min(precision, recall) at 5 cm of D1-4 & overhead against objects, "
        "mean over validation views; ties to the lower thresholds")
#: ground-truth and predicted samples per square metre while choosing (evaluate's is 10,000:
#: a quarter of it is 2 cm apart, and a mean over ~10⁵ samples per view moves by < 0.01)
DENSITY = 2_500.0


@dataclass(frozen=True)
class CandidateView:
    """What the candidates of one view are made from.

    view        : the predicted view with the arg-max masks (the loosest candidate); D5 unused
    front_score : (2, H, W) float32  the least object probability of a kept pixel of D1/D2
                  (layer 1) and of D3/D4 (layers 1 and 3), −1 where the arg-max drops it
    top_score   : (R, R) float32     the same for the overhead heights (−1 at the floor)
    """

    view: "EvalView"
    front_score: np.ndarray
    top_score: np.ndarray


def _at(t: float | None) -> float:
    return 0.0 if t is None else float(t)


def candidate_views(c: CandidateView, fronts: Sequence[float | None],
                    tops: Sequence[float | None]) -> tuple[list["EvalView"], list["EvalView"]]:
    """The view at each frontal threshold (D1..D4 kept where their score reaches it, no
    overhead) and at each overhead threshold (only the overhead heights)."""
    nan = np.float32(np.nan)
    none = np.full_like(c.view.depth, nan)
    empty_top = np.full_like(c.view.overhead_height, nan)
    front_views = []
    for t in fronts:
        keep = c.front_score >= _at(t)
        depth = none.copy()
        depth[:2] = np.where(keep[0], c.view.depth[:2], nan)
        depth[2:4] = np.where(keep[1], c.view.depth[2:4], nan)
        front_views.append(replace(c.view, depth=depth, overhead_height=empty_top))
    top_views = [replace(c.view, depth=none, overhead_height=np.where(c.top_score >= _at(u), c.view.overhead_height, nan))
                 for u in tops]
    return front_views, top_views


def score_candidates(c: CandidateView, gt: "GroundTruthMesh", fronts: Sequence[float | None],
                     tops: Sequence[float | None], rng: np.random.Generator, *, threshold: float = 0.05,
                     density: float = DENSITY, meshing: "MeshingConfig | None" = None) -> tuple[np.ndarray, np.ndarray]:
    """Precision and recall (len(fronts), len(tops)) at ``threshold`` of D1-4 & overhead
    against the objects of ``gt``, for every pair of thresholds, as ``evaluate predictions``
    measures them (:func:`~sceneforge.evaluate.score_parts`; NaN recall without objects)."""
    from ..evaluate import OVERHEAD, MeshDistance, concatenate, precision_recall, sample_surface

    gt_samples = sample_surface(gt.objects, density, rng)
    to_objects = MeshDistance(gt.objects)
    front_views, top_views = candidate_views(c, fronts, tops)

    def measure(mesh):
        samples = sample_surface(mesh, density, rng)
        return to_objects(samples), MeshDistance(mesh)(gt_samples)

    front = [measure(concatenate([v.meshes(meshing)[name] for name in LAYER_NAMES[:4]])) for v in front_views]
    top = [measure(v.meshes(meshing)[OVERHEAD]) for v in top_views]
    precision = np.empty((len(fronts), len(tops)))
    recall = np.empty_like(precision)
    for i, (pred_f, gt_f) in enumerate(front):
        for j, (pred_t, gt_t) in enumerate(top):
            p, r = precision_recall(np.concatenate([pred_f, pred_t]), np.minimum(gt_f, gt_t), [threshold])
            precision[i, j], recall[i, j] = p[0], r[0]
    return precision, recall


def choose(precision: np.ndarray, recall: np.ndarray) -> tuple[int, int]:
    """Indices (frontal, overhead) of the pair where precision meets recall (mean tables
    (F, T)): the largest min(P, R); ties (within 1e-9) to the lowest frontal, then the
    lowest overhead threshold. A table without any finite value chooses (0, 0)."""
    worst = np.minimum(precision, recall)
    if not np.isfinite(worst).any():
        return 0, 0
    best = np.nanmax(worst)
    i, j = np.argwhere(worst >= best - 1e-9)[0]
    return int(i), int(j)


@dataclass(frozen=True)
class OperatingPoint:
    """The thresholds a prediction used, and how they were set.

    rule      : "given" (the config's or the options') or "validation" (chosen by :data:`RULE`)
    min_object_probability, min_overhead_object_probability : the thresholds (None: arg-max)
    For "validation": the grid, the views and houses it was chosen on, the mean precision
    and recall tables (fronts × tops) and the seconds it took.
    """

    rule: str
    min_object_probability: float | None
    min_overhead_object_probability: float | None
    fronts: tuple[float | None, ...] = ()
    tops: tuple[float | None, ...] = ()
    views: int = 0
    houses: int = 0
    precision: np.ndarray | None = field(default=None, compare=False)
    recall: np.ndarray | None = field(default=None, compare=False)
    seconds: float = 0.0

    @classmethod
    def chosen(cls, precision: np.ndarray, recall: np.ndarray, fronts, tops, views: int, houses: int,
               seconds: float = 0.0) -> "OperatingPoint":
        """The point :func:`choose` picks from per-view tables (n_views, F, T)."""
        p, r = _nanmean(precision), _nanmean(recall)
        i, j = choose(p, r)
        return cls("validation", fronts[i], tops[j], tuple(fronts), tuple(tops), views, houses, p, r, seconds)

    @property
    def scores(self) -> tuple[float, float] | None:
        """Validation precision and recall at the chosen point."""
        if self.precision is None:
            return None
        i, j = self.fronts.index(self.min_object_probability), self.tops.index(self.min_overhead_object_probability)
        return float(self.precision[i, j]), float(self.recall[i, j])

    def describe(self) -> str:
        """One line for people."""
        f, t = (_threshold(x) for x in (self.min_object_probability, self.min_overhead_object_probability))
        text = f"operating point: least object probability {f} (frontal), {t} (overhead)"
        if self.rule != "validation":
            return f"{text}, as given"
        p, r = self.scores
        return (f"{text}, chosen on {self.views} views of {self.houses} validation houses where precision "
                f"meets recall (P {p:.3f}, R {r:.3f} of {VARIANT} at 5 cm)")

    def text(self) -> str:
        """What ``evaluate predictions`` prints (:meth:`describe`)."""
        return self.describe()

    def to_dict(self) -> dict:
        out = {"rule": self.rule, "min_object_probability": self.min_object_probability,
               "min_overhead_object_probability": self.min_overhead_object_probability}
        if self.rule == "validation":
            p, r = self.scores
            out.update(chosen_by=RULE, variant=VARIANT, views=self.views, houses=self.houses,
                       precision=p, recall=r, fronts=list(self.fronts), tops=list(self.tops),
                       precision_table=_table(self.precision), recall_table=_table(self.recall),
                       seconds=round(self.seconds, 1))
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "OperatingPoint":
        if data.get("rule") != "validation":
            return cls("given", data.get("min_object_probability"), data.get("min_overhead_object_probability"))
        table = lambda rows: np.array([[np.nan if x is None else x for x in row] for row in rows])  # noqa: E731
        return cls("validation", data["min_object_probability"], data["min_overhead_object_probability"],
                   tuple(data["fronts"]), tuple(data["tops"]), data["views"], data["houses"],
                   table(data["precision_table"]), table(data["recall_table"]), data.get("seconds", 0.0))


def _threshold(t: float | None) -> str:
    return "arg-max" if t is None else f"{t:g}"


def _table(a: np.ndarray) -> list[list[float | None]]:
    return [[float(x) if np.isfinite(x) else None for x in row] for row in a]


def evenly(indices: Sequence[int], most: int) -> list[int]:
    """At most ``most`` of ``indices``, evenly spread (all when there are fewer)."""
    indices = list(indices)
    if len(indices) <= most:
        return indices
    return [indices[int(k)] for k in np.linspace(0, len(indices) - 1, most).round().astype(int)]


def score_views(views: Iterable[tuple[int, CandidateView, "GroundTruthMesh"]], fronts, tops, seed: int,
                **kwargs) -> tuple[np.ndarray, np.ndarray]:
    """Per-view tables (n_views, F, T) of :func:`score_candidates`; view ``index`` draws from
    ``np.random.default_rng((seed, index))``."""
    p, r = [], []
    for index, c, gt in views:
        pi, ri = score_candidates(c, gt, fronts, tops, np.random.default_rng((seed, index)), **kwargs)
        p.append(pi)
        r.append(ri)
    shape = (0, len(fronts), len(tops))
    return (np.stack(p), np.stack(r)) if p else (np.zeros(shape), np.zeros(shape))
