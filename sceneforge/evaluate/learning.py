"""Did the nets learn? Per-pixel scores of predicted views next to a trivial predictor's
(docs/spec.md §11.5): what ``sceneforge evaluate predictions`` prints under "learning" and writes
under the JSON key ``"learning"``.

Three scores, each for the model (the predictions of ``sceneforge predict``) and for a
baseline that knows only the training houses of the split and never looks at the image:

- ``depth_absrel``: mean ``|d̂ − d| / d`` over the object pixels of D1..D4 (finite true
  depth) that the model predicted, the four layers' pixels pooled; the baseline predicts
  each pixel's mean depth of that layer over the training views (the layer's mean over
  every pixel where no training view has one). Both are scored on the same pixels;
  ``depth_coverage`` is the fraction of the object pixels they are (the model leaves a
  pixel out where its segmentation sees no object there: the paper's masks).
- ``seg_miou``: intersection over union per segmentation class
  (:data:`~sceneforge.conventions.NYU40_TO_SEG`: envelope classes are background), pooled
  over layers 1 and 3 of every scored view, averaged over the classes present in the
  prediction or the truth; pixels where the ray hits nothing are left out (as in training).
  The baseline predicts the training views' most frequent class everywhere.
- ``overhead_height_l1``: mean ``|ĥ − h|`` over the overhead pixels whose true height is
  above 5 cm (the paper's) that the model predicted a height for; the baseline predicts the
  training views' mean height over those pixels everywhere. Both are scored on the same
  pixels, as for depth: ``overhead_coverage`` is the fraction of the object pixels they are
  (the model leaves a pixel out where its floor removal sees floor). The floor removal
  itself is scored by the reconstruction's precision and recall, not here. Only where the
  predicted overhead cameras are the store's (no camera proposal run): other cameras see
  other pixels.

A score is None where the prediction has no such output (a depth run predicts no classes).
Everything here reads arrays of opened stores; nothing imports PyTorch.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..conventions import NYU40_TO_SEG, SEG_CLASSES
from ..errors import SceneforgeError

#: true heights at or below this above the floor are not scored *(paper §5)*
MIN_HEIGHT = 0.05
#: object layers of the depth score (D1..D4)
OBJECT_LAYERS = 4
#: views read at once
_BLOCK = 64
_TO_SEG = np.asarray(NYU40_TO_SEG, dtype=np.int64)
#: the score names, in the order they are printed
SCORES = ("depth_absrel", "seg_miou", "overhead_height_l1")
#: which prediction stage makes each score
_STAGE = {"depth_absrel": "depth", "seg_miou": "seg", "overhead_height_l1": "overhead"}
_BETTER = {"depth_absrel": "lower", "seg_miou": "higher", "overhead_height_l1": "lower"}


def _blocks(indices: Sequence[int]):
    indices = np.asarray(sorted(indices), dtype=np.int64)
    for k in range(0, len(indices), _BLOCK):
        yield indices[k:k + _BLOCK]


def _read(store, name: str, rows: np.ndarray) -> np.ndarray:
    """Rows ``rows`` (sorted) of array ``name``: one read of their span, then the rows."""
    block = np.asarray(store.array(name)[int(rows[0]):int(rows[-1]) + 1])
    return block[rows - rows[0]]


def seg_targets(category: np.ndarray, depth: np.ndarray, empty: int = -1) -> np.ndarray:
    """The segmentation classes of layers 1 and 3 of views, the frontal nets' targets:
    ``category`` (n, 3, H, W) uint8 NYU40 ids, ``depth`` (n, 5, H, W) → (n, 2, H, W) int64
    classes, ``empty`` where the ray hits nothing (neither the layer nor the envelope D5)."""
    nothing = np.isnan(depth[:, [0, 2]]) & np.isnan(depth[:, 4:5])
    return np.where(nothing, empty, _TO_SEG[category[:, :2].astype(np.int64)])


@dataclass(frozen=True)
class Baselines:
    """What the trivial predictor knows: statistics of the training views alone.

    depth  : (4, H, W) float64 per-pixel mean of D1..D4 over the training views
    seg    : the most frequent segmentation class of layers 1 and 3
    height : mean true overhead height above :data:`MIN_HEIGHT`, metres
    views  : training views they come from
    """

    depth: np.ndarray
    seg: int
    height: float
    views: int


def training_baselines(gt, train: Sequence[int]) -> Baselines:
    """The :class:`Baselines` of views ``train`` of the store ``gt`` (its training houses).

    Raises :class:`SceneforgeError` when ``train`` is empty.
    """
    if not len(train):
        raise SceneforgeError("the split has no training view in the ground-truth store: the baselines "
                              "are statistics of the training houses")
    depth_sum = depth_n = None
    classes = np.zeros(SEG_CLASSES, np.int64)
    height_sum, height_n = 0.0, 0
    for rows in _blocks(train):
        depth = _read(gt, "depth", rows)
        d = depth[:, :OBJECT_LAYERS].astype(np.float64)
        finite = np.isfinite(d)
        s, n = np.where(finite, d, 0).sum(axis=0), finite.sum(axis=0)
        depth_sum, depth_n = (s, n) if depth_sum is None else (depth_sum + s, depth_n + n)
        target = seg_targets(_read(gt, "category", rows), depth)
        classes += np.bincount(target[target >= 0], minlength=SEG_CLASSES)
        h = _read(gt, "overhead_height", rows).astype(np.float64)
        above = np.isfinite(h) & (h > MIN_HEIGHT)
        height_sum, height_n = height_sum + h[above].sum(), height_n + int(above.sum())
    per_pixel = depth_sum / np.maximum(depth_n, 1)
    layer_n = depth_n.sum(axis=(1, 2))
    layer_mean = np.where(layer_n > 0, depth_sum.sum(axis=(1, 2)) / np.maximum(layer_n, 1),
                          depth_sum.sum() / max(depth_n.sum(), 1))  # a layer no training view has: all layers'
    per_pixel = np.where(depth_n > 0, per_pixel, layer_mean[:, None, None])
    return Baselines(per_pixel, int(classes.argmax()), height_sum / height_n if height_n else math.nan, len(train))


def _miou(intersection: np.ndarray, union: np.ndarray) -> float:
    present = union > 0
    return float((intersection[present] / union[present]).mean()) if present.any() else math.nan


def _iou_counts(pred: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    area_p = np.bincount(pred, minlength=SEG_CLASSES)
    area_t = np.bincount(true, minlength=SEG_CLASSES)
    inter = np.bincount(true[pred == true], minlength=SEG_CLASSES)
    return inter, area_p + area_t - inter


@dataclass(frozen=True)
class LearningReport:
    """The model's and the baseline's scores on the scored views (None: not predicted)."""

    scores: dict[str, tuple[float, float] | None]
    #: fraction of D1..D4's object pixels both depth scores are over
    depth_coverage: float
    views: int
    train_views: int
    #: why a score is missing, by score name
    missing: dict[str, str]
    #: fraction of the overhead object pixels (true height above 5 cm) both height scores are over
    overhead_coverage: float = math.nan

    def to_dict(self) -> dict:
        """JSON-ready: ``{"depth_absrel": {"model": x, "baseline": y}, ...}`` (None where
        not predicted), with the views counted."""
        out: dict = {"views": self.views, "train_views": self.train_views,
                     "depth_coverage": _finite_or_none(self.depth_coverage),
                     "overhead_coverage": _finite_or_none(self.overhead_coverage)}
        for name in SCORES:
            pair = self.scores.get(name)
            out[name] = None if pair is None else {"model": _finite_or_none(pair[0]),
                                                   "baseline": _finite_or_none(pair[1]),
                                                   "better": _BETTER[name]}
        return out

    def text(self) -> str:
        lines = [f"learning: the model next to a trivial predictor of the {_n(self.train_views, 'training view')} "
                 f"(no image), on {_n(self.views, 'view')}",
                 f"{'score':<22}{'model':>9}{'baseline':>10}  better"]
        for name in SCORES:
            pair = self.scores.get(name)
            if pair is None:
                lines.append(f"{name:<22}{'—':>9}{'—':>10}  ({self.missing.get(name, 'not predicted')})")
            else:
                lines.append(f"{name:<22}{pair[0]:>9.3f}{pair[1]:>10.3f}  {_BETTER[name]}")
        if self.scores.get("depth_absrel") is not None:
            lines.append(f"depth scored on {self.depth_coverage:.1%} of D1-D4's object pixels "
                         "(those the model predicted)")
        if self.scores.get("overhead_height_l1") is not None:
            lines.append(f"overhead heights scored on {self.overhead_coverage:.1%} of the object pixels above "
                         "5 cm (those the model kept)")
        return "\n".join(lines)


def _n(count: int, what: str) -> str:
    return f"{count} {what}{'' if count == 1 else 's'}"


def _finite_or_none(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def learning_scores(pred, gt, indices: Sequence[int], baselines: Baselines,
                    stages: Sequence[str] = ("depth", "seg", "overhead"),
                    same_overhead_cameras: bool = True) -> LearningReport:
    """Scores of views ``indices`` of the predictions ``pred`` against the truth ``gt``
    (view ``i`` of one is view ``i`` of the other: the caller checks), next to ``baselines``.

    stages : what ``pred`` predicted (its ``prediction`` attribute's ``stages``)
    same_overhead_cameras : whether ``pred``'s overhead cameras are ``gt``'s
    """
    absrel = np.zeros(2)  # model, baseline sums
    depth_n = depth_total = 0
    inter = {"model": np.zeros(SEG_CLASSES), "baseline": np.zeros(SEG_CLASSES)}
    union = {"model": np.zeros(SEG_CLASSES), "baseline": np.zeros(SEG_CLASSES)}
    l1 = np.zeros(2)
    height_n = height_total = 0
    scored = {"depth_absrel": "depth" in stages, "seg_miou": "seg" in stages,
              "overhead_height_l1": "overhead" in stages and same_overhead_cameras}
    missing = {name: f"no {_STAGE[name]} prediction" for name in SCORES if _STAGE[name] not in stages}
    if "overhead" in stages and not same_overhead_cameras:
        missing["overhead_height_l1"] = "the overhead cameras are proposed, not the store's"
    for rows in _blocks(indices):
        true_depth = _read(gt, "depth", rows)
        if scored["depth_absrel"]:
            t = true_depth[:, :OBJECT_LAYERS].astype(np.float64)
            p = _read(pred, "depth", rows)[:, :OBJECT_LAYERS].astype(np.float64)
            objects = np.isfinite(t) & (t > 0)
            keep = objects & np.isfinite(p)
            base = np.broadcast_to(baselines.depth, t.shape)
            absrel += (np.abs(p[keep] - t[keep]) / t[keep]).sum(), (np.abs(base[keep] - t[keep]) / t[keep]).sum()
            depth_n += int(keep.sum())
            depth_total += int(objects.sum())
        if scored["seg_miou"]:
            true = seg_targets(_read(gt, "category", rows), true_depth)
            guess = _TO_SEG[_read(pred, "category", rows)[:, :2].astype(np.int64)]
            counted = true >= 0
            for who, p in (("model", guess[counted]), ("baseline", np.full(int(counted.sum()), baselines.seg))):
                i, u = _iou_counts(p, true[counted])
                inter[who] += i
                union[who] += u
        if scored["overhead_height_l1"]:
            h = _read(gt, "overhead_height", rows).astype(np.float64)
            above = np.isfinite(h) & (h > MIN_HEIGHT)
            guess = _read(pred, "overhead_height", rows).astype(np.float64)
            keep = above & np.isfinite(guess)
            l1 += np.abs(guess[keep] - h[keep]).sum(), np.abs(baselines.height - h[keep]).sum()
            height_n += int(keep.sum())
            height_total += int(above.sum())
    scores: dict[str, tuple[float, float] | None] = dict.fromkeys(SCORES)
    if scored["depth_absrel"]:
        scores["depth_absrel"] = tuple(absrel / depth_n) if depth_n else (math.nan, math.nan)
    if scored["seg_miou"]:
        scores["seg_miou"] = (_miou(inter["model"], union["model"]), _miou(inter["baseline"], union["baseline"]))
    if scored["overhead_height_l1"]:
        scores["overhead_height_l1"] = tuple(l1 / height_n) if height_n else (math.nan, math.nan)
    return LearningReport(scores, depth_n / depth_total if depth_total else math.nan, len(indices),
                          baselines.views, missing,
                          overhead_coverage=height_n / height_total if height_total else math.nan)
