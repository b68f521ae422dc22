"""Seconds per view of the evaluation (docs/spec.md §11) at the default settings, against baselines.

- **Coverage** (paper Table 1: six layer unions × two ground truths, 10 000 samples/m²,
  61 thresholds): sceneforge meshes, samples and measures each part of a view once and
  assembles the unions from those; the baseline scores every (union, ground truth) pair
  from scratch with :func:`~sceneforge.evaluate.surface_precision_recall`, as the
  reference's ``MeshPrecisionRecall`` does per call. Both use Open3D distances, so the
  ratio is the sharing's. Their recalls at 5 cm are printed side by side (they differ by
  sampling noise only).
- **Voxel IoU** (400³ voxels of 2.5 cm): sceneforge's layer occupancy sweeps z-slices
  with two projections per voxel row/column; the baseline projects all 64 M voxel
  centres. Their occupancies must be equal.

Views: ``--views`` sampled cameras per bundled toy house, 320×240, ground truth from
``compute_view`` (not timed).

    python benchmarks/bench_evaluate.py [--views 2] [--quick]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from sceneforge.camera_sampler import sample_cameras
from sceneforge.evaluate import (
    COVERAGE_VARIANTS,
    GT_KINDS,
    EvalView,
    GroundTruthMesh,
    SurfaceConfig,
    VoxelConfig,
    concatenate,
    layer_occupancy,
    mesh_occupancy,
    score_view,
    surface_precision_recall,
)
from sceneforge.houses import BUNDLED_TOY, discover, load
from sceneforge.raytrace import HouseTracer
from sceneforge.view import compute_view


def views(per_house: int):
    for source in discover(BUNDLED_TOY):
        house = load(source)
        tracer = HouseTracer(house)
        cameras, _ = sample_cameras(house, per_house, np.random.default_rng(0), None, tracer)
        for camera in cameras:
            gt = compute_view(house, camera, tracer=tracer)
            yield EvalView.from_ground_truth(gt), GroundTruthMesh.from_ground_truth(gt)


def baseline_recall(view: EvalView, gt: GroundTruthMesh, rng, config: SurfaceConfig) -> np.ndarray:
    """(n_variants, 2) recall at 5 cm, every (union, ground truth) pair scored from scratch."""
    parts = view.meshes()
    truths = {"all": concatenate([gt.objects, gt.envelope]), "objects": gt.objects}
    out = np.empty((len(COVERAGE_VARIANTS), len(GT_KINDS)))
    at = config.thresholds.index(config.threshold)
    for i, variant in enumerate(COVERAGE_VARIANTS):
        union = concatenate([parts[p] for p in variant.parts])
        for k, kind in enumerate(GT_KINDS):
            _, recall = surface_precision_recall(union, truths[kind], rng, config)
            out[i, k] = recall[at]
    return out


def naive_layer_occupancy(depth: np.ndarray, K: np.ndarray, config: VoxelConfig) -> np.ndarray:
    """Every voxel centre projected through K, one z-slice at a time."""
    xy, zs = config.centres()
    h, w = depth.shape[1:]
    y, x = np.meshgrid(xy, xy, indexing="ij")
    out = np.zeros((config.resolution,) * 3, dtype=bool)
    d = depth[:4].reshape(4, -1).astype(np.float64)
    for k, z in enumerate(zs):
        col = np.floor(K[0, 0] * x / z + K[0, 2])
        row = np.floor(K[1, 1] * y / z + K[1, 2])
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        pixel = (row * w + col)[inside].astype(np.int64)
        with np.errstate(invalid="ignore"):
            hit = ((d[0, pixel] < z) & (z < d[1, pixel])) | ((d[2, pixel] < z) & (z < d[3, pixel]))
        out[k][inside] = hit
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=2, help="cameras per bundled toy house")
    parser.add_argument("--quick", action="store_true", help="one camera per house, 2 000 samples/m²")
    args = parser.parse_args()
    per_house = 1 if args.quick else args.views
    config = SurfaceConfig(density=2_000.0 if args.quick else 10_000.0)

    import open3d  # noqa: F401  (its import takes seconds: keep it out of the timings)

    data = list(views(per_house))
    n = len(data)
    print(f"{n} views of the bundled toy houses, 320×240, {config.density:g} samples/m², "
          f"{len(config.thresholds)} thresholds")

    t0 = time.perf_counter()
    ours = [score_view(v, g, COVERAGE_VARIANTS, np.random.default_rng(i), config)
            for i, (v, g) in enumerate(data)]
    t_ours = (time.perf_counter() - t0) / n
    t0 = time.perf_counter()
    base = [baseline_recall(v, g, np.random.default_rng(i), config) for i, (v, g) in enumerate(data)]
    t_base = (time.perf_counter() - t0) / n

    recall = np.mean([s.recall[:, :, -1] for s in ours], axis=0)
    recall_base = np.mean(base, axis=0)
    print("\nrecall at 5 cm, mean over views    sceneforge (all, objects)   baseline (all, objects)")
    for i, v in enumerate(COVERAGE_VARIANTS):
        print(f"  {v.name:<18} {recall[i, 0]:>22.3f} {recall[i, 1]:>8.3f} {recall_base[i, 0]:>17.3f} "
              f"{recall_base[i, 1]:>8.3f}")
    print(f"\ncoverage, s/view:  sceneforge {t_ours:.2f}   baseline (per pair) {t_base:.2f}   "
          f"ratio {t_base / t_ours:.1f}×")

    voxels = VoxelConfig()
    t_layers = t_naive = t_mesh = 0.0
    for view, gt in data:
        t0 = time.perf_counter()
        fast = layer_occupancy(view.depth, view.K, voxels)
        t1 = time.perf_counter()
        slow = naive_layer_occupancy(view.depth, view.K, voxels)
        t2 = time.perf_counter()
        mesh_occupancy(gt.objects, view.K, view.cam_to_world, view.depth.shape[1:], voxels)
        t3 = time.perf_counter()
        if not np.array_equal(fast, slow):
            raise SystemExit(f"layer occupancy differs from the naive one on {np.sum(fast != slow)} voxels")
        t_layers, t_naive, t_mesh = t_layers + t1 - t0, t_naive + t2 - t1, t_mesh + t3 - t2
    print(f"voxel IoU {voxels.resolution}³, s/view:  layer occupancy {t_layers / n:.3f} "
          f"(naive projection of every voxel {t_naive / n:.2f}, ratio {t_naive / t_layers:.1f}×; "
          f"identical), ground-truth mesh occupancy {t_mesh / n:.2f}")


if __name__ == "__main__":
    main()
