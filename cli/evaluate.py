"""``sceneforge evaluate``: score layer reconstructions against the ground-truth meshes (SPEC §11)."""

from __future__ import annotations

import json
from pathlib import Path

import click


def _surface_options(func):
    """The options every surface precision/recall command shares."""
    for option in reversed((
        click.option("--density", type=click.FloatRange(min=0, min_open=True), default=10_000.0,
                     show_default=True, help="Surface samples per m²."),
        click.option("--seed", type=int, default=0, show_default=True,
                     help="Seed of the surface sampling; view i draws from (seed, i)."),
        click.option("--a", "a", type=click.FloatRange(min=0, min_open=True), default=7.0, show_default=True,
                     help="Edge rule: no triangle edge across a depth jump above a × the pixel footprint."),
        click.option("--threshold", type=click.FloatRange(min=0, min_open=True), default=0.05,
                     show_default=True, help="Match threshold of the table, metres."),
        click.option("--limit", type=click.IntRange(min=1), default=None,
                     help="Only the first LIMIT views."),
        click.option("--json", "json_path", type=click.Path(dir_okay=False), default=None,
                     help="Also write the table values and mean curves to this JSON file."),
    )):
        func = option(func)
    return func


def _views(store, limit) -> list[int]:
    """Indices of the views to score: those among the first ``limit`` whose ground truth
    did not fail (a failed view is blank in the store)."""
    import numpy as np

    n = len(store) if limit is None else min(limit, len(store))
    if "valid" not in store.names:
        return list(range(n))
    return np.flatnonzero(np.asarray(store.array("valid")[:n], dtype=bool)).tolist()


def _report(pairs, variants, seed, density, threshold, a):
    from sceneforge.evaluate import MeshingConfig, SurfaceConfig, evaluate_views

    config = SurfaceConfig(density=density, threshold=threshold)
    return evaluate_views(pairs, variants, seed, config, MeshingConfig(a=a))


def _write(report, text, plot, json_path, title):
    click.echo(text)
    Path(plot).parent.mkdir(parents=True, exist_ok=True)
    report.plot(title).savefig(plot, dpi=100)
    click.echo(f"curves: {plot}")
    if json_path:
        Path(json_path).write_text(json.dumps(report.to_dict(), indent=1))
        click.echo(f"values: {json_path}")


@click.group()
def evaluate():
    """Score reconstructions from depth layers against the ground-truth meshes of a store:
    surface precision/recall (paper Table 1 and the table of §5) and voxel IoU."""


@evaluate.command()
@click.argument("store")
@_surface_options
@click.option("--plot", type=click.Path(dir_okay=False), default="coverage.png", show_default=True,
              help="PNG of the precision and recall curves.")
def coverage(store, density, seed, a, threshold, limit, json_path, plot):
    """How much of each view's ground-truth mesh the meshes of its ground-truth layers
    cover (paper Table 1): recall at the threshold of D1, D1-2, D1-3, D1-4, D1-5 and
    D1-5 & overhead against objects + envelope, averaged over views, beside the paper's
    SUNCG numbers; also recall against objects alone and precision."""
    from sceneforge.evaluate import COVERAGE_VARIANTS, EvalView, GroundTruthMesh
    from sceneforge.store import open_store

    s = open_store(store)
    pairs = ((i, EvalView.from_arrays(s.view(i)), GroundTruthMesh.from_arrays(s.mesh(i)))
             for i in _views(s, limit))
    report = _report(pairs, COVERAGE_VARIANTS, seed, density, threshold, a)
    _write(report, report.coverage_text(), plot, json_path, f"coverage of ground-truth layers: {store}")


@evaluate.command()
@click.argument("pred")
@click.argument("gt")
@_surface_options
@click.option("--plot", type=click.Path(dir_okay=False), default="predictions.png", show_default=True,
              help="PNG of the precision and recall curves.")
def predictions(pred, gt, density, seed, a, threshold, limit, json_path, plot):
    """Precision and recall of predicted layers (PRED, written by `sceneforge predict` in
    the store layout) against the ground-truth meshes of GT (the paper's table in §5): D1,
    D1 & overhead, D1-4 and D1-4 & overhead against objects, beside the paper's SUNCG
    numbers. Cameras and overhead cameras are PRED's; view i of PRED must be view i of GT."""
    from sceneforge.evaluate import PREDICTION_VARIANTS, EvalView, GroundTruthMesh
    from sceneforge.store import open_store

    p, g = open_store(pred), open_store(gt)
    pairs = ((i, EvalView.from_arrays(_matching(p, g, i)), GroundTruthMesh.from_arrays(g.mesh(i)))
             for i in _views(p, limit))
    report = _report(pairs, PREDICTION_VARIANTS, seed, density, threshold, a)
    _write(report, report.predictions_text(), plot, json_path, f"predictions: {pred} against {gt}")


def _matching(pred, gt, i: int) -> dict:
    """View ``i`` of ``pred``, after checking that it is view ``i`` of ``gt``."""
    import numpy as np

    from sceneforge.errors import SceneforgeError

    if len(pred) > len(gt):
        raise SceneforgeError(f"the predictions have {len(pred)} views but the ground truth only {len(gt)}")
    p, g = pred.view(i), gt.view(i)
    for key in ("house_id", "camera_id"):
        if str(p[key]) != str(g[key]):
            raise SceneforgeError(f"view {i}: {key} {p[key]} in the predictions, {g[key]} in the truth")
    if not np.allclose(p["cam_to_world"], g["cam_to_world"], atol=1e-6):
        raise SceneforgeError(f"view {i}: the predictions come from another camera pose than the truth")
    return p


@evaluate.command()
@click.argument("layers")
@click.argument("gt", required=False)
@click.option("--resolution", type=click.IntRange(min=1), default=400, show_default=True,
              help="Voxels along each axis.")
@click.option("--size", type=click.FloatRange(min=0, min_open=True), default=10.0, show_default=True,
              help="Side of the voxel cube in front of the camera, metres.")
@click.option("--limit", type=click.IntRange(min=1), default=None, help="Only the first LIMIT views.")
@click.option("--plot", type=click.Path(dir_okay=False), default="voxel_iou.png", show_default=True,
              help="PNG of the histogram of per-view IoU.")
def voxels(layers, gt, resolution, size, limit, plot):
    """Voxel IoU of the layer intervals (D1, D2) and (D3, D4) of LAYERS against the solid
    ground-truth object mesh of GT, per view, in a grid of RESOLUTION³ voxels over a
    SIZE m cube in front of the camera (paper supplement: 400³, 10 m). Without GT the
    layers and meshes are both LAYERS's: the IoU of the ground-truth layers themselves."""
    import numpy as np

    from sceneforge.evaluate import GroundTruthMesh, VoxelConfig, plot_iou_histogram, score_voxels
    from sceneforge.store import open_store

    config = VoxelConfig(resolution=resolution, size=size)
    source = open_store(layers)
    truth = open_store(gt) if gt else source
    ious = []
    for i in _views(source, limit):
        view = _matching(source, truth, i) if gt else source.view(i)
        score = score_voxels(view["depth"], view["K"], view["cam_to_world"],
                             GroundTruthMesh.from_arrays(truth.mesh(i)).objects, config)
        ious.append(score.iou)
        click.echo(f"view {i:>4}  {str(view['house_id']):<16} camera {int(view['camera_id']):>3}  IoU "
                   f"{score.iou:.3f}  (predicted {score.predicted:,}, truth {score.truth:,} voxels)")
    values = np.asarray(ious, dtype=np.float64)
    scored = values[np.isfinite(values)]
    mean = f"{scored.mean():.3f}" if len(scored) else "—"
    click.echo(f"mean voxel IoU {mean} over {len(scored)} views "
               f"({len(values) - len(scored)} without objects)")
    Path(plot).parent.mkdir(parents=True, exist_ok=True)
    plot_iou_histogram(values, f"voxel IoU of {layers}").savefig(plot, dpi=100)
    click.echo(f"histogram: {plot}")
