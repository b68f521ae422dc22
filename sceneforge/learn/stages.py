"""The training stages of the paper as objects, by name in :data:`REGISTRY` (docs/spec.md §10.5).

A stage says what its runs read, build, freeze, minimise and predict, so that training
and loading a run (:mod:`.train`) and prediction ask it instead of testing its name
(:func:`get_stage`). In the paper's order:

- ``depth``: the frontal depth net (``depth``) on RGB; predicts the layers D1..D5
- ``seg``: the frontal segmentation net (``seg``) on RGB; predicts the classes of layers 1, 3
- ``overhead``: the overhead height and segmentation nets (``height``, ``overhead_seg``) on
  the EFT of the frozen depth and seg runs' features; predicts all of the above and the
  overhead height and classes
- ``camera``: the virtual camera proposal (``camera``) on the frozen depth run's features;
  predicts the overhead cameras of an overhead run's prediction
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import replace

import torch
from torch import Tensor, nn

from ..errors import SceneforgeError
from .config import FROZEN, TrainConfig
from .dataset import SEG_CLASSES
from .eft import EpipolarFeatureTransformer, EpipolarGeometry, epipolar_geometry
from .losses import camera_loss, depth_loss, height_loss, segmentation_loss
from .metrics import DEPTH_METRICS, Metrics, depth_errors, height_error, segmentation_iou
from .networks import (
    DEPTH_NET,
    OVERHEAD_NET,
    SEG_NET,
    CameraNetConfig,
    CameraProposalNet,
    FrontalDepthNet,
    FrontalSegNet,
    OverheadNet,
    masked_layers,
)

#: nets by name, the keys of a checkpoint's ``models``
Nets = dict[str, nn.Module]


class Stage(ABC):
    """One stage of training: what its runs read, build, freeze, minimise and predict."""

    #: the name a :class:`~sceneforge.learn.train.TrainConfig` gives it (``config.stage``)
    name: str
    #: sample fields of its batches (:data:`sceneforge.learn.dataset.SAMPLE_FIELDS` keys)
    fields: tuple[str, ...]
    #: stages whose trained runs (``config.<stage>_run``) it reads, frozen (as
    #: :data:`sceneforge.learn.config.FROZEN`, which the torch-free CLI reads)
    frozen: tuple[str, ...] = ()
    #: the parts of its loss logged beside it in ``metrics.csv``
    loss_parts: tuple[str, ...] = ()
    #: what a prediction from one of its runs gives
    predicts: tuple[str, ...]
    #: the stage whose run a prediction of this one joins (camera: overhead); None: it
    #: predicts on its own
    predicts_with: str | None = None
    #: whether it runs the Epipolar Feature Transformer (``config.eft``)
    uses_eft: bool = False
    #: the validation metrics it logs beside the loss (:mod:`.metrics`)
    val_metrics: tuple[str, ...] = ()
    #: the sample fields that a left-right mirror of the image mirrors too (``config.flip``);
    #: empty: the stage's targets are not image-aligned (cameras, overhead views) and it
    #: is never mirrored
    flip_fields: tuple[str, ...] = ()

    @abstractmethod
    def build(self, config: TrainConfig, frontal: Nets) -> Nets:
        """The freshly initialised nets it trains; ``frontal``: the frozen nets of :attr:`frozen`."""

    @abstractmethod
    def forward(self, config: TrainConfig, nets: Nets, frontal: Nets, eft: EpipolarFeatureTransformer | None,
                batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """The trained nets' outputs on a batch, by net name."""

    @abstractmethod
    def objective(self, config: TrainConfig, outputs: dict[str, Tensor], batch: dict[str, Tensor]
                  ) -> tuple[Tensor, dict[str, Tensor]]:
        """The loss of :meth:`forward`'s outputs (a scalar with its graph) and its logged parts
        (:attr:`loss_parts`, 0-d and detached: read only when logged, reading waits for the device)."""

    def measure(self, config: TrainConfig, outputs: dict[str, Tensor], batch: dict[str, Tensor],
                metrics: Metrics) -> None:
        """Add a batch's :attr:`val_metrics` to ``metrics`` (default: none)."""
        return None

    def loss(self, config: TrainConfig, nets: Nets, frontal: Nets, eft: EpipolarFeatureTransformer | None,
             batch: dict[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]]:
        """The loss on a batch (a scalar with its graph) and its logged parts (:attr:`loss_parts`)."""
        return self.objective(config, self.forward(config, nets, frontal, eft, batch), batch)

    def __repr__(self) -> str:
        return f"<{self.name} stage>"


def _widths(config: TrainConfig, paper):
    """The paper's net widths scaled by ``config.width``, with the run's BatchNorm momentum."""
    return replace(paper.scaled(config.width), bn_momentum=config.bn_momentum)


class DepthStage(Stage):
    """The frontal depth net: D1..D5 from RGB (masked Huber loss, equation 1)."""

    name, fields, predicts = "depth", ("rgb", "depth"), ("depth",)
    val_metrics = DEPTH_METRICS
    flip_fields = fields

    def build(self, config, frontal):
        return {"depth": FrontalDepthNet(_widths(config, DEPTH_NET))}

    def forward(self, config, nets, frontal, eft, batch):
        return {"depth": nets["depth"](batch["rgb"]).prediction}

    def objective(self, config, outputs, batch):
        return depth_loss(outputs["depth"], batch["depth"], config.loss), {}

    def measure(self, config, outputs, batch, metrics):
        depth_errors(outputs["depth"], batch["depth"], metrics)


class SegStage(Stage):
    """The frontal segmentation net: the classes of layers 1 and 3 from RGB (cross-entropy)."""

    name, fields, predicts = "seg", ("rgb", "seg"), ("seg",)
    val_metrics = ("seg_miou",)
    flip_fields = fields

    def build(self, config, frontal):
        return {"seg": FrontalSegNet(_widths(config, SEG_NET))}

    def forward(self, config, nets, frontal, eft, batch):
        return {"seg": nets["seg"](batch["rgb"]).prediction}

    def objective(self, config, outputs, batch):
        return segmentation_loss(outputs["seg"], batch["seg"], config.loss), {}

    def measure(self, config, outputs, batch, metrics):
        segmentation_iou(outputs["seg"], batch["seg"], metrics, "seg_miou")


class OverheadStage(Stage):
    """The overhead height and segmentation nets on the EFT of the frozen frontal nets."""

    name = "overhead"
    fields = ("rgb", "depth", "camera", "overhead_height", "overhead_seg")
    frozen = FROZEN["overhead"]
    loss_parts = ("height_l1", "seg_ce")
    predicts = ("depth", "seg", "overhead")
    uses_eft = True
    val_metrics = ("height_l1_above_5cm", "overhead_seg_miou")
    #: the fields its objective reads: with its input cached, batches need only these
    #: (:mod:`.cache`)
    targets = ("overhead_height", "overhead_seg")

    def build(self, config, frontal):
        cin = EpipolarFeatureTransformer.out_channels(frontal["depth"].feature_channels,
                                                      frontal["seg"].feature_channels)
        return {"height": OverheadNet(cin, 1, _widths(config, OVERHEAD_NET)),
                "overhead_seg": OverheadNet(cin, SEG_CLASSES, _widths(config, OVERHEAD_NET))}

    def forward(self, config, nets, frontal, eft, batch):
        if "overhead_input" in batch:  # read from the feature cache (:mod:`.cache`)
            x = batch["overhead_input"].float()
        else:
            x, _, _ = overhead_input(frontal, eft, batch, config.eft_layers == "truth")
        return {"height": nets["height"](x), "overhead_seg": nets["overhead_seg"](x)}

    def objective(self, config, outputs, batch):
        h = overhead_height_loss(config, outputs["height"], batch)
        s = segmentation_loss(outputs["overhead_seg"], batch["overhead_seg"], config.loss)
        return h + config.loss.overhead_seg_weight * s, {"height_l1": h.detach(), "seg_ce": s.detach()}

    def measure(self, config, outputs, batch, metrics):
        height_error(outputs["height"], batch["overhead_height"], metrics)
        segmentation_iou(outputs["overhead_seg"], batch["overhead_seg"], metrics, "overhead_seg_miou")


def overhead_height_loss(config: TrainConfig, pred: Tensor, batch: dict[str, Tensor]) -> Tensor:
    """The height loss of predicted heights (B, 1, R, R) on a batch's targets: the object
    pixels only *(paper)*, or every pixel with a height (the floor as 0) with ``floor_as_zero``."""
    supervised = None if config.floor_as_zero else batch["overhead_foreground"]
    return height_loss(pred, batch["overhead_height"], supervised)


class CameraStage(Stage):
    """The virtual camera proposal ``(tx, ty, sigma)`` on the frozen depth net's features (L1)."""

    name, fields = "camera", ("rgb", "camera")
    frozen = FROZEN["camera"]
    predicts, predicts_with = ("camera",), "overhead"

    def build(self, config, frontal):
        depth = frontal["depth"]
        return {"camera": CameraProposalNet(depth.feature_channels, depth.config.channels[-1],
                                            _widths(config, CameraNetConfig()))}

    def forward(self, config, nets, frontal, eft, batch):
        with torch.no_grad():
            out = frontal["depth"](batch["rgb"])
        return {"camera": nets["camera"](out.features, out.encoding)}

    def objective(self, config, outputs, batch):
        pred = outputs["camera"]
        return camera_loss(pred, batch["overhead_params"][:, [0, 1, 4]].to(pred.dtype)), {}


#: every stage by name, in training order (the order of ``sceneforge.learn.train.STAGES``)
REGISTRY: dict[str, Stage] = {s.name: s for s in (DepthStage(), SegStage(), OverheadStage(), CameraStage())}


def get_stage(name: str) -> Stage:
    """The registered stage called ``name``; :class:`SceneforgeError` names the known ones."""
    try:
        return REGISTRY[name]
    except KeyError:
        raise SceneforgeError(f"unknown training stage {name!r}; known: {', '.join(REGISTRY)}") from None


# ------------------------------------------------------------------- the overhead input


def geometry(batch: dict[str, Tensor], frontal_hw: tuple[int, int], resolution: int) -> EpipolarGeometry:
    """The EFT geometry of a batch with the ``camera`` fields (K at the images' resolution)."""
    return epipolar_geometry(batch["K"], batch["cam_to_world"], batch["overhead_cam_to_world"],
                             batch["overhead_extent"], batch["overhead_params"][:, 2], frontal_hw, resolution)


@torch.no_grad()
def overhead_input(frontal: Nets, eft: EpipolarFeatureTransformer, batch: dict[str, Tensor],
                   true_layers: bool = False) -> tuple[Tensor, Tensor, Tensor]:
    """Run the frozen frontal nets and the EFT on a batch.

    Returns the overhead nets' input (B, 232, R, R), the frontal layers the EFT used
    (B, 5, H, W; NaN where empty) and the segmentation logits (B, 80, H, W).
    """
    rgb = batch["rgb"]
    depth, seg = frontal["depth"](rgb), frontal["seg"](rgb)
    layers = batch["depth"] if true_layers else masked_layers(depth.prediction, seg.prediction)
    geom = geometry(batch, tuple(rgb.shape[-2:]), eft.resolution)
    return eft(rgb, depth.features, seg.features, layers[:, :4], geom), layers, seg.prediction
