"""Training losses (docs/spec.md §10.4, paper equation 1). Targets use NaN (heights, depths) or
:data:`~sceneforge.learn.dataset.EMPTY` (classes) for "no value"; the depth and height
losses are normalised per example by its own number of valid pixels, then averaged over the
batch, so a view with little content weighs as much as a full one."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.nn import functional as F

from .config import LossConfig  # defined without torch, for the CLI and the schema
from .dataset import BACKGROUND, EMPTY, SEG_CLASSES


def _per_example_mean(values: Tensor, valid: Tensor) -> Tensor:
    """(B, ...) values and validity → (B,) mean over each example's valid entries (0 if none)."""
    values = torch.where(valid, values, torch.zeros_like(values))
    dims = tuple(range(1, values.dim()))
    return values.sum(dim=dims) / valid.sum(dim=dims).clamp(min=1)


def depth_loss(pred: Tensor, target: Tensor, config: LossConfig | None = None) -> Tensor:
    """Masked Huber loss of equation (1), ``L = Σ_l (M_l / ||M_l||_1) · ρ(D_l, D̄_l)``.

    pred   : (B, 5, H, W) predicted D1..D5
    target : (B, 5, H, W) true D1..D5, NaN where a layer is empty
    Returns a scalar: per example, Σ over layers of weight · mean Huber over the layer's
    finite targets; averaged over the batch.

    The reading of the normalisation: ``||M_l||_1`` counts the valid pixels of layer ``l``
    *of one example*, because equation 1 is written for one image's layers ``D`` (no batch
    index) and the paper's masks are per image. So each layer of each view weighs the same
    whatever its area (a D3 seen on 2 % of the pixels counts as much as D5 on all of them),
    rather than the batch's pixels being pooled per layer. The envelope weight 0.5 is the
    authors' code's, not the equation's (``LossConfig.envelope_weight``).
    """
    config = config or LossConfig()
    valid = torch.isfinite(target)
    huber = F.huber_loss(pred, torch.nan_to_num(target), reduction="none", delta=config.huber_delta)
    B, L = pred.shape[:2]
    per_layer = _per_example_mean(huber.reshape(B * L, -1), valid.reshape(B * L, -1)).reshape(B, L)
    weights = torch.ones(L, dtype=pred.dtype, device=pred.device)
    weights[-1] = config.envelope_weight
    return (per_layer * weights).sum(dim=1).mean()


def segmentation_loss(logits: Tensor, target: Tensor, config: LossConfig | None = None) -> Tensor:
    """Cross-entropy per layer over the batch's non-empty pixels, averaged over the layers
    *(ref: the authors ignore empty pixels and average layers 1 and 3)*.

    logits : (B, L·40, H, W) class scores, layer after layer (L = 2 for the frontal net,
             1 for the overhead net)
    target : (B, L, H, W) int64 classes, :data:`EMPTY` where the ray hits nothing; or
             (B, H, W) when L = 1
    ``config.seg_empty == "background"`` counts empty pixels as background instead. A
    layer without any non-empty pixel adds 0. ``config.seg_balance`` > 0 weighs each pixel
    by :func:`class_balance_weights` (a weighted mean per layer).
    """
    config = config or LossConfig()
    B, C, H, W = logits.shape
    L = C // SEG_CLASSES
    target = target.reshape(B, L, H, W)
    if config.seg_empty == "background":
        target = torch.where(target == EMPTY, BACKGROUND, target)
    ce = F.cross_entropy(logits.reshape(B, L, SEG_CLASSES, H, W).transpose(1, 2), target, reduction="none",
                         ignore_index=EMPTY)
    if config.seg_balance == 0:
        counted = (target != EMPTY).sum(dim=(0, 2, 3)).clamp(min=1)
        return (ce.sum(dim=(0, 2, 3)) / counted).mean()
    weights = class_balance_weights(target, config.seg_balance)
    return ((ce * weights).sum(dim=(0, 2, 3)) / weights.sum(dim=(0, 2, 3)).clamp(min=1e-12)).mean()


def class_balance_weights(target: Tensor, balance: float) -> Tensor:
    """Per-pixel weights (B, L, H, W) of the targets (B, L, H, W): ``n_c ** -balance``, ``n_c``
    the pixels of the pixel's class in its layer of the batch, 0 where :data:`EMPTY`. With
    ``balance`` 1 every class present in a layer weighs as much in total as any other."""
    B, L, H, W = target.shape
    valid = target != EMPTY
    classes = torch.where(valid, target, torch.zeros_like(target)).transpose(0, 1).reshape(L, -1)
    counts = torch.zeros(L, SEG_CLASSES, device=target.device).scatter_add_(
        1, classes, valid.transpose(0, 1).reshape(L, -1).float())
    per_class = counts.clamp(min=1) ** -balance
    weights = per_class.gather(1, classes).reshape(L, B, H, W).transpose(0, 1)
    return torch.where(valid, weights, torch.zeros_like(weights))


def height_loss(pred: Tensor, target: Tensor, supervised: Tensor | None = None) -> Tensor:
    """L1 on overhead heights, per example over its supervised pixels.

    pred       : (B, 1, R, R) predicted heights above the floor
    target     : (B, R, R) true heights, NaN where unknown
    supervised : (B, R, R) bool pixels to supervise (the paper: the foreground objects);
                 default: every finite target
    """
    target = target.unsqueeze(1)
    valid = torch.isfinite(target) if supervised is None else supervised.unsqueeze(1) & torch.isfinite(target)
    return _per_example_mean((pred - torch.nan_to_num(target)).abs(), valid).mean()


def camera_loss(pred: Tensor, target: Tensor) -> Tensor:
    """L1 between predicted and true ``(tx, ty, sigma)`` (B, 3), metres."""
    return (pred - target).abs().mean()
