"""The training loop and its pieces, each on its own (used by :func:`sceneforge.learn.train.train`).

- :class:`Trainer`     — a stage's nets, their Adam optimiser and the frozen nets they read:
  one optimiser step on a batch, the mean loss over a dataset (validation)
- :class:`Checkpoint`  — ``checkpoint.pt``: weights, optimiser and :class:`Position`,
  replaced atomically, restored on resume; ``best.pt`` the same at the lowest validation loss
- :class:`MetricsLog`  — ``metrics.csv``, TensorBoard scalars and (optional) Weights & Biases
- :class:`EpochLoop`   — the schedule: epochs of steps in a seeded order, a train row every
  ``log_every`` steps (images/s of the training steps alone, validation time left out), a
  checkpoint every ``checkpoint_every`` steps and at the end of every epoch, validation
  (the loss and the stage's metrics, :mod:`.metrics`) after every whole epoch
"""

from __future__ import annotations

import csv
import importlib.util
import math
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

import torch
from torch import Tensor

from ..errors import SceneforgeError
from .config import TrainConfig
from .dataset import StoreDataset
from .eft import EpipolarFeatureTransformer
from .metrics import Metrics
from .stages import Nets, get_stage

CHECKPOINT = "checkpoint.pt"
#: the checkpoint of the lowest validation loss so far
BEST = "best.pt"


class TrainProgress(Protocol):
    """Receives a run's progress: ``start`` once, then ``step`` after every optimiser step."""

    def start(self, total: int, done: int) -> None: ...

    def step(self, step: int, loss: float) -> None: ...


@dataclass(frozen=True)
class Position:
    """Where a run is: optimiser steps done, the current epoch and the batches of it done."""

    step: int = 0
    epoch: int = 0
    batch: int = 0


def _loader(dataset, batch_size: int, sampler, workers: int, device: torch.device):
    return torch.utils.data.DataLoader(dataset, batch_size=batch_size, sampler=sampler, num_workers=workers,
                                       pin_memory=device.type == "cuda", persistent_workers=False)


def _to(batch: dict[str, Tensor], device: torch.device) -> dict[str, Tensor]:
    return {k: v.to(device, non_blocking=True) for k, v in batch.items()}


class Trainer:
    """The nets ``config.stage`` trains (initialised from ``config.seed``), their optimiser,
    and the frozen nets and EFT (None: the stage uses none) they read. Knows no files and
    no schedule."""

    def __init__(self, config: TrainConfig, frontal: Nets, eft: EpipolarFeatureTransformer | None,
                 device: torch.device):
        self.config, self.frontal, self.eft, self.device = config, frontal, eft, device
        self.stage = get_stage(config.stage)
        torch.manual_seed(config.seed)
        self.nets = self.stage.build(config, frontal)
        for net in self.nets.values():
            net.to(device).train()
        params = [p for net in self.nets.values() for p in net.parameters()]
        self.optimizer = torch.optim.Adam(params, lr=config.lr)

    def loss(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict[str, float]]:
        """The stage's loss on a batch (on the device) and its logged parts."""
        return self.stage.loss(self.config, self.nets, self.frontal, self.eft, batch)

    def step(self, batch: dict[str, Tensor], number: int) -> dict[str, float]:
        """One optimiser step on a batch; its losses as logged (``loss`` and the parts).

        number : the step's number, for the error a diverged loss raises
        """
        loss, parts = self.loss(batch)
        if not torch.isfinite(loss):
            raise SceneforgeError(f"step {number}: the loss is {loss.item()} (diverged); lower --lr")
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        return {"loss": loss.item(), **parts}

    def validate(self, dataset: StoreDataset, workers: int = 0) -> dict[str, float]:
        """Mean loss (``loss``) and the stage's :attr:`~.stages.Stage.val_metrics` over a
        dataset, nets in eval mode (and back in training mode after)."""
        for net in self.nets.values():
            net.eval()
        total, n, metrics = 0.0, 0, Metrics()
        with torch.no_grad():
            for batch in _loader(dataset, self.config.batch_size, None, workers, self.device):
                batch = _to(batch, self.device)
                outputs = self.stage.forward(self.config, self.nets, self.frontal, self.eft, batch)
                loss, _ = self.stage.objective(self.config, outputs, batch)
                self.stage.measure(self.config, outputs, batch, metrics)
                total += loss.item() * len(batch["index"])
                n += len(batch["index"])
        for net in self.nets.values():
            net.train()
        return {"loss": total / max(n, 1), **metrics.result()}


@dataclass(frozen=True)
class Checkpoint:
    """A run's ``checkpoint.pt``: the trained nets' weights (``models``), the optimiser,
    the :class:`Position` and the config, written to a temporary file and moved into place
    so an interrupted save leaves the previous checkpoint whole."""

    path: Path

    def exists(self) -> bool:
        return self.path.exists()

    def save(self, trainer: Trainer, at: Position) -> None:
        state = {"models": {k: v.state_dict() for k, v in trainer.nets.items()},
                 "optimizer": trainer.optimizer.state_dict(), "step": at.step, "epoch": at.epoch,
                 "batch": at.batch, "config": trainer.config.to_dict()}
        tmp = self.path.with_suffix(".tmp")
        torch.save(state, tmp)
        os.replace(tmp, self.path)

    def load(self, device: torch.device | str = "cpu") -> dict:
        """The saved state (tensors on ``device``)."""
        return torch.load(self.path, map_location=device, weights_only=True)

    def restore(self, trainer: Trainer) -> Position:
        """Load the weights and the optimiser into ``trainer``; where the run stopped."""
        state = self.load(trainer.device)
        for name, net in trainer.nets.items():
            net.load_state_dict(state["models"][name])
        trainer.optimizer.load_state_dict(state["optimizer"])
        return Position(state["step"], state["epoch"], state["batch"])


class MetricsLog:
    """``metrics.csv`` (and TensorBoard scalars when it is installed, Weights & Biases when
    asked for and installed: neither is a dependency).

    parts : the loss parts of train rows; metrics : the validation metrics of val rows
    wandb : a dict of ``wandb.init`` arguments (project, name, config, ...); None: off
    """

    def __init__(self, run: Path, parts: tuple[str, ...], resume_step: int | None, tensorboard: bool,
                 metrics: tuple[str, ...] = (), wandb: dict | None = None):
        self.path = run / "metrics.csv"
        self.columns = ["step", "epoch", "split", "loss", *parts, *metrics, "lr", "images_per_s", "seconds"]
        rows = []
        if resume_step is not None and self.path.exists():
            # rows logged after the checkpoint are redone by the resumed run
            rows = [r for r in read_metrics(self.path) if int(r["step"]) <= resume_step]
        self.rows = rows
        with self.path.open("w", newline="") as f:
            writer = csv.DictWriter(f, self.columns, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)
        self.wandb = None
        if wandb is not None:
            if importlib.util.find_spec("wandb") is None:
                raise SceneforgeError("--wandb needs the wandb package: pip install wandb")
            import wandb as wb

            self.wandb = wb.init(dir=str(run), resume="allow", **wandb)
        self.tb = None
        if tensorboard and importlib.util.find_spec("tensorboard") is not None:
            from torch.utils.tensorboard import SummaryWriter

            self.tb = SummaryWriter(str(run / "tensorboard"))

    def write(self, row: dict) -> None:
        self.rows.append(row)
        with self.path.open("a", newline="") as f:
            csv.DictWriter(f, self.columns).writerow(row)
        scalars = {key: float(row[key]) for key in self.columns[3:] if row.get(key) not in (None, "")}
        if self.tb is not None:
            for key, value in scalars.items():
                self.tb.add_scalar(f"{row['split']}/{key}", value, int(row["step"]))
        if self.wandb is not None:
            self.wandb.log({f"{row['split']}/{k}": v for k, v in scalars.items()}, step=int(row["step"]))

    def best_val_loss(self) -> float:
        """The lowest validation loss logged (inf: none)."""
        losses = [float(r["loss"]) for r in self.rows if r["split"] == "val"]
        return min(losses, default=math.inf)

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()
        if self.wandb is not None:
            self.wandb.finish()


def read_metrics(path: str | Path) -> list[dict]:
    """The rows of a run's ``metrics.csv`` as dicts of strings."""
    with Path(path).open(newline="") as f:
        return list(csv.DictReader(f))


class EpochSampler(torch.utils.data.Sampler):
    """Indices of one epoch: a permutation seeded by (seed, epoch), from batch ``start`` on."""

    def __init__(self, n: int, seed: int, epoch: int, start: int, batch_size: int):
        self.order = torch.randperm(n, generator=torch.Generator().manual_seed(seed * 100003 + epoch))
        self.order = self.order[start * batch_size:]

    def __iter__(self):
        return iter(self.order.tolist())

    def __len__(self) -> int:
        return len(self.order)


class _TrainWindow:
    """The training losses and images since the last train row of the metrics."""

    def __init__(self):
        self.started, self.images, self.sums, self.count = time.perf_counter(), 0, {}, 0
        self.paused = 0.0  # seconds spent on anything but training steps (validation)

    def add(self, images: int, losses: dict[str, float]) -> None:
        self.images += images
        for key, value in losses.items():
            self.sums[key] = self.sums.get(key, 0.0) + value
        self.count += 1

    def images_per_s(self) -> float:
        return self.images / max(time.perf_counter() - self.started - self.paused, 1e-9)

    def means(self) -> dict[str, float]:
        return {k: v / self.count for k, v in self.sums.items()}


class EpochLoop:
    """Steps a :class:`Trainer` from a :class:`Position` to ``total`` steps (or the last epoch),
    writing the metrics and checkpoints on the way (schedule: module docstring); after a
    validation with a lower loss than any before, the checkpoint is also saved as ``best``
    (None: not kept). After :meth:`run`, ``train_loss``/``val_loss`` are the last logged
    ones (NaN: none), ``val_metrics`` the last validation's, and ``images_per_s`` the rate
    of the last train row."""

    def __init__(self, trainer: Trainer, train_set: StoreDataset, val_set: StoreDataset | None, total: int,
                 log: MetricsLog, checkpoint: Checkpoint, workers: int = 0, progress: TrainProgress | None = None,
                 best: Checkpoint | None = None):
        self.trainer, self.config = trainer, trainer.config
        self.train_set, self.val_set, self.total = train_set, val_set, total
        self.log, self.checkpoint, self.workers, self.progress = log, checkpoint, workers, progress
        self.best, self.best_loss = best, log.best_val_loss()
        self.val_metrics: dict[str, float] = {}
        self.per_epoch = math.ceil(len(train_set) / self.config.batch_size)
        self.train_loss = self.val_loss = float("nan")
        self.images_per_s = 0.0
        self.started = time.perf_counter()
        self._window = _TrainWindow()

    def run(self, at: Position) -> Position:
        """Train from ``at``; where the run stopped (as saved in the last checkpoint)."""
        while at.step < self.total and at.epoch < self.config.epochs:
            at = self._epoch(at)
            if at.batch >= self.per_epoch:
                at = Position(at.step, at.epoch + 1, 0)
            improved = self.val_set is not None and at.batch == 0 and self._validate(at)
            self.checkpoint.save(self.trainer, at)
            if improved and self.best is not None:
                self.best.save(self.trainer, at)
        return at

    def _epoch(self, at: Position) -> Position:
        """The steps of epoch ``at.epoch`` from batch ``at.batch`` on, until it or the run ends."""
        config, dev = self.config, self.trainer.device
        sampler = EpochSampler(len(self.train_set), config.seed, at.epoch, at.batch, config.batch_size)
        for batch in _loader(self.train_set, config.batch_size, sampler, self.workers, dev):
            batch = _to(batch, dev)
            losses = self.trainer.step(batch, at.step)
            at = replace(at, step=at.step + 1, batch=at.batch + 1)
            self._window.add(len(batch["index"]), losses)
            if self.progress:
                self.progress.step(at.step, losses["loss"])
            if at.step % config.log_every == 0 or at.step == self.total:
                self._log_train(at)
            if at.step % config.checkpoint_every == 0:
                self.checkpoint.save(self.trainer, at)
            if at.step >= self.total:
                break
        return at

    def _log_train(self, at: Position) -> None:
        self.images_per_s = self._window.images_per_s()
        means = self._window.means()
        self.train_loss = means["loss"]
        self.log.write({"step": at.step, "epoch": at.epoch, "split": "train", "lr": self.config.lr, **means,
                        "images_per_s": round(self.images_per_s, 3), "seconds": self._seconds()})
        self._window = _TrainWindow()

    def _validate(self, at: Position) -> bool:
        """Validation after epoch ``at.epoch - 1``; whether its loss is the lowest so far."""
        started = time.perf_counter()
        self.val_metrics = self.trainer.validate(self.val_set, self.workers)
        self.val_loss = self.val_metrics["loss"]
        self.log.write({"step": at.step, "epoch": at.epoch - 1, "split": "val", **self.val_metrics,
                        "lr": self.config.lr, "seconds": self._seconds()})
        self._window.paused += time.perf_counter() - started
        improved = self.val_loss < self.best_loss
        self.best_loss = min(self.best_loss, self.val_loss)
        return improved

    def _seconds(self) -> float:
        return round(time.perf_counter() - self.started, 3)
