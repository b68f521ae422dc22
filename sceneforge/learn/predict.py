"""Predictions of trained runs, written in the store layout (docs/spec.md §9, §10.6).

``predict(run, store, out)`` runs a run's nets on the views of a store's test houses (the
run's split file; ``split="all"``: every view) and writes a new store with the same
per-view arrays, so the evaluation reads predictions exactly like ground truth:

- ``depth``: the depth net's D1..D5; with a segmentation net, D1/D2 (D3/D4) are NaN where
  it sees no object in layer 1 (3) — the paper's predicted masks;
- ``category``: the segmentation net's NYU40 classes of layers 1 and 3 where the layer is
  set (0 elsewhere and for D5, which no net labels);
- ``overhead_height``: the overhead height net's heights, NaN where the overhead
  segmentation net sees background (the floor: the paper's test-time rule; ``floor=
  "height"``: not) and at or below ``min_height`` above the floor (the paper evaluates
  only pixels > 5 cm);
- ``overhead_category``: the overhead segmentation net's classes;
- cameras, ids and ``valid`` are copied from the source store, the overhead camera too
  unless a camera proposal run gives it (``camera_run``: the frontal camera's gravity
  frame at the true overhead camera height, centred on the predicted ``(tx, ty)``, of
  half-diagonal ``sigma``, as the paper does at test time);
- what no net predicts (``instance``, ``overhead_depth``) holds the fill values, and so
  does every view outside the split; there is no ``rgb``, ``normal`` or mesh.

The store's ``prediction`` attribute records the run, the split and the indices of the
views predicted (``views``), which are the only ones ``sceneforge evaluate`` scores.

Which nets run depends on the run: a depth or segmentation run predicts its frontal
outputs; an overhead run predicts everything (its config names its frozen depth and
segmentation runs).
"""

from __future__ import annotations

import math
import typing
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..errors import SceneforgeError
from ..store.guard import check_apart, check_store_output
from .config import OperatingPointRule
from .dataset import CLASS_TO_NYU40, SAMPLE_FIELDS, SEG_CLASSES, StoreDataset, index_stores
from .eft import EpipolarFeatureTransformer
from .networks import SEG_LAYERS, masked_layers, object_pixels, object_scores
from .operating_point import OperatingPoint
from .split import default_split_file, read_split
from .stages import REGISTRY, get_stage
from .train import load_run, overhead_input, resolve_device
from .trainer import default_workers, end_workers, make_loader

if TYPE_CHECKING:
    from sceneforge.config import DatasetConfig
    from sceneforge.store import SceneStore, StoreWriter

    from .dataset import ViewIndex

#: predicted heights at or below this (metres above the floor) are floor: NaN
MIN_HEIGHT = 0.05
#: arrays copied from the source store (the overhead camera ones unless a camera run places them)
COPIED = ("house_id", "camera_id", "valid", "K", "cam_to_world", "overhead_cam_to_world", "overhead_params",
          "overhead_extent", "overhead_floor_source")


@dataclass(frozen=True)
class PredictSummary:
    """What a prediction run wrote: the new store, its views and the stages predicted."""

    path: str
    views: int
    predicted: int
    stages: tuple[str, ...]
    seconds: float
    #: the split predicted, and the houses of it that the store holds
    split: str = "all"
    houses: int = 0
    #: the thresholds used, and how they were set
    operating_point: OperatingPoint | None = None


def proposed_overhead_cameras(K: np.ndarray, cam_to_world: np.ndarray, size: tuple[int, int],
                              overhead_cam_to_world: np.ndarray, params: np.ndarray,
                              proposal: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Overhead cameras placed from proposed ``(tx, ty, sigma)``, per view.

    K (n, 3, 3), cam_to_world (n, 4, 4), size (H, W): the frontal cameras;
    overhead_cam_to_world (n, 4, 4) and params (n, 5): the true overhead cameras, whose
    height is kept (known at test time, paper §5); proposal (n, 3).
    Returns poses (n, 4, 4), half-extents (n,) and params (n, 5), like the store's.
    """
    from sceneforge.cameras import Camera
    from sceneforge.overhead import gravity_frame

    poses, extents, out = [], [], []
    for k, (tx, ty, sigma) in enumerate(np.asarray(proposal, dtype=np.float64)):
        sigma = max(sigma, 1e-3)  # a regressed radius can come out <= 0; a camera needs an extent
        frame = gravity_frame(Camera(K[k], cam_to_world[k], size[1], size[0]))
        up = frame.to_frame(overhead_cam_to_world[k][None, :3, 3])[0, 1]
        pose = np.eye(4)
        pose[:3, 0], pose[:3, 1], pose[:3, 2] = frame.right, -frame.forward, (0.0, -1.0, 0.0)
        pose[:3, 3] = frame.to_world(np.array([[tx, up, ty]]))[0]
        poses.append(pose)
        extents.append(sigma / math.sqrt(2.0))
        out.append([tx, ty, params[k][2], frame.theta, sigma])
    return np.array(poses), np.array(extents), np.array(out)


def overhead_heights(height: torch.Tensor, seg_logits: torch.Tensor, floor: str = "segmentation",
                     min_probability: float | None = None) -> torch.Tensor:
    """Predicted heights (B, R, R) with the floor removed (NaN): where the overhead
    segmentation logits (B, 40, R, R) say background (``floor="segmentation"``; with
    ``min_probability``, also where their object probability is below it:
    :func:`~.networks.object_pixels`), and at or below :data:`MIN_HEIGHT` in any case."""
    keep = height > MIN_HEIGHT
    if floor == "segmentation":
        keep &= object_pixels(seg_logits, min_probability)
    return torch.where(keep, height, torch.nan)


def _predict_batch(nets: dict, eft: EpipolarFeatureTransformer | None, batch: dict, camera: bool,
                   floor: str = "segmentation", thresholds: tuple[float | None, float | None] = (None, None),
                   scores: bool = False) -> dict:
    """Every output of a batch as numpy arrays, keyed by store array name; ``thresholds``:
    the least object probabilities of the frontal and the overhead segmentation (None: the
    arg-max alone). With ``scores``, also each kept pixel's least threshold that keeps it
    (:func:`~.networks.object_scores`): ``front_score`` (B, 2, H, W) of D1/D2 and of D3/D4,
    ``top_score`` (B, R, R) of the overhead heights (1 where no segmentation removes them)."""
    front, top_threshold = thresholds
    rgb = batch["rgb"]
    out: dict[str, np.ndarray] = {}
    if camera:
        feats = nets["camera_depth"](rgb)
        proposal = nets["camera"](feats.features, feats.encoding).cpu().numpy()
        pose, extent, params = proposed_overhead_cameras(
            batch["K"].cpu().numpy(), batch["cam_to_world"].cpu().numpy(), tuple(rgb.shape[-2:]),
            batch["overhead_cam_to_world"].cpu().numpy(), batch["overhead_params"].cpu().numpy(), proposal)
        batch = {**batch, "overhead_cam_to_world": torch.from_numpy(pose).to(rgb.device),
                 "overhead_extent": torch.from_numpy(extent).to(rgb.device),
                 "overhead_params": torch.from_numpy(params).to(rgb.device)}
        out.update(overhead_cam_to_world=pose, overhead_extent=extent, overhead_params=params)
    if eft is not None:
        x, layers, logits = overhead_input(nets, eft, batch)
        if front is not None:  # the EFT read the arg-max layers it was trained with; the output keeps fewer
            layers = masked_layers(layers, logits, front)
        top = nets["overhead_seg"](x)
        out["overhead_height"] = overhead_heights(nets["height"](x)[:, 0], top, floor, top_threshold).cpu().numpy()
        if scores:
            top_score = object_scores(top) if floor == "segmentation" else torch.ones_like(top[:, 0])
            out["top_score"] = top_score.float().cpu().numpy()
        out["overhead_category"] = CLASS_TO_NYU40[top.argmax(dim=1).cpu().numpy()].astype(np.uint8)
    else:
        logits = nets["seg"](rgb).prediction if "seg" in nets else None
        layers = None
        if "depth" in nets:
            depth = nets["depth"](rgb).prediction
            layers = depth if logits is None else masked_layers(depth, logits, front)
    if layers is not None:
        out["depth"] = layers.float().cpu().numpy()
    if logits is not None and scores:
        B, _, H, W = logits.shape
        first, third = object_scores(logits.reshape(B, SEG_LAYERS, SEG_CLASSES, H, W), dim=2).unbind(1)
        out["front_score"] = torch.stack([first, torch.minimum(first, third)], dim=1).float().cpu().numpy()
    if logits is not None:
        B, _, H, W = logits.shape
        classes = logits.reshape(B, SEG_LAYERS, SEG_CLASSES, H, W).argmax(dim=2).cpu().numpy()
        category = np.zeros((B, 3, H, W), np.uint8)
        category[:, :2] = CLASS_TO_NYU40[classes]
        if layers is not None:
            present = np.isfinite(out["depth"][:, [0, 2]])
            category[:, :2] = np.where(present, category[:, :2], 0)
        out["category"] = category
    return out


def predict(run: str | Path, store: str, out: str, *, camera_run: str | Path | None = None,
            batch_size: int = 8, split: str = "test", split_file: str | Path | None = None,
            floor: str = "segmentation", min_object_probability: float | None = None,
            min_overhead_object_probability: float | None = None, operating_point: str = "given",
            operating_point_views: int = 48,
            device: str = "auto", workers: int | None = None, overwrite: bool = False,
            progress=None) -> PredictSummary:
    """Write the predictions of ``run`` for the views of ``split`` of ``store`` to a new store ``out``.

    camera_run : a camera proposal run; the overhead cameras come from it instead of the store
    split      : ``test``, ``val``, ``train`` (the houses of that split) or ``all`` (every view)
    split_file : the split file (default: the one the run was trained with)
    floor      : how the floor leaves the overhead heights (:func:`overhead_heights`)
    min_object_probability, min_overhead_object_probability : None (the arg-max, the
                 paper's), or the least object probability of a kept pixel of the frontal
                 layers (D1..D4) and of the overhead heights (:func:`~.networks.object_pixels`)
    operating_point : "given" (the two thresholds above) or "validation": both chosen on at
                 most ``operating_point_views`` views of the split's validation houses
                 (:mod:`.operating_point`; the thresholds must then be None)
    workers    : DataLoader worker processes reading the store (None: the trainer's default,
                 :func:`~.trainer.default_workers`; 0: read in this process)
    progress   : a :class:`sceneforge.pipeline.Progress` (``start``/``advance`` in views)
    Raises :class:`SceneforgeError` for a camera run given as RUN, an existing ``out``
    without ``overwrite``, a store without RGB images, or a split without views in ``store``.
    """
    import time

    from sceneforge.store import StoreWriter, open_store

    t0 = time.perf_counter()
    if operating_point not in typing.get_args(OperatingPointRule):
        raise ValueError(f"operating_point must be one of {typing.get_args(OperatingPointRule)}, "
                         f"got {operating_point!r}")
    if operating_point == "validation" and (min_object_probability, min_overhead_object_probability) != (None, None):
        raise SceneforgeError("--operating-point validation chooses the least object probabilities on the "
                              "validation houses: give no --min-object-probability or "
                              "--min-overhead-object-probability with it")
    check_apart(out, "prediction store", [("input store", store), ("run", run), ("camera run", camera_run),
                                          ("split file", split_file)])
    check_store_output(out, "prediction", overwrite=overwrite)
    with StoreWriter(out) as writer:  # the store's lock, for the whole run
        if writer.exists() and not overwrite:
            raise SceneforgeError(f"{out} exists: pass --overwrite to replace it")
        dev = resolve_device(device)
        config, nets, stages = _load_nets(run, camera_run, dev)

        every = index = index_stores([store])
        houses = None
        if split != "all" or operating_point == "validation":
            chosen = read_split(split_file or config.split.file or default_split_file(config.stores))
        if split != "all":
            houses = chosen.of(split)
            index = index.subset(houses)
            if not len(index):
                raise SceneforgeError(f"{store} has no valid view of the {len(houses)} {split} houses of "
                                      f"{chosen.path}: predict another split (--split all: every view)")
        valid = index.view
        source = open_store(store)
        eft = None
        if get_stage(config.stage).uses_eft:
            eft = EpipolarFeatureTransformer(config.eft, resolution=index.shapes["Wo"])
        dataset = StoreDataset(index, ("rgb", "camera"))
        loader = make_loader(dataset, dev, default_workers() if workers is None else workers,
                             batch_size=batch_size)

        if operating_point == "validation":
            point = choose_operating_point(nets, eft, store, source, every.subset(chosen.of("val")),
                                           camera_run is not None, floor, dev, batch_size, workers,
                                           operating_point_views, progress)
            min_object_probability = point.min_object_probability
            min_overhead_object_probability = point.min_overhead_object_probability
        else:
            point = OperatingPoint("given", min_object_probability, min_overhead_object_probability)

        render_config = _prediction_config(source.config)
        n = len(source)
        prediction = {"run": str(Path(run).resolve()), "stage": config.stage, "stages": list(stages),
                      "source": str(store), "camera_run": None if camera_run is None else str(Path(camera_run).resolve()),
                      "min_height": MIN_HEIGHT, "floor": floor, "min_object_probability": min_object_probability,
                      "min_overhead_object_probability": min_overhead_object_probability,
                      "operating_point": point.to_dict(),
                      "split": split, "views": [int(i) for i in valid],
                      "split_file": None if houses is None else str(chosen.path)}
        # recorded from the start: an interrupted prediction store is still known as predict's
        # (sceneforge.store.guard), so a later --overwrite may replace it and render may not
        writer.create(render_config, source.attrs["houses_source"], n, replace=True, prediction=prediction)
        shards = _Shards(writer, render_config, source, valid)
        if progress:
            progress.start("predicting views", len(valid), "views")
        try:
            with torch.no_grad():
                for batch in loader:
                    batch = {k: v.to(dev) for k, v in batch.items()}
                    outputs = _predict_batch(nets, eft, batch, camera_run is not None, floor,
                                             (min_object_probability, min_overhead_object_probability))
                    for row, i in enumerate(valid[batch["index"].cpu().numpy()]):
                        shards.add(int(i), {name: value[row] for name, value in outputs.items()})
                    shards.flush()
                    if progress:
                        progress.advance(len(batch["index"]))
        finally:
            end_workers(loader)
        shards.flush(final=True)

        writer.finalize(render_config, source.attrs["houses_source"], n, houses=source.attrs["houses"],
                        failures=source.attrs["failures"], prediction=prediction)
    return PredictSummary(str(out), n, len(valid), stages, time.perf_counter() - t0, split,
                          len(set(index.house)), point)


def choose_operating_point(nets: dict, eft: EpipolarFeatureTransformer | None, store: str, source: "SceneStore",
                           index: "ViewIndex",
                           camera: bool, floor: str, dev: torch.device, batch_size: int, workers: int | None,
                           most: int, progress=None, seed: int = 0) -> OperatingPoint:
    """The thresholds where precision meets recall on at most ``most`` views of ``index``
    (the validation houses' views of ``store``, opened as ``source``), by
    :data:`.operating_point.RULE`.

    The ground-truth meshes are the store's, or made from its houses and cached beside it
    as ``sceneforge evaluate`` does. Raises :class:`SceneforgeError` without views to
    choose on, or without a segmentation net (nothing to threshold).
    """
    import time

    from sceneforge.evaluate import EvalView, GroundTruthMesh
    from sceneforge.pipeline.gt_mesh import GroundTruthMeshes, cache_folder

    from .operating_point import GRID, CandidateView, evenly, score_views

    t0 = time.perf_counter()
    if "seg" not in nets:
        raise SceneforgeError("--operating-point validation sets the segmentation nets' thresholds: "
                              "this run has no segmentation net")
    if not len(index):
        raise SceneforgeError(f"{store} has no valid view of the validation houses: the operating point is "
                              "chosen on them (give the thresholds instead: --operating-point given)")
    index = index.take(evenly(range(len(index)), most))
    meshes = GroundTruthMeshes(source, cache_folder(store))
    fronts = GRID
    tops = GRID if eft is not None and floor == "segmentation" else (None,)
    loader = make_loader(StoreDataset(index, ("rgb", "camera")), dev,
                         default_workers() if workers is None else workers, batch_size=batch_size)
    if progress:
        progress.start("choosing the operating point", len(index), "views")

    def candidates():
        with torch.no_grad():
            for batch in loader:
                batch = {k: v.to(dev) for k, v in batch.items()}
                outputs = _predict_batch(nets, eft, batch, camera, floor, scores=True)
                cameras = {k: batch[k].cpu().numpy() for k in SAMPLE_FIELDS["camera"]}
                for row, i in enumerate(index.view[batch["index"].cpu().numpy()]):
                    # the loader's cameras, then what the nets predicted (a camera run's overhead cameras too)
                    arrays = {k: v[row] for k, v in cameras.items()}
                    arrays.update({k: outputs[k][row] for k in outputs
                                   if k in ("depth", "overhead_height", *SAMPLE_FIELDS["camera"])})
                    front = outputs["front_score"][row]
                    top = outputs.get("top_score")
                    view = EvalView.from_arrays(arrays)
                    if top is None:  # no overhead net: no overhead part
                        view = replace(view, overhead_height=np.full_like(view.overhead_height, np.nan))
                        top = np.full(view.overhead_height.shape, -1.0, np.float32)
                    else:
                        top = top[row]
                    yield int(i), CandidateView(view, front, top), GroundTruthMesh.from_arrays(meshes.mesh(int(i)))
                    if progress:
                        progress.advance(1)

    try:
        precision, recall = score_views(candidates(), fronts, tops, seed)
    finally:
        end_workers(loader)
    return OperatingPoint.chosen(precision, recall, fronts, tops, len(index), len(set(index.house)),
                                 time.perf_counter() - t0)


def _load_nets(run: str | Path, camera_run: str | Path | None, dev: torch.device) -> tuple:
    """The run's config and nets (with the camera run's, when given) and the stages predicted."""
    config, nets = load_run(run, dev)
    stage = get_stage(config.stage)
    if stage.predicts_with is not None:
        raise SceneforgeError(f"{run} is a {stage.name} run: give the {stage.predicts_with} run it goes with as "
                              f"RUN, and this one with --{stage.name}-run")
    stages = stage.predicts
    if camera_run is not None:
        camera = REGISTRY["camera"]
        if stage.name != camera.predicts_with:
            raise SceneforgeError(f"--camera-run places overhead cameras: it needs an {camera.predicts_with} run")
        cam_config, cam_nets = load_run(camera_run, dev)
        if cam_config.stage != camera.name:
            raise SceneforgeError(f"{camera_run} is a {cam_config.stage} run, not a camera run")
        nets.update(camera=cam_nets["camera"], camera_depth=cam_nets["depth"])
        stages += camera.predicts
    return config, nets, stages


def _prediction_config(config: "DatasetConfig") -> "DatasetConfig":
    """The source store's render config, less what no net predicts: RGB, normals, the labels of
    every layer, the ray-intersection layers, meshes."""
    return replace(config, rgb=replace(config.rgb, enabled=False),
                   store=replace(config.store, normals=False, gt_mesh="none"),
                   view=replace(config.view, layers=replace(config.view.layers, labels="paper", intersections=0)))


class _Shards:
    """Predicted views held until every valid view of their shard has its prediction; then
    the shard is written whole (fill values where no net predicts, cameras and ids copied
    from the source store), in view order."""

    def __init__(self, writer: "StoreWriter", config: "DatasetConfig", source: "SceneStore", valid: np.ndarray):
        from sceneforge.store import array_specs, sizes_of

        self.writer, self.source = writer, source
        self.n = len(source)
        self.specs = array_specs(config, per_view=True)
        self.sizes = sizes_of(config, self.n)
        self.per_shard = config.store.views_per_shard
        self.is_valid = np.zeros(self.n, bool)
        self.is_valid[valid] = True
        self.predicted: dict[int, dict[str, np.ndarray]] = {}
        self.next_shard = 0  # first view of the next shard to write

    def add(self, i: int, outputs: dict[str, np.ndarray]) -> None:
        """Hold view ``i``'s predictions (one view's entries, keyed by array name)."""
        self.predicted[i] = outputs

    def flush(self, final: bool = False) -> None:
        """Write every shard whose valid views all have their predictions (every shard left
        when ``final``)."""
        while self.next_shard < self.n:
            a, b = self.next_shard, min(self.next_shard + self.per_shard, self.n)
            if not final and any(self.is_valid[i] and i not in self.predicted for i in range(a, b)):
                return
            block = {spec.name: np.stack([spec.blank(self.sizes)] * (b - a)) for spec in self.specs}
            for name in COPIED:
                block[name] = np.asarray(self.source.array(name)[a:b])
            for i in range(a, b):
                for name, value in self.predicted.pop(i, {}).items():
                    block[name][i - a] = value
            self.writer.write_shard(a // self.per_shard, [{name: v[k] for name, v in block.items()}
                                                          for k in range(b - a)])
            self.next_shard = b
