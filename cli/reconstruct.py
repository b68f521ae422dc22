"""``sceneforge reconstruct``: a trained overhead run on RGB photos → layers, panel and mesh."""

from __future__ import annotations

import math

import click

from .progress import RichProgress, progress_bar


@click.command()
@click.argument("run", type=click.Path(exists=True, file_okay=False))
@click.argument("images", nargs=-1, required=True, type=click.Path(exists=True))
@click.option("--out", required=True, type=click.Path(file_okay=False), help="Folder for the outputs.")
@click.option("--fov", type=click.FloatRange(0, 180, min_open=True, max_open=True), default=None,
              help="Horizontal field of view of the photos, degrees. [default: the paper's 63.4°]")
@click.option("--K", "K", type=float, nargs=4, default=None, metavar="FX FY CX CY",
              help="Intrinsics of the photos in pixels (instead of --fov).")
@click.option("--height", type=click.FloatRange(min=0, min_open=True), default=1.5, show_default=True,
              help="Camera height above the floor, metres.")
@click.option("--pitch", type=click.FloatRange(-89.9, 89.9), default=math.degrees(math.atan(0.2)),
              show_default="11.31, the paper's", help="Downward pitch of the camera, degrees.")
@click.option("--camera-run", type=click.Path(exists=True, file_okay=False), default=None,
              help="A camera proposal run placing the overhead camera. [default: the store's heuristics "
                   "on the predicted layers]")
@click.option("--resolution", type=click.IntRange(min=8), default=300, show_default=True,
              help="Overhead image size, pixels.")
@click.option("--floor-removal", type=click.Choice(["segmentation", "height"]), default="segmentation",
              show_default=True, help="Remove the floor from the overhead heights by the overhead segmentation "
                                      "(the paper's) or by the 5 cm threshold alone.")
@click.option("--min-object-probability", type=click.FloatRange(0, 1), default=None,
              help="Keep a frontal object pixel only where the segmentation net's object probability is at "
                   "least this, besides its arg-max (as predict's). [default: the arg-max alone, the paper's]")
@click.option("--min-overhead-object-probability", type=click.FloatRange(0, 1), default=None,
              help="The same for the overhead heights, with the overhead segmentation net.")
@click.option("--batch-size", type=click.IntRange(min=1), default=4, show_default=True, help="Photos per batch.")
@click.option("--device", default="auto", show_default=True, help="auto (GPU when present), cpu, cuda, ...")
@click.option("--overwrite", is_flag=True,
              help="Replace the files of these photos (NAME.npz, .exr, .png, .ply) that OUT already holds; "
                   "nothing else in OUT is touched.")
def reconstruct(run, images, out, fov, K, height, pitch, camera_run, resolution, floor_removal,
                min_object_probability, min_overhead_object_probability, batch_size, device, overwrite):
    """Reconstruct RGB photos (PNG/JPEG files or folders of them) in 3D with the trained
    overhead RUN (and its frozen depth and segmentation runs): per image, the predicted
    layers (NAME.npz, NAME.exr), a panel (NAME.png) and a mesh of the frontal layers and
    the overhead heights in the camera's gravity-aligned frame (NAME.ply: +Y up, +Z the
    flattened view direction, camera at the origin, the floor at -HEIGHT).
    """
    from rich.console import Console

    from sceneforge.errors import SceneforgeError
    from sceneforge.learn.reconstruct import PhotoCamera
    from sceneforge.learn.reconstruct import reconstruct as run_reconstruction

    if fov is not None and K:
        raise SceneforgeError("give --fov or --K, not both")
    matrix = None if not K else ((K[0], 0.0, K[2]), (0.0, K[1], K[3]), (0.0, 0.0, 1.0))
    camera = PhotoCamera(K=matrix, height=height, pitch=math.radians(pitch),
                         **({} if fov is None else {"half_fov_x": math.radians(fov) / 2}))
    console = Console(highlight=False, stderr=True)
    with progress_bar(console) as bar:
        written = run_reconstruction(run, images, out, camera=camera, camera_run=camera_run, resolution=resolution,
                                     batch_size=batch_size, device=device, floor_removal=floor_removal,
                                     min_object_probability=min_object_probability,
                                     min_overhead_object_probability=min_overhead_object_probability,
                                     overwrite=overwrite, progress=RichProgress(bar))
    console.print(f"{out}: {len(written)} photos reconstructed (npz, exr, png panel, ply mesh each)")
