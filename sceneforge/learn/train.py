"""Training runs: one stage at a time, as in the paper (docs/spec.md §10.5).

Stages, in order: ``depth`` and ``seg`` (frontal nets, on RGB), then ``overhead`` (height
and segmentation nets on the EFT of the *frozen* frontal nets' features) and ``camera``
(the virtual camera proposal on the frozen depth net's features); each is an object of
:mod:`.stages`. Adam, lr 5e-4, batch 24 *(paper)*. The loop and its pieces (checkpoint,
metrics, validation) are in :mod:`.trainer`.

A run lives in one folder::

    RUN/config.json        the resolved TrainConfig (reload: TrainConfig.from_dict)
    RUN/split.json         the houses (and view counts) of train / val / test, as read
                           from the stores' split file (:mod:`.split`)
    RUN/checkpoint.pt      weights, optimiser and position; rewritten every
                           ``checkpoint_every`` steps and at the end of every epoch
    RUN/best.pt            the same, at the end of the epoch of the lowest validation loss
    RUN/metrics.csv        step, epoch, split, loss (+ its parts; + the validation metrics
                           of :mod:`.metrics` on val rows), lr, images/s, seconds
    RUN/loss_curve.png     train and validation loss against steps, drawn at the end
    RUN/tensorboard/       the same scalars, when TensorBoard is installed
    RUN/wandb/             the same, with ``wandb=True`` (Weights & Biases, if installed)
    RUN/feature_cache/     the overhead stage's input per view (:mod:`.cache`)

``train(config, run)`` with ``resume=True`` continues an interrupted run from its
checkpoint with the same data order (a seeded permutation per epoch). Ctrl-C or SIGTERM
saves the checkpoint of the last whole step first (:class:`~.trainer.EpochLoop`).

The run folder holds only what training writes: ``train`` refuses, before writing anything,
a folder that is, holds or lies inside one of its inputs (a store, a frozen run, the split
file) or lies inside any store, and a non-empty folder that is not a training run (no
readable ``config.json``). A run with no checkpoint never took a step and starts again.

Fast by default: DataLoader workers (:func:`.trainer.default_workers`), channels-last
nets and images, bf16 autocast and ``cudnn.benchmark`` on a GPU (``config.amp``); under ``torchrun`` one
process per GPU, each on its share of every batch (:mod:`.distributed`), rank 0 alone
writing the run folder.
"""

from __future__ import annotations

import importlib.util
import json
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from torch import nn

from ..errors import Interrupted, MissingDependencyError, SceneforgeError
from ..store.guard import check_apart, check_not_in_store
from ..store.location import resolve
from .cache import cached_datasets
from .config import STAGES, TrainConfig  # noqa: F401  (re-exported: the config needs no torch)
from .dataset import StoreDataset, ViewIndex, index_stores
from .distributed import Distributed
from .eft import EpipolarFeatureTransformer
from .split import SPLITS, default_split_file, fixed_split
from .stages import Stage, get_stage, overhead_input  # noqa: F401  (overhead_input: predict reads it here)
from .trainer import (
    BEST,
    CHECKPOINT,
    Checkpoint,
    EpochLoop,
    MetricsLog,
    Position,
    Trainer,
    TrainProgress,
    default_workers,
    read_metrics,
    resolve_amp,
)

# ------------------------------------------------------------------------- networks


def build_nets(config: TrainConfig, frontal: dict[str, nn.Module] | None = None) -> dict[str, nn.Module]:
    """The freshly initialised nets a stage trains, by name (the keys of a checkpoint's ``models``).

    frontal : the frozen nets of :func:`frontal_nets` (overhead and camera stages)
    """
    return get_stage(config.stage).build(config, frontal or {})


def load_run(run: str | Path, device: torch.device | str = "cpu") -> tuple[TrainConfig, dict[str, nn.Module]]:
    """A run's config and every net it runs, in eval mode: the nets it trained with the
    checkpoint's weights, plus (overhead and camera runs) its frozen frontal nets.

    Raises :class:`SceneforgeError` when the folder holds no checkpoint.
    """
    run = Path(run)
    config = read_config(run)
    checkpoint = Checkpoint(run / CHECKPOINT)
    if not checkpoint.exists():
        raise SceneforgeError(f"{run}: no {CHECKPOINT} (the run has not saved a step yet)")
    models = checkpoint.load(device)["models"]
    frontal = frontal_nets(config, device)
    nets = build_nets(config, frontal)
    for name, net in nets.items():
        net.load_state_dict(models[name])
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
    """The frozen nets of the runs ``config.stage`` reads (:attr:`Stage.frozen`: overhead
    depth + seg, camera depth; none for the frontal stages)."""
    nets = {}
    for stage in get_stage(config.stage).frozen:
        run = getattr(config, f"{stage}_run")
        if run is None:
            raise SceneforgeError(f"the {config.stage} stage needs a trained {stage} run (--{stage}-run)")
        frozen_config, loaded = load_run(run, device)
        if frozen_config.stage != stage:
            raise SceneforgeError(f"{run} is a {frozen_config.stage} run, not a {stage} run")
        _check_same_split(config, frozen_config, run)
        nets[stage] = loaded[stage].requires_grad_(False)
    return nets


def _check_same_split(config: TrainConfig, frozen: TrainConfig, run) -> None:
    """A stage on the stores of its frozen run must use that run's split file: another split
    would validate and test it on the frozen nets' training houses."""
    ours, theirs = config.split.file, frozen.split.file
    shared = {resolve(s) for s in config.stores} & {resolve(s) for s in frozen.stores}
    if ours and theirs and shared and resolve(ours) != resolve(theirs):
        raise SceneforgeError(f"{run} was trained on the split of {theirs}, this run splits the same stores by "
                              f"{ours}: pass --split-file {theirs}")


# --------------------------------------------------------------------------- running


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


def draw_losses(ax, rows: list[dict]) -> None:
    """Train (line) and validation (dots) loss of ``metrics.csv`` rows against steps, log
    scale, on the matplotlib axes ``ax``."""
    for split, style in (("train", "-"), ("val", "o-")):
        pts = [(int(r["step"]), float(r["loss"])) for r in rows if r["split"] == split]
        if pts:
            ax.plot(*zip(*pts), style, label=split, markersize=4)
    ax.set_yscale("log")
    ax.set_xlabel("step")


def plot_loss_curve(run: str | Path) -> Path:
    """Draw ``loss_curve.png`` (train and validation loss against steps) from the metrics."""
    from matplotlib.figure import Figure

    run = Path(run)
    fig = Figure(figsize=(7, 4))
    ax = fig.add_subplot()
    draw_losses(ax, read_metrics(run / "metrics.csv"))
    config = read_config(run)
    ax.set_ylabel("loss")
    ax.set_title(f"{config.stage}: batch {config.batch_size}, lr {config.lr:g}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    out = run / "loss_curve.png"
    fig.savefig(out, dpi=100, bbox_inches="tight")
    return out


def _absolute_runs(config: TrainConfig) -> TrainConfig:
    """The frozen runs and the split file as absolute paths: found again from any working
    directory (the split file's default, :func:`~.split.default_split_file`, written out)."""
    split_file = config.split.file if config.split.file is not None else default_split_file(config.stores)
    return replace(config, depth_run=config.depth_run and str(Path(config.depth_run).resolve()),
                   seg_run=config.seg_run and str(Path(config.seg_run).resolve()),
                   split=replace(config.split, file=resolve(split_file)))


def _is_run(run: Path) -> bool:
    """Whether the folder holds a training run (a readable ``config.json``)."""
    try:
        read_config(run)
    except SceneforgeError:
        return False
    return True


def _check_run_folder(config: TrainConfig, run: Path) -> None:
    """Raise :class:`SceneforgeError` for a run folder training may not write into: one
    that is, holds or lies inside an input (``config`` with absolute paths) or lies inside
    a store, and a file or non-empty folder that is not a training run."""
    check_not_in_store(run, "run folder")
    check_apart(run, "run folder", [*(("input store", s) for s in config.stores), ("depth run", config.depth_run),
                                    ("seg run", config.seg_run), ("split file", config.split.file)])
    if run.exists() and not _is_run(run) and (not run.is_dir() or any(run.iterdir())):
        raise SceneforgeError(f"{run}: holds files that are not a training run (no readable config.json); "
                              "choose a new or empty run folder")


def _prepare_run(config: TrainConfig, run: Path, resume: bool, device: torch.device) -> TrainConfig:
    """Check the run folder (:func:`_check_run_folder`); with ``resume``, the config must be
    the saved one (epochs and max_steps may change) and that is what the run continues
    with. ``amp`` is resolved on ``device`` (what ``auto`` means there) before it is saved
    or compared."""
    _check_run_folder(config, run)
    config = replace(config, amp=resolve_amp(config.amp, device))
    has_checkpoint = (run / CHECKPOINT).exists()
    if not resume:
        if has_checkpoint:
            raise SceneforgeError(f"{run} already holds a run: pass --resume to continue it, or choose "
                                  "another run folder")
        return config
    if not has_checkpoint:
        raise SceneforgeError(f"{run}: nothing to resume (no {CHECKPOINT})")
    saved = read_config(run)
    saved = replace(saved, amp=resolve_amp(saved.amp, device))  # runs saved before amp was a setting
    ours = replace(config, epochs=saved.epochs, max_steps=saved.max_steps)
    if ours != saved:
        diff = [k for k, v in saved.to_dict().items() if ours.to_dict()[k] != v]
        raise SceneforgeError(f"{run}: --resume with a different config ({', '.join(diff)}); start a new run")
    return replace(saved, epochs=config.epochs, max_steps=config.max_steps)


def _split(config: TrainConfig) -> tuple[ViewIndex, dict[str, ViewIndex], dict]:
    """The stores' views split by house (the split saved for the stores, drawn and saved on
    first use), and the record of the split for ``RUN/split.json``."""
    index = index_stores(config.stores)
    split = fixed_split(index.house, config.stores, config.split)
    subsets = {s: index.subset(split.of(s)) for s in SPLITS}
    if not len(subsets["train"]):
        raise SceneforgeError(f"no training views: the split leaves {len(index)} views of "
                              f"{len(set(index.house))} houses to validation and test")
    record = {"stores": list(config.stores), "seed": config.split.seed, "file": config.split.file,
              **{s: {"houses": sorted(split.of(s) & set(index.house)), "views": len(subsets[s])} for s in SPLITS}}
    return index, subsets, record


def _write_run_files(run: Path, config: TrainConfig, split_record: dict) -> None:
    run.mkdir(parents=True, exist_ok=True)
    (run / "split.json").write_text(json.dumps(split_record, indent=2) + "\n")
    (run / "config.json").write_text(json.dumps(config.to_dict(), indent=2) + "\n")


def _datasets(stage: Stage, config: TrainConfig, subsets: dict[str, ViewIndex]
              ) -> tuple[StoreDataset, StoreDataset | None]:
    """The training views and the validation views (None when there are none) as samples."""
    train_set = StoreDataset(subsets["train"], stage.fields)
    val_set = StoreDataset(subsets["val"], stage.fields) if len(subsets["val"]) else None
    return train_set, val_set


def _total_steps(config: TrainConfig, views: int) -> int:
    """The steps of the run: ``epochs`` over ``views`` training views, capped by ``max_steps``."""
    steps = config.epochs * math.ceil(views / config.batch_size)
    return steps if config.max_steps is None else min(config.max_steps, steps)


def train(
    config: TrainConfig,
    run: str | Path,
    *,
    device: str = "auto",
    workers: int | None = None,
    resume: bool = False,
    tensorboard: bool = True,
    wandb: bool = False,
    progress: TrainProgress | None = None,
) -> TrainResult:
    """Train ``config.stage`` into the folder ``run`` (layout: module docstring).

    device  : ``auto`` (the GPU when present), ``cpu``, ``cuda``, ``cuda:1``, ...; under
              torchrun, a GPU device means GPU ``LOCAL_RANK``
    workers : DataLoader worker processes (0: read in this process; None:
              :func:`~.trainer.default_workers`)
    resume  : continue the run saved in ``run`` (same config; ``epochs``/``max_steps`` may grow)
    wandb   : also log to Weights & Biases (project ``sceneforge``, the run folder's name);
              needs the ``wandb`` package
    Under torchrun (``WORLD_SIZE`` > 1 in the environment, :mod:`.distributed`) every
    process calls it; rank 0 alone writes the run folder and reports progress, and every
    process returns the same :class:`TrainResult`.
    Raises :class:`SceneforgeError` for unusable stores, a missing frozen run, a run folder
    that already holds a run (without ``resume``) or that training may not write into
    (module docstring); :class:`~sceneforge.errors.Interrupted` on Ctrl-C (SIGTERM in the
    CLI), saying whether to run it again with ``--resume`` or without.
    """
    if importlib.util.find_spec("matplotlib") is None:
        raise MissingDependencyError("matplotlib", "the loss curve of a training run",
                                     "pip install sceneforge[learn]")
    dist = Distributed.from_env()
    dev = dist.device(resolve_device(device))
    started = dist.start(dev)
    try:
        return _train(config, Path(run), dev, dist, default_workers(dist.local_world_size) if workers is None
                      else workers, resume, tensorboard, wandb, progress if dist.is_main else None)
    except KeyboardInterrupt:
        if dist.is_main:  # the one that saves the checkpoint alone knows whether there is one
            raise _interrupted(Path(run)) from None
        raise
    finally:
        if started:
            dist.stop()


def _interrupted(run: Path) -> Interrupted:
    """What to run after an interrupt: ``--resume`` from the checkpoint the run saved, or,
    before its first step, the same command again."""
    checkpoint = Checkpoint(run / CHECKPOINT)
    if checkpoint.exists():
        return Interrupted(f"run it again with --resume to continue from step {checkpoint.step()}")
    return Interrupted("no step was taken, so there is nothing to resume: run the same command again "
                       "(without --resume)")


def _train(config: TrainConfig, run: Path, dev: torch.device, dist: Distributed, workers: int, resume: bool,
           tensorboard: bool, wandb: bool, progress: TrainProgress | None) -> TrainResult:
    config = _prepare_run(_absolute_runs(config), run, resume, dev)
    if dev.type == "cuda":
        torch.backends.cudnn.benchmark = True  # the images are all of one size: pick the fastest kernels
    frontal = frontal_nets(config, dev)
    # rank 0 draws (and saves) the split on first use, then the others read it
    if dist.is_main:
        index, subsets, split_record = _split(config)
        _write_run_files(run, config, split_record)
    dist.barrier()
    if not dist.is_main:
        index, subsets, split_record = _split(config)

    stage = get_stage(config.stage)
    # the overhead nets are supervised at the stores' overhead resolution
    eft = EpipolarFeatureTransformer(config.eft, resolution=index.shapes["Wo"]) if stage.uses_eft else None
    trainer = Trainer(config, frontal, eft, dev, dist)
    checkpoint = Checkpoint(run / CHECKPOINT)
    start = checkpoint.restore(trainer) if resume else Position()
    train_set, val_set = _datasets(stage, config, subsets)
    if stage.uses_eft:
        train_set, val_set = cached_datasets(config, run, frontal, eft, dev, stage.targets, train_set, val_set)
    total = _total_steps(config, len(train_set))
    log = None
    if dist.is_main:
        log = MetricsLog(run, stage.loss_parts, start.step if resume else None, tensorboard, stage.val_metrics,
                         {"project": "sceneforge", "name": run.name, "config": config.to_dict()} if wandb else None)
    if progress:
        progress.start(total, start.step)
    loop = EpochLoop(trainer, train_set, val_set, total, log, checkpoint, workers, progress, Checkpoint(run / BEST))
    try:
        end = loop.run(start)
    finally:
        loop.close()
        if log is not None:
            log.close()
    if dist.is_main:
        plot_loss_curve(run)
    dist.barrier()  # the others return once the run folder is whole
    return TrainResult(run, end.step, end.epoch, loop.train_loss, loop.val_loss, loop.images_per_s,
                       time.perf_counter() - loop.started)
