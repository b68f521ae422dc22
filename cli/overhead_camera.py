"""``sceneforge overhead-camera``: show how the overhead camera of each view is chosen."""

from __future__ import annotations

from pathlib import Path

import click
from click.core import ParameterSource

from sceneforge.config import DatasetConfig

from .options import HOUSE_OPTIONS, ConfigOption, config_options
from .output import check_output, save_figure


def _box_line(cand) -> str:
    if cand.box is None:
        where = "no box"
    else:
        (r0, f0), (r1, f1) = cand.box.lo, cand.box.hi
        where = (f"right [{r0:6.2f}, {r1:6.2f}]  forward [{f0:6.2f}, {f1:6.2f}]  "
                 f"area {cand.box.area:6.2f} m²")
    verdict = f"weight {cand.weight:g}" if cand.weight > 0 else f"rejected: {cand.reason}"
    return f"  {cand.name:<17} {where}  {verdict}  ({cand.n_points} points)"


@click.command("overhead-camera")
@click.argument("house", required=False)
@config_options(DatasetConfig, (*HOUSE_OPTIONS, ConfigOption("--seed", "seed")))
@click.option("--camera-file", type=click.Path(exists=True, dir_okay=False), default=None,
              help="PBRS camera file (one camera per line). Default: sample --views cameras.")
@click.option("--views", type=click.IntRange(min=1), default=1, show_default=True,
              help="Number of cameras to sample when no --camera-file is given.")
@click.option("--view", "view_index", type=click.IntRange(min=0), default=None,
              help="Only this view (0-based index; with --store, the store's view index). Default: every view.")
@click.option("--store", default=None, metavar="STORE",
              help="Explain view --view of this store instead: its house, camera and settings as the store "
                   "recorded them (the result is the store's overhead_params).")
@click.option("--plot", type=click.Path(dir_okay=False), default=None,
              help="Draw the frontal points with the candidate boxes to this PNG "
                   "(with several views: one file per view, suffixed _<view>).")
def overhead_camera(house, config, camera_file, views, view_index, store, plot):
    """Print, per view of HOUSE, the three candidate overhead boxes (depth statistics,
    envelope/frustum, majority room) with their weights or why they were rejected, and
    the overhead camera chosen: tx, ty (box centre right/forward of the camera), tz
    (height above the floor), theta and sigma.

    Boxes are in the view's gravity-aligned frame, metres: right and forward of the
    camera on the floor plane. Houses, the camera sampler and the overhead camera are
    set as for `sceneforge render` (--config: its `houses`, `sampler` and `view.overhead`
    sections), and sampled cameras are render's: `--views N --seed S` gives the first N
    cameras `render --views-per-house N --seed S` gives the house. `--store S --view I`
    explains view I of a rendered store exactly.
    """
    from sceneforge.pipeline.explain import explain_overhead_cameras, explain_stored_view, plot_candidates

    ctx = click.get_current_context()
    given = [f"--{name.replace('_', '-')}" for name in ("views", "seed", "camera_file")
             if ctx.get_parameter_source(name) == ParameterSource.COMMANDLINE]
    if store is not None:
        if house is not None or given or view_index is None:
            raise click.UsageError("--store takes --view and no HOUSE, --views, --seed or --camera-file")
    elif house is None:
        raise click.UsageError("Missing argument 'HOUSE' (or --store STORE --view I).")
    elif camera_file and len(given) > 1:
        raise click.UsageError(f"--camera-file and {'/'.join(g for g in given if g != '--camera-file')} "
                               "exclude each other")

    check_output(plot, "plot")
    if store is not None:
        explained = [explain_stored_view(store, view_index)]
    else:
        found = explain_overhead_cameras(house, camera_file or views, options=config.houses, sampler=config.sampler,
                                         seed=config.seed, config=config.view.overhead, view_index=view_index)
        report = found.sampled
        if report is not None and len(found.cameras) < views:
            click.echo(f"sampled {len(found.cameras)} of {views} cameras "
                       f"({report.candidates} candidates; rejected: {report.rejected})")
        explained = found.views
    for view in explained:
        pos = view.camera.cam_to_world[:3, 3]
        click.echo(f"view {view.index}: camera at ({pos[0]:.2f}, {pos[1]:.2f}, {pos[2]:.2f})")
        for cand in view.overhead.candidates:
            click.echo(_box_line(cand))
        tx, ty, tz, theta, sigma = view.overhead.params
        click.echo(f"  overhead: tx {tx:.3f}  ty {ty:.3f}  tz {tz:.3f}  theta {theta:.4f}  "
                   f"sigma {sigma:.3f}  half-extent {view.overhead.half_extent:.3f} m  "
                   f"floor y {view.overhead.floor_y:.3f}")
        if plot:
            out = Path(plot)
            if len(explained) > 1:
                out = out.with_name(f"{out.stem}_{view.index}{out.suffix}")
            save_figure(plot_candidates(view.points, view.overhead), out)
            click.echo(f"  plot: {out}")
