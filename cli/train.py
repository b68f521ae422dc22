"""``sceneforge train`` and ``sceneforge predict``: the paper's networks on a store."""

from __future__ import annotations

from pathlib import Path

import click

from sceneforge.learn.config import PredictConfig, TrainConfig

from .options import ConfigOption, absolute_path, check_device, config_options
from .output import check_output, plural
from .progress import RichProgress, progress_bar

#: where runs go when no --run is given, and where the frozen runs are looked for
RUNS = "runs"
#: the options of ``train`` and the config fields they set (help and defaults: the fields')
TRAIN_OPTIONS = (
    ConfigOption("stores", "stores"),
    ConfigOption("--stage", "stage"),
    ConfigOption("--depth-run", "depth_run", type=click.Path(file_okay=False)),
    ConfigOption("--seg-run", "seg_run", type=click.Path(file_okay=False)),
    ConfigOption("--epochs", "epochs", type=click.IntRange(min=1)),
    ConfigOption("--max-steps", "max_steps", type=click.IntRange(min=1)),
    ConfigOption("--batch-size", "batch_size", type=click.IntRange(min=1)),
    ConfigOption("--lr", "lr", type=click.FloatRange(min=0, min_open=True)),
    ConfigOption("--lr-schedule", "lr_schedule"),
    ConfigOption("--flip", "flip"),
    ConfigOption("--width", "width", type=click.FloatRange(min=0, min_open=True)),
    ConfigOption("--bn-momentum", "bn_momentum", type=click.FloatRange(0, 1, min_open=True)),
    ConfigOption("--seed", "seed"),
    ConfigOption("--amp", "amp"),
    ConfigOption("--sync-batchnorm", "sync_batchnorm"),
    ConfigOption("--eft-layers", "eft_layers"),
    ConfigOption("--gating", "eft.gating"),
    ConfigOption("--floor-as-zero", "floor_as_zero"),
    ConfigOption("--feature-cache", "feature_cache"),
    ConfigOption("--feature-cache-gib", "feature_cache_gib", type=click.FloatRange(min=0)),
    ConfigOption("--seg-empty", "loss.seg_empty"),
    ConfigOption("--seg-balance", "loss.seg_balance", type=click.FloatRange(0, 1)),
    ConfigOption("--huber-delta", "loss.huber_delta", type=click.FloatRange(min=0, min_open=True)),
    ConfigOption("--val-fraction", "split.val_fraction", type=click.FloatRange(0, 1)),
    ConfigOption("--test-fraction", "split.test_fraction", type=click.FloatRange(0, 1)),
    ConfigOption("--split-seed", "split.seed"),
    ConfigOption("--split-file", "split.file", type=click.Path(dir_okay=False), convert=absolute_path),
)
#: the options of ``predict`` and the config fields they set
PREDICT_OPTIONS = (
    ConfigOption("--camera-run", "camera_run", type=click.Path(exists=True, file_okay=False)),
    ConfigOption("--batch-size", "batch_size", type=click.IntRange(min=1)),
    ConfigOption("--split", "split"),
    ConfigOption("--floor-removal", "floor_removal"),
    ConfigOption("--min-object-probability", "min_object_probability", type=click.FloatRange(0, 1)),
    ConfigOption("--min-overhead-object-probability", "min_overhead_object_probability",
                 type=click.FloatRange(0, 1)),
    ConfigOption("--operating-point", "operating_point"),
    ConfigOption("--operating-point-views", "operating_point_views", type=click.IntRange(min=1)),
    ConfigOption("--split-file", "split_file", type=click.Path(exists=True, dir_okay=False), convert=absolute_path),
)


class _TrainBar:
    """A run's steps on a rich bar, with the last loss."""

    def __init__(self, bar):
        self.bar, self.task = bar, None

    def start(self, total: int, done: int) -> None:
        if not self.bar.live.is_started:
            self.bar.start()
        self.task = self.bar.add_task("training", total=total, completed=done, loss=float("nan"))

    def step(self, step: int, loss: float) -> None:
        self.bar.update(self.task, completed=step, loss=loss)


def _train_bar(console):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from .progress import shown_from_first_task

    return shown_from_first_task(Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                          TextColumn("loss {task.fields[loss]:.4f}"), TextColumn("ETA"),
                                          TimeRemainingColumn(), console=console))


@click.command()
@config_options(TrainConfig, TRAIN_OPTIONS)
@click.option("--run", "--run-dir", "run_dir", type=click.Path(file_okay=False), default=None,
              help="Run folder (config, split, checkpoint, metrics, loss curve); under torchrun write "
                   "--run-dir (torchrun reads --run as its own --run-path). [default: runs/STAGE]")
@click.option("--device", default="auto", show_default=True,
              help="auto (the GPU when torch sees one), cpu, cuda, cuda:N (GPU N) or mps.")
@click.option("--workers", type=click.IntRange(min=0), default=None,
              help="DataLoader worker processes per training process (0: read in the training process). "
                   "[default: the usable CPU cores (shared by the processes of a torchrun), at most 4]")
@click.option("--resume", is_flag=True, help="Continue the run saved in the run folder.")
@click.option("--tensorboard/--no-tensorboard", default=True, show_default=True,
              help="Also log to RUN/tensorboard when TensorBoard is installed.")
@click.option("--wandb", is_flag=True, help="Also log to Weights & Biases (needs the wandb package).")
def train(config, run_dir, device, workers, resume, tensorboard, wandb):
    """Train one STAGE of the paper's networks on the zarr STORES (split by house).

    Train `depth` and `seg` first, then `overhead` and `camera`, which read the frozen
    frontal runs (default: runs/depth and runs/seg). The first run on a set of stores
    splits their houses into train, validation and test (with --split-seed, not --seed)
    and saves the split beside the first store in a file named by the stores (a.split.json
    for a.zarr; several stores: a+N.HASH.split.json) or in --split-file; every later run,
    `predict` and `evaluate` read it. Adam, with the paper's learning rate
    and batch size by default. The run folder gets the resolved config (reload it with --config
    RUN/config.json), the house split, a checkpoint (saved on Ctrl-C too; --resume continues
    from it), the metrics as CSV and a loss-curve PNG at the end. It must be a new, empty or
    training run folder apart from the stores, the frozen runs and the split file.

    \b
    Several GPUs: one process per GPU, started by torchrun, e.g. on 8 GPUs
      torchrun --standalone --nproc_per_node 8 -m sceneforge train STORES --stage depth --run-dir RUN
    Each process takes --batch-size / 8 views of every step (the batch size stays the
    whole step's; it must divide evenly) and averages gradients with the others (NCCL;
    gloo on the CPU); BatchNorm uses the whole batch's statistics (--no-sync-batchnorm:
    each process's own). Rank 0 alone writes the run folder; --resume works the same.
    """
    import contextlib
    import os

    from rich.console import Console

    from sceneforge.learn.train import train as run_training

    run = Path(run_dir or Path(RUNS) / config.stage)
    check_output(run, "run folder", kind="store")
    check_device(device)
    config = config.with_frozen_runs(RUNS)
    main = int(os.environ.get("RANK", 0)) == 0  # under torchrun, rank 0 alone reports
    console = Console(highlight=False, stderr=True, quiet=not main)
    with _train_bar(console) if main else contextlib.nullcontext() as bar:
        result = run_training(config, run, device=device, workers=workers, resume=resume,
                              tensorboard=tensorboard, wandb=wandb, progress=_TrainBar(bar) if main else None)
    console.print(f"{result.run}: {plural(result.steps, 'step')}, {plural(result.epochs, 'epoch')} in "
                  f"{result.seconds:.1f} s "
                  f"({result.images_per_s:.1f} images/s); train loss {result.train_loss:.4g}, "
                  f"val loss {result.val_loss:.4g}")
    console.print(f"metrics: {result.run / 'metrics.csv'}  loss curve: {result.run / 'loss_curve.png'}")


@click.command()
@click.argument("run", type=click.Path(exists=True, file_okay=False))
@click.argument("store")
@click.argument("out")
@config_options(PredictConfig, PREDICT_OPTIONS)
@click.option("--device", default="auto", show_default=True,
              help="auto (the GPU when torch sees one), cpu, cuda, cuda:N (GPU N) or mps.")
@click.option("--workers", type=click.IntRange(min=0), default=None,
              help="DataLoader worker processes reading STORE (0: read in this process). "
                   "[default: the usable CPU cores, at most 4]")
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
def predict(run, store, out, config, device, workers, overwrite):
    """Write the predictions of the trained RUN for the test views of STORE (the houses of
    the run's split file; --split all: every view) to the store OUT, in the store layout,
    so `sceneforge evaluate` reads them like ground truth.

    An overhead run predicts the frontal layers and classes (with its frozen depth and
    segmentation runs) and the overhead heights and classes; a depth or seg run only its
    own outputs.
    """
    from rich.console import Console

    from sceneforge.learn.predict import predict as run_prediction

    check_output(out, "prediction store", kind="store")
    check_device(device)
    console = Console(highlight=False, stderr=True)
    with progress_bar(console) as bar:
        summary = run_prediction(run, store, out, camera_run=config.camera_run, batch_size=config.batch_size,
                                 split=config.split, split_file=config.split_file, floor=config.floor_removal,
                                 min_object_probability=config.min_object_probability,
                                 min_overhead_object_probability=config.min_overhead_object_probability,
                                 operating_point=config.operating_point,
                                 operating_point_views=config.operating_point_views,
                                 device=device, workers=workers,
                                 overwrite=overwrite, progress=RichProgress(bar))
    console.print(summary.operating_point.describe())
    console.print(f"split: {summary.split} ({plural(summary.predicted, 'view')} of {plural(summary.houses, 'house')})")
    console.print(f"{summary.path}: {summary.predicted} of {summary.views} views predicted "
                  f"({', '.join(summary.stages)}) in {summary.seconds:.1f} s")
