"""``sceneforge train`` and ``sceneforge predict``: the paper's networks on a store."""

from __future__ import annotations

from pathlib import Path

import click

from .progress import RichProgress, progress_bar

STAGES = ("depth", "seg", "overhead", "camera")


class _TrainBar:
    """A run's steps on a rich bar, with the last loss."""

    def __init__(self, bar):
        self.bar, self.task = bar, None

    def start(self, total: int, done: int) -> None:
        self.task = self.bar.add_task("training", total=total, completed=done, loss=float("nan"))

    def step(self, step: int, loss: float) -> None:
        self.bar.update(self.task, completed=step, loss=loss)


def _train_bar(console):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TextColumn("loss {task.fields[loss]:.4f}"), TextColumn("ETA"), TimeRemainingColumn(),
                    console=console)


@click.command()
@click.argument("stores", nargs=-1, required=True)
@click.option("--stage", type=click.Choice(STAGES), required=True,
              help="What to train: the frontal depth or segmentation net, then the overhead nets "
                   "(on the frozen frontal nets) or the virtual camera proposal.")
@click.option("--run", "run_dir", type=click.Path(file_okay=False), default=None,
              help="Run folder (config, split, checkpoint, metrics, loss curve). [default: runs/STAGE]")
@click.option("--depth-run", type=click.Path(file_okay=False), default=None,
              help="overhead/camera: the trained depth run to freeze. [default: runs/depth]")
@click.option("--seg-run", type=click.Path(file_okay=False), default=None,
              help="overhead: the trained segmentation run to freeze. [default: runs/seg]")
@click.option("--epochs", type=click.IntRange(min=1), default=40, show_default=True,
              help="Passes over the data.")
@click.option("--max-steps", type=click.IntRange(min=1), default=None, help="Stop after this many steps.")
@click.option("--batch-size", type=click.IntRange(min=1), default=24, show_default=True,
              help="Views per batch.")
@click.option("--lr", type=click.FloatRange(min=0, min_open=True), default=5e-4, show_default=True,
              help="Adam learning rate.")
@click.option("--width", type=click.FloatRange(min=0, min_open=True), default=1.0, show_default=True,
              help="Multiplies every network width of the paper (e.g. 0.25 for a quick run).")
@click.option("--bn-momentum", type=click.FloatRange(0, 1, min_open=True), default=0.005, show_default=True,
              help="BatchNorm momentum (paper: 0.005; about 0.1 for a run of a few hundred steps).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of initialisation and data order.")
@click.option("--eft-layers", type=click.Choice(["predicted", "truth"]), default="predicted",
              show_default=True,
              help="overhead: frontal layers the EFT reads, the frozen nets' or the store's.")
@click.option("--gating", type=click.Choice(["volume", "surface"]), default="volume", show_default=True,
              help="overhead: EFT gating, mean along ray segments or z-buffer of their ends.")
@click.option("--val-fraction", type=click.FloatRange(0, 1), default=0.1, show_default=True,
              help="Fraction of the houses held out for validation.")
@click.option("--test-fraction", type=click.FloatRange(0, 1), default=0.1, show_default=True,
              help="Fraction of the houses held out for testing.")
@click.option("--device", default="auto", show_default=True,
              help="auto (GPU when present), cpu, cuda, cuda:1, ...")
@click.option("--workers", type=click.IntRange(min=0), default=0, show_default=True,
              help="DataLoader worker processes.")
@click.option("--resume", is_flag=True, help="Continue the run saved in the run folder.")
@click.option("--tensorboard/--no-tensorboard", default=True, show_default=True,
              help="Also log to RUN/tensorboard when TensorBoard is installed.")
def train(stores, stage, run_dir, depth_run, seg_run, epochs, max_steps, batch_size, lr, width, bn_momentum,
          seed, eft_layers, gating, val_fraction, test_fraction, device, workers, resume, tensorboard):
    """Train one STAGE of the paper's networks on the zarr STORES (split by house).

    Train `depth` and `seg` first, then `overhead` and `camera`, which read the frozen
    frontal runs. Adam, lr 5e-4 and batch 24 as in the paper. The run folder gets the
    resolved config, the house split, a checkpoint (--resume continues from it), the
    metrics as CSV and a loss-curve PNG at the end.
    """
    from rich.console import Console

    from sceneforge.learn.dataset import SplitConfig
    from sceneforge.learn.eft import EFTConfig
    from sceneforge.learn.train import TrainConfig
    from sceneforge.learn.train import train as run_training

    if val_fraction + test_fraction >= 1:
        raise click.BadParameter("validation and test fractions must sum below 1",
                                 param_hint="--val-fraction")
    run = Path(run_dir or Path("runs") / stage)
    if stage in ("overhead", "camera"):
        depth_run = depth_run or str(Path("runs") / "depth")
    if stage == "overhead":
        seg_run = seg_run or str(Path("runs") / "seg")
    config = TrainConfig(stage=stage, stores=stores, batch_size=batch_size, lr=lr, epochs=epochs,
                         max_steps=max_steps, seed=seed, width=width, bn_momentum=bn_momentum,
                         depth_run=depth_run, seg_run=seg_run,
                         eft_layers=eft_layers, eft=EFTConfig(gating=gating),
                         split=SplitConfig(val_fraction=val_fraction, test_fraction=test_fraction, seed=seed))
    console = Console(highlight=False, stderr=True)
    with _train_bar(console) as bar:
        result = run_training(config, run, device=device, workers=workers, resume=resume,
                              tensorboard=tensorboard, progress=_TrainBar(bar))
    console.print(f"{result.run}: {result.steps} steps, {result.epochs} epochs in {result.seconds:.1f} s "
                  f"({result.images_per_s:.1f} images/s); train loss {result.train_loss:.4g}, "
                  f"val loss {result.val_loss:.4g}")
    console.print(f"metrics: {result.run / 'metrics.csv'}  loss curve: {result.run / 'loss_curve.png'}")


@click.command()
@click.argument("run", type=click.Path(exists=True, file_okay=False))
@click.argument("store")
@click.argument("out")
@click.option("--camera-run", type=click.Path(exists=True, file_okay=False), default=None,
              help="A camera proposal run: place the overhead cameras from its predictions "
                   "instead of the store's.")
@click.option("--batch-size", type=click.IntRange(min=1), default=8, show_default=True,
              help="Views per batch.")
@click.option("--device", default="auto", show_default=True, help="auto (GPU when present), cpu, cuda, ...")
@click.option("--workers", type=click.IntRange(min=0), default=0, show_default=True,
              help="DataLoader worker processes.")
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
def predict(run, store, out, camera_run, batch_size, device, workers, overwrite):
    """Write the predictions of the trained RUN for every view of STORE to the store OUT,
    in the store layout, so `sceneforge evaluate` reads them like ground truth.

    An overhead run predicts the frontal layers and classes (with its frozen depth and
    segmentation runs) and the overhead heights and classes; a depth or seg run only its
    own outputs.
    """
    from rich.console import Console

    from sceneforge.learn.predict import predict as run_prediction

    console = Console(highlight=False, stderr=True)
    with progress_bar(console) as bar:
        summary = run_prediction(run, store, out, camera_run=camera_run, batch_size=batch_size, device=device,
                                 workers=workers, overwrite=overwrite, progress=RichProgress(bar))
    console.print(f"{summary.path}: {summary.predicted} of {summary.views} views predicted "
                  f"({', '.join(summary.stages)}) in {summary.seconds:.1f} s")
