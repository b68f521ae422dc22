"""``sceneforge render``, ``validate``, ``show`` and ``export``: write a store and look at it."""

from __future__ import annotations

import re
from pathlib import Path

import click
from click.core import ParameterSource

from .options import house_options
from .progress import RichProgress, progress_bar

#: house option parameter → its field of the config's ``houses`` section
_HOUSE_FIELDS = {"fmt": "format", "strict": "strict", "scale": "scale", "up_axis": "up_axis",
                 "name_map": "name_map", "future_dir": "future_dir"}


def _resolution(ctx, param, value):
    if value is None:
        return None
    match = re.fullmatch(r"(\d+)[xX×](\d+)", value)
    if not match or not all(int(g) > 0 for g in match.groups()):
        raise click.BadParameter(f"expected WIDTHxHEIGHT such as 320x240, got {value!r}")
    return int(match.group(1)), int(match.group(2))


@click.command()
@click.argument("houses")
@click.argument("out")
@house_options
@click.option("--config", "config_file", type=click.Path(exists=True, dir_okay=False), default=None,
              help="JSON config (schemas/config.schema.json); the options below override it.")
@click.option("--views-per-house", type=click.IntRange(min=1), default=None,
              help="Cameras sampled per house. [config default: 4]")
@click.option("--cameras", "cameras_dir", type=click.Path(exists=True, file_okay=False), default=None,
              help="Folder of PBRS camera files DIR/<house id>/room_camera.txt (every line, in order) "
                   "instead of sampled cameras.")
@click.option("--resolution", callback=_resolution, default=None, metavar="WxH",
              help="Frontal image size. [config default: 320x240]")
@click.option("--overhead-resolution", type=click.IntRange(min=1), default=None,
              help="Overhead image size (square). [config default: 300]")
@click.option("--seed", type=int, default=None, help="Seed of the camera sampler. [config default: 0]")
@click.option("--rgb/--no-rgb", default=None, help="Render RGB images (needs pyrender and EGL). [default: on]")
@click.option("--workers", type=click.IntRange(min=1), default=1, show_default=True,
              help="Worker processes; with --scheduler local, the LocalCluster's workers; ignored "
                   "with a remote scheduler.")
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="Run on a Dask cluster: its scheduler address (tcp://host:8786), or `local` to start "
                   "a LocalCluster of --workers processes.")
@click.option("--overwrite", is_flag=True, help="Delete the store at OUT first and start over.")
def render(houses, out, load_options, config_file, views_per_house, cameras_dir, resolution,
           overhead_resolution, seed, rgb, workers, scheduler, overwrite):
    """Render every house in HOUSES into the zarr store OUT (a path or an fsspec URL).

    Per view: five depth layers, classes, instances, the overhead camera and its ground
    truth, RGB and the ground-truth meshes (layout: schemas/store.schema.json). HOUSES is
    anything `sceneforge houses inspect` takes, e.g. `bundled:toy`.

    Run the same command again after an interruption to resume; the result is identical
    to an uninterrupted run. Houses that fail are recorded in the store's failure log and
    the others complete; the exit code is then 1.
    """
    from rich.console import Console

    from sceneforge.config import load_config
    from sceneforge.pipeline import render_dataset

    ctx = click.get_current_context()
    if cameras_dir is not None and views_per_house is not None:
        raise click.UsageError("--cameras and --views-per-house exclude each other")
    overrides: dict = {}
    if resolution is not None:
        overrides["width"], overrides["height"] = resolution
    if views_per_house is not None:
        overrides["views_per_house"] = views_per_house
    if cameras_dir is not None:
        overrides["cameras"] = str(Path(cameras_dir).resolve())
    if seed is not None:
        overrides["seed"] = seed
    if overhead_resolution is not None:
        overrides["view"] = {"overhead": {"resolution": overhead_resolution}}
    if rgb is not None:
        overrides["rgb"] = {"enabled": rgb}
    given = {f: getattr(load_options, f) for p, f in _HOUSE_FIELDS.items()
             if ctx.get_parameter_source(p) == ParameterSource.COMMANDLINE}
    if given:
        overrides["houses"] = given
    config = load_config(config_file, overrides)

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
