"""Views per second of ``sceneforge render`` on the bundled toy houses, 1 worker vs 2.

End to end (planning, worker start-up, ground truth, RGB, writing, finalizing) and in
steady state (the rendering step once the workers are warm), per-stage worker time per
view (load, trace, overhead, mesh, render, write) and store bytes per view. The baseline
is the 1-worker run; the ratio is the 2-worker speed-up.

The pipeline reports load, ground truth, render and write time per view; the ground truth
is split into its stages (frontal trace + layers, overhead camera + overhead trace, mesh)
by timing them on the same views in this process.

    python benchmarks/bench_pipeline.py [--views-per-house 16] [--resolution 320x240] [--quick]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads: BLAS threads fight Open3D's

from sceneforge.cameras import Camera  # noqa: E402
from sceneforge.config import load_config  # noqa: E402
from sceneforge.frustum import view_mesh  # noqa: E402
from sceneforge.houses import BUNDLED_TOY, discover, load  # noqa: E402
from sceneforge.layers import frontal_layers  # noqa: E402
from sceneforge.overhead import overhead_camera, overhead_truth  # noqa: E402
from sceneforge.pipeline import render_dataset  # noqa: E402
from sceneforge.raytrace import HouseTracer  # noqa: E402
from sceneforge.store import open_store  # noqa: E402


class Clock:
    """Progress receiver that notes when the rendering step starts and each shard lands."""

    def __init__(self):
        self.step, self.marks = None, []

    def start(self, step, total, unit, done=0):
        self.step = step
        if step.startswith("rendering"):
            self.marks = [(time.perf_counter(), done)]

    def advance(self, n):
        if self.step.startswith("rendering"):
            self.marks.append((time.perf_counter(), self.marks[-1][1] + n))

    def steady_rate(self, workers: int) -> float:
        """Views per second once every worker has finished its first shard (start-up and the
        renderer's first use excluded); NaN with too few shards."""
        if len(self.marks) <= workers + 1:
            return float("nan")
        (t0, v0), (t1, v1) = self.marks[workers], self.marks[-1]
        return (v1 - v0) / (t1 - t0)


def run(workers: int, overrides: dict, root: Path) -> dict:
    out = root / f"bench_{workers}.zarr"
    clock = Clock()
    t0 = time.perf_counter()
    summary = render_dataset(BUNDLED_TOY, str(out), load_config(None, overrides), workers=workers, progress=clock)
    wall = time.perf_counter() - t0
    n = summary.views
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    return {"workers": workers, "views": n, "wall": wall, "end_to_end": n / wall, "steady": clock.steady_rate(workers),
            "per_view": {k: v / n for k, v in summary.timings.items()}, "bytes_per_view": size / n, "store": out}


def ground_truth_stages(store_path: Path) -> dict[str, float]:
    """Seconds per view of the frontal trace, the overhead and the mesh, on the stored views."""
    store = open_store(str(store_path))
    config = store.config
    houses = {s.id: load(s) for s in discover(BUNDLED_TOY)}
    tracers = {hid: HouseTracer(h) for hid, h in houses.items()}
    totals = dict.fromkeys(("trace", "overhead", "mesh"), 0.0)
    for i in range(len(store)):
        v = store.view(i)
        house, tracer = houses[str(v["house_id"])], tracers[str(v["house_id"])]
        camera = Camera(v["K"], v["cam_to_world"], config.width, config.height)
        t0 = time.perf_counter()
        layers = frontal_layers(house, camera, tracer)
        t1 = time.perf_counter()
        top = overhead_camera(house, camera, layers, config.view.overhead)
        overhead_truth(house, top, tracer, config.view.overhead)
        t2 = time.perf_counter()
        view_mesh(house, camera, layers, config.view.mesh)
        t3 = time.perf_counter()
        totals["trace"] += t1 - t0
        totals["overhead"] += t2 - t1
        totals["mesh"] += t3 - t2
    return {k: v / len(store) for k, v in totals.items()}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--views-per-house", type=int, default=16)
    parser.add_argument("--resolution", default="320x240")
    parser.add_argument("--quick", action="store_true", help="4 views per house (a smoke run)")
    args = parser.parse_args()
    width, height = map(int, args.resolution.lower().split("x"))
    overrides = {"width": width, "height": height, "views_per_house": 4 if args.quick else args.views_per_house}
    print(f"sceneforge render, bundled toy houses, {width}x{height}, overhead 300, RGB on, "
          f"{overrides['views_per_house']} views per house, {os.cpu_count()} CPUs")
    with tempfile.TemporaryDirectory() as tmp:
        results = [run(w, overrides, Path(tmp)) for w in (1, 2)]
        stages = ground_truth_stages(results[0]["store"])
        same = all((a.read_bytes() == b.read_bytes()) for a, b in zip(
            sorted(p for p in results[0]["store"].rglob("*") if p.is_file()),
            sorted(p for p in results[1]["store"].rglob("*") if p.is_file())))
    print(f"{'workers':>7} {'views':>5} {'wall s':>7} {'end-to-end v/s':>15} {'steady v/s':>11} "
          f"{'load':>6} {'gt':>6} {'render':>6} {'write':>6}  (worker ms/view)")
    for r in results:
        p = r["per_view"]
        print(f"{r['workers']:>7} {r['views']:>5} {r['wall']:>7.1f} {r['end_to_end']:>15.2f} {r['steady']:>11.2f} "
              + " ".join(f"{1000 * p.get(k, 0.0):>6.0f}" for k in ("load", "ground_truth", "render", "write")))
    print("ground truth split (ms/view, measured in-process): "
          + ", ".join(f"{k} {1000 * v:.0f}" for k, v in stages.items()))
    print(f"store: {results[0]['bytes_per_view'] / 1024:.0f} KiB per view; 1- and 2-worker stores byte-identical: "
          f"{same}")
    base, two = results
    print(f"ratio 2 workers / 1 worker: end-to-end {two['end_to_end'] / base['end_to_end']:.2f}x, "
          f"steady {two['steady'] / base['steady']:.2f}x")
    target = 4.0
    print(f"target >= {target} views/s with 2 workers (steady): {'met' if two['steady'] >= target else 'NOT met'} "
          f"({two['steady']:.2f})")


if __name__ == "__main__":
    main()
