"""Training runs: one stage at a time, as in the paper (SPEC §10).

Stages, in order: ``depth`` and ``seg`` (frontal nets, on RGB), then ``overhead`` (height
and segmentation nets on the EFT of the *frozen* frontal nets' features) and ``camera``
(the virtual camera proposal on the frozen depth net's features). Adam, lr 5e-4, batch
24 *(paper)*.

A run lives in one folder::

    RUN/config.json        the resolved TrainConfig (reload: TrainConfig.from_dict)
    RUN/split.json         the houses (and view counts) of train / val / test
    RUN/checkpoint.pt      weights, optimiser and position; rewritten every
                           ``checkpoint_every`` steps and at the end of every epoch
    RUN/metrics.csv        step, epoch, split, loss (+ its parts), lr, images/s, seconds
    RUN/loss_curve.png     train and validation loss against steps, drawn at the end
    RUN/tensorboard/       the same scalars, when TensorBoard is installed

``train(config, run)`` with ``resume=True`` continues an interrupted run from its
checkpoint with the same data order (a seeded permutation per epoch).
"""

from __future__ import annotations

import csv
import importlib.util
import json
import math
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

import torch
from torch import Tensor, nn

from ..errors import MissingDependencyError, SceneforgeError
from .config import FROZEN, STAGES, TrainConfig  # noqa: F401  (re-exported: the config needs no torch)
from .dataset import SEG_CLASSES, SPLITS, StoreDataset, ViewIndex, index_stores, split_houses
from .eft import EpipolarFeatureTransformer, EpipolarGeometry, epipolar_geometry
from .losses import camera_loss, depth_loss, height_loss, segmentation_loss
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

#: the parts of each stage's loss logged beside it
LOSS_PARTS = {"depth": (), "seg": (), "overhead": ("height_l1", "seg_ce"), "camera": ()}
#: sample fields each stage reads (see :data:`sceneforge.learn.dataset.SAMPLE_FIELDS`)
FIELDS = {"depth": ("rgb", "depth"), "seg": ("rgb", "seg"),
          "overhead": ("rgb", "depth", "camera", "overhead_height", "overhead_seg"),
          "camera": ("rgb", "camera")}
CHECKPOINT = "checkpoint.pt"


# ------------------------------------------------------------------------- networks


def build_nets(config: TrainConfig, frontal: dict[str, nn.Module] | None = None) -> dict[str, nn.Module]:
    """The freshly initialised nets a stage trains, by name (the keys of a checkpoint's ``models``).

    frontal : the frozen nets of :func:`frontal_nets` (overhead and camera stages)
    """
    def widths(paper):
        return replace(paper.scaled(config.width), bn_momentum=config.bn_momentum)

    if config.stage == "depth":
        return {"depth": FrontalDepthNet(widths(DEPTH_NET))}
    if config.stage == "seg":
        return {"seg": FrontalSegNet(widths(SEG_NET))}
    if config.stage == "overhead":
        cin = EpipolarFeatureTransformer.out_channels(frontal["depth"].feature_channels,
                                                      frontal["seg"].feature_channels)
        return {"height": OverheadNet(cin, 1, widths(OVERHEAD_NET)),
                "overhead_seg": OverheadNet(cin, SEG_CLASSES, widths(OVERHEAD_NET))}
    depth = frontal["depth"]
    return {"camera": CameraProposalNet(depth.feature_channels, depth.config.channels[-1],
                                        widths(CameraNetConfig()))}


def load_run(run: str | Path, device: torch.device | str = "cpu") -> tuple[TrainConfig, dict[str, nn.Module]]:
    """A run's config and every net it runs, in eval mode: the nets it trained with the
    checkpoint's weights, plus (overhead and camera runs) its frozen frontal nets.

    Raises :class:`SceneforgeError` when the folder holds no checkpoint.
    """
    run = Path(run)
    config = read_config(run)
    path = run / CHECKPOINT
    if not path.exists():
        raise SceneforgeError(f"{run}: no {CHECKPOINT} (the run has not saved a step yet)")
    state = torch.load(path, map_location=device, weights_only=True)
    frontal = frontal_nets(config, device) if config.stage in ("overhead", "camera") else {}
    nets = build_nets(config, frontal)
    for name, net in nets.items():
        net.load_state_dict(state["models"][name])
        net.to(device).eval()
    return config, {**frontal, **nets}


def read_config(run: str | Path) -> TrainConfig:
    """The resolved config saved in a run folder."""
    path = Path(run) / "config.json"
    try:
        data = json.loads(path.read_text())
    except OSError:
        raise SceneforgeError(f"{run}: not a training run (no readable config.json)") from None
    return TrainConfig.from_dict(data, what=str(path))


def frontal_nets(config: TrainConfig, device: torch.device | str = "cpu") -> dict[str, nn.Module]:
    """The frozen frontal nets an overhead (depth + seg) or camera (depth) stage reads."""
    needed = FROZEN[config.stage]
    nets = {}
    for stage in needed:
        run = getattr(config, f"{stage}_run")
        if run is None:
            raise SceneforgeError(f"the {config.stage} stage needs a trained {stage} run (--{stage}-run)")
        frozen_config, loaded = load_run(run, device)
        if frozen_config.stage != stage:
            raise SceneforgeError(f"{run} is a {frozen_config.stage} run, not a {stage} run")
        nets[stage] = loaded[stage].requires_grad_(False)
    return nets


def geometry(batch: dict[str, Tensor], frontal_hw: tuple[int, int], resolution: int) -> EpipolarGeometry:
    """The EFT geometry of a batch with the ``camera`` fields (K at the images' resolution)."""
    return epipolar_geometry(batch["K"], batch["cam_to_world"], batch["overhead_cam_to_world"],
                             batch["overhead_extent"], batch["overhead_params"][:, 2], frontal_hw, resolution)


@torch.no_grad()
def overhead_input(frontal: dict[str, nn.Module], eft: EpipolarFeatureTransformer, batch: dict[str, Tensor],
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


def stage_loss(config: TrainConfig, nets: dict[str, nn.Module], frontal: dict[str, nn.Module],
               eft: EpipolarFeatureTransformer | None, batch: dict[str, Tensor]
               ) -> tuple[Tensor, dict[str, float]]:
    """The stage's loss on a batch and its logged parts (:data:`LOSS_PARTS`)."""
    if config.stage == "depth":
        return depth_loss(nets["depth"](batch["rgb"]).prediction, batch["depth"], config.loss), {}
    if config.stage == "seg":
        return segmentation_loss(nets["seg"](batch["rgb"]).prediction, batch["seg"]), {}
    if config.stage == "overhead":
        x, _, _ = overhead_input(frontal, eft, batch, config.eft_layers == "truth")
        h = height_loss(nets["height"](x), batch["overhead_height"])
        s = segmentation_loss(nets["overhead_seg"](x), batch["overhead_seg"])
        return h + config.loss.overhead_seg_weight * s, {"height_l1": h.item(), "seg_ce": s.item()}
    with torch.no_grad():
        out = frontal["depth"](batch["rgb"])
    pred = nets["camera"](out.features, out.encoding)
    return camera_loss(pred, batch["overhead_params"][:, [0, 1, 4]].to(pred.dtype)), {}


# --------------------------------------------------------------------------- running


class TrainProgress(Protocol):
    """Receives a run's progress: ``start`` once, then ``step`` after every optimiser step."""

    def start(self, total: int, done: int) -> None: ...

    def step(self, step: int, loss: float) -> None: ...


@dataclass(frozen=True)
class TrainResult:
    """What a run did: its folder, steps, and the last logged losses (NaN: none)."""

    run: Path
    steps: int
    epochs: int
    train_loss: float
    val_loss: float
    images_per_s: float
    seconds: float


def resolve_device(device: str) -> torch.device:
    """``auto`` → the GPU when one is present, else the CPU; otherwise the named device."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise SceneforgeError(f"device {device!r} asked for, but torch sees no CUDA GPU")
    return dev


class EpochSampler(torch.utils.data.Sampler):
    """Indices of one epoch: a permutation seeded by (seed, epoch), from batch ``start`` on."""

    def __init__(self, n: int, seed: int, epoch: int, start: int, batch_size: int):
        self.order = torch.randperm(n, generator=torch.Generator().manual_seed(seed * 100003 + epoch))
        self.order = self.order[start * batch_size:]

    def __iter__(self):
        return iter(self.order.tolist())

    def __len__(self) -> int:
        return len(self.order)


def _loader(dataset, batch_size: int, sampler, workers: int, device: torch.device):
    return torch.utils.data.DataLoader(dataset, batch_size=batch_size, sampler=sampler, num_workers=workers,
                                       pin_memory=device.type == "cuda", persistent_workers=False)


def _to(batch: dict[str, Tensor], device: torch.device) -> dict[str, Tensor]:
    return {k: v.to(device, non_blocking=True) for k, v in batch.items()}


class MetricsLog:
    """``metrics.csv`` (and TensorBoard scalars when it is installed)."""

    def __init__(self, run: Path, parts: tuple[str, ...], resume_step: int | None, tensorboard: bool):
        self.path = run / "metrics.csv"
        self.columns = ["step", "epoch", "split", "loss", *parts, "lr", "images_per_s", "seconds"]
        rows = []
        if resume_step is not None and self.path.exists():
            # rows logged after the checkpoint are redone by the resumed run
            rows = [r for r in read_metrics(self.path) if int(r["step"]) <= resume_step]
        with self.path.open("w", newline="") as f:
            writer = csv.DictWriter(f, self.columns)
            writer.writeheader()
            writer.writerows(rows)
        self.tb = None
        if tensorboard and importlib.util.find_spec("tensorboard") is not None:
            from torch.utils.tensorboard import SummaryWriter

            self.tb = SummaryWriter(str(run / "tensorboard"))

    def write(self, row: dict) -> None:
        with self.path.open("a", newline="") as f:
            csv.DictWriter(f, self.columns).writerow(row)
        if self.tb is not None:
            for key in self.columns[3:]:
                if row.get(key) not in (None, ""):
                    self.tb.add_scalar(f"{row['split']}/{key}", float(row[key]), int(row["step"]))

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()


def read_metrics(path: str | Path) -> list[dict]:
    """The rows of a run's ``metrics.csv`` as dicts of strings."""
    with Path(path).open(newline="") as f:
        return list(csv.DictReader(f))


def plot_loss_curve(run: str | Path) -> Path:
    """Draw ``loss_curve.png`` (train and validation loss against steps) from the metrics."""
    from matplotlib.figure import Figure

    run = Path(run)
    rows = read_metrics(run / "metrics.csv")
    fig = Figure(figsize=(7, 4))
    ax = fig.add_subplot()
    for split, style in (("train", "-"), ("val", "o-")):
        pts = [(int(r["step"]), float(r["loss"])) for r in rows if r["split"] == split]
        if pts:
            ax.plot(*zip(*pts), style, label=split, markersize=4)
    config = read_config(run)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_title(f"{config.stage}: batch {config.batch_size}, lr {config.lr:g}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    out = run / "loss_curve.png"
    fig.savefig(out, dpi=100, bbox_inches="tight")
    return out


def _save(path: Path, state: dict) -> None:
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def _prepare_run(config: TrainConfig, run: Path, resume: bool) -> TrainConfig:
    """Check the run folder; with ``resume``, the config must be the saved one (epochs and
    max_steps may change) and that is what the run continues with."""
    has_checkpoint = (run / CHECKPOINT).exists()
    if not resume:
        if has_checkpoint:
            raise SceneforgeError(f"{run} already holds a run: pass --resume to continue it, or choose "
                                  "another run folder")
        return config
    if not has_checkpoint:
        raise SceneforgeError(f"{run}: nothing to resume (no {CHECKPOINT})")
    saved = read_config(run)
    ours = replace(config, epochs=saved.epochs, max_steps=saved.max_steps)
    if ours != saved:
        diff = [k for k, v in saved.to_dict().items() if ours.to_dict()[k] != v]
        raise SceneforgeError(f"{run}: --resume with a different config ({', '.join(diff)}); start a new run")
    return replace(saved, epochs=config.epochs, max_steps=config.max_steps)


def _split(config: TrainConfig) -> tuple[ViewIndex, dict[str, ViewIndex], dict]:
    """The stores' views split by house, and the record of the split for ``split.json``."""
    index = index_stores(config.stores)
    houses = split_houses(index.house, config.split)
    subsets = {s: index.subset(houses[s]) for s in SPLITS}
    if not len(subsets["train"]):
        raise SceneforgeError(f"no training views: the split leaves {len(index)} views of "
                              f"{len(set(index.house))} houses to validation and test")
    record = {"stores": list(config.stores), "seed": config.split.seed,
              **{s: {"houses": houses[s], "views": len(subsets[s])} for s in SPLITS}}
    return index, subsets, record


def _evaluate(config, nets, frontal, eft, dataset, device, workers) -> float:
    """Mean loss over a dataset, nets in eval mode."""
    for net in nets.values():
        net.eval()
    total, n = 0.0, 0
    with torch.no_grad():
        for batch in _loader(dataset, config.batch_size, None, workers, device):
            batch = _to(batch, device)
            loss, _ = stage_loss(config, nets, frontal, eft, batch)
            total += loss.item() * len(batch["index"])
            n += len(batch["index"])
    for net in nets.values():
        net.train()
    return total / max(n, 1)


def train(
    config: TrainConfig,
    run: str | Path,
    *,
    device: str = "auto",
    workers: int = 0,
    resume: bool = False,
    tensorboard: bool = True,
    progress: TrainProgress | None = None,
) -> TrainResult:
    """Train ``config.stage`` into the folder ``run`` (layout: module docstring).

    device  : ``auto`` (the GPU when present), ``cpu``, ``cuda``, ``cuda:1``, ...
    workers : DataLoader worker processes (0: read in this process)
    resume  : continue the run saved in ``run`` (same config; ``epochs``/``max_steps`` may grow)
    Raises :class:`SceneforgeError` for unusable stores, a missing frozen run, or a run
    folder that already holds a run (without ``resume``).
    """
    if importlib.util.find_spec("matplotlib") is None:
        raise MissingDependencyError("matplotlib", "the loss curve of a training run",
                                     "pip install sceneforge[learn]")
    run = Path(run)
    # frozen runs are found again from any working directory
    config = replace(config, depth_run=config.depth_run and str(Path(config.depth_run).resolve()),
                     seg_run=config.seg_run and str(Path(config.seg_run).resolve()))
    config = _prepare_run(config, run, resume)
    dev = resolve_device(device)
    frontal = frontal_nets(config, dev) if config.stage in ("overhead", "camera") else {}
    index, subsets, split_record = _split(config)
    run.mkdir(parents=True, exist_ok=True)
    (run / "split.json").write_text(json.dumps(split_record, indent=2) + "\n")
    (run / "config.json").write_text(json.dumps(config.to_dict(), indent=2) + "\n")

    torch.manual_seed(config.seed)
    nets = build_nets(config, frontal)
    for net in nets.values():
        net.to(dev).train()
    # the overhead nets are supervised at the stores' overhead resolution
    eft = EpipolarFeatureTransformer(config.eft, resolution=index.shapes["Wo"]) if config.stage == "overhead" else None
    params = [p for net in nets.values() for p in net.parameters()]
    optimizer = torch.optim.Adam(params, lr=config.lr)

    step = epoch = start_batch = 0
    if resume:
        state = torch.load(run / CHECKPOINT, map_location=dev, weights_only=True)
        for name, net in nets.items():
            net.load_state_dict(state["models"][name])
        optimizer.load_state_dict(state["optimizer"])
        step, epoch, start_batch = state["step"], state["epoch"], state["batch"]

    fields = FIELDS[config.stage]
    train_set = StoreDataset(subsets["train"], fields, config.floor_as_zero)
    val_set = StoreDataset(subsets["val"], fields, config.floor_as_zero) if len(subsets["val"]) else None
    per_epoch = math.ceil(len(train_set) / config.batch_size)
    total = config.epochs * per_epoch if config.max_steps is None else min(config.max_steps,
                                                                           config.epochs * per_epoch)
    log = MetricsLog(run, LOSS_PARTS[config.stage], step if resume else None, tensorboard)
    if progress:
        progress.start(total, step)

    def checkpoint(epoch_: int, batch_: int) -> None:
        _save(run / CHECKPOINT, {"models": {k: v.state_dict() for k, v in nets.items()},
                                 "optimizer": optimizer.state_dict(), "step": step, "epoch": epoch_,
                                 "batch": batch_, "config": config.to_dict()})

    t_run = time.perf_counter()
    t_log, images, sums, count = time.perf_counter(), 0, {}, 0
    last_train = last_val = float("nan")
    rate = 0.0
    while step < total and epoch < config.epochs:
        sampler = EpochSampler(len(train_set), config.seed, epoch, start_batch, config.batch_size)
        batch_no = start_batch
        for batch in _loader(train_set, config.batch_size, sampler, workers, dev):
            batch = _to(batch, dev)
            loss, parts = stage_loss(config, nets, frontal, eft, batch)
            if not torch.isfinite(loss):
                raise SceneforgeError(f"step {step}: the loss is {loss.item()} (diverged); lower --lr")
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            step, batch_no = step + 1, batch_no + 1
            images += len(batch["index"])
            for key, value in {"loss": loss.item(), **parts}.items():
                sums[key] = sums.get(key, 0.0) + value
            count += 1
            if progress:
                progress.step(step, loss.item())
            if step % config.log_every == 0 or step == total:
                rate = images / max(time.perf_counter() - t_log, 1e-9)
                last_train = sums["loss"] / count
                log.write({"step": step, "epoch": epoch, "split": "train", "lr": config.lr,
                           **{k: v / count for k, v in sums.items()}, "images_per_s": round(rate, 3),
                           "seconds": round(time.perf_counter() - t_run, 3)})
                t_log, images, sums, count = time.perf_counter(), 0, {}, 0
            if step % config.checkpoint_every == 0:
                checkpoint(epoch, batch_no)
            if step >= total:
                break
        if batch_no >= per_epoch:
            epoch, start_batch = epoch + 1, 0
        else:
            start_batch = batch_no
        if val_set is not None and start_batch == 0:
            last_val = _evaluate(config, nets, frontal, eft, val_set, dev, workers)
            log.write({"step": step, "epoch": epoch - 1, "split": "val", "loss": last_val, "lr": config.lr,
                       "seconds": round(time.perf_counter() - t_run, 3)})
        checkpoint(epoch, start_batch)
    log.close()
    plot_loss_curve(run)
    return TrainResult(run, step, epoch, last_train, last_val, rate, time.perf_counter() - t_run)
