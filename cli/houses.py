"""``sceneforge houses``: look at houses before rendering them."""

from __future__ import annotations

from pathlib import Path

import click

from sceneforge.config import DatasetConfig
from sceneforge.errors import EXIT_FAILURES

from .options import HOUSE_OPTIONS, config_options
from .output import atomic_output, check_output, plural


@click.group()
def houses():
    """Inspect house files (any supported format)."""


@houses.command()
@click.argument("path")
@config_options(DatasetConfig, HOUSE_OPTIONS)
@click.option("--preview", "preview_dir", type=click.Path(file_okay=False), default=None,
              help="Write a top-down PNG per house into this folder (<house id>.png).")
@click.option("--cameras", "show_cameras", is_flag=True,
              help="Also sample the cameras `sceneforge render` would (same --config, seed and "
                   "views per house) and print the sampler's report: rejections by reason, each "
                   "room's share, and what each accepted view sees.")
def inspect(path, config, preview_dir, show_cameras):
    """Print a table per house in PATH: instances per NYU40 class, triangles, rooms,
    bounding box, the names that fell to void (with their share of the triangles) and
    problems found (no floor, no walls, no rooms, loader warnings), and notes (the up axis
    detected, and why). Houses are read as `sceneforge render` reads them (the `houses`
    section of --config); an unreadable house is named with its parser's message. A folder
    whose mesh files look like the objects of one scene gets a hint: how to read it as one.

    PATH is one house, a folder of houses in any supported format, a SUNCG root, a
    3D-FRONT root, a folder of one scene's per-object meshes (scene.json), or `bundled:toy`
    for the toy houses shipped with sceneforge. A house that fails to load is reported in
    red and the others go on; the exit code is 3 when any failed.
    """
    from rich.console import Console
    from rich.table import Table

    from sceneforge.houses import iter_houses
    from sceneforge.houses.inspect import SceneFolderHints, summarize, write_preview

    check_output(preview_dir, "preview folder", kind="folder")
    out = Console(highlight=False, soft_wrap=True)
    ok = failed = 0
    hints = SceneFolderHints()
    for source, house, error in iter_houses(path, config.houses):
        hints.add(source, house, error)
        if error is not None:
            failed += 1
            out.print(f"[red]failed: {error}[/red]")
            continue
        ok += 1
        s = summarize(house)
        lo, hi = s.bounds
        table = Table(title=f"{s.id}  ({s.source_format}: {s.source_path})", title_justify="left")
        table.add_column("NYU40 class")
        table.add_column("instances", justify="right")
        table.add_column("triangles", justify="right")
        for name, n, t in s.categories:
            table.add_row(name, str(n), f"{t:,}")
        table.add_section()
        table.add_row("total", str(s.instances), f"{s.triangles:,}")
        out.print(table)
        if s.void_names:
            out.print("names that fell to void:")
            for label, n, t, share in s.void_names:
                out.print(f"  {label!r}  {n} instances  {t:,} triangles  {100 * share:.1f} %")
        out.print(f"rooms {s.rooms}  levels {s.levels}  bounds "
                  f"[{lo[0]:.2f}, {lo[1]:.2f}, {lo[2]:.2f}] .. [{hi[0]:.2f}, {hi[1]:.2f}, {hi[2]:.2f}] m")
        for note in s.notes:
            out.print(f"note: {note}")
        if s.problems:
            for p in s.problems:
                out.print(f"[yellow]problem: {p}[/yellow]")
        else:
            out.print("problems: none")
        if show_cameras and config.cameras is None:
            from sceneforge.pipeline.plan import sample_house_cameras

            _cameras, report = sample_house_cameras(house, config)
            for line in report.lines():
                out.print(line)
        if preview_dir:
            png = Path(preview_dir) / f"{s.id}.png"
            with atomic_output(png) as tmp:
                write_preview(house, tmp)
            out.print(f"preview: {png}")
        out.print()
    for line in hints.lines():
        out.print(f"[yellow]hint: {line}[/yellow]")
    out.print(f"{plural(ok, 'house')} read, {failed} failed")
    if failed:
        raise SystemExit(EXIT_FAILURES)
