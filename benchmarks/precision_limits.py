"""What limits the precision of predicted layers: the masks or the depths?

`sceneforge evaluate predictions PRED GT` scores the predicted D1-D4 and overhead heights
where the segmentation nets see objects (the paper's masks). This script scores the same
views again with one ingredient of the prediction swapped for the truth, so that each row
says how far fixing that ingredient alone would go (5 cm, against the objects, as the
predictions table; same samples per view as `evaluate`'s default seed):

- ``prediction``: the predictions as stored (what `evaluate predictions` prints);
- ``true depths, predicted masks``: every predicted pixel keeps its place but takes the
  true depth (D1-D4) or height (overhead) there: perfect depth nets, the same segmentation;
- ``true overhead mask``: predicted heights, kept exactly where the truth has an object
  more than 5 cm above the floor: a perfect floor removal;
- ``depth scale per view``: D1-D4 times the median of true/predicted D1 over the view's
  predicted object pixels: the prediction without its per-view scale error;
- ``truth``: the true layers and heights at this resolution (the ceiling).

    python benchmarks/precision_limits.py PRED GT [--every 1] [--density 10000]

PRED and GT as for `sceneforge evaluate predictions` (e.g. the learning check's
WORKDIR/pred.zarr and WORKDIR/gt.zarr); ``--every K`` scores every K-th predicted view;
``--density`` samples per m² (`evaluate`'s default).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from sceneforge.conventions import LAYER_NAMES
from sceneforge.evaluate import (
    GT_KINDS,
    EvalView,
    GroundTruthMesh,
    SurfaceConfig,
    Variant,
    matching_view,
    score_view,
    views_to_score,
)
from sceneforge.evaluate.inputs import OVERHEAD
from sceneforge.evaluate.learning import MIN_HEIGHT, OBJECT_LAYERS
from sceneforge.pipeline.gt_mesh import GroundTruthMeshes, cache_folder
from sceneforge.store import open_store

OBJECT_PARTS = tuple(LAYER_NAMES[:OBJECT_LAYERS])
VARIANTS = (Variant("D1", ("D1",)), Variant("D1-4", OBJECT_PARTS), Variant("overhead", (OVERHEAD,)),
            Variant("D1-4 & overhead", (*OBJECT_PARTS, OVERHEAD)))


def prediction(depth, height, true_depth, true_height):
    return depth, height


def true_depths(depth, height, true_depth, true_height):
    out = depth.copy()
    out[:OBJECT_LAYERS] = np.where(np.isfinite(depth[:OBJECT_LAYERS]), true_depth[:OBJECT_LAYERS], np.nan)
    return out, np.where(np.isfinite(height), true_height, np.nan)


def true_overhead_mask(depth, height, true_depth, true_height):
    with np.errstate(invalid="ignore"):
        return depth, np.where(true_height > MIN_HEIGHT, height, np.nan)


def depth_scale_per_view(depth, height, true_depth, true_height):
    both = np.isfinite(depth[0]) & np.isfinite(true_depth[0])
    out = depth.copy()
    if both.any():
        out[:OBJECT_LAYERS] *= np.median(true_depth[0][both] / depth[0][both])
    return out, height


def truth(depth, height, true_depth, true_height):
    return true_depth, true_height


ROWS = {"prediction": prediction, "true depths, predicted masks": true_depths,
        "true overhead mask": true_overhead_mask, "depth scale per view": depth_scale_per_view,
        "truth": truth}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("pred", help="store of predictions (sceneforge predict)")
    parser.add_argument("gt", help="their ground-truth store")
    parser.add_argument("--every", type=int, default=1, help="score every K-th predicted view (default: all)")
    parser.add_argument("--density", type=float, default=SurfaceConfig.density,
                        help="surface samples per square metre (default: evaluate's)")
    args = parser.parse_args()
    pred, gt = open_store(args.pred), open_store(args.gt)
    meshes = GroundTruthMeshes(gt, cache_folder(args.gt))
    indices = views_to_score(pred)[::args.every]
    config = SurfaceConfig(density=args.density)
    objects = GT_KINDS.index("objects")
    views = []
    for i in indices:
        p, g = matching_view(pred, gt, i), gt.view(i)
        views.append((i, p, np.asarray(g["depth"], np.float32), np.asarray(g["overhead_height"], np.float32),
                      GroundTruthMesh.from_arrays(meshes.mesh(i))))
    print(f"{len(views)} views of {args.pred}; precision / recall at {config.threshold * 100:g} cm against "
          f"the objects")
    print(f"{'':30}" + "".join(f"{v.name:>18}" for v in VARIANTS))
    for name, swap in ROWS.items():
        t0 = time.perf_counter()
        precision, recall = [], []
        for i, p, true_depth, true_height, mesh in views:
            depth, height = swap(np.asarray(p["depth"], np.float32), np.asarray(p["overhead_height"], np.float32),
                                 true_depth, true_height)
            view = EvalView(depth, p["K"], p["cam_to_world"], height, p["overhead_cam_to_world"],
                            float(np.asarray(p["overhead_extent"])), p["overhead_params"])
            scores = score_view(view, mesh, VARIANTS, np.random.default_rng((0, i)), config)
            precision.append(scores.precision[:, objects, -1])
            recall.append(scores.recall[:, objects, -1])
        p_mean, r_mean = np.nanmean(precision, axis=0), np.nanmean(recall, axis=0)
        cells = "".join(f"{f'{a:.3f} / {b:.3f}':>18}" for a, b in zip(p_mean, r_mean))
        print(f"{name:30}{cells}   ({time.perf_counter() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
