"""The configs of training and prediction runs, without PyTorch (docs/spec.md §10).

They live here, not beside the code that runs them, so that ``sceneforge train --help``
and ``schemas/train.schema.json`` are built from them without importing torch; the
modules that use them re-export them (``sceneforge.learn.train.TrainConfig``,
``.eft.EFTConfig``, ``.losses.LossConfig``, ``.dataset.SplitConfig``).
"""

from __future__ import annotations

import typing
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

#: the stages of the paper's training, in the order they are trained
Stage = Literal["depth", "seg", "overhead", "camera"]
STAGES: tuple[str, ...] = typing.get_args(Stage)
#: the frozen runs each stage reads, by the stage they come from
FROZEN: dict[str, tuple[str, ...]] = {"overhead": ("depth", "seg"), "camera": ("depth",)}
#: what the overhead stage's EFT reads: the frozen nets' layers or the store's
EFTLayers = Literal["predicted", "truth"]
EFT_LAYERS: tuple[str, ...] = typing.get_args(EFTLayers)
#: how the EFT gates features along a ray
Gating = Literal["volume", "surface"]
GATINGS: tuple[str, ...] = typing.get_args(Gating)
#: what the segmentation losses make of pixels where the ray hits nothing
SegEmpty = Literal["ignore", "background"]
#: how the floor is removed from predicted overhead heights
FloorRemoval = Literal["segmentation", "height"]
#: how predict's object-probability thresholds are set (sceneforge.learn.operating_point)
OperatingPointRule = Literal["given", "validation"]
#: how the learning rate changes over a run: "constant", or "cosine" (from ``lr`` down to 0
#: at the run's last step, half a cosine)
LRSchedule = Literal["constant", "cosine"]
#: what the overhead stage caches of its input (:mod:`sceneforge.learn.cache`)
FeatureCache = Literal["float16", "float32", "off"]
#: mixed precision of a training run's forward pass: "auto" (bf16 on a GPU that supports it,
#: else off), "bf16", "fp16" (with a gradient scaler) or "off" (float32 throughout)
Amp = Literal["auto", "bf16", "fp16", "off"]
AMPS: tuple[str, ...] = typing.get_args(Amp)
#: the views a prediction or an evaluation takes: the houses of one split, or every view
SplitName = Literal["test", "val", "train", "all"]


@dataclass(frozen=True)
class EFTConfig:
    """How frontal features are carried to the overhead view."""

    #: EFT gating: "volume" (mean along ray segments, the paper's choice) or "surface"
    #: (z-buffer of their ends)
    gating: Gating = "volume"
    #: samples per overhead pixel along a segment's major axis (1 ≈ a Bresenham line)
    samples_per_pixel: float = 1.0
    #: rays are sampled in chunks of at most this many samples (bounds memory)
    max_samples: int = 1 << 21

    def __post_init__(self):
        if self.gating not in GATINGS:
            raise ValueError(f"gating must be one of {GATINGS}, got {self.gating!r}")
        if not self.samples_per_pixel > 0:
            raise ValueError(f"samples_per_pixel must be > 0, got {self.samples_per_pixel}")


@dataclass(frozen=True)
class LossConfig:
    """Weights and parameters of the losses."""

    #: Huber threshold δ of the depth loss, metres (paper: 1; the CPU learning recipe takes
    #: 0.1, nearly L1, whose median a 5 cm precision rewards)
    huber_delta: float = 1.0
    #: weight of the envelope layer D5 in the depth loss (D1..D4 weigh 1)
    envelope_weight: float = 0.5
    #: weight of the overhead segmentation loss next to the overhead height loss
    overhead_seg_weight: float = 1.0
    #: pixels where the ray hits nothing in the segmentation losses: "ignore" them (the
    #: authors') or count them as "background"
    seg_empty: SegEmpty = "ignore"
    #: weigh each pixel of the segmentation losses by (pixels of its class in its layer of
    #: the batch) ** -seg_balance: 0 plain cross-entropy (the paper's); 1 every class of a
    #: batch weighs as much as any other, so small objects are not drowned by background
    seg_balance: float = 0.0

    def __post_init__(self):
        if not self.huber_delta > 0:
            raise ValueError(f"huber_delta must be > 0 metres, got {self.huber_delta}")
        for name in ("envelope_weight", "overhead_seg_weight"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.seg_balance <= 1:
            raise ValueError(f"seg_balance must be in [0, 1], got {self.seg_balance}")
        if self.seg_empty not in typing.get_args(SegEmpty):
            raise ValueError(f"seg_empty must be one of {typing.get_args(SegEmpty)}, got {self.seg_empty!r}")


@dataclass(frozen=True)
class SplitConfig:
    """How houses are divided into train, validation and test: once per set of stores, saved
    in a split file that every later stage, ``predict`` and ``evaluate`` read
    (:mod:`sceneforge.learn.split`)."""

    #: fraction of the houses (rounded down) held out for validation
    val_fraction: float = 0.1
    #: fraction of the houses (rounded down) held out for testing
    test_fraction: float = 0.1
    #: seed of the shuffle that assigns houses to splits (its own: not the training seed)
    seed: int = 0
    #: the split file, written by the first run on the stores and read by every later one;
    #: None = the stores' own, beside the first: a.split.json for a.zarr (several stores:
    #: a+N.HASH.split.json)
    file: str | None = None

    def __post_init__(self):
        v, t = self.val_fraction, self.test_fraction
        if not (0 <= v and 0 <= t and v + t < 1):
            raise ValueError(f"val and test fractions must be >= 0 and sum below 1, got "
                             f"{self.val_fraction} and {self.test_fraction}")


@dataclass(frozen=True)
class TrainConfig:
    """Everything that decides what a training run learns (not how fast: the device, the
    number of data workers and the processes of a torchrun are options of
    :func:`~sceneforge.learn.train.train` and of its environment). ``batch_size`` is the
    whole batch of a step, shared among the processes of a distributed run."""

    #: the fields naming files or folders, made absolute when the config is resolved
    PATHS: typing.ClassVar[tuple[str, ...]] = ("split.file", "depth_run", "seg_run")

    #: the stage to train: the frontal depth or segmentation net, then the overhead nets
    #: (on the frozen frontal nets) or the virtual camera proposal (on the frozen depth net)
    stage: Stage
    #: stores to train on; their views are split by house
    stores: tuple[str, ...]
    #: views per batch (paper: 24)
    batch_size: int = 24
    #: Adam learning rate (paper: 5e-4)
    lr: float = 5e-4
    #: passes over the training views (paper: 40)
    epochs: int = 40
    #: stop after this many optimiser steps; None = after ``epochs``
    max_steps: int | None = None
    #: how the learning rate changes over the run's steps: "constant" (the paper's) or
    #: "cosine" (from lr down to 0 at the last step; a short run settles into its minimum)
    lr_schedule: LRSchedule = "constant"
    #: mirror each training view left-right with probability 1/2, image and targets alike,
    #: decided by (seed, step, view) (the depth and seg stages; the others ignore it)
    flip: bool = False
    #: seed of the weights' initialisation and of the data order
    seed: int = 0
    #: multiplies every network width of the paper (e.g. 0.25 for a quick run; tests train
    #: nets a few channels wide)
    width: float = 1.0
    #: BatchNorm running-statistics momentum of every net (paper: 0.005); a run of a few
    #: hundred steps needs about 0.1 for its eval-mode statistics to settle
    bn_momentum: float = 0.005
    #: the depth run whose frozen net the overhead and camera stages use
    depth_run: str | None = None
    #: the segmentation run whose frozen net the overhead stage uses
    seg_run: str | None = None
    #: frontal layers the EFT reads in the overhead stage: "predicted" (the frozen nets'
    #: depths, masked by their segmentation) or "truth" (the store's)
    eft_layers: EFTLayers = "predicted"
    #: also supervise the overhead heights where only the floor is seen, as 0 (the paper's
    #: rejected alternative, which lets the height net segment the floor; default: object
    #: pixels only, the floor being removed by the overhead segmentation at test time)
    floor_as_zero: bool = False
    #: the overhead stage's input (the EFT of the frozen nets' features) per view, computed
    #: once before the first step into RUN/feature_cache and read back every step after:
    #: "float16" (half the disk, values rounded to 11 significant bits), "float32" (exact)
    #: or "off" (recomputed every step)
    feature_cache: FeatureCache = "float16"
    #: disk bound of the feature cache, GiB: a split whose views do not fit is not cached
    feature_cache_gib: float = 64.0
    #: write a train row to the metrics every this many steps
    log_every: int = 10
    #: save the checkpoint every this many steps (and at the end of every epoch)
    checkpoint_every: int = 500
    #: mixed precision of the forward pass: "auto" (bf16 on a CUDA GPU that supports it,
    #: else off), "bf16", "fp16" (with a gradient scaler) or "off"; the run saves what
    #: "auto" resolved to, so a resumed run keeps it
    amp: Amp = "auto"
    #: with several processes (torchrun), BatchNorm statistics over the whole batch of all
    #: of them (as one process with the whole batch computes them); off: each process's own
    sync_batchnorm: bool = True
    #: the epipolar feature transform (its resolution is the stores' overhead resolution)
    eft: EFTConfig = field(default_factory=EFTConfig)
    #: loss weights
    loss: LossConfig = field(default_factory=LossConfig)
    #: the house split
    split: SplitConfig = field(default_factory=SplitConfig)

    def __post_init__(self):
        if self.stage not in STAGES:
            raise ValueError(f"stage must be one of {', '.join(STAGES)}, got {self.stage!r}")
        if self.amp not in AMPS:
            raise ValueError(f"amp must be one of {', '.join(AMPS)}, got {self.amp!r}")
        if self.eft_layers not in EFT_LAYERS:
            raise ValueError(f"eft_layers must be one of {EFT_LAYERS}, got {self.eft_layers!r}")
        if not self.stores:
            raise ValueError("at least one store is needed")
        for name in ("batch_size", "epochs", "log_every", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.max_steps is not None and self.max_steps < 1:
            raise ValueError(f"max_steps must be at least 1, got {self.max_steps}")
        if not self.lr > 0 or not self.width > 0:
            raise ValueError(f"lr and width must be > 0, got {self.lr} and {self.width}")
        if self.lr_schedule not in typing.get_args(LRSchedule):
            raise ValueError(f"lr_schedule must be one of {typing.get_args(LRSchedule)}, got {self.lr_schedule!r}")
        if self.feature_cache not in typing.get_args(FeatureCache):
            raise ValueError(f"feature_cache must be one of {typing.get_args(FeatureCache)}, "
                             f"got {self.feature_cache!r}")
        if not self.feature_cache_gib >= 0:
            raise ValueError(f"feature_cache_gib must be >= 0, got {self.feature_cache_gib}")
        if not 0 < self.bn_momentum <= 1:
            raise ValueError(f"bn_momentum must be in (0, 1], got {self.bn_momentum}")
        object.__setattr__(self, "stores", tuple(str(s) for s in self.stores))

    def to_dict(self) -> dict:
        """The resolved config as JSON-ready data (what ``RUN/config.json`` holds)."""
        from sceneforge.config import dataclass_to_dict

        return dataclass_to_dict(self)

    @classmethod
    def from_dict(cls, data: dict, *, what: str = "train config") -> "TrainConfig":
        """Validate ``data`` against ``schemas/train.schema.json`` and build the config.

        Raises :class:`SceneforgeError` naming ``what`` and the problem.
        """
        from sceneforge.config import build_config

        return build_config(cls, _without_legacy_keys(data), schema="train", what=what)

    def with_frozen_runs(self, root: str | Path) -> "TrainConfig":
        """The config with every frozen run its stage reads and that is not set taken from
        ``root/<stage>`` (``runs/depth`` for ``root="runs"``)."""
        unset = {f"{s}_run": str(Path(root) / s) for s in FROZEN.get(self.stage, ())
                 if getattr(self, f"{s}_run") is None}
        return replace(self, **unset)


def _without_legacy_keys(data: dict) -> dict:
    """``data`` without keys that older runs saved and that are no longer settings: the
    EFT's ``resolution`` now always comes from the stores' overhead size."""
    eft = data.get("eft")
    if isinstance(eft, dict) and "resolution" in eft:
        data = {**data, "eft": {k: v for k, v in eft.items() if k != "resolution"}}
    return data


@dataclass(frozen=True)
class PredictConfig:
    """How a trained run's predictions are made (what they are is the run's own config)."""

    #: the fields naming files or folders, made absolute when the config is resolved
    PATHS: typing.ClassVar[tuple[str, ...]] = ("camera_run", "split_file")

    #: views per batch
    batch_size: int = 8
    #: a camera proposal run: place the overhead cameras from its predictions instead of
    #: the store's
    camera_run: str | None = None
    #: the views to predict: those of the houses of this split ("all": every view)
    split: SplitName = "test"
    #: the split file; None = the one the run was trained with
    split_file: str | None = None
    #: how the floor is removed from the overhead heights: "segmentation" (where the overhead
    #: segmentation net sees background, the paper's) or "height" (only by the threshold);
    #: heights at or below 5 cm are removed either way (the paper evaluates only above)
    floor_removal: FloorRemoval = "segmentation"
    #: keep a frontal object pixel (D1..D4) only where the segmentation net's object
    #: probability (1 minus background's) is at least this, besides its arg-max: fewer,
    #: surer points (precision for recall); None = the arg-max alone (the paper's)
    min_object_probability: float | None = None
    #: the same for the overhead heights, with the overhead segmentation net
    min_overhead_object_probability: float | None = None
    #: how those two are set: "given" (as above) or "validation": chosen per run on the
    #: validation houses of the split, where precision meets recall (the largest
    #: min(precision, recall) at 5 cm of D1-4 & overhead against objects; the two above must
    #: then be unset)
    operating_point: OperatingPointRule = "given"
    #: the most validation views the operating point is chosen on (evenly spread)
    operating_point_views: int = 48

    def __post_init__(self):
        for name in ("min_object_probability", "min_overhead_object_probability"):
            value = getattr(self, name)
            if value is not None and not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be None or between 0 and 1, got {value}")
        if self.floor_removal not in typing.get_args(FloorRemoval):
            raise ValueError(f"floor_removal must be one of {typing.get_args(FloorRemoval)}, "
                             f"got {self.floor_removal!r}")
        if self.split not in typing.get_args(SplitName):
            raise ValueError(f"split must be one of {typing.get_args(SplitName)}, got {self.split!r}")
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be at least 1, got {self.batch_size}")
        if self.operating_point not in typing.get_args(OperatingPointRule):
            raise ValueError(f"operating_point must be one of {typing.get_args(OperatingPointRule)}, "
                             f"got {self.operating_point!r}")
        if self.operating_point == "validation" and (self.min_object_probability is not None
                                                     or self.min_overhead_object_probability is not None):
            raise ValueError("operating_point 'validation' chooses min_object_probability and "
                             "min_overhead_object_probability: leave them unset")
        if self.operating_point_views < 1:
            raise ValueError(f"operating_point_views must be at least 1, got {self.operating_point_views}")

    def to_dict(self) -> dict:
        from sceneforge.config import dataclass_to_dict

        return dataclass_to_dict(self)

    @classmethod
    def from_dict(cls, data: dict, *, what: str = "predict config") -> "PredictConfig":
        """Validate ``data`` against ``schemas/predict.schema.json`` and build the config."""
        from sceneforge.config import build_config

        return build_config(cls, data, schema="predict", what=what)

