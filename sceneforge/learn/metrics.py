"""Validation metrics beside the loss (docs/spec.md §10.5): what ``metrics.csv`` logs for a ``val`` row.

- per frontal layer ``D1..D5``: absolute relative error ``|pred − true| / true`` and RMSE,
  metres, over the finite targets (``d1_absrel``, ``d1_rmse``, ...);
- segmentation mIoU: the mean over classes present (in prediction or truth) of
  intersection / union, pooled over the whole validation set (``seg_miou``,
  ``overhead_seg_miou``), empty pixels left out;
- overhead height L1 above 5 cm: mean ``|pred − true|`` over the pixels whose true height
  is more than 5 cm above the floor, the pixels the paper evaluates (``height_l1_above_5cm``).

A :class:`Metrics` pools sums over batches so that every metric is over all pixels of the
set, not a mean of per-batch means.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .dataset import EMPTY, SEG_CLASSES

#: heights at or below this above the floor are not evaluated *(paper §5)*
EVAL_MIN_HEIGHT = 0.05
DEPTH_METRICS = tuple(f"d{k}_{m}" for k in range(1, 6) for m in ("absrel", "rmse"))


class Metrics:
    """Sums over a dataset: means, root-mean-squares and per-class IoU counts."""

    def __init__(self):
        self.sums: dict[str, float] = {}
        self.counts: dict[str, float] = {}
        self.ious: dict[str, tuple[Tensor, Tensor]] = {}

    def add_mean(self, name: str, total: Tensor, n: Tensor) -> None:
        self.sums[name] = self.sums.get(name, 0.0) + float(total)
        self.counts[name] = self.counts.get(name, 0.0) + float(n)

    def add_rms(self, name: str, squares: Tensor, n: Tensor) -> None:
        self.add_mean(f"{name}\0rms", squares, n)

    def add_iou(self, name: str, intersection: Tensor, union: Tensor) -> None:
        i, u = self.ious.get(name, (0, 0))
        self.ious[name] = (intersection.double().cpu() + i, union.double().cpu() + u)

    def result(self) -> dict[str, float]:
        """Every metric (NaN where nothing was counted)."""
        out = {}
        for key, total in self.sums.items():
            n = self.counts[key]
            mean = total / n if n else math.nan
            name, _, rms = key.partition("\0")
            out[name] = math.sqrt(mean) if rms else mean
        for name, (i, u) in self.ious.items():
            present = u > 0
            out[name] = float((i[present] / u[present]).mean()) if present.any() else math.nan
        return out


def depth_errors(pred: Tensor, target: Tensor, metrics: Metrics) -> None:
    """Abs-rel and RMSE of each layer over finite targets; pred, target (B, 5, H, W)."""
    valid = torch.isfinite(target) & (target > 0)
    err = torch.where(valid, pred.float() - torch.nan_to_num(target), torch.zeros(()))
    true = torch.where(valid, target, torch.ones(()))
    for k in range(target.shape[1]):
        n = valid[:, k].sum()
        metrics.add_mean(f"d{k + 1}_absrel", (err[:, k].abs() / true[:, k]).sum(), n)
        metrics.add_rms(f"d{k + 1}_rmse", (err[:, k] ** 2).sum(), n)


def segmentation_iou(logits: Tensor, target: Tensor, metrics: Metrics, name: str) -> None:
    """Per-class intersection and union of the argmax classes; logits (B, L·40, H, W),
    target (B, L, H, W) or (B, H, W), :data:`~sceneforge.learn.dataset.EMPTY` left out."""
    B, C, H, W = logits.shape
    L = C // SEG_CLASSES
    pred = logits.reshape(B, L, SEG_CLASSES, H, W).argmax(dim=2).flatten()
    true = target.reshape(B, L, H, W).flatten()
    keep = true != EMPTY
    pred, true = pred[keep], true[keep]
    area_p = torch.bincount(pred, minlength=SEG_CLASSES)
    area_t = torch.bincount(true, minlength=SEG_CLASSES)
    inter = torch.bincount(true[pred == true], minlength=SEG_CLASSES)
    metrics.add_iou(name, inter, area_p + area_t - inter)


def height_error(pred: Tensor, target: Tensor, metrics: Metrics) -> None:
    """L1 of predicted heights (B, 1, R, R) over true heights (B, R, R) above 5 cm."""
    keep = torch.isfinite(target) & (target > EVAL_MIN_HEIGHT)
    err = torch.where(keep, pred[:, 0].float() - torch.nan_to_num(target), torch.zeros(()))
    metrics.add_mean("height_l1_above_5cm", err.abs().sum(), keep.sum())
