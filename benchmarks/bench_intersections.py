"""Milliseconds per view of the ground truth a render computes, without and with K ray-intersection
layers (docs/spec.md §4.7), and the intersection layers alone the K-nearest way and the naive way.

In one run, on the same 320×240 cameras (sampled per house, seeded):

- ``render``: :func:`~sceneforge.view.compute_view` with a default render's view config (the
  frontal layers, the overhead camera and its ground truth; no mesh: a default store keeps
  none), as ``sceneforge render`` computes each view today; the baseline.
- ``render, K``: the same with ``view.layers.intersections = K``, and its ratio to the
  baseline (the cost of asking for the layers).
- ``K-nearest``: the intersection layers alone (:func:`~sceneforge.intersections.ray_intersections`):
  the extension's traversal that keeps each ray's K nearest hits and stops where no farther
  one can be among them, in ray packets, then the arrays.
- ``naive``: every hit of every ray (the extension's all-hit collection, sorted and merged),
  cut after the K-th in numpy, then the same arrays in numpy (what the Open3D engine's path
  does); the K-nearest result equals it (the tests hold them equal on every pixel), and its
  ratio to the K-nearest way.
- the hits alone, without the arrays: the K-nearest traversal
  (:meth:`~sceneforge.raytrace.HouseTracer.nearest_hits`) against every hit, cut.

Each figure is the mean over a house's views of each view's fastest of ``--repeat`` runs,
the modes interleaved view by view (this machine's speed drifts from minute to minute, and
other processes share its cores); every run gets a fresh camera, so no run reuses rays an
earlier one computed. Tracing threads: every core, as a render with one worker; numpy with
one BLAS thread and the render workers' malloc settings, as in the pipeline.

    python benchmarks/bench_intersections.py [--views 3] [--repeat 7] [-k 10] [--houses toy,breakfast]
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads, as in the pipeline's workers

import numpy as np  # noqa: E402

from sceneforge.camera_sampler import CameraSamplerConfig, sample_cameras  # noqa: E402
from sceneforge.config import DatasetConfig  # noqa: E402
from sceneforge.houses import BUNDLED_TOY, discover, load  # noqa: E402
from sceneforge.intersections import Intersections, ray_intersections  # noqa: E402
from sceneforge.layers import LayersConfig, instance_labels  # noqa: E402
from sceneforge.pipeline.executors import tune_allocator  # noqa: E402
from sceneforge.raytrace import HouseTracer, NearestHits, _nearest_surfaces  # noqa: E402
from sceneforge.raytrace.embree_backend import AVAILABLE as EMBREE_EXTENSION  # noqa: E402
from sceneforge.view import compute_view  # noqa: E402

BREAKFAST = Path(__file__).resolve().parents[2] / "shared" / "scenes" / "breakfast_room" / "BreakfastRoom.gltf"
WIDTH, HEIGHT = 320, 240


def all_hits_cut(camera, k: int, tracer: HouseTracer) -> NearestHits:
    """Every hit of every ray, cut after the k-th (in numpy)."""
    origins, directions, _ = camera.rays()
    hits = tracer.all_hits(origins, directions)
    n = hits.n_rays
    rank = np.arange(len(hits.t)) - np.repeat(hits.offsets[:-1], hits.counts)
    keep = rank < k
    ray, rank = hits.ray_ids()[keep], rank[keep]
    nearest = NearestHits(np.full((k, n), np.nan), np.full((k, n), -1, dtype=np.int64), np.zeros((k, n), dtype=bool))
    nearest.t[rank, ray] = hits.t[keep]
    nearest.face[rank, ray] = tracer.triangles.global_index(hits.instance[keep], hits.triangle[keep])
    nearest.front_facing[rank, ray] = hits.front_facing[keep]
    return nearest


def naive_intersections(house, camera, k: int, tracer: HouseTracer) -> Intersections:
    """The intersection layers from every hit of every ray, cut after the k-th, in numpy."""
    nearest = all_hits_cut(camera, k, tracer)
    _, _, depth_scale = camera.rays()
    category, _ = instance_labels(house)
    s = _nearest_surfaces(tracer.triangles, nearest, depth_scale, camera.cam_to_world[:3, :3].T, category)
    H, W = camera.shape
    return Intersections(s.depth.reshape(k, H, W), s.normal.reshape(k, 3, H, W), s.instance.reshape(k, H, W),
                         s.label.reshape(k, H, W), s.front_facing.reshape(k, H, W))


def houses(chosen: set[str]):
    """[(name, house)]: the bundled toy houses and the breakfast room (where ../shared is)."""
    out = []
    if "toy" in chosen:
        out += [(source.id, load(source)) for source in discover(BUNDLED_TOY)]
    if "breakfast" in chosen:
        if BREAKFAST.exists():
            out.append(("breakfast room", load(BREAKFAST)))
        else:
            print(f"(no {BREAKFAST}: the breakfast room is left out)")
    return out


def time_house(house, views: int, repeat: int, k: int) -> dict[str, float]:
    """Mean over the house's views of each mode's fastest run, ms."""
    tracer = HouseTracer(house)
    sampler = CameraSamplerConfig(width=WIDTH, height=HEIGHT, max_escape_fraction=0.5)
    cameras, _ = sample_cameras(house, views, np.random.default_rng(0), sampler, tracer)
    base = DatasetConfig(width=WIDTH, height=HEIGHT).view
    with_k = replace(base, layers=LayersConfig(intersections=k))
    modes = {
        "render": lambda cam: compute_view(house, cam, base, tracer),
        f"render, K={k}": lambda cam: compute_view(house, cam, with_k, tracer),
        "K-nearest": lambda cam: ray_intersections(house, cam, k, tracer),
        "naive": lambda cam: naive_intersections(house, cam, k, tracer),
        "hits, K-nearest": lambda cam: tracer.nearest_hits(*cam.rays()[:2], k),
        "hits, all cut": lambda cam: all_hits_cut(cam, k, tracer),
    }
    for run in modes.values():  # warm-up: first-call costs, the engine's scenes
        run(cameras[0])
    best = {name: [np.inf] * len(cameras) for name in modes}
    for _ in range(repeat):
        for v, cam in enumerate(cameras):
            for name, run in modes.items():
                fresh = cam.resized(cam.width, cam.height)  # its rays are not cached yet
                t0 = time.perf_counter()
                run(fresh)
                best[name][v] = min(best[name][v], time.perf_counter() - t0)
    out = {name: 1e3 * float(np.mean(times)) for name, times in best.items()}
    out["views"] = len(cameras)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", type=int, default=3, help="cameras per house")
    ap.add_argument("--repeat", type=int, default=7, help="runs of each view in each mode; the fastest counts")
    ap.add_argument("-k", type=int, default=10, help="ray-intersection layers")
    ap.add_argument("--houses", default="toy,breakfast", help="comma-separated: toy (the bundled toy houses), "
                    "breakfast (the breakfast room, where ../shared/scenes is)")
    args = ap.parse_args()
    if not EMBREE_EXTENSION:
        raise SystemExit("sceneforge's Embree extension is not built: the K-nearest traversal is the extension's")
    tune_allocator()
    print(f"{WIDTH}x{HEIGHT}, K = {args.k}, {args.views} views per house, fastest of {args.repeat} runs; "
          f"tracing threads: every core ({os.cpu_count()})")
    print(f"{'':<22}{'a view (ms)':^25}  {'the K layers alone (ms)':^27}  {'their hits alone (ms)':^27}")
    print(f"{'house':<16} {'views':>5} {'render':>7} {f'K={args.k}':>7} {'ratio':>7}  {'K-nearest':>9} "
          f"{'naive':>7} {'ratio':>7}  {'K-nearest':>9} {'all, cut':>8} {'ratio':>6}")
    for name, house in houses(set(args.houses.split(","))):
        r = time_house(house, args.views, args.repeat, args.k)
        k_render, k_hits, cut = r[f"render, K={args.k}"], r["hits, K-nearest"], r["hits, all cut"]
        print(f"{name:<16} {r['views']:>5} {r['render']:>7.1f} {k_render:>7.1f} {k_render / r['render']:>7.2f}  "
              f"{r['K-nearest']:>9.1f} {r['naive']:>7.1f} {r['naive'] / r['K-nearest']:>7.2f}  "
              f"{k_hits:>9.1f} {cut:>8.1f} {cut / k_hits:>6.2f}")


if __name__ == "__main__":
    main()
