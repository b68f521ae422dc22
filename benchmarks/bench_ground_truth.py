"""Seconds per view for the full ground truth (frontal layers + overhead + mesh), against the
physical limit of its ray work.

The limit is plain Embree doing the same ray queries, compiled from
``benchmarks/native_all_hits.cpp`` at run time with the system compiler: per view, the
frontal 320×240 rays and the overhead 300×300 rays, each a first-hit pass against the
closing instances (in ray packets, as sceneforge's extension traces first hits) and one
traversal per ray of the objects up to the closing hit whose filter callback collects
every hit, sorted per ray into CSR arrays; and the envelope
surface's D5 rays (the view at ``ViewMeshConfig.envelope_upscale`` times its resolution,
480×360), a first-hit pass against the envelope. sceneforge's time is
its whole ground truth (tracing, layer rules, normals, overhead camera and truth, mesh
clipping) with each engine, on the same cameras, at the same thread count, so the ratio
is everything sceneforge does beyond the unavoidable traversals.

Also the same without the mesh, against the native limit without the D5 rays: what a
render computes by default (its store keeps no meshes; ``sceneforge evaluate`` makes them).

Houses: a bundled toy house, the breakfast room subdivided to >= 1 M triangles (when
../shared/scenes is present), and a synthetic furnished room of >= 1 M triangles with
several hits per ray. Then the throughput of two worker processes, and the peak memory of
one worker over many views.

Run with one OpenBLAS thread and the malloc thresholds of the render pipeline's workers
(:data:`sceneforge.pipeline.executors.MALLOC_THRESHOLDS`; numpy's thread pool costs more
than it saves on a view's small matrix products, and fights the tracing threads for the
cores); set ``OPENBLAS_NUM_THREADS`` to override.

    python benchmarks/bench_ground_truth.py [--views 4] [--repeat 5] [--threads 2] [--houses toy,breakfast,furnished] [--quick]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import shutil
import subprocess
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads, as in the pipeline's workers

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from sceneforge.camera_sampler import CameraSamplerConfig, sample_cameras  # noqa: E402
from sceneforge.conventions import tol  # noqa: E402
from sceneforge.frustum import view_mesh  # noqa: E402
from sceneforge.houses import BUNDLED_TOY, House, Room, discover, load, make_instance  # noqa: E402
from sceneforge.layers import frontal_layers, instance_labels  # noqa: E402
from sceneforge.overhead import overhead_camera, overhead_instances, overhead_truth  # noqa: E402
from sceneforge.pipeline.executors import tune_allocator  # noqa: E402
from sceneforge.raytrace import HouseTracer  # noqa: E402
from sceneforge.raytrace.embree_backend import AVAILABLE as EMBREE_EXTENSION  # noqa: E402
from sceneforge.view import ViewConfig, compute_view  # noqa: E402

HERE = Path(__file__).resolve().parent
BREAKFAST = HERE.parents[1] / "shared" / "scenes" / "breakfast_room" / "BreakfastRoom.gltf"
NATIVE = HERE / "native_all_hits.cpp"


# ---------------------------------------------------------------------------- houses

def subdivided(house: House, min_triangles: int) -> House:
    """The house with every instance subdivided (1 → 4 triangles) until it has enough."""
    while house.triangle_count < min_triangles:
        instances = []
        for inst in house.instances:
            v, f = trimesh.remesh.subdivide(inst.vertices, inst.faces)
            instances.append(replace(inst, vertices=v, faces=f, uv=None))
        house = replace(house, instances=instances, id=house.id + "_x4")
    return house


def furnished_room(min_triangles: int = 1_000_000) -> House:
    """An 8 × 3 × 8 m room (floor, ceiling, four walls) with a 7 × 7 grid of "lamps" around
    eye height, each four nested spheres of 5,120 triangles (a shade and its inner
    layers), so that a ray through one crosses up to eight surfaces: 1 M triangles and
    several object hits per ray."""
    h = House(id="furnished_room", instances=[], rooms=[Room("r0", "living_room", 0)])

    def add(name, category, vertices, faces):
        make_instance(h, name=name, category=category, label=name, room_id="r0", vertices=vertices, faces=faces)

    size, height, t = 8.0, 3.0, 0.1
    half = size / 2
    for name, category, extents, centre in (
        ("floor", 2, (size, t, size), (0, -t / 2, 0)), ("ceiling", 22, (size, t, size), (0, height + t / 2, 0)),
        ("wall0", 1, (t, height, size), (-half - t / 2, height / 2, 0)),
        ("wall1", 1, (t, height, size), (half + t / 2, height / 2, 0)),
        ("wall2", 1, (size, height, t), (0, height / 2, -half - t / 2)),
        ("wall3", 1, (size, height, t), (0, height / 2, half + t / 2)),
    ):
        box = trimesh.creation.box(extents=extents).apply_translation(centre)
        add(name, category, box.vertices, box.faces)
    sphere = trimesh.creation.icosphere(subdivisions=4)
    shells = (1.0, 0.85, 0.7, 0.55)
    per_lamp = len(shells) * len(sphere.faces)
    n = -(-min_triangles // per_lamp)
    side = int(np.ceil(np.sqrt(n)))
    for k in range(n):
        ix, iz = divmod(k, side)
        centre = np.array([-half + (ix + 0.5) * size / side, 1.3 + 0.2 * ((3 * ix + iz) % 3),
                           -half + (iz + 0.5) * size / side])
        radius = 0.34 + 0.03 * ((ix + iz) % 3)
        v = np.concatenate([sphere.vertices * radius * s + centre for s in shells])
        f = np.concatenate([sphere.faces + j * len(sphere.vertices) for j in range(len(shells))])
        add(f"lamp{k}", 40, v, f)
    return h


def cameras_of(house: House, n: int, width: int = 320, height: int = 240):
    sampler = CameraSamplerConfig(width=width, height=height)
    cams, _ = sample_cameras(house, n, np.random.default_rng(0), sampler)
    if len(cams) < n:  # rooms with windows or full of objects: relax the checks rather than skip
        sampler = replace(sampler, max_escape_fraction=0.5, min_object_fraction=0.02)
        cams, _ = sample_cameras(house, n, np.random.default_rng(0), sampler)
    return cams


# ---------------------------------------------------------------------------- native limit

def native_program(workdir: Path) -> Path:
    """Compile native_all_hits.cpp against the system's Embree (4 where present, else 3)."""
    compiler = shutil.which("c++") or shutil.which("g++")
    if compiler is None:
        raise SystemExit("no C++ compiler: apt-get install g++ libembree-dev (scripts/system-deps.sh)")
    major = next((m for m in (4, 3) for root in ("/usr", "/usr/local")
                  if (Path(root) / "include" / f"embree{m}" / "rtcore.h").is_file()), None)
    if major is None:
        raise SystemExit("no Embree headers: apt-get install libembree-dev (scripts/system-deps.sh)")
    exe = workdir / "native_all_hits"
    subprocess.run([compiler, "-std=c++17", "-O2", *(["-DSF_EMBREE4"] if major == 4 else []), str(NATIVE),
                    f"-lembree{major}", "-pthread", "-o", str(exe)], check=True)
    return exe


def view_queries(house: House, cameras, tracer: HouseTracer, config: ViewConfig):
    """Each view's three queries as sceneforge makes them: (rays (n, 6) float64, objects,
    closing (n_instances,) bool, near); the envelope surface's D5 rays have no objects (a
    first-hit query only)."""
    _, envelope = instance_labels(house)
    seen = overhead_instances(house, config.overhead)
    out = []
    for cam in cameras:
        o, d, _ = cam.rays()
        out.append((np.c_[np.broadcast_to(o, d.shape), d], ~envelope, envelope, 0.0))
        top = overhead_camera(house, cam, frontal_layers(house, cam, tracer), config.overhead)
        o, d, _ = top.rays()
        out.append((np.c_[o, np.broadcast_to(d, o.shape)], seen & ~envelope, seen & envelope,
                    config.overhead.floor_clearance))
        if config.with_mesh:
            up = config.mesh.envelope_upscale
            o, d, _ = cam.resized(round(cam.width * up), round(cam.height * up)).rays()
            out.append((np.c_[np.broadcast_to(o, d.shape), d], np.zeros_like(envelope), envelope, 0.0))
    return out


def native_seconds(exe: Path, house: House, queries, rounds: int, threads: int) -> tuple[float, float, int, int]:
    """(best wall seconds for all queries, CPU seconds of that round, hits, rays) of the
    native program on these queries, in the same float32 coordinates (shifted to the house
    centre) as sceneforge's engines."""
    vertices = np.concatenate([i.vertices for i in house.instances])
    shift = 0.5 * (vertices.min(0) + vertices.max(0))
    fv = np.cumsum([0] + [len(i.vertices) for i in house.instances]).astype(np.int64)
    ff = np.cumsum([0] + [len(i.faces) for i in house.instances]).astype(np.int64)
    faces = np.concatenate([i.faces + fv[k] for k, i in enumerate(house.instances)]).astype(np.uint32)
    with tempfile.NamedTemporaryFile(suffix=".bin") as f:
        np.array([len(vertices), len(faces), len(house.instances), len(queries), rounds, threads],
                 np.int64).tofile(f)
        (vertices - shift).astype(np.float32).tofile(f)
        faces.tofile(f)
        fv.tofile(f)
        ff.tofile(f)
        for rays, objects, closing, near in queries:
            np.array([len(rays)], np.int64).tofile(f)
            objects.astype(np.uint8).tofile(f)
            closing.astype(np.uint8).tofile(f)
            np.array([near, tol.envelope_slack], np.float32).tofile(f)
            r = rays.copy()
            r[:, :3] -= shift
            r.astype(np.float32).tofile(f)
        f.flush()
        out = subprocess.run([str(exe), f.name], check=True, capture_output=True, text=True).stdout.split()
    return float(out[0]), float(out[1]), int(out[2]), int(out[3])


# ---------------------------------------------------------------------------- sceneforge

def time_views(house, cameras, tracer, config: ViewConfig, repeat: int) -> dict[str, float]:
    """Mean seconds per view of each stage (tracer build excluded, it is once per house), from
    the fastest of ``repeat`` rounds over the views (this VM's speed drifts by ±20 % from
    minute to minute; the fastest round is the least disturbed), and the process CPU
    seconds per view of that round ("CPU": all threads; robust to other processes on the
    machine). Each round uses fresh camera objects, so no round reuses the rays an earlier
    one computed."""
    compute_view(house, cameras[0], config, tracer)  # warm-up: first-call costs, subset scenes
    best = None
    for _ in range(repeat):
        stages = {"frontal": 0.0, "overhead camera": 0.0, "overhead truth": 0.0, "mesh": 0.0}
        cpu = time.process_time()
        for cam in cameras:
            cam = cam.resized(cam.width, cam.height)  # a new Camera: its rays are not cached yet
            t0 = time.perf_counter()
            layers = frontal_layers(house, cam, tracer)
            t1 = time.perf_counter()
            top = overhead_camera(house, cam, layers, config.overhead)
            t2 = time.perf_counter()
            overhead_truth(house, top, tracer, config.overhead)
            t3 = time.perf_counter()
            view_mesh(house, cam, layers, config.mesh, tracer)
            t4 = time.perf_counter()
            for k, dt in zip(stages, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
                stages[k] += dt / len(cameras)
        stages["total"] = sum(stages.values())
        stages["CPU"] = (time.process_time() - cpu) / len(cameras)
        if best is None or stages["total"] < best["total"]:
            best = stages
    return best


def _warm() -> None:
    HouseTracer  # noqa: B018  (the worker has imported sceneforge: nothing else to do)


def _views_of(house, cameras, config, threads):
    tr = HouseTracer(house, threads=threads)
    for cam in cameras:
        compute_view(house, cam, config, tr)


def throughput(house, cameras, n_jobs: int = 2, config: ViewConfig | None = None) -> float:
    """Seconds per view when ``n_jobs`` processes share the views (each builds its tracer
    and, as the render pipeline's workers do, traces with its share of the cores)."""
    config = config or ViewConfig()
    threads = max(1, (os.cpu_count() or 1) // n_jobs)
    with ProcessPoolExecutor(n_jobs) as pool:
        list(pool.map(_warm_job, range(n_jobs)))  # start the workers before timing
        t0 = time.perf_counter()
        list(pool.map(_views_of, [house] * n_jobs, [cameras[k::n_jobs] for k in range(n_jobs)],
                      [config] * n_jobs, [threads] * n_jobs))
        return (time.perf_counter() - t0) / len(cameras)


def _warm_job(_):
    _warm()


def _rss_mib() -> tuple[float, float]:
    """(resident, peak resident) MiB of this process's memory image (VmRSS, VmHWM; not
    ru_maxrss, which on Linux keeps the peak of the process before its exec)."""
    with open("/proc/self/status") as f:
        kib = {k: int(v.split()[0]) for k, v in (line.split(":", 1) for line in f) if k in ("VmRSS", "VmHWM")}
    return kib["VmRSS"] / 1024, kib["VmHWM"] / 1024


def _memory_job(house, cameras, n_views: int, threads: int, checkpoints):
    tune_allocator()  # a worker's settings (this process is spawned)
    config = ViewConfig()
    tr = HouseTracer(house, threads=threads)
    out = []
    for k in range(1, n_views + 1):
        cam = cameras[k % len(cameras)]
        compute_view(house, cam.resized(cam.width, cam.height), config, tr)
        if k in checkpoints:
            out.append((k, *_rss_mib()))
    return out


def memory_over_views(house, cameras, n_views: int, threads: int):
    """[(views done, resident MiB, peak resident MiB)] of one fresh worker process computing
    ``n_views`` full views (RGB excluded), at ten checkpoints."""
    checkpoints = {1, *np.linspace(n_views / 10, n_views, 10).astype(int).tolist()}
    # spawned, not forked: a fork would inherit this process's memory (Open3D, other houses)
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(_memory_job, house, cameras, n_views, threads, checkpoints).result()


# ---------------------------------------------------------------------------- main

def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", type=int, default=4, help="cameras per house")
    ap.add_argument("--repeat", type=int, default=5, help="rounds over the views; the fastest is reported")
    ap.add_argument("--threads", type=int, default=2, help="tracing threads (sceneforge and native)")
    ap.add_argument("--memory-views", type=int, default=500, help="views of the memory run (0: skip it)")
    ap.add_argument("--houses", default="toy,breakfast,furnished",
                    help="comma-separated: toy (a bundled toy house), breakfast (the breakfast room subdivided to "
                         ">= 1 M triangles, where ../shared/scenes is), furnished (the synthetic 1 M-triangle room)")
    ap.add_argument("--quick", action="store_true", help="toy house only, 50 views of memory run")
    args = ap.parse_args()
    chosen = {"toy"} if args.quick else set(args.houses.split(","))
    if not chosen <= {"toy", "breakfast", "furnished"}:
        ap.error(f"--houses: unknown {', '.join(sorted(chosen - {'toy', 'breakfast', 'furnished'}))}")
    tune_allocator()  # as in the pipeline's worker processes (forked pools below inherit it)

    toy = load(discover(BUNDLED_TOY)[0])
    houses = [toy] if "toy" in chosen else []
    if "breakfast" in chosen and BREAKFAST.exists():
        houses.append(subdivided(load(BREAKFAST), 1_000_000))
    if "furnished" in chosen:
        houses.append(furnished_room())
    engines = ["embree", "open3d"] if EMBREE_EXTENSION else ["open3d"]
    config = ViewConfig()
    print(f"{args.threads} tracing threads, {os.cpu_count()} cores; best of {args.repeat} rounds; "
          f"{'Embree extension built' if EMBREE_EXTENSION else 'no Embree extension: Open3D only'}")
    with tempfile.TemporaryDirectory() as tmp:
        exe = native_program(Path(tmp))
        for house in houses:
            cameras = cameras_of(house, args.views)
            tracers = {e: HouseTracer(house, e, threads=args.threads) for e in engines}
            queries = view_queries(house, cameras, tracers[engines[0]], config)
            # rounds alternate between the native program and each engine, so that the
            # machine's drift (other jobs) hits them alike; each figure is its best round,
            # and the ratios are also taken round by round (their median)
            natives, lean_natives, times = [], [], {e: [] for e in engines}
            # a store keeps no meshes by default (store.gt_mesh none), so a render's ground
            # truth is the frontal and overhead queries alone: their own native limit
            lean_queries = [q for q in queries if q[1].any()]
            for _ in range(args.repeat):
                natives.append(native_seconds(exe, house, queries, 1, args.threads))
                lean_natives.append(native_seconds(exe, house, lean_queries, 1, args.threads))
                for e in engines:
                    times[e].append(time_views(house, cameras, tracers[e], config, 1))
            hits, rays = natives[0][2:]
            native = min(n[0] for n in natives) / len(cameras)
            native_cpu = min(n[1] for n in natives) / len(cameras)
            best = {e: min(rounds, key=lambda r: r["total"]) for e, rounds in times.items()}
            paired = {e: np.median([r["total"] / (n[0] / len(cameras)) for r, n in zip(times[e], natives)])
                      for e in engines}
            print(f"\n{house.id}: {house.triangle_count:,} triangles, {len(cameras)} views of 320x240 "
                  f"+ 300x300 overhead, {hits / rays:.1f} object hits per ray")
            print(f"  {'stage':<16}" + "".join(f"{f'{e} s/view':>16}" for e in engines) + f"{'native s/view':>16}")
            for stage in best[engines[0]]:
                native_column = {"total": f"{native:>16.4f}"}.get(stage, "")
                if stage == "CPU":
                    row = "".join(f"{min(r['CPU'] for r in times[e]):>16.4f}" for e in engines)
                    print(f"  {'CPU (best)':<16}{row}{native_cpu:>16.4f}")
                    continue
                print(f"  {stage:<16}" + "".join(f"{best[e][stage]:>16.4f}" for e in engines) + native_column)
            print("  ratio to native " + "".join(f"{best[e]['total'] / native:>15.2f}x" for e in engines)
                  + "   (round by round, median: " + ", ".join(f"{paired[e]:.2f}x" for e in engines)
                  + "; CPU: " + ", ".join(f"{min(r['CPU'] for r in times[e]) / native_cpu:.2f}x" for e in engines)
                  + ")")
            lean_native = min(n[0] for n in lean_natives) / len(cameras)
            lean = {e: min(r["total"] - r["mesh"] for r in rounds) for e, rounds in times.items()}
            print(f"  {'without mesh':<16}" + "".join(f"{lean[e]:>16.4f}" for e in engines) + f"{lean_native:>16.4f}"
                  + "   (a render's default: no ground-truth mesh, no D5 rays)")
            print("  ratio to native " + "".join(f"{lean[e] / lean_native:>15.2f}x" for e in engines))
        if "toy" in chosen:
            pair = throughput(toy, cameras_of(toy, 12))
            print(f"\n2 worker processes on {toy.id}: {pair:.4f} s/view (throughput)")
        if args.memory_views and houses:
            n = 50 if args.quick else args.memory_views
            for house in houses[:1] + houses[1:][-1:]:  # the first house and the last large one
                views = n if house is toy else max(1, n // 10)
                marks = memory_over_views(house, cameras_of(house, 8), views, args.threads)
                print(f"one worker, {house.id}, {views} views: resident / peak MiB after "
                      + ", ".join(f"{k}: {r:.0f}/{p:.0f}" for k, r, p in marks))


if __name__ == "__main__":
    main()
