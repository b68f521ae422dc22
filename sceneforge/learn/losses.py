"""Training losses (SPEC §10, paper equation 1). Targets use NaN for "no value"; every loss
is normalised per example by its own number of valid pixels, then averaged over the batch,
so a view with little content weighs as much as a full one."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.nn import functional as F

from .config import LossConfig  # defined without torch, for the CLI and the schema
from .dataset import SEG_CLASSES


def _per_example_mean(values: Tensor, valid: Tensor) -> Tensor:
    """(B, ...) values and validity → (B,) mean over each example's valid entries (0 if none)."""
    values = torch.where(valid, values, torch.zeros_like(values))
    dims = tuple(range(1, values.dim()))
    return values.sum(dim=dims) / valid.sum(dim=dims).clamp(min=1)


def depth_loss(pred: Tensor, target: Tensor, config: LossConfig | None = None) -> Tensor:
    """Masked Huber loss of equation (1).

    pred   : (B, 5, H, W) predicted D1..D5
    target : (B, 5, H, W) true D1..D5, NaN where a layer is empty
    Returns a scalar: per example, Σ over layers of weight · mean Huber over the layer's
    finite targets; averaged over the batch.
    """
    config = config or LossConfig()
    valid = torch.isfinite(target)
    huber = F.huber_loss(pred, torch.nan_to_num(target), reduction="none", delta=config.huber_delta)
    B, L = pred.shape[:2]
    per_layer = _per_example_mean(huber.reshape(B * L, -1), valid.reshape(B * L, -1)).reshape(B, L)
    weights = torch.ones(L, dtype=pred.dtype, device=pred.device)
    weights[-1] = config.envelope_weight
    return (per_layer * weights).sum(dim=1).mean()


def segmentation_loss(logits: Tensor, target: Tensor) -> Tensor:
    """Cross-entropy per layer, summed over layers.

    logits : (B, L·40, H, W) class scores, layer after layer (L = 2 for the frontal net,
             1 for the overhead net)
    target : (B, L, H, W) int64 classes, or (B, H, W) when L = 1
    """
    B, C, H, W = logits.shape
    L = C // SEG_CLASSES
    target = target.reshape(B, L, H, W)
    ce = F.cross_entropy(logits.reshape(B, L, SEG_CLASSES, H, W).transpose(1, 2), target, reduction="none")
    return ce.mean(dim=(2, 3)).sum(dim=1).mean()


def height_loss(pred: Tensor, target: Tensor) -> Tensor:
    """L1 on finite overhead heights.

    pred   : (B, 1, R, R) predicted heights above the floor
    target : (B, R, R) true heights, NaN where unknown
    """
    target = target.unsqueeze(1)
    valid = torch.isfinite(target)
    return _per_example_mean((pred - torch.nan_to_num(target)).abs(), valid).mean()


def camera_loss(pred: Tensor, target: Tensor) -> Tensor:
    """L1 between predicted and true ``(tx, ty, sigma)`` (B, 3), metres."""
    return (pred - target).abs().mean()
