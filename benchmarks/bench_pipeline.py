"""Views per second of ``sceneforge render``: the old store defaults against the new, with and
without RGB, on the bundled toy houses and the breakfast room.

"before" is the store as it was before lean stores (``store.gt_mesh: all``: every view's
ground-truth meshes computed and kept; ``store.codec: blosc-zstd``: every array
byte-shuffled with Blosc's own blocks), still selectable and byte-identical to the old
code's; "after" is today's defaults (no meshes, per-array codecs). Each scene and RGB mode
renders before then after, back to back, into fresh stores; every run plans, starts its
workers, renders and finalizes as ``sceneforge render`` does (:func:`render_dataset`, which
it calls). Per run: views/s end to end (the whole call) and steady (once every worker has
finished its first shard: start-up and the renderer's first use excluded; a warm-up render
first imports what rendering imports, for the runs with 1 worker, in this process), the workers'
milliseconds per view by stage (load, ground truth, RGB, store write) and store bytes
per view; per pair the after/before ratios, and a check that the after store holds the
before store's values (``array_digests`` of every array both have). The ground truth is
then split into its stages (frontal trace + layers, overhead camera + trace, mesh) by
timing them on the first stored views in this process.

``--workers 1,2`` renders each with 1 and then 2 workers and checks that the stores of
different worker counts are byte-identical, file for file.

    python benchmarks/bench_pipeline.py [--scenes toy,breakfast_room] [--rgb raster,none] [--workers 2]
        [--views-per-house 16] [--breakfast-views 24] [--resolution 320x240] [--quick]
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
from sceneforge.store import array_digests, open_store  # noqa: E402

BREAKFAST_ROOM = Path(__file__).resolve().parents[2] / "shared" / "scenes" / "breakfast_room" / "BreakfastRoom.gltf"
SCENES = {"toy": BUNDLED_TOY, "breakfast_room": str(BREAKFAST_ROOM)}
#: the store defaults before lean stores: every view's meshes kept, every array byte-shuffled
BEFORE = {"store": {"gt_mesh": "all", "codec": "blosc-zstd"}}
STAGES = ("load", "ground_truth", "render", "write")


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


def run(houses: str, out: Path, overrides: dict, workers: int) -> dict:
    """Render ``houses`` into ``out`` with ``workers`` processes; the run's figures."""
    clock = Clock()
    t0 = time.perf_counter()
    summary = render_dataset(houses, str(out), load_config(None, overrides), workers=workers, progress=clock)
    wall = time.perf_counter() - t0
    n = summary.views
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    return {"views": n, "wall": wall, "end_to_end": n / wall, "steady": clock.steady_rate(workers),
            "per_view": {k: v / n for k, v in summary.timings.items()}, "bytes_per_view": size / n, "store": out}


def ground_truth_stages(houses: str, store_path: Path, max_views: int = 8) -> dict[str, float]:
    """Seconds per view of the frontal trace, the overhead and the mesh, on the first
    ``max_views`` stored views, in this process (the tracer on every core)."""
    store = open_store(str(store_path))
    config = store.config
    loaded = {s.id: load(s) for s in discover(houses)}
    tracers = {hid: HouseTracer(h) for hid, h in loaded.items()}
    totals = dict.fromkeys(("trace", "overhead", "mesh"), 0.0)
    n = min(max_views, len(store))
    for i in range(n):
        v = store.view(i)
        house, tracer = loaded[str(v["house_id"])], tracers[str(v["house_id"])]
        camera = Camera(v["K"], v["cam_to_world"], config.width, config.height)
        t0 = time.perf_counter()
        layers = frontal_layers(house, camera, tracer)
        t1 = time.perf_counter()
        top = overhead_camera(house, camera, layers, config.view.overhead)
        overhead_truth(house, top, tracer, config.view.overhead)
        t2 = time.perf_counter()
        view_mesh(house, camera, layers, config.view.mesh, tracer)
        t3 = time.perf_counter()
        totals["trace"] += t1 - t0
        totals["overhead"] += t2 - t1
        totals["mesh"] += t3 - t2
    return {k: v / n for k, v in totals.items()}


def same_values(before: Path, after: Path) -> str:
    """Whether every array of ``after`` holds the values of the same array of ``before``."""
    b, a = array_digests(str(before)), array_digests(str(after))
    differ = sorted(k for k in a if b.get(k) != a[k])
    return f"{len(a) - len(differ)} of {len(a)} equal" + (f" (DIFFERENT: {', '.join(differ)})" if differ else "")


def same_files(one: Path, other: Path) -> bool:
    files = [sorted(p for p in s.rglob("*") if p.is_file()) for s in (one, other)]
    return [p.relative_to(one) for p in files[0]] == [p.relative_to(other) for p in files[1]] and all(
        a.read_bytes() == b.read_bytes() for a, b in zip(*files))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default=",".join(SCENES), help="comma-separated: toy, breakfast_room")
    parser.add_argument("--rgb", default="raster,none", help="comma-separated RGB modes: raster, none")
    parser.add_argument("--workers", default="2", help="comma-separated worker counts, e.g. 1,2")
    parser.add_argument("--views-per-house", type=int, default=16, help="views of each toy house")
    parser.add_argument("--breakfast-views", type=int, default=24, help="views of the breakfast room")
    parser.add_argument("--resolution", default="320x240")
    parser.add_argument("--quick", action="store_true", help="4 views per toy house, 8 of the breakfast room")
    args = parser.parse_args()
    width, height = map(int, args.resolution.lower().split("x"))
    scenes = args.scenes.split(",")
    modes = args.rgb.split(",")
    worker_counts = [int(w) for w in args.workers.split(",")]
    if set(scenes) - set(SCENES) or set(modes) - {"raster", "none"}:
        parser.error(f"--scenes from {', '.join(SCENES)}; --rgb from raster, none")
    views = {"toy": 4 if args.quick else args.views_per_house,
             "breakfast_room": 8 if args.quick else args.breakfast_views}
    print(f"sceneforge render, {width}x{height}, overhead 300, {os.cpu_count()} CPUs, load average "
          f"{' '.join(f'{x:.1f}' for x in os.getloadavg())}; before = {BEFORE}, after = the defaults")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        # a run with 1 worker renders in this process: import what rendering imports first
        # (Open3D, pyrender: seconds), or the first measured run alone would pay for it
        render_dataset(BUNDLED_TOY, str(Path(tmp) / "warm_up.zarr"),
                       load_config(None, {"width": 32, "height": 24, "views_per_house": 1}))
        for scene in scenes:
            if scene == "breakfast_room" and not BREAKFAST_ROOM.exists():
                print(f"== {scene}: skipped, {BREAKFAST_ROOM} is absent (the shared scenes are not checked out)")
                continue
            for mode in modes:
                rgb = {"enabled": False} if mode == "none" else {"mode": mode}
                base = {"width": width, "height": height, "views_per_house": views[scene], "rgb": rgb}
                for workers in worker_counts:
                    pair = {}
                    for label, overrides in (("before", {**base, **BEFORE}), ("after", base)):
                        out = Path(tmp) / f"{scene}_{mode}_{label}_{workers}.zarr"
                        pair[label] = run(SCENES[scene], out, overrides, workers)
                        rows.append({"scene": scene, "rgb": mode, "defaults": label, "workers": workers, **pair[label]})
                    rows[-1]["values"] = same_values(pair["before"]["store"], pair["after"]["store"])
                    rows[-1]["ratio"] = {k: pair["after"][k] / pair["before"][k] for k in ("end_to_end", "steady")}
                    rows[-2]["ratio"] = None
            first = next(r for r in rows if r["scene"] == scene and r["defaults"] == "before")
            stages = ground_truth_stages(SCENES[scene], first["store"])
            print(f"== {scene}: ground truth split (ms/view, measured in-process on its 'before' views): "
                  + ", ".join(f"{k} {1000 * v:.0f}" for k, v in stages.items()))
        if len(worker_counts) > 1:
            for (scene, mode, label), group in _groups(rows).items():
                same = all(same_files(group[0]["store"], r["store"]) for r in group[1:])
                print(f"{scene}, RGB {mode}, {label}: stores of {', '.join(str(r['workers']) for r in group)} "
                      f"workers byte-identical: {same}")
    print(f"\n{'scene':<15}{'RGB':<7}{'store':<7}{'workers':>8}{'views':>6}{'wall s':>8}{'end-to-end v/s':>15}"
          f"{'steady v/s':>11}" + "".join(f"{k.replace('ground_truth', 'gt'):>8}" for k in STAGES)
          + f"{'kB/view':>9}   (worker ms per view)")
    for r in rows:
        p = r["per_view"]
        print(f"{r['scene']:<15}{r['rgb']:<7}{r['defaults']:<7}{r['workers']:>8}{r['views']:>6}{r['wall']:>8.1f}"
              f"{r['end_to_end']:>15.2f}{r['steady']:>11.2f}"
              + "".join(f"{1000 * p.get(k, 0.0):>8.0f}" for k in STAGES) + f"{r['bytes_per_view'] / 1e3:>9.1f}")
        if r.get("ratio"):
            print(f"{'':<29}after / before: end to end {r['ratio']['end_to_end']:.2f}x, steady "
                  f"{r['ratio']['steady']:.2f}x; array values: {r['values']}")


def _groups(rows: list[dict]) -> dict[tuple, list[dict]]:
    out: dict[tuple, list[dict]] = {}
    for r in rows:
        out.setdefault((r["scene"], r["rgb"], r["defaults"]), []).append(r)
    return out


if __name__ == "__main__":
    main()
