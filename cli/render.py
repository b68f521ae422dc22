"""``sceneforge render``, ``validate``, ``show`` and ``export``: write a store and look at it."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import click
from click.core import ParameterSource

from sceneforge.config import DatasetConfig
from sceneforge.errors import EXIT_FAILURES, listed
from sceneforge.store.export import FORMATS

from .options import HOUSE_OPTIONS, ConfigOption, Size, absolute_path, config_options
from .output import atomic_output, check_output, plural
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


#: the options of ``render`` and the config fields they set (help and defaults: the fields', but for
#: an option of several fields, which says its own help)
RENDER_OPTIONS = (
    *HOUSE_OPTIONS,
    ConfigOption("--views-per-house", "views_per_house", type=click.IntRange(min=1)),
    ConfigOption("--cameras", "cameras", type=click.Path(exists=True, file_okay=False), convert=absolute_path,
                 metavar="DIR"),
    ConfigOption("--resolution", ("width", "height"), type=Size(), metavar="WxH",
                 help="frontal image size, width x height in pixels"),
    ConfigOption("--overhead-resolution", "view.overhead.resolution", type=click.IntRange(min=1)),
    ConfigOption("--seed", "seed"),
    ConfigOption("--rgb", ("rgb.mode", "rgb.enabled"), type=RGBMode(),
                 help="how RGB images are made: raster (pyrender through EGL, fast), pathtraced (Mitsuba 3, "
                      "global illumination, seconds per view) or none (no RGB images: the store has no rgb "
                      "array); sets rgb.mode and rgb.enabled"),
    ConfigOption("--rgb-samples", "rgb.samples", type=click.IntRange(min=1)),
    ConfigOption("--rgb-denoise", "rgb.denoise"),
    ConfigOption("--gt-mesh", "store.gt_mesh"),
    ConfigOption("--intersections", "view.layers.intersections", type=click.IntRange(min=0, max=255), metavar="K"),
    ConfigOption("--labels", "view.layers.labels"),
)


@click.command()
@click.argument("houses")
@click.argument("out")
@config_options(DatasetConfig, RENDER_OPTIONS)
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Worker processes (1: render in this process); with --scheduler local, the LocalCluster's "
                   "workers; ignored with a remote scheduler. Stores are identical whatever the number. "
                   "[default: one per usable CPU core, at most one per house or shard]")
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="Run on a Dask cluster: its scheduler address (tcp://host:8786), or `local` to start "
                   "a LocalCluster of --workers processes.")
@click.option("--overwrite", is_flag=True, help="Delete the store at OUT first and start over.")
@click.option("--update", is_flag=True,
              help="When houses changed, were added or removed since OUT was rendered (their files are "
                   "fingerprinted), redo exactly those; without it such a run is refused, naming them.")
@click.option("--retry-failed", is_flag=True, help="Render the houses that failed again.")
@click.option("--repair", is_flag=True,
              help="Render with the config OUT records (the options above are not needed): with any re-run, "
                   "the shards whose files are damaged or missing are rendered again and files no run wrote "
                   "are removed, so that OUT ends as a clean render (`sceneforge validate` prints this command).")
@click.option("--no-rgb", is_flag=True, help="The same as --rgb none.")
def render(houses, out, config, workers, scheduler, overwrite, update, retry_failed, repair, no_rgb):
    """Render every house in HOUSES into the zarr store OUT (a path or an fsspec URL).

    Per view: five depth layers, classes, instances, the overhead camera and its ground
    truth and RGB (layout: schemas/store.schema.json); the ground-truth meshes only with
    --gt-mesh all (else `sceneforge evaluate` makes them from the houses). HOUSES is
    anything `sceneforge houses inspect` takes, e.g. `bundled:toy`.

    Run the same command again after an interruption to resume; the result is identical
    to an uninterrupted run. A re-run on a complete store checks its files against the
    hashes recorded when they were written and renders the damaged shards again (--repair:
    without restating the options). One run writes a store at a time (a second is refused). Houses
    that fail are recorded in the store's failure log and the others complete; the exit
    code is then 3 (1: an error, nothing lost; 2: a bad option).
    """
    from rich.console import Console

    from sceneforge.pipeline import render_dataset

    ctx = click.get_current_context()
    if all(ctx.get_parameter_source(p) == ParameterSource.COMMANDLINE for p in ("cameras", "views_per_house")):
        raise click.UsageError("--cameras and --views-per-house exclude each other")

    if no_rgb:
        config = replace(config, rgb=replace(config.rgb, enabled=False))
    check_output(out, "store", kind="store")
    console = Console(highlight=False, stderr=True, soft_wrap=True)
    with progress_bar(console) as bar:
        summary = render_dataset(houses, out, config, workers=workers, scheduler=scheduler, overwrite=overwrite,
                                 update=update, retry_failed=retry_failed, repair=repair,
                                 progress=RichProgress(bar))
    if summary.damaged:
        console.print(f"repaired: {plural(len(summary.damaged), 'file')} not as written "
                      f"({listed(summary.damaged, 3)}); their shards rendered again")
    if summary.removed:
        console.print(f"removed: {plural(len(summary.removed), 'file')} no run wrote ({listed(summary.removed, 3)})")
    if summary.changes:
        console.print(f"updated: {summary.changes.describe()}")
    if summary.retried:
        console.print(f"retried: {', '.join(summary.retried)}")
    if summary.already_complete:
        console.print(f"{summary.path}: already complete ({plural(summary.views, 'view')}); nothing to do")
    else:
        # the progress bar's rate: views rendered now over the rendering step's wall time
        rate = summary.views_rendered / summary.render_seconds if summary.render_seconds > 0 else 0.0
        console.print(f"{summary.path}: {plural(summary.views, 'view')} of {plural(summary.houses, 'house')} in "
                      f"{plural(summary.shards, 'shard')} ({summary.shards_run} written now) in "
                      f"{summary.seconds:.1f} s; rendering {rate:.1f} views/s")
    for f in summary.failures:
        where = f"view {f['view']}" if f.get("view") is not None else f["stage"]
        reason = f["reason"].removeprefix(f"house {f['house']}: ")  # load errors name the house too
        console.print(f"[red]failed: house {f['house']} ({where}): {reason}[/red]")
    if summary.failed_houses:
        retry = "" if retry_failed else "; --retry-failed renders them again"
        console.print(f"[red]{plural(len(summary.failed_houses), 'house')} failed[/red] (failure log: the store's "
                      f"`failures` attribute{retry})")
        raise SystemExit(EXIT_FAILURES)


@click.command()
@click.argument("store")
@click.option("--quiet", "-q", is_flag=True, help="Print only the summary line.")
def validate(store, quiet):
    """Check the store STORE (a dataset or a prediction store) for what a reader relies on:
    the schema and layout; every shard file present with the SHA-256 recorded when it was
    written (the store's manifest.json), none left over, no staging folder; every shard
    decodable; attributes consistent with the arrays; cameras, classes and, in a dataset
    store, the ground-truth layer rules (masks match NaNs, layers in order); meshes
    non-empty where the view has layers, offsets and faces in range.

    Prints one summary line (of a prediction store: how many of its views were predicted,
    and of which split), then a line per problem (each rule once, with the views that
    break it). Exit code: 0 valid, 3 invalid or incomplete, 1 no store there.
    """
    from sceneforge.store import check_store

    check = check_store(store)
    click.secho(check.summary(), fg=None if check.valid else "red", err=not check.valid)
    if not quiet:
        for p in check.problems if check.complete else []:
            click.secho(f"  {p}", fg="red", err=True)
        for note in check.notes:
            click.echo(f"  note: {note}", err=not check.valid)
    if not check.valid:
        raise SystemExit(EXIT_FAILURES)


@click.command()
@click.argument("store")
@click.option("--view", "index", type=int, required=True,
              help="View index, 0 to the store's views − 1; of a prediction store, one it predicted.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="PNG to write. Default: <store name>_view<I>.png in the current folder.")
@click.option("--3d", "ply", type=click.Path(dir_okay=False), default=None,
              help="Also write the view's layers as a PLY point cloud coloured by layer.")
@click.option("--truth", default=None,
              help="STORE holds predictions (sceneforge predict): draw them under this ground-truth "
                   "store's same view instead (its RGB, D1..D5, classes, overhead heights).")
def show(store, index, output, ply, truth):
    """Write a PNG panel of one view: RGB, D1..D5 with a colour bar, layer classes, overhead
    height and classes, and a top-down view with the overhead camera's footprint. With
    --truth, a predicted view under its truth instead. Of a prediction store, only a view it
    predicted (the others are blank)."""
    from sceneforge.evaluate.stores import check_predicted, matching_view
    from sceneforge.preview import write_panel, write_point_cloud
    from sceneforge.store import open_store

    for path, what in ((output, "panel"), (ply, "point cloud")):
        check_output(path, what)
    s = open_store(store)
    if not 0 <= index < len(s):
        span = f"numbered 0 to {len(s) - 1}" if len(s) else "none"
        raise click.BadParameter(f"{index}: the store has {plural(len(s), 'view')} ({span})", param_hint="--view")
    check_predicted(s, index)  # a view predict skipped is blank: drawing it would show an empty prediction
    gt = None
    if truth is not None:
        gt = open_store(truth)
        matching_view(s, gt, index)
    name = Path(store.rstrip("/")).name.removesuffix(".zarr")
    png = Path(output or f"{name}_view{index}.png")
    check_output(png, "panel")
    with atomic_output(png) as tmp:
        write_panel(s, index, tmp, truth=gt)
    click.echo(f"panel: {png}")
    if ply:
        with atomic_output(ply) as tmp:
            write_point_cloud(s, index, tmp)
        click.echo(f"point cloud: {ply}")


@click.command()
@click.argument("store")
@click.argument("out_dir", type=click.Path(file_okay=False))
@click.option("--format", "fmt", type=click.Choice(sorted(FORMATS)), default="exr", show_default=True,
              help="File format. " + "; ".join(f"{name}: {f.help}" for name, f in FORMATS.items()) + ".")
@click.option("--split-file", type=click.Path(exists=True, dir_okay=False), default=None,
              help="lari: the house split its lists follow. [default: the split file beside STORE, if any]")
@click.option("--overwrite", is_flag=True,
              help="Replace an earlier export in OUT_DIR, of either format: its files are deleted first (all of "
                   "them, also views beyond this store's count). A folder holding any other file is refused.")
def export(store, out_dir, fmt, split_file, overwrite):
    """Write every view of STORE as files in OUT_DIR, named by its view index with six
    digits: view_000000.exr, view_000001.exr, ... (each written atomically).

    OUT_DIR is new or empty, or holds an earlier export (replaced with --overwrite); never
    the store, a folder inside or around it, or inside any zarr store. An EXR file holds the
    view's depth layers, RGB, classes (NYU40, 0 = none) and instances (the int32 bits: -1,
    none, reads as 4294967295 until viewed as int32). --format lari writes the valid views
    of a store rendered with --intersections K in LaRI's ScanNet++ layout (docs/store.md)."""
    from rich.console import Console

    from sceneforge.store import open_store
    from sceneforge.store.export import check_export_folder, remove_export

    exporter = FORMATS[fmt]
    earlier = check_export_folder(out_dir, store, overwrite=overwrite)
    s = open_store(store)
    views = exporter.views(s)
    split, split_path = _house_split(store, split_file) if exporter.lists else (None, None)
    lists = exporter.lists(s, views, split) if exporter.lists else {}
    check_output(out_dir, "export folder", kind="folder")
    remove_export(earlier)  # all of it, so that the folder never mixes two exports
    out = Path(out_dir)
    with progress_bar(Console(stderr=True), transient=True) as bar:
        progress = RichProgress(bar)
        progress.start("exporting", len(views), "views")
        for i in views:
            for name, write in exporter.files(s, i):
                with atomic_output(out / name) as tmp:
                    write(tmp)
            progress.advance(1)
    for name, data in lists.items():
        with atomic_output(out / name) as tmp:
            tmp.write_bytes(data)
    left_out = f" ({plural(len(s) - len(views), 'failed view')} left out)" if len(views) < len(s) else ""
    listed_in = f"; lists {', '.join(lists)} ({f'split {split_path}' if split else 'no split file'})" if lists else ""
    click.echo(f"{plural(len(views), 'view')} written to {out}{left_out}{listed_in}")


def _house_split(store: str, split_file: str | None) -> tuple[dict | None, str | None]:
    """The house ids of each split, by the split file given or else the one beside STORE
    (none: (None, None)), and its path."""
    from sceneforge.learn.split import SPLITS, default_split_file, read_split
    from sceneforge.store.location import read_file

    path = split_file or default_split_file([store])
    if split_file is None and read_file(path) is None:
        return None, None
    houses = read_split(path).houses
    return {name: houses[name] for name in SPLITS}, path
