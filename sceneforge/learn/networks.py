"""The paper's networks (docs/spec.md §10.2; architectures of the authors' release *(ref)*).

Every network is a U-Net of five levels (full, ½, ¼, ⅛, 1/16 resolution) with skip
connections and dilated convolutions: the two finest levels use two 5×5 convolutions of
dilation 4, the coarser ones a 3×3 convolution of dilation 2 and two plain 3×3
convolutions; every convolution is followed by BatchNorm and a LeakyReLU (slope 0.01,
BatchNorm momentum 0.005, paper appendix). Inputs of any size are zero-padded to a
multiple of 16 and the outputs cropped back.

- :class:`FrontalDepthNet`: RGB → D1..D5, one output branch per layer; its 48-channel
  feature map (the trunk's output, just before the branches) feeds the EFT.
- :class:`FrontalSegNet`: RGB → 80 logits (40 classes × layers 1 and 3); 64 features.
- :class:`OverheadNet`: the EFT's 232 channels → height (1) or classes (40).
- :class:`CameraProposalNet`: the depth net's features and bottleneck → ``(tx, ty, sigma)``.
- :func:`masked_layers`: the depth net's layers, emptied where the segmentation net sees
  no object, as the paper reconstructs from predictions.

Widths come from the configs, so tests build the same architectures a few channels wide.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from .dataset import BACKGROUND, SEG_CLASSES

#: levels of every U-Net; inputs are padded to a multiple of 2 ** (LEVELS - 1)
LEVELS = 5
#: frontal depth layers predicted (D1..D5)
DEPTH_LAYERS = 5
#: frontal layers segmented (layers 1 and 3)
SEG_LAYERS = 2


@dataclass(frozen=True)
class UNetConfig:
    """Widths and normalisation of a U-Net (and of the frontal depth net's branches)."""

    #: channels of the five levels, finest first; the first is the width of the feature map
    #: the EFT reads (48 for depth, 64 for segmentation in the paper)
    channels: tuple[int, int, int, int, int] = (48, 64, 64, 384, 768)
    #: channels of the hidden layers of each output branch (depth net only)
    branch_channels: int = 32
    #: BatchNorm running-statistics momentum (PyTorch convention; paper appendix: 0.005)
    bn_momentum: float = 0.005
    #: negative slope of the LeakyReLUs (paper appendix)
    leaky_slope: float = 0.01

    def __post_init__(self):
        if len(self.channels) != LEVELS or min(self.channels) < 1:
            raise ValueError(f"channels must be {LEVELS} positive widths, got {self.channels}")
        if self.branch_channels < 1:
            raise ValueError(f"branch_channels must be >= 1, got {self.branch_channels}")

    def scaled(self, width: float) -> "UNetConfig":
        """The same architecture with every width multiplied by ``width`` (at least 2)."""
        if not width > 0:
            raise ValueError(f"width must be > 0, got {width}")
        return replace(self, channels=tuple(max(2, round(c * width)) for c in self.channels),
                       branch_channels=max(2, round(self.branch_channels * width)))


#: the paper's widths of each network *(ref)*
DEPTH_NET = UNetConfig()
SEG_NET = UNetConfig(channels=(64, 64, 64, 384, 768))
OVERHEAD_NET = UNetConfig(channels=(64, 64, 128, 256, 768))


@dataclass(frozen=True)
class CameraNetConfig:
    """Widths of the virtual camera proposal net."""

    #: channels of the four strided convolution stages over the depth net's feature map
    channels: tuple[int, int, int, int] = (64, 128, 256, 512)
    #: width of the hidden fully connected layer
    hidden: int = 1024
    #: BatchNorm momentum
    bn_momentum: float = 0.01

    def scaled(self, width: float) -> "CameraNetConfig":
        """Every width multiplied by ``width`` (at least 2)."""
        if not width > 0:
            raise ValueError(f"width must be > 0, got {width}")
        return replace(self, channels=tuple(max(2, round(c * width)) for c in self.channels),
                       hidden=max(2, round(self.hidden * width)))


def _norm_act(channels: int, config: UNetConfig) -> list[nn.Module]:
    return [nn.BatchNorm2d(channels, momentum=config.bn_momentum), nn.LeakyReLU(config.leaky_slope)]


def wide_block(cin: int, cout: int, config: UNetConfig) -> nn.Sequential:
    """Two 5×5 convolutions of dilation 4 (a 17-pixel receptive field each)."""
    return nn.Sequential(
        nn.Conv2d(cin, cout, 5, padding=8, dilation=4, bias=False), *_norm_act(cout, config),
        nn.Conv2d(cout, cout, 5, padding=8, dilation=4, bias=False), *_norm_act(cout, config),
    )


def deep_block(cin: int, cout: int, config: UNetConfig) -> nn.Sequential:
    """A 3×3 convolution of dilation 2, then two plain 3×3 convolutions."""
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=2, dilation=2, bias=False), *_norm_act(cout, config),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False), *_norm_act(cout, config),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False), *_norm_act(cout, config),
    )


class UNet(nn.Module):
    """Encoder-decoder with skip connections; returns the finest decoder features.

    forward(x (B, C_in, H, W)) → (features (B, channels[0], H, W), encoding
    (B, channels[4], ⌈H/16⌉, ⌈W/16⌉) the bottleneck).
    """

    def __init__(self, in_channels: int, config: UNetConfig):
        super().__init__()
        c = config.channels
        blocks = (wide_block, wide_block, deep_block, deep_block, deep_block)
        self.encoders = nn.ModuleList(
            blocks[i](in_channels if i == 0 else c[i - 1], c[i], config) for i in range(LEVELS))
        self.decoders = nn.ModuleList(
            blocks[i](c[i + 1] + c[i], c[i], config) for i in reversed(range(LEVELS - 1)))

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        H, W = x.shape[-2:]
        m = 2 ** (LEVELS - 1)
        ph, pw = -H % m, -W % m
        x = F.pad(x, (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2))
        skips = []
        for i, encoder in enumerate(self.encoders):
            x = encoder(x if i == 0 else F.max_pool2d(x, 2))
            skips.append(x)
        encoding = out = skips.pop()
        for decoder in self.decoders:
            skip = skips.pop()
            out = decoder(torch.cat([skip, F.interpolate(out, size=skip.shape[-2:], mode="bilinear",
                                                         align_corners=False)], dim=1))
        return out[..., ph // 2: ph // 2 + H, pw // 2: pw // 2 + W], encoding


class FrontalOutput(NamedTuple):
    """What a frontal net returns.

    prediction : (B, 5, H, W) depths (depth net) or (B, 80, H, W) logits (segmentation net)
    features   : (B, channels[0], H, W) the trunk's output, the EFT's input
    encoding   : (B, channels[4], H/16, W/16) the bottleneck, the camera proposal's input
    """

    prediction: Tensor
    features: Tensor
    encoding: Tensor


class FrontalDepthNet(nn.Module):
    """RGB (B, 3, H, W), normalised → D1..D5 (B, 5, H, W) metres, one branch per layer."""

    def __init__(self, config: UNetConfig = DEPTH_NET):
        super().__init__()
        self.config = config
        self.trunk = UNet(3, config)
        c0, cb = config.channels[0], config.branch_channels
        self.branches = nn.ModuleList(
            nn.Sequential(deep_block(c0, cb, config), nn.Conv2d(cb, 1, 3, padding=1, bias=False))
            for _ in range(DEPTH_LAYERS))

    @property
    def feature_channels(self) -> int:
        return self.config.channels[0]

    def forward(self, rgb: Tensor) -> FrontalOutput:
        features, encoding = self.trunk(rgb)
        depth = torch.cat([branch(features) for branch in self.branches], dim=1)
        return FrontalOutput(depth, features, encoding)


class FrontalSegNet(nn.Module):
    """RGB (B, 3, H, W), normalised → logits (B, 80, H, W): channels ``40·k + c`` score class
    ``c`` (see :func:`sceneforge.learn.dataset.segmentation_target`) in layer ``k`` ∈ {1, 3}."""

    def __init__(self, config: UNetConfig = SEG_NET):
        super().__init__()
        self.config = config
        self.trunk = UNet(3, config)
        self.head = nn.Conv2d(config.channels[0], SEG_LAYERS * SEG_CLASSES, 3, padding=1)

    @property
    def feature_channels(self) -> int:
        return self.config.channels[0]

    def forward(self, rgb: Tensor) -> FrontalOutput:
        features, encoding = self.trunk(rgb)
        return FrontalOutput(self.head(features), features, encoding)


class OverheadNet(nn.Module):
    """EFT output (B, in_channels, R, R) → (B, out_channels, R, R): heights above the floor
    (``out_channels = 1``, metres) or class logits (``out_channels = 40``)."""

    def __init__(self, in_channels: int, out_channels: int, config: UNetConfig = OVERHEAD_NET):
        super().__init__()
        self.config = config
        self.trunk = UNet(in_channels, config)
        self.head = nn.Conv2d(config.channels[0], out_channels, 3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        return self.head(self.trunk(x)[0])


class CameraProposalNet(nn.Module):
    """The depth net's features (B, Cf, H, W) and bottleneck (B, Ce, h, w) → ``(tx, ty,
    sigma)`` (B, 3) of the virtual overhead camera, metres.

    Strided dilated convolutions over the features and the pooled bottleneck are joined by
    fully connected layers *(ref)*; global average pooling makes it independent of the
    image size.
    """

    def __init__(self, feature_channels: int, encoding_channels: int, config: CameraNetConfig | None = None):
        super().__init__()
        config = config or CameraNetConfig()
        self.config = config
        layers, cin = [], feature_channels
        for cout in config.channels:
            layers += [nn.Conv2d(cin, cout, 3, padding=2, dilation=2),
                       nn.BatchNorm2d(cout, momentum=config.bn_momentum), nn.ReLU(),
                       nn.MaxPool2d(2, ceil_mode=True)]
            cin = cout
        self.features = nn.Sequential(*layers, nn.AdaptiveAvgPool2d(1), nn.Flatten())
        self.encoding = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Flatten(),
                                      nn.Linear(encoding_channels, config.hidden), nn.ReLU())
        self.out = nn.Linear(cin + config.hidden, 3)

    def forward(self, features: Tensor, encoding: Tensor) -> Tensor:
        return self.out(torch.cat([self.features(features), self.encoding(encoding)], dim=1))


def masked_layers(depth: Tensor, logits: Tensor, min_probability: float | None = None) -> Tensor:
    """Predicted layers with the segmentation's support, NaN = empty (the store's convention).

    depth  : (B, 5, H, W) the depth net's D1..D5
    logits : (B, 80, H, W) the segmentation net's scores
    min_probability : None, or a pixel of a layer is an object only where its object
             probability (1 − background's) is at least this too (:func:`object_pixels`)
    Returns (B, 5, H, W): D1, D2 where layer 1's class is an object, D3, D4 where layer 3's
    is (and layer 1's), D5 everywhere.
    """
    B, _, H, W = logits.shape
    objects = object_pixels(logits.reshape(B, SEG_LAYERS, SEG_CLASSES, H, W), min_probability, dim=2)
    first, second = objects[:, 0], objects[:, 0] & objects[:, 1]
    keep = torch.stack([first, first, second, second, torch.ones_like(first)], dim=1)
    return torch.where(keep, depth, torch.full_like(depth, torch.nan))


def object_pixels(logits: Tensor, min_probability: float | None = None, dim: int = 1) -> Tensor:
    """Where class scores ``logits`` (classes along ``dim``) see an object: the arg-max
    class is not background (the paper's rule) and, with ``min_probability``, the
    probability of any object class, 1 − P(background), is at least that. The threshold
    trades recall for precision: it only ever removes pixels the arg-max keeps."""
    objects = logits.argmax(dim=dim) != BACKGROUND
    if min_probability is not None:
        background = logits.softmax(dim=dim).select(dim, BACKGROUND)
        objects &= (1.0 - background) >= min_probability
    return objects


def object_scores(logits: Tensor, dim: int = 1) -> Tensor:
    """The least ``min_probability`` at which :func:`object_pixels` keeps each pixel: its
    object probability, 1 − P(background), where the arg-max is an object, −1 where it is
    not (no threshold keeps it). ``object_pixels(logits, t) == (object_scores(logits) >= t)``
    for every t in [0, 1]."""
    objects = logits.argmax(dim=dim) != BACKGROUND
    background = logits.softmax(dim=dim).select(dim, BACKGROUND)
    return torch.where(objects, 1.0 - background, torch.full_like(background, -1.0))
