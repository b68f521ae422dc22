"""``sceneforge render``, ``validate``, ``show`` and ``export``: write a store and look at it."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import click
from click.core import ParameterSource

from sceneforge.config import DatasetConfig

from .options import HOUSE_OPTIONS, ConfigOption, Size, absolute_path, config_options
from .progress import RichProgress, progress_bar


class RGBMode(click.Choice):
    """``raster``, ``pathtraced`` or ``none`` → (``rgb.mode``, ``rgb.enabled``)."""

    def __init__(self):
        super().__init__(["raster", "pathtraced", "none"])

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        mode = super().convert(value, param, ctx)
        return ("raster", False) if mode == "none" else (mode, True)

    @staticmethod
    def show(values) -> str:
        return values[0] if values[1] else "none"


#: the options of ``render`` and the config fields they set (help and defaults: the fields')
RENDER_OPTIONS = (
    *HOUSE_OPTIONS,
    ConfigOption("--views-per-house", "views_per_house", type=click.IntRange(min=1)),
    ConfigOption("--cameras", "cameras", type=click.Path(exists=True, file_okay=False), convert=absolute_path,
                 metavar="DIR"),
    ConfigOption("--resolution", ("width", "height"), type=Size(), metavar="WxH"),
    ConfigOption("--overhead-resolution", "view.overhead.resolution", type=click.IntRange(min=1)),
    ConfigOption("--seed", "seed"),
    ConfigOption("--rgb", ("rgb.mode", "rgb.enabled"), type=RGBMode()),
    ConfigOption("--rgb-samples", "rgb.samples", type=click.IntRange(min=1)),
)


@click.command()
@click.argument("houses")
@click.argument("out")
@config_options(DatasetConfig, RENDER_OPTIONS)
@click.option("--workers", type=click.IntRange(min=1), default=1, show_default=True,
              help="Worker processes; with --scheduler local, the LocalCluster's workers; ignored "
                   "with a remote scheduler.")
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="Run on a Dask cluster: its scheduler address (tcp://host:8786), or `local` to start "
                   "a LocalCluster of --workers processes.")
@click.option("--overwrite", is_flag=True, help="Delete the store at OUT first and start over.")
@click.option("--no-rgb", is_flag=True, help="The same as --rgb none.")
def render(houses, out, config, workers, scheduler, overwrite, no_rgb):
    """Render every house in HOUSES into the zarr store OUT (a path or an fsspec URL).

    Per view: five depth layers, classes, instances, the overhead camera and its ground
    truth, RGB and the ground-truth meshes (layout: schemas/store.schema.json). HOUSES is
    anything `sceneforge houses inspect` takes, e.g. `bundled:toy`.

    Run the same command again after an interruption to resume; the result is identical
    to an uninterrupted run. Houses that fail are recorded in the store's failure log and
    the others complete; the exit code is then 1.
    """
    from rich.console import Console

    from sceneforge.pipeline import render_dataset

    ctx = click.get_current_context()
    if all(ctx.get_parameter_source(p) == ParameterSource.COMMANDLINE for p in ("cameras", "views_per_house")):
        raise click.UsageError("--cameras and --views-per-house exclude each other")

    if no_rgb:
        config = replace(config, rgb=replace(config.rgb, enabled=False))
    console = Console(highlight=False, stderr=True, soft_wrap=True)
    with progress_bar(console) as bar:
        summary = render_dataset(houses, out, config, workers=workers, scheduler=scheduler, overwrite=overwrite,
                                 progress=RichProgress(bar))
    if summary.already_complete:
        console.print(f"{summary.path}: already complete ({summary.views} views); nothing to do")
    else:
        rate = summary.views / summary.seconds if summary.seconds > 0 else 0.0
        console.print(f"{summary.path}: {summary.views} views of {summary.houses} houses in {summary.shards} shards "
                      f"({summary.shards_run} written now) in {summary.seconds:.1f} s ({rate:.1f} views/s)")
    for f in summary.failures:
        where = f"view {f['view']}" if f.get("view") is not None else f["stage"]
        reason = f["reason"].removeprefix(f"house {f['house']}: ")  # load errors name the house too
        console.print(f"[red]failed: house {f['house']} ({where}): {reason}[/red]")
    if summary.failed_houses:
        console.print(f"[red]{len(summary.failed_houses)} houses failed[/red] (failure log: the store's "
                      "`failures` attribute)")
        raise SystemExit(1)


@click.command()
@click.argument("store")
def validate(store):
    """Check the store STORE against schemas/store.schema.json and for internal consistency
    (masks match NaNs, classes in range, cameras orthonormal, meshes in range)."""
    from sceneforge.store import validate_store

    problems = validate_store(store)
    for p in problems:
        click.secho(f"invalid: {p}", fg="red", err=True)
    if problems:
        raise SystemExit(1)
    click.echo(f"{store}: valid")


@click.command()
@click.argument("store")
@click.option("--view", "index", type=int, required=True, help="View index (negative counts from the end).")
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="PNG to write. Default: <store name>_view<I>.png in the current folder.")
@click.option("--3d", "ply", type=click.Path(dir_okay=False), default=None,
              help="Also write the view's layers as a PLY point cloud coloured by layer.")
def show(store, index, output, ply):
    """Write a PNG panel of one view: RGB, D1..D5 with a colour bar, layer classes, overhead
    height and classes, and a top-down view with the overhead camera's footprint."""
    from sceneforge.preview import write_panel, write_point_cloud
    from sceneforge.store import open_store

    s = open_store(store)
    if not -len(s) <= index < len(s):
        raise click.BadParameter(f"the store has {len(s)} views", param_hint="--view")
    name = Path(store.rstrip("/")).name.removesuffix(".zarr")
    png = write_panel(s, index, output or f"{name}_view{index % len(s)}.png")
    click.echo(f"panel: {png}")
    if ply:
        click.echo(f"point cloud: {write_point_cloud(s, index, ply)}")


@click.command()
@click.argument("store")
@click.argument("out_dir", type=click.Path(file_okay=False))
@click.option("--format", "fmt", type=click.Choice(["exr"]), default="exr", show_default=True,
              help="File format: one multi-part OpenEXR per view (frontal D1..D5 and RGB, overhead "
                   "height and D1..D5, camera metadata in the headers).")
def export(store, out_dir, fmt):
    """Write every view of STORE as a file in OUT_DIR (view_<index>.exr)."""
    from rich.progress import track

    from sceneforge.store import export_exr, open_store

    s = open_store(store)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for i in track(range(len(s)), description="exporting", transient=True):
        export_exr(s, i, out / f"view_{i:06d}.{fmt}")
    click.echo(f"{len(s)} views written to {out}")
