"""The training loop and its pieces, each on its own (used by :func:`sceneforge.learn.train.train`).

- :class:`Trainer`     — a stage's nets, their Adam optimiser and the frozen nets they read:
  one optimiser step on a batch (in the run's mixed precision, :func:`resolve_amp`; a
  DistributedDataParallel copy of the nets with several processes, :mod:`.distributed`),
  the mean loss over a dataset (validation)
- :func:`make_loader`  — the DataLoader of a dataset: worker processes that open the
  stores themselves (forked where zarr survives a fork, else from a fork server), read
  whole batches and prefetch, kept for the whole run
- :class:`Checkpoint`  — ``checkpoint.pt``: weights, optimiser and :class:`Position`,
  replaced atomically, restored on resume; ``best.pt`` the same at the lowest validation loss
- :class:`MetricsLog`  — ``metrics.csv``, TensorBoard scalars and (optional) Weights & Biases
- :class:`EpochLoop`   — the schedule: epochs of steps in a seeded order, a train row every
  ``log_every`` steps (images/s of the training steps alone, validation and checkpoint
  writing left out), a checkpoint every ``checkpoint_every`` steps and at the end of every
  epoch, validation
  (the loss and the stage's metrics, :mod:`.metrics`) after every whole epoch, and a
  checkpoint of the last whole step when Ctrl-C or SIGTERM stops it (:func:`held_interrupts`);
  with several processes, each steps on its share of every batch (:class:`EpochSampler`)
  and rank 0 alone writes and validates. A step waits for nothing on the device: its
  losses are read once a train row (and before a checkpoint), and a non-finite one stops
  the run there, naming its step, before any checkpoint holds its weights
"""

from __future__ import annotations

import contextlib
import csv
import functools
import importlib.util
import math
import multiprocessing
import os
import signal
import threading
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

import torch
from torch import Tensor

from ..errors import SceneforgeError
from .config import TrainConfig
from .dataset import Samples, StoreDataset
from .distributed import Distributed, sync_batchnorm
from .eft import EpipolarFeatureTransformer
from .metrics import Metrics
from .stages import Nets, get_stage

CHECKPOINT = "checkpoint.pt"
#: the checkpoint of the lowest validation loss so far
BEST = "best.pt"


class TrainProgress(Protocol):
    """Receives a run's progress: ``start`` once, then ``step`` after every optimiser step
    with the mean loss of the last train row (NaN before the first): a step's own loss
    would wait for the device at every step."""

    def start(self, total: int, done: int) -> None: ...

    def step(self, step: int, loss: float) -> None: ...


@dataclass(frozen=True)
class Position:
    """Where a run is: optimiser steps done, the current epoch and the batches of it done."""

    step: int = 0
    epoch: int = 0
    batch: int = 0


@contextlib.contextmanager
def held_interrupts():
    """Hold Ctrl-C and SIGTERM back until the block ends, then deliver them to their own
    handlers: a block that changes a run's state (a step moves the BatchNorm statistics in
    its forward pass and the weights in the optimiser's; an epoch's end logs its validation
    and saves) is done whole or not at all, so the checkpoint an interrupt saves is one an
    uninterrupted run passes through. Only the main thread receives signals: elsewhere the
    block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = []
    previous = {s: signal.signal(s, lambda signum, frame: held.append(signum))
                for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    for s in dict.fromkeys(held):
        signal.raise_signal(s)


#: the most DataLoader worker processes a run starts by default (per training process)
MAX_DEFAULT_WORKERS = 4
#: batches each DataLoader worker prepares ahead of the one being trained on
PREFETCH = 4
#: modules the fork server imports once, so that each worker it forks starts at once
_WORKER_PRELOAD = ["torch", "sceneforge.learn.dataset"]


def default_workers(processes: int = 1) -> int:
    """DataLoader workers of a training process when none are asked for: the CPU cores this
    process may use, shared among the ``processes`` of a torchrun on this machine, at most
    :data:`MAX_DEFAULT_WORKERS` and at least 1."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(MAX_DEFAULT_WORKERS, cores // max(processes, 1)))


def worker_context(method: str | None = None) -> multiprocessing.context.BaseContext:
    """How DataLoader workers start (``method``: None = the default).

    Every worker opens the stores itself on first use (:class:`~.dataset.StoreDataset`
    pickles no zarr handle), so a forked worker shares no zarr state with the training
    process. Forking (fast, and scripts need no ``__main__`` guard) is the default where
    zarr resets its background event loop in a forked child; elsewhere workers come from a
    fork server, a fresh process that has imported torch and the dataset module and
    nothing else (as does ``method="forkserver"``), or are spawned where there is none.
    """
    methods = multiprocessing.get_all_start_methods()
    if method is None:
        from sceneforge.store import reads_survive_fork

        method = "fork" if "fork" in methods and reads_survive_fork() else "forkserver"
    if method == "forkserver" and method not in methods:
        method = "spawn"
    ctx = multiprocessing.get_context(method)
    if method == "forkserver":
        ctx.set_forkserver_preload(_WORKER_PRELOAD)
    return ctx


def _leave_interrupts_to_the_parent(worker: int) -> None:
    """A DataLoader worker ignores Ctrl-C and SIGTERM, which a terminal or a job scheduler
    sends the whole process group: killed by them, it would fail the training process
    ("DataLoader worker is killed by signal") before that saves its checkpoint; the
    training process ends its workers when it stops."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


def end_workers(loader: torch.utils.data.DataLoader | None) -> None:
    """End the worker processes of a :func:`make_loader` loader now. Dropping the loader is
    not enough after an error: the traceback keeps the loop's iterator alive, and at exit
    multiprocessing ends workers with the SIGTERM they ignore
    (:func:`_leave_interrupts_to_the_parent`), so the process would wait for them for ever."""
    iterator = getattr(loader, "_iterator", None)  # persistent workers: the loader keeps its iterator
    if iterator is not None:
        iterator._shutdown_workers()


def collate(samples: list, layout: torch.memory_format = torch.channels_last):
    """The ``collate_fn`` of :func:`make_loader`: the batch that :class:`~.dataset.Samples`
    carry as it was read (else the default collation); of a batch of named tensors, every
    4-D floating one in ``layout`` (:func:`memory_format`), as :func:`_to` moves it. Made so
    in the worker that read the batch, it leaves the training process nothing to copy on the
    CPU, and a GPU copy lands in the nets' layout."""
    batch = samples.batch if isinstance(samples, Samples) else torch.utils.data.default_collate(samples)
    if not isinstance(batch, dict):
        return batch
    return {k: v.contiguous(memory_format=layout) if torch.is_tensor(v) and v.dim() == 4
            and v.is_floating_point() else v for k, v in batch.items()}


def make_loader(dataset, device: torch.device, workers: int, *, batch_size: int = 1, batch_sampler=None,
                timeout: float = 0, start: str | None = None,
                layout: torch.memory_format = torch.channels_last) -> torch.utils.data.DataLoader:
    """A DataLoader of ``dataset`` in batches of ``batch_size`` in order, or those of
    ``batch_sampler``. A dataset with ``__getitems__`` (:class:`~.dataset.StoreDataset`)
    reads each batch at once, in the worker that makes it, and the batch comes as it was
    read (:func:`collate`). With ``workers`` > 0 they are
    :func:`worker_context` processes (``start``: its method) kept alive between epochs
    (persistent), each :data:`PREFETCH` batches ahead, that leave Ctrl-C and SIGTERM to this
    process; on CUDA the batches come in pinned memory (copied to the GPU without blocking,
    :func:`_to`). Batches come in the sampler's order whatever the number of workers.

    timeout : seconds to wait for a worker's batch before raising (0: for ever)
    layout  : the images' memory layout (:func:`collate`; the nets', :func:`memory_format`)
    """
    kw = {"num_workers": workers, "pin_memory": device.type == "cuda",
          "collate_fn": functools.partial(collate, layout=layout)}
    if workers > 0:
        kw.update(multiprocessing_context=worker_context(start), persistent_workers=True, timeout=timeout,
                  prefetch_factor=PREFETCH, worker_init_fn=_leave_interrupts_to_the_parent)
    if batch_sampler is not None:
        return torch.utils.data.DataLoader(dataset, batch_sampler=batch_sampler, **kw)
    return torch.utils.data.DataLoader(dataset, batch_size=batch_size, shuffle=False, **kw)


def resolve_amp(amp: str, device: torch.device) -> str:
    """The mixed precision ``amp`` (``TrainConfig.amp``) means on ``device``: ``auto`` is
    ``bf16`` on a CUDA GPU that supports bfloat16 and ``off`` anywhere else."""
    if amp != "auto":
        return amp
    return "bf16" if device.type == "cuda" and torch.cuda.is_bf16_supported() else "off"


def cpu_has_bf16(cpuinfo: str | None = None) -> bool:
    """Whether the CPU computes bfloat16 itself: ``avx512_bf16`` or ``amx_bf16`` among the
    flags of ``cpuinfo`` (default: /proc/cpuinfo; False where there is none). Elsewhere
    PyTorch emulates bf16, several times slower than float32 (docs/benchmarks.md)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return False
    flags = {f for line in cpuinfo.splitlines() if line.startswith("flags") for f in line.split(":", 1)[-1].split()}
    return bool(flags & {"avx512_bf16", "amx_bf16"})


#: autocast dtypes of the mixed-precision modes
AMP_DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16}


def memory_format(device: torch.device, amp: str) -> torch.memory_format:
    """The layout of the nets and images on ``device`` in mixed precision ``amp`` (resolved,
    :func:`resolve_amp`): channels-last (NHWC), where cuDNN's convolutions (and tensor
    cores under mixed precision) and oneDNN's fp32 ones on the CPU are fastest (a
    width-0.25 depth step of 8 views at 160×120 on 2 cores: 0.58 s against 0.77 s
    contiguous); but contiguous for autocast on the CPU, where PyTorch 2.13's bfloat16
    backward of a dilated convolution in channels-last gives NaN gradients or crashes
    (the depth net's first step; ``tests/test_learn_fast.py``)."""
    if device.type == "cpu" and amp != "off":
        return torch.contiguous_format
    return torch.channels_last


def _to(batch: dict[str, Tensor], device: torch.device,
        layout: torch.memory_format = torch.channels_last) -> dict[str, Tensor]:
    """The batch on ``device``, its images (4-D floating tensors) in ``layout``
    (:func:`memory_format`)."""
    out = {}
    for k, v in batch.items():
        if v.dim() == 4 and v.is_floating_point():
            out[k] = v.to(device, non_blocking=True, memory_format=layout)
        else:
            out[k] = v.to(device, non_blocking=True)
    return out


def _float(outputs: dict[str, Tensor]) -> dict[str, Tensor]:
    """The nets' outputs in float32: the losses are computed outside autocast."""
    return {k: v.float() if torch.is_tensor(v) and v.is_floating_point() else v for k, v in outputs.items()}


class Trainer:
    """The nets ``config.stage`` trains (initialised from ``config.seed``), their optimiser,
    and the frozen nets and EFT (None: the stage uses none) they read. Knows no files and
    no schedule.

    Mixed precision (``config.amp``, :func:`resolve_amp`): the nets' forward pass runs
    under autocast, the losses in float32; fp16 scales the loss (a GradScaler, its state
    saved in the checkpoint). The nets and images are channels-last but for autocast on the
    CPU (:func:`memory_format`).
    With ``dist`` enabled, the nets train as DistributedDataParallel copies (``train_nets``;
    ``nets`` are the modules themselves, what checkpoints save), their BatchNorms over the
    whole batch when ``config.sync_batchnorm``.
    """

    def __init__(self, config: TrainConfig, frontal: Nets, eft: EpipolarFeatureTransformer | None,
                 device: torch.device, dist: Distributed | None = None):
        self.config, self.frontal, self.eft, self.device = config, frontal, eft, device
        self.dist = dist or Distributed()
        self.stage = get_stage(config.stage)
        self.amp = resolve_amp(config.amp, device)
        if self.amp == "bf16" and device.type == "cuda" and not torch.cuda.is_bf16_supported():
            raise SceneforgeError(f"--amp bf16: {torch.cuda.get_device_name(device)} has no bfloat16; "
                                  "use --amp fp16 or off")
        if self.amp == "bf16" and device.type == "cpu" and not cpu_has_bf16():
            warnings.warn("--amp bf16 on a CPU without avx512_bf16 or amx_bf16: PyTorch emulates bfloat16 "
                          "there, several times slower than --amp off", stacklevel=2)
        self.layout = memory_format(device, self.amp)
        torch.manual_seed(config.seed)
        self.nets = self.stage.build(config, frontal)
        for name, net in self.nets.items():
            if self.dist.enabled and config.sync_batchnorm:
                net = self.nets[name] = sync_batchnorm(net, device)
            net.to(device, memory_format=self.layout).train()
        for net in frontal.values():
            net.to(memory_format=self.layout)
        params = [p for net in self.nets.values() for p in net.parameters()]
        self.optimizer = torch.optim.Adam(params, lr=config.lr)
        self.scaler = torch.amp.GradScaler(device.type, enabled=self.amp == "fp16")
        self.train_nets = self.nets
        if self.dist.enabled:
            from torch.nn.parallel import DistributedDataParallel

            ids = [device.index] if device.type == "cuda" else None
            self.train_nets = {k: DistributedDataParallel(v, device_ids=ids) for k, v in self.nets.items()}

    def autocast(self):
        """The context of the nets' forward pass: autocast in the run's precision."""
        if self.amp == "off":
            return contextlib.nullcontext()
        return torch.autocast(self.device.type, dtype=AMP_DTYPES[self.amp])

    def _outputs(self, nets: Nets, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        if self.amp == "off":
            return self.stage.forward(self.config, nets, self.frontal, self.eft, batch)
        with self.autocast():
            outputs = self.stage.forward(self.config, nets, self.frontal, self.eft, batch)
        return _float(outputs)

    def loss(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]]:
        """The stage's loss on a batch (on the device) and its logged parts (0-d, detached)."""
        return self.stage.objective(self.config, self._outputs(self.train_nets, batch), batch)

    def set_lr(self, lr: float) -> None:
        """The learning rate of the next steps (the schedule's, :func:`learning_rate`)."""
        for group in self.optimizer.param_groups:
            group["lr"] = lr

    def step(self, batch: dict[str, Tensor], number: int) -> dict[str, Tensor]:
        """One optimiser step on a batch; its losses as logged (``loss`` and the parts),
        0-d tensors on the device, detached. Nothing here waits for the device (no host
        synchronisation; fp16's loss scaler excepted): reading a loss does, so the loop
        reads them once a train row (:class:`EpochLoop`), and :func:`check_finite` tells
        a diverged one.

        number : which views ``config.flip`` mirrors (:func:`mirrored`)
        """
        if self.config.flip and self.stage.flip_fields:
            batch = mirrored(batch, self.stage.flip_fields, self.config.seed, number)
        loss, parts = self.loss(batch)
        self.optimizer.zero_grad(set_to_none=True)
        self.scaler.scale(loss).backward()
        self.scaler.step(self.optimizer)
        self.scaler.update()
        return {"loss": loss.detach(), **parts}

    def validate(self, dataset: StoreDataset, workers: int = 0, loader=None) -> dict[str, float]:
        """Mean loss (``loss``) and the stage's :attr:`~.stages.Stage.val_metrics` over a
        dataset (read by ``loader`` when given), nets in eval mode (and back in training
        mode after)."""
        for net in self.nets.values():
            net.eval()
        total, n, metrics = torch.zeros((), dtype=torch.float64, device=self.device), 0, Metrics()
        own = loader is None
        if own:
            loader = make_loader(dataset, self.device, workers, batch_size=self.config.batch_size,
                                 layout=self.layout)
        try:
            with torch.no_grad():
                for batch in loader:
                    batch = _to(batch, self.device, self.layout)
                    outputs = self._outputs(self.nets, batch)
                    loss, _ = self.stage.objective(self.config, outputs, batch)
                    self.stage.measure(self.config, outputs, batch, metrics)
                    total += loss.detach() * len(batch["index"])
                    n += len(batch["index"])
        finally:
            if own:
                end_workers(loader)
        for net in self.nets.values():
            net.train()
        return {"loss": float(total) / max(n, 1), **metrics.result()}


def learning_rate(config: TrainConfig, step: int, total: int) -> float:
    """The learning rate of step ``step`` (0-based) of a run of ``total`` steps:
    ``config.lr`` throughout (``constant``), or half a cosine from ``config.lr`` at the
    first step to 0 after the last (``cosine``)."""
    if config.lr_schedule == "constant":
        return config.lr
    return config.lr * 0.5 * (1.0 + math.cos(math.pi * min(step, total) / max(total, 1)))


def mirrored(batch: dict[str, Tensor], fields: tuple[str, ...], seed: int, step: int) -> dict[str, Tensor]:
    """``batch`` with about half its views mirrored left-right in ``fields`` (images and
    image-aligned targets, last axis = columns): view ``index`` is mirrored at ``step``
    when a hash of (seed, step, index) is odd, so the choice is the same whatever the
    worker or process count and a resumed run makes it again."""
    index = batch["index"].to(torch.int64)
    h = (index * 0x9E3779B1 + step * 0x85EBCA77 + seed * 0xC2B2AE3D) & 0xFFFFFFFF
    h = ((h ^ (h >> 15)) * 0x2C1B3C6D) & 0xFFFFFFFF
    flip = ((h >> 16) & 1).bool()  # no test of whether any is set: that waits for the device
    out = dict(batch)
    for name in fields:
        v = batch[name]
        mask = flip.to(v.device).reshape(-1, *([1] * (v.dim() - 1)))
        out[name] = torch.where(mask, v.flip(-1), v)
    return out


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
        if trainer.scaler.is_enabled():
            state["scaler"] = trainer.scaler.state_dict()
        tmp = self.path.with_suffix(".tmp")
        torch.save(state, tmp)
        os.replace(tmp, self.path)

    def load(self, device: torch.device | str = "cpu") -> dict:
        """The saved state (tensors on ``device``)."""
        return torch.load(self.path, map_location=device, weights_only=True)

    def step(self) -> int:
        """The step it was saved at (the weights mapped, not read)."""
        return torch.load(self.path, map_location="cpu", weights_only=True, mmap=True)["step"]

    def restore(self, trainer: Trainer) -> Position:
        """Load the weights and the optimiser into ``trainer``; where the run stopped."""
        state = self.load(trainer.device)
        for name, net in trainer.nets.items():
            net.load_state_dict(state["models"][name])
        trainer.optimizer.load_state_dict(state["optimizer"])
        if trainer.scaler.is_enabled() and "scaler" in state:
            trainer.scaler.load_state_dict(state["scaler"])
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
    """The batches of an epoch (a batch sampler): a permutation of the ``n`` views seeded
    by (seed, epoch) cut into batches of ``batch_size``, from batch ``start`` on
    (:meth:`set_epoch`). Of ``world_size`` processes, rank ``rank`` takes its contiguous
    share of every batch (``batch_size / world_size`` views); of an epoch's short last
    batch, near-equal shares, and a process left none repeats one of its views (every
    process must take the same number of steps)."""

    def __init__(self, n: int, seed: int, batch_size: int, rank: int = 0, world_size: int = 1):
        if batch_size % world_size:
            raise SceneforgeError(f"--batch-size {batch_size} is not shared evenly by {world_size} processes: "
                                  f"use a multiple of {world_size}")
        self.n, self.seed, self.batch_size, self.rank, self.world_size = n, seed, batch_size, rank, world_size
        self.set_epoch(0)

    def set_epoch(self, epoch: int, start: int = 0) -> None:
        """Serve epoch ``epoch`` from its batch ``start`` on."""
        order = torch.randperm(self.n, generator=torch.Generator().manual_seed(self.seed * 100003 + epoch))
        self.order = order[start * self.batch_size:]

    def __iter__(self):
        for first in range(0, len(self.order), self.batch_size):
            batch = self.order[first:first + self.batch_size]
            share = batch.tensor_split(self.world_size)[self.rank]
            if not len(share):
                share = batch[self.rank % len(batch)].reshape(1)
            yield share.tolist()

    def __len__(self) -> int:
        return math.ceil(len(self.order) / self.batch_size)


def check_finite(losses: list[tuple[int, Tensor | float]]) -> None:
    """Raise :class:`SceneforgeError` naming the first of ``(step number, loss)`` whose loss
    is not finite (the run diverged); one wait for the device for them all."""
    if not losses:
        return
    values = torch.stack([torch.as_tensor(loss, dtype=torch.float64) for _, loss in losses]).cpu()
    bad = torch.nonzero(~torch.isfinite(values))
    if len(bad):
        k = int(bad[0, 0])
        raise SceneforgeError(f"step {losses[k][0]}: the loss is {values[k].item()} (diverged); lower --lr")


class _TrainWindow:
    """The training losses and images since the last train row of the metrics. Each step's
    losses stay where the step left them (on the device) until the row (:meth:`pooled`) or a
    checkpoint (:meth:`check`) reads them: one wait for the device per row, none per step."""

    def __init__(self):
        self.started, self.images, self.sums, self.count = time.perf_counter(), 0, {}, 0
        self.paused = 0.0  # seconds spent on anything but training steps (validation)
        self.losses: list[tuple[int, dict[str, Tensor]]] = []  # (step number, its losses)
        self.checked = 0  # losses[:checked] are known to be finite

    def add(self, number: int, images: int, losses: dict[str, Tensor | float]) -> None:
        self.images += images
        self.losses.append((number, losses))

    def check(self) -> None:
        """Raise :class:`SceneforgeError` when a loss since the last check is not finite."""
        check_finite([(n, losses["loss"]) for n, losses in self.losses[self.checked:]])
        self.checked = len(self.losses)

    def pooled(self, dist: Distributed) -> None:
        """Check the losses, then pool the images and loss sums of every process (each must
        call it at once)."""
        self.check()
        keys = sorted(self.losses[0][1])
        first = torch.as_tensor(self.losses[0][1]["loss"])
        as64 = dict(dtype=torch.float64, device=first.device)
        sums = [torch.stack([torch.as_tensor(losses[k], **as64) for _, losses in self.losses]).sum() for k in keys]
        values = dist.sum(torch.stack([torch.tensor(float(self.images), **as64),
                                       torch.tensor(float(len(self.losses)), **as64), *sums])).tolist()
        self.images, self.count = int(values[0]), int(values[1])
        self.sums = dict(zip(keys, values[2:]))

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
    of the last train row (of every process together).

    The data loaders (``workers`` processes each, :func:`make_loader`) live as long as the
    loop: :meth:`close` ends their workers. With several processes (``trainer.dist``), only
    rank 0 gets a ``log`` (the others None), saves checkpoints and validates.

    ``at`` is where the run is: the last whole step, or an epoch's end whose validation is
    done, logged and saved. Interrupted (KeyboardInterrupt: Ctrl-C, or SIGTERM where the
    CLI makes it one), :meth:`run` saves the checkpoint at ``at`` when a step was taken
    since it started; steps and epoch ends hold the interrupt back until they are whole
    (:func:`held_interrupts`), so a resumed run goes on as the uninterrupted one would.
    """

    def __init__(self, trainer: Trainer, train_set: StoreDataset, val_set: StoreDataset | None, total: int,
                 log: MetricsLog | None, checkpoint: Checkpoint, workers: int = 0,
                 progress: TrainProgress | None = None, best: Checkpoint | None = None):
        self.trainer, self.config, self.dist = trainer, trainer.config, trainer.dist
        self.train_set, self.val_set, self.total = train_set, val_set, total
        self.log, self.checkpoint, self.workers, self.progress = log, checkpoint, workers, progress
        self.best = best
        self.best_loss = log.best_val_loss() if log is not None else math.inf
        self.val_metrics: dict[str, float] = {}
        self.sampler = EpochSampler(len(train_set), self.config.seed, self.config.batch_size, self.dist.rank,
                                    self.dist.world_size)
        self.per_epoch = math.ceil(len(train_set) / self.config.batch_size)
        self.train_loss = self.val_loss = float("nan")
        self.images_per_s = 0.0
        self.started = time.perf_counter()
        dev = trainer.device
        layout = self.trainer.layout
        self._train_loader = make_loader(train_set, dev, workers, batch_sampler=self.sampler, layout=layout)
        self._val_loader = None
        if val_set is not None and self.dist.is_main:
            self._val_loader = make_loader(val_set, dev, workers, batch_size=self.config.batch_size,
                                           layout=layout)
        self._window = _TrainWindow()
        self.at = Position()

    def run(self, at: Position) -> Position:
        """Train from ``at``; where the run stopped (as saved in the last checkpoint)."""
        self.at = start = at
        try:
            # an interrupt during an epoch's validation saves the epoch's end (its last
            # batch done), which owes that validation even at the last step
            while at.batch >= self.per_epoch or (at.step < self.total and at.epoch < self.config.epochs):
                at = self._epoch(at)
                if at.batch >= self.per_epoch:
                    at = self._end_epoch(at)
                else:
                    with held_interrupts():
                        self._save(self.checkpoint, at)
        except KeyboardInterrupt:
            if self.at.step > start.step:
                with held_interrupts():  # a second Ctrl-C does not cut this save short
                    self._save(self.checkpoint, self.at)
            raise
        return at

    def close(self) -> None:
        """End the loaders' worker processes."""
        end_workers(self._train_loader)
        end_workers(self._val_loader)
        self._train_loader = self._val_loader = None

    def _save(self, checkpoint: Checkpoint, at: Position) -> None:
        if self.dist.is_main:
            self._window.check()  # a diverged run's weights are never saved
            started = time.perf_counter()
            checkpoint.save(self.trainer, at)
            self._window.paused += time.perf_counter() - started

    def _epoch(self, at: Position) -> Position:
        """The steps of epoch ``at.epoch`` from batch ``at.batch`` on, until it or the run ends."""
        config, dev = self.config, self.trainer.device
        self.sampler.set_epoch(at.epoch, at.batch)
        for batch in self._train_loader:
            with held_interrupts():
                batch = _to(batch, dev, self.trainer.layout)
                self.trainer.set_lr(learning_rate(config, at.step, self.total))
                losses = self.trainer.step(batch, at.step)
                self._window.add(at.step, len(batch["index"]), losses)
                self.at = at = replace(at, step=at.step + 1, batch=at.batch + 1)
                if at.step % config.log_every == 0 or at.step == self.total:
                    self._log_train(at)
                if at.step % config.checkpoint_every == 0:
                    self._save(self.checkpoint, at)
                if self.progress:
                    self.progress.step(at.step, self.train_loss)
            if at.step >= self.total:
                break
        return at

    def _end_epoch(self, at: Position) -> Position:
        """Validate after the epoch ``at`` finished, save, and move to the next epoch."""
        ended = Position(at.step, at.epoch + 1, 0)
        started = time.perf_counter()
        # validation changes nothing the checkpoint holds: an interrupt may stop it
        metrics = None if self._val_loader is None else self.trainer.validate(self.val_set, loader=self._val_loader)
        self._window.paused += time.perf_counter() - started
        with held_interrupts():
            improved = metrics is not None and self._log_validation(ended, metrics)
            self._save(self.checkpoint, ended)
            if improved and self.best is not None:
                self._save(self.best, ended)
            self.at = ended
        return ended

    def _log_train(self, at: Position) -> None:
        self._window.pooled(self.dist)
        self.images_per_s = self._window.images_per_s()
        means = self._window.means()
        self.train_loss = means["loss"]
        if self.log is not None:
            lr = learning_rate(self.config, at.step - 1, self.total)
            self.log.write({"step": at.step, "epoch": at.epoch, "split": "train", "lr": lr, **means,
                            "images_per_s": round(self.images_per_s, 3), "seconds": self._seconds()})
        self._window = _TrainWindow()

    def _log_validation(self, at: Position, metrics: dict[str, float]) -> bool:
        """Log the validation after epoch ``at.epoch - 1``; whether its loss is the lowest so far."""
        self.val_metrics = metrics
        self.val_loss = self.val_metrics["loss"]
        if self.log is not None:
            self.log.write({"step": at.step, "epoch": at.epoch - 1, "split": "val", **self.val_metrics,
                            "lr": learning_rate(self.config, at.step, self.total), "seconds": self._seconds()})
        improved = self.val_loss < self.best_loss
        self.best_loss = min(self.best_loss, self.val_loss)
        return improved

    def _seconds(self) -> float:
        return round(time.perf_counter() - self.started, 3)
