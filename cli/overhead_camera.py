"""``sceneforge overhead-camera``: show how the overhead camera of each view is chosen."""

from __future__ import annotations

from pathlib import Path

import click
from click.core import ParameterSource

from .options import house_options


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
@click.argument("house")
@house_options
@click.option("--camera-file", type=click.Path(exists=True, dir_okay=False), default=None,
              help="PBRS camera file (one camera per line). Default: sample --views cameras.")
@click.option("--views", type=click.IntRange(min=1), default=1, show_default=True,
              help="Number of cameras to sample when no --camera-file is given.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the camera sampler.")
@click.option("--view", "view_index", type=click.IntRange(min=0), default=None,
              help="Only this view (0-based index). Default: every view.")
@click.option("--plot", type=click.Path(dir_okay=False), default=None,
              help="Draw the frontal points with the candidate boxes to this PNG "
                   "(with several views: one file per view, suffixed _<view>).")
def overhead_camera(house, load_options, camera_file, views, seed, view_index, plot):
    """Print, per view of HOUSE, the three candidate overhead boxes (depth statistics,
    envelope/frustum, majority room) with their weights or why they were rejected, and
    the overhead camera chosen: tx, ty (box centre right/forward of the camera), tz
    (height above the floor), theta and sigma.

    Boxes are in the view's gravity-aligned frame, metres: right and forward of the
    camera on the floor plane.
    """
    import numpy as np

    from sceneforge.cameras import read_pbrs_cameras, sample_cameras
    from sceneforge.houses import load
    from sceneforge.layers import frontal_layers
    from sceneforge.overhead import OverheadConfig, overhead_camera_and_points, plot_candidates
    from sceneforge.raytrace import HouseTracer

    ctx = click.get_current_context()
    sampler_options = [f"--{name}" for name in ("views", "seed")
                       if ctx.get_parameter_source(name) == ParameterSource.COMMANDLINE]
    if camera_file and sampler_options:
        raise click.UsageError(f"--camera-file and {'/'.join(sampler_options)} exclude each other")

    h = load(house, load_options)
    tracer = HouseTracer(h)
    if camera_file:
        cameras = read_pbrs_cameras(camera_file)
    else:
        cameras, report = sample_cameras(h, views, np.random.default_rng(seed), None, tracer)
        if len(cameras) < views:
            click.echo(f"sampled {len(cameras)} of {views} cameras "
                       f"({report.candidates} candidates; rejected: {report.rejected})")
    if view_index is not None and view_index >= len(cameras):
        raise click.BadParameter(f"there are {len(cameras)} views", param_hint="--view")
    indices = range(len(cameras)) if view_index is None else [view_index]

    config = OverheadConfig()
    for i in indices:
        camera = cameras[i]
        layers = frontal_layers(h, camera, tracer)
        over, points = overhead_camera_and_points(h, camera, layers, config)
        pos = camera.cam_to_world[:3, 3]
        click.echo(f"view {i}: camera at ({pos[0]:.2f}, {pos[1]:.2f}, {pos[2]:.2f})")
        for cand in over.candidates:
            click.echo(_box_line(cand))
        tx, ty, tz, theta, sigma = over.params
        click.echo(f"  overhead: tx {tx:.3f}  ty {ty:.3f}  tz {tz:.3f}  theta {theta:.4f}  "
                   f"sigma {sigma:.3f}  half-extent {over.half_extent:.3f} m  "
                   f"floor y {over.floor_y:.3f}")
        if plot:
            out = Path(plot)
            if len(indices) > 1:
                out = out.with_name(f"{out.stem}_{i}{out.suffix}")
            out.parent.mkdir(parents=True, exist_ok=True)
            plot_candidates(points, over).savefig(out, dpi=100)
            click.echo(f"  plot: {out}")
