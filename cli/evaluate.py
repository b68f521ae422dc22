"""``sceneforge evaluate``: score layer reconstructions against the ground-truth meshes (docs/spec.md §11)."""

from __future__ import annotations

import json
from pathlib import Path

import click

from sceneforge.evaluate.config import EvaluateConfig

from .options import ConfigOption, config_options
from .output import check_output, plural, save_figure, write_text

#: the options of the surface precision/recall commands and the config fields they set
SURFACE_OPTIONS = (
    ConfigOption("--density", "surface.density", type=click.FloatRange(min=0, min_open=True)),
    ConfigOption("--seed", "seed"),
    ConfigOption("--preset", "meshing.preset"),
    ConfigOption("--a", "meshing.a", type=click.FloatRange(min=0, min_open=True)),
    ConfigOption("--threshold", "surface.threshold", type=click.FloatRange(min=0, min_open=True)),
)
#: the options of the layered point scores (``evaluate points``, ``evaluate predictions``) and their fields
POINTS_OPTIONS = (
    ConfigOption("--points", "points.samples", type=click.IntRange(min=1)),
    ConfigOption("--fscore-threshold", "points.thresholds", type=click.FloatRange(min=0, min_open=True)),
    ConfigOption("--intersections/--no-intersections", "points.intersections"),
)
#: the options of ``evaluate voxels`` and the config fields they set
VOXEL_OPTIONS = (
    ConfigOption("--resolution", "voxels.resolution", type=click.IntRange(min=1)),
    ConfigOption("--size", "voxels.size", type=click.FloatRange(min=0, min_open=True)),
)


def _limit(func):
    return click.option("--limit", type=click.IntRange(min=1), default=None, help="Only the first LIMIT views.")(func)


def _json(func):
    return click.option("--json", "json_path", type=click.Path(dir_okay=False), default=None,
                        help="Also write the table values and mean curves to this JSON file.")(func)


def _beside(store: str, kind: str) -> str:
    """The default plot of a command on ``store``: ``NAME.KIND.png`` beside ``NAME.zarr``
    (in the current folder when the store is a URL), never a fixed name in the current
    folder that the next evaluation of another store would replace."""
    from sceneforge.store.location import is_url

    name = store.rstrip("/").rsplit("/", 1)[-1].removesuffix(".zarr")
    if is_url(store):
        return f"{name}.{kind}.png"
    return str(Path(store.rstrip("/")).parent / f"{name}.{kind}.png")


def _check(plot, json_path, inputs):
    """Both outputs writable and none of the ``inputs`` ((what, path) pairs), before hours of scoring."""
    from sceneforge.store.guard import check_apart

    for path, what in ((plot, "plot"), (json_path, "JSON file")):
        check_output(path, what)
        if path is not None:
            check_apart(path, what, inputs)


def _truth(path: str):
    """The store at ``path`` and its views' ground-truth meshes: its own, or made from its
    houses and cached beside it (``PATH.gt_mesh/``) when it keeps none."""
    from sceneforge.pipeline.gt_mesh import GroundTruthMeshes, cache_folder
    from sceneforge.store import open_store

    store = open_store(path)
    return store, GroundTruthMeshes(store, cache_folder(path))


def _scored(views, total: int):
    """``views`` on a progress bar of ``total`` views (scoring takes seconds per view)."""
    from rich.console import Console

    from .progress import RichProgress, progress_bar

    with progress_bar(Console(stderr=True), transient=True) as bar:
        progress = RichProgress(bar)
        progress.start("scoring views", total, "views")
        for view in views:
            yield view
            progress.advance(1)


def _write(report, text, plot, json_path, title, extra: dict | None = None):
    """The table, then the values (JSON first: a plot that fails loses no numbers), then the plot.

    extra : more top-level entries of the JSON file (and their text, printed after the table)
    """
    click.echo(text)
    extra = extra or {}
    for entry in extra.values():
        click.echo(entry.text())
    if json_path:
        write_text(json_path, json.dumps({**report.to_dict(), **{k: v.to_dict() for k, v in extra.items()}},
                                         indent=1))
        click.echo(f"values: {json_path}")
    save_figure(report.plot(title), plot)
    click.echo(f"curves: {plot}")


@click.group()
def evaluate():
    """Score reconstructions from depth layers against the ground-truth meshes of a store:
    surface precision/recall (paper Table 1 and the table of paper §5) and voxel IoU; and
    layered point sets against a store's layers, the way LaRI does (Chamfer-L1, F-score)."""


@evaluate.command()
@click.argument("store")
@config_options(EvaluateConfig, SURFACE_OPTIONS)
@_limit
@_json
@click.option("--plot", type=click.Path(dir_okay=False), default=None,
              help="PNG of the precision and recall curves. [default: NAME.coverage.png beside the store NAME.zarr]")
def coverage(store, config, limit, json_path, plot):
    """How much of each view's ground-truth mesh the meshes of its ground-truth layers
    cover (paper Table 1): recall at the threshold of D1, D1-2, D1-3, D1-4, D1-5 and
    D1-5 & overhead against objects + envelope, averaged over views, beside the paper's
    SUNCG numbers; also recall against objects alone and precision."""
    from sceneforge.evaluate import COVERAGE_VARIANTS, coverage_views, evaluate_views
    from sceneforge.evaluate.stores import views_to_score

    plot = plot or _beside(store, "coverage")
    _check(plot, json_path, [("store", store)])
    s, meshes = _truth(store)
    views = _scored(coverage_views(s, limit, meshes), len(views_to_score(s, limit)))
    report = evaluate_views(views, COVERAGE_VARIANTS, config.seed, config.surface, config.meshing)
    _write(report, report.coverage_text(), plot, json_path, f"coverage of ground-truth layers: {store}")


def _house_split(split_file: str | None, pred, gt: str):
    """The split file given, else the one the prediction recorded, else the one beside GT."""
    from sceneforge.learn.split import default_split_file, read_split

    recorded = pred.attrs.get("prediction", {}).get("split_file")
    return read_split(split_file or recorded or default_split_file([gt]))


@evaluate.command()
@click.argument("pred")
@click.argument("gt")
@config_options(EvaluateConfig, SURFACE_OPTIONS + POINTS_OPTIONS)
@_limit
@_json
@click.option("--plot", type=click.Path(dir_okay=False), default=None,
              help="PNG of the precision and recall curves. [default: NAME.predictions.png beside PRED, NAME.zarr]")
@click.option("--split", type=click.Choice(["test", "val", "train", "all"]), default="test", show_default=True,
              help="Score the views of this split's houses only (all: every predicted view).")
@click.option("--split-file", type=click.Path(exists=True, dir_okay=False), default=None,
              help="The split file. [default: the one PRED was predicted with, else split.json beside GT]")
def predictions(pred, gt, config, limit, json_path, plot, split, split_file):
    """Precision and recall of predicted layers (PRED, written by `sceneforge predict` in
    the store layout) against the ground-truth meshes of GT (the table of paper §5): D1,
    D1 & overhead, D1-4 and D1-4 & overhead against objects, beside the paper's SUNCG
    numbers, on the test houses by default. Cameras and overhead cameras are PRED's; view
    i of PRED must be view i of GT.

    Then whether the nets learned: depth abs-rel of D1-D4, segmentation mIoU and overhead
    height L1 of PRED, each beside a baseline that knows only the training houses of the
    split (per-pixel mean depth, most frequent class, mean height), printed as a table and
    written under "learning" in --json.

    It names the operating point PRED was predicted at (the least object probabilities of
    kept pixels, and whether they were given or chosen on the validation houses: `sceneforge
    predict --operating-point validation`), under "operating_point" in --json.

    Last, the layered point scores of `sceneforge evaluate points` on the same views,
    written under "layered_points" in --json."""
    from sceneforge.errors import SceneforgeError
    from sceneforge.evaluate import PREDICTION_VARIANTS, evaluate_views, prediction_views
    from sceneforge.evaluate.learning import learning_scores, training_baselines
    from sceneforge.evaluate.stores import check_matching, empty_views, score_store_points, views_to_score
    from sceneforge.learn.operating_point import OperatingPoint
    from sceneforge.store import open_store

    plot = plot or _beside(pred, "predictions")
    _check(plot, json_path, [("prediction store", pred), ("ground-truth store", gt), ("split file", split_file)])
    pred_store, (gt_store, gt_meshes) = open_store(pred), _truth(gt)
    try:
        houses = _house_split(split_file, pred_store, gt)
    except SceneforgeError as e:
        if split != "all":
            raise
        houses, no_split = None, e  # every view is scored; only the baselines need the training houses
    indices = views_to_score(pred_store, limit, None if houses is None else houses.of(split))
    if not indices:
        raise SceneforgeError(f"{pred} holds no predicted view of the {split} split: predict it "
                              f"(sceneforge predict --split {split}) or choose another --split")
    check_matching(pred_store, gt_store, indices)  # a mismatch is one red line, before anything is printed
    train = None if houses is None else views_to_score(gt_store, None, houses.of("train"))
    if train is not None and not train:
        raise SceneforgeError(f"{gt} holds no view of the {len(houses.of('train'))} training houses of "
                              f"{houses.path}: the baselines are statistics of the training houses")
    scored_houses = {str(pred_store.array("house_id")[i]) for i in indices}
    click.echo(f"split: {split} ({plural(len(indices), 'view')} of {plural(len(scored_houses), 'house')})")
    empty = empty_views(pred_store, indices)
    if empty:
        click.secho(f"{len(empty)} of {len(indices)} predictions are empty (no finite D1-D4 nor overhead height): "
                    f"scored precision 1 and recall 0 by convention (views {', '.join(map(str, empty[:8]))}"
                    f"{', ...' if len(empty) > 8 else ''})", fg="yellow")
    extra = {}
    prediction = pred_store.attrs.get("prediction", {})
    extra["operating_point"] = OperatingPoint.from_dict(prediction.get("operating_point") or prediction)
    if houses is None:
        click.secho(f"learning scores left out: the baselines need the training houses ({no_split})", fg="yellow")
    else:
        extra["learning"] = learning_scores(pred_store, gt_store, indices, training_baselines(gt_store, train),
                                            prediction.get("stages", ("depth", "seg", "overhead")),
                                            same_overhead_cameras=prediction.get("camera_run") is None)
    views = _scored(prediction_views(pred_store, gt_store, indices=indices, meshes=gt_meshes), len(indices))
    report = evaluate_views(views, PREDICTION_VARIANTS, config.seed, config.surface, config.meshing)
    extra["layered_points"] = score_store_points(pred_store, gt_store, _scored(indices, len(indices)),
                                                 config.points, config.seed)
    _write(report, report.predictions_text(), plot, json_path, f"predictions: {pred} against {gt}", extra)


@evaluate.command()
@click.argument("pred")
@click.argument("gt")
@config_options(EvaluateConfig, (ConfigOption("--seed", "seed"), *POINTS_OPTIONS))
@_limit
@click.option("--json", "json_path", type=click.Path(dir_okay=False), default=None,
              help="Also write the table values to this JSON file.")
def points(pred, gt, config, limit, json_path):
    """Layered points of PRED (written by `sceneforge predict`, or any store) against those
    of GT, the way LaRI scores them: per view, Chamfer-L1 and F-score at each threshold of
    the first surface (visible), of the surfaces behind it (unseen) and of both (all), in
    the camera frame, as predicted and after a least-squares scale and shift fitted on the
    first surface; means over views. Each store's ray-intersection layers where it holds
    them, else its D1-D5. View i of PRED must be view i of GT; no meshes are read."""
    from sceneforge.errors import SceneforgeError
    from sceneforge.evaluate.stores import check_matching, score_store_points, views_to_score
    from sceneforge.store import open_store

    _check(None, json_path, [("prediction store", pred), ("ground-truth store", gt)])
    pred_store, gt_store = open_store(pred), open_store(gt)
    indices = views_to_score(pred_store, limit)
    if not indices:
        raise SceneforgeError(f"{pred} holds no view to score")
    check_matching(pred_store, gt_store, indices)
    report = score_store_points(pred_store, gt_store, _scored(indices, len(indices)), config.points, config.seed)
    click.echo(report.text())
    if json_path:
        write_text(json_path, json.dumps(report.to_dict(), indent=1))
        click.echo(f"values: {json_path}")


def _voxel_line(v) -> str:
    return (f"view {v.index:>4}  {v.house_id:<16} camera {v.camera_id:>3}  IoU {v.score.iou:.3f}  "
            f"(predicted {v.score.predicted:,}, truth {v.score.truth:,} voxels)")


@evaluate.command()
@click.argument("layers")
@click.argument("gt", required=False)
@config_options(EvaluateConfig, VOXEL_OPTIONS)
@_limit
@click.option("--plot", type=click.Path(dir_okay=False), default=None,
              help="PNG of the histogram of per-view IoU. [default: NAME.voxel_iou.png beside LAYERS, NAME.zarr]")
def voxels(layers, gt, config, limit, plot):
    """Voxel IoU of the layer intervals (D1, D2) and (D3, D4) of LAYERS against the solid
    ground-truth object mesh of GT, per view, in a grid of RESOLUTION³ voxels over a
    SIZE m cube in front of the camera (paper supplement: 400³, 10 m). Without GT the
    layers and meshes are both LAYERS's: the IoU of the ground-truth layers themselves."""
    from sceneforge.evaluate import plot_iou_histogram, score_store_voxels
    from sceneforge.store import open_store

    plot = plot or _beside(layers, "voxel_iou")
    check_output(plot, "plot")
    truth, meshes = _truth(gt or layers)
    report = score_store_voxels(open_store(layers) if gt else truth, truth if gt else None, config.voxels, limit,
                                on_view=lambda v: click.echo(_voxel_line(v)), meshes=meshes)
    mean = "—" if report.scored == 0 else f"{report.mean:.3f}"
    click.echo(f"mean voxel IoU {mean} over {report.scored} views "
               f"({len(report.views) - report.scored} without objects)")
    save_figure(plot_iou_histogram(report.ious, f"voxel IoU of {layers}"), plot)
    click.echo(f"histogram: {plot}")
