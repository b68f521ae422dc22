"""Milliseconds per 320×240 RGB frame in each mode, and resident memory over a long run (docs/spec.md §8).

In one run on the same scenes and cameras:

- ms per frame of each RGB mode (``raster``: pyrender/EGL, per-pixel lights; ``pathtraced``:
  Mitsuba 3 at ``--samples`` samples per pixel) on a toy house, the textured breakfast room
  (when ../shared/scenes is present) and a room of ≥ 1 M triangles (a box room around a
  finely tessellated sphere), with the ratio to the raster mode (the baseline). Frames are
  rendered scene by scene, as the pipeline does; the scene build (upload, lights; for
  Mitsuba also its kernel compilation) is timed apart.
- resident memory of one worker's renderer after 10 frames and after ``--frames`` frames
  (raster) or ``--pt-frames`` frames (path tracing, which takes seconds per frame),
  cycling through the scenes with a new one every 2 frames (so the scene is rebuilt and the
  previous one freed every other frame). RSS is sampled after glibc's ``malloc_trim``; a
  single sample depends on the heap layout of its moment, so the trend over all samples is
  the leak figure.
- the raster mode's split: ms per frame at 8×6 pixels (our Python, pyrender's and the
  driver's per-draw work, the tone mapping of a few pixels: almost no rasterisation) next to
  320×240, whose difference is the rasteriser's (on Mesa's llvmpipe: CPU threads).
- ``--figure PNG``: one view of the breakfast room in each mode side by side (docs/rgb.md's),
  with the fraction of its pixels clipped to white.
- ``--per-pixel`` (and nothing else): the raster mode's per-pixel cost before and after
  issue 39's item 2, in one run: ms per frame at 8×6, 320×240, 640×480 and 1280×960 of the
  toy house and the breakfast room, and the difference 1280×960 − 8×6, for three renderers
  measured in turns, one at a time (the machine is shared; the best pass counts): ``before`` (pyrender's
  light loops, which Mesa unrolls, the float radiance read back and tone-mapped with numpy),
  ``loops`` (the light loops fixed, numpy tone mapping: ``gpu_tonemap=False``), ``GL tone``
  (tone mapping in GL passes, bytes read back, every fragment that passes the depth test
  shaded), ``pre-pass`` (also a depth pre-pass, each pixel shaded once) and ``after`` (the
  default: the pre-pass where the scene has at most a quarter as many triangles as the frame
  has pixels).

    python benchmarks/bench_render.py [--views 3] [--frames 500] [--pt-frames 20] [--samples 64]
    python benchmarks/bench_render.py --per-pixel [--views 3] [--repeats 5]
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import gc
import time
from pathlib import Path

import numpy as np

from sceneforge.camera_sampler import CameraSamplerConfig, sample_cameras
from sceneforge.cameras import look_at_camera
from sceneforge.houses import BUNDLED_TOY, House, Material, Room, discover, load, make_instance
from sceneforge.raytrace import HouseTracer
from sceneforge.render import RenderConfig, Renderer, open_renderer, raster

BREAKFAST = Path(__file__).resolve().parents[2] / "shared" / "scenes" / "breakfast_room" / "BreakfastRoom.gltf"
WIDTH, HEIGHT = 320, 240


def rss_mb() -> float:
    """Resident set size of this process after glibc's ``malloc_trim``, MiB (Linux /proc)."""
    ctypes.CDLL("libc.so.6").malloc_trim(0)
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def million_triangle_room() -> House:
    """A 6 × 3 × 6 m room (floor, ceiling, four walls: 0.1 m boxes) around a sphere of 1.3 M
    triangles (an icosphere, 8 subdivisions)."""
    import trimesh

    house = House(id="million", instances=[], rooms=[Room("r0", "room", 0)])
    parts = [("floor", 2, (6, 0.1, 6), (0, -0.05, 0)), ("ceiling", 22, (6, 0.1, 6), (0, 3.05, 0))]
    parts += [(f"wall{i}", 1, e, c) for i, (e, c) in enumerate([((0.1, 3, 6), (-3.05, 1.5, 0)), ((0.1, 3, 6), (3.05, 1.5, 0)),
                                                              ((6, 3, 0.1), (0, 1.5, -3.05)), ((6, 3, 0.1), (0, 1.5, 3.05))])]
    for name, category, extents, centre in parts:
        box = trimesh.creation.box(extents=extents)
        make_instance(house, name=name, category=category, label=name, room_id="r0",
                      vertices=np.asarray(box.vertices) + centre, faces=np.asarray(box.faces))
    sphere = trimesh.creation.icosphere(subdivisions=8, radius=0.8)
    make_instance(house, name="sphere", category=0, label="sculpture", room_id="r0",
                  vertices=np.asarray(sphere.vertices) + [0.0, 1.0, 0.0], faces=np.asarray(sphere.faces),
                  material=Material((0.7, 0.5, 0.3, 1.0)))
    return house


def scenes_and_cameras(views: int):
    """[(name, house, [camera, ...])]: a toy house, the breakfast room, the 1 M-triangle room."""
    scenes = [("toy house", load(discover(BUNDLED_TOY)[0]))]
    if BREAKFAST.exists():
        scenes.append(("breakfast room", load(BREAKFAST)))
    scenes.append(("1.3 M-triangle room", million_triangle_room()))
    loose = CameraSamplerConfig(max_escape_fraction=0.5)
    out = []
    for name, house in scenes:
        if house.id == "million":  # one object in an empty room: the sampler finds it uninformative
            cameras = [look_at_camera([2.4 - 0.3 * k, 1.6, -2.4], [-0.8 + 0.3 * k, -0.25, 1.0], width=WIDTH,
                                      height=HEIGHT) for k in range(views)]
        else:
            cameras, _ = sample_cameras(house, views, np.random.default_rng(0), loose, HouseTracer(house))
        out.append((name, house, cameras))
    return out


def raster_split(scenes, repeats: int) -> list[float]:
    """Per scene: raster ms per frame at 8×6 pixels, best of ``repeats`` passes over its views."""
    out = []
    with open_renderer("raster", 8, 6) as r:
        for _, house, cameras in scenes:
            small = [c.resized(8, 6) for c in cameras]
            r.render(house, small[0])
            best = float("inf")
            for _ in range(repeats):
                start = time.perf_counter()
                for c in small:
                    r.render(house, c)
                best = min(best, time.perf_counter() - start)
            out.append(1e3 * best / len(small))
    return out


@contextlib.contextmanager
def unrolled_light_loops():
    """Renderers made inside draw with the mesh shader as it was before issue 39 (item 2):
    pyrender's light loops as they are, which Mesa unrolls (``raster._LOOP_PATCHES`` left out)."""
    saved = raster._LOOP_PATCHES
    raster._LOOP_PATCHES = ()
    raster._mesh_shader.cache_clear()
    try:
        yield
    finally:
        raster._LOOP_PATCHES = saved
        raster._mesh_shader.cache_clear()


#: the renderers of ``--per-pixel``: name → (unrolled light loops, gpu_tonemap, depth pre-pass)
PER_PIXEL_PATHS = {"before": (True, False, False), "loops": (False, False, False), "GL tone": (False, True, False),
                   "pre-pass": (False, True, True), "after": (False, True, "auto")}
PER_PIXEL_SIZES = ((8, 6), (320, 240), (640, 480), (1280, 960))


def per_pixel(scenes, repeats: int, rounds: int = 3) -> dict[str, dict[str, dict[tuple[int, int], dict[str, float]]]]:
    """clock (``wall``, ``cpu``: this process's CPU time, llvmpipe's threads included) →
    scene → size → path → raster ms per frame (``render``: RGB bytes), the best of
    ``repeats`` passes over the scene's views in each of ``rounds`` rounds; each round makes
    a renderer of each path in turn (in alternating order), one at a time as a worker has
    it (with several EGL contexts alive, llvmpipe's frames of one slow down by up to 10 ms
    depending on the order the others were made in). On a shared machine the CPU time is
    the steadier measure of the work; the wall clock is what a worker waits."""
    out = {"wall": {}, "cpu": {}}
    paths = list(PER_PIXEL_PATHS)
    for name, house, cameras in scenes:
        for clock in out.values():
            clock[name] = {}
        for W, H in PER_PIXEL_SIZES:
            views = [c.resized(W, H) for c in cameras]
            best = {clock: dict.fromkeys(paths, float("inf")) for clock in out}
            for k in range(rounds):
                for path in paths if k % 2 == 0 else paths[::-1]:
                    unrolled, gpu_tonemap, prepass = PER_PIXEL_PATHS[path]
                    with unrolled_light_loops() if unrolled else contextlib.nullcontext():
                        r = Renderer(W, H, gpu_tonemap=gpu_tonemap)
                    r._gl.depth_prepass = prepass
                    with r:
                        r.render(house, views[0])  # the scene build
                        for _ in range(repeats):
                            wall, cpu = time.perf_counter(), time.process_time()
                            for c in views:
                                r.render(house, c)
                            best["wall"][path] = min(best["wall"][path], time.perf_counter() - wall)
                            best["cpu"][path] = min(best["cpu"][path], time.process_time() - cpu)
            for clock, times in best.items():
                out[clock][name][W, H] = {path: 1e3 * t / len(views) for path, t in times.items()}
    return out


def print_per_pixel(times, clock: str) -> None:
    paths = list(PER_PIXEL_PATHS)
    (w0, h0), (w1, h1) = PER_PIXEL_SIZES[0], PER_PIXEL_SIZES[-1]
    for name, by_size in times.items():
        print(f"\n{name + ', ' + clock:<24}" + "".join(f"{p:>10}" for p in paths) + f"{'before / after':>16}")
        for (W, H), t in by_size.items():
            print(f"  {f'{W}×{H}':<22}" + "".join(f"{t[p]:>10.1f}" for p in paths))
        cost = {p: by_size[w1, h1][p] - by_size[w0, h0][p] for p in paths}
        print(f"  {f'{w1}×{h1} − {w0}×{h0}':<22}" + "".join(f"{cost[p]:>10.1f}" for p in paths)
              + f"{cost['before'] / cost['after']:>15.2f}×")


def time_mode(mode: str, scenes, repeats: int, samples: int) -> list[tuple[float, float]]:
    """Per scene: (ms per frame with its scene built, best of ``repeats`` passes over its views;
    ms of the first frame, scene build included). Mode ``raster+shadows``: raster with the
    window lights' shadow maps."""
    out = []
    config = RenderConfig(shadows=mode.endswith("+shadows"))
    with open_renderer(mode.removesuffix("+shadows"), WIDTH, HEIGHT, samples=samples, config=config) as r:
        for _, house, cameras in scenes:
            start = time.perf_counter()
            r.render(house, cameras[0])
            build = time.perf_counter() - start
            best = float("inf")  # the least disturbed pass: the machine is shared
            for _ in range(repeats):
                start = time.perf_counter()
                for c in cameras:
                    r.render(house, c)
                best = min(best, time.perf_counter() - start)
            out.append((1e3 * best / len(cameras), 1e3 * build))
    return out


def memory_run(mode: str, scenes, frames: int, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Frame counts (k,) and trimmed RSS MiB (k,) of one renderer that gets a new scene every 2
    frames, after one warm-up frame per scene; sampled after frame 10, after the last frame
    and every 7 frames in between."""
    ks, rss = [], []
    with open_renderer(mode, WIDTH, HEIGHT, samples=samples) as r:
        for _, house, cameras in scenes:
            r.render(house, cameras[0])
        for k in range(1, frames + 1):
            _, house, cameras = scenes[(k - 1) // 2 % len(scenes)]
            r.render(house, cameras[(k - 1) % len(cameras)])
            if k == 10 or k == frames or (k > 10 and k % 7 == 3):
                gc.collect()
                ks.append(k)
                rss.append(rss_mb())
    return np.array(ks), np.array(rss)


def figure(path: Path, samples: int) -> None:
    """The breakfast room from one camera: raster | path-traced, labelled, as a PNG."""
    from PIL import Image, ImageDraw

    house = load(BREAKFAST)
    (camera,), _ = sample_cameras(house, 1, np.random.default_rng(0), CameraSamplerConfig(max_escape_fraction=0.5),
                                  HouseTracer(house))
    panels = []
    for mode in ("raster", "pathtraced"):
        with open_renderer(mode, WIDTH, HEIGHT, samples=samples) as r:
            start = time.perf_counter()
            rgb = r.render(house, camera)
            seconds = time.perf_counter() - start
        print(f"figure: {mode}: {100 * (rgb.max(-1) == 255).mean():.2f} % of pixels clipped to white")
        panel = Image.fromarray(rgb)
        label = f"--rgb {mode}" + (f" ({samples} spp)" if mode == "pathtraced" else "")
        draw = ImageDraw.Draw(panel)
        draw.rectangle([0, 0, 7 * len(label) + 6, 14], fill=(0, 0, 0))
        draw.text((3, 2), label, fill=(255, 255, 255))
        panels.append(panel)
        print(f"figure: {mode} {seconds:.1f} s (scene build included)")
    out = Image.new("RGB", (WIDTH * len(panels) + 4 * (len(panels) - 1), HEIGHT), (255, 255, 255))
    for k, panel in enumerate(panels):
        out.paste(panel, (k * (WIDTH + 4), 0))
    path.parent.mkdir(parents=True, exist_ok=True)
    out.save(path, optimize=True)
    print(f"figure: {path}")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=3, help="cameras per scene")
    parser.add_argument("--repeats", type=int, default=2, help="passes over a scene's views (raster); the best counts")
    parser.add_argument("--samples", type=int, default=64, help="path tracing: samples per pixel")
    parser.add_argument("--frames", type=int, default=500, help="frames of the raster memory run")
    parser.add_argument("--pt-frames", type=int, default=20, help="frames of the path-tracing memory run")
    parser.add_argument("--modes", default="raster,raster+shadows,pathtraced",
                        help="modes to measure, comma-separated (raster+shadows: timing only)")
    parser.add_argument("--figure", type=Path, default=None, help="also write the side-by-side figure here")
    parser.add_argument("--per-pixel", action="store_true",
                        help="only the raster per-pixel cost before/after issue 39 item 2 (8×6 to 1280×960)")
    args = parser.parse_args()
    modes = args.modes.split(",")

    scenes = scenes_and_cameras(args.views)
    with open_renderer("raster", 8, 8) as probe:
        info = probe.gl_info()
        print(f"raster: EGL device {probe.device.index} ({probe.device.kind}), {info['renderer']}")
    if args.per_pixel:
        scenes = [s for s in scenes if s[1].id != "million"]
        print("scenes: " + ", ".join(f"{n} ({h.triangle_count:,} triangles, {len(c)} views)" for n, h, c in scenes))
        print(f"best of {args.repeats} passes over each scene's views in each of 3 rounds; "
              "a renderer of each path in turn, one at a time")
        print("raster, ms per frame (RGB bytes); before: pyrender's light loops (unrolled by Mesa), float readback, "
              "numpy tone mapping; loops: light loops fixed, numpy tone mapping; GL tone: tone mapping in GL, bytes "
              "read back; pre-pass: GL tone and a depth pre-pass (each pixel shaded once); after: the default, "
              "the pre-pass where triangles <= pixels / 4")
        times = per_pixel(scenes, args.repeats)
        print_per_pixel(times["wall"], "wall clock")
        print_per_pixel(times["cpu"], "CPU time")
        return
    if "pathtraced" in modes:
        with open_renderer("pathtraced", 8, 8) as probe:
            print(f"pathtraced: Mitsuba variant {probe.variant}, {args.samples} samples per pixel")
    print("scenes: " + ", ".join(f"{n} ({h.triangle_count:,} triangles, {len(c)} views)" for n, h, c in scenes))

    times = {mode: time_mode(mode, scenes, args.repeats if mode == "raster" else 1, args.samples) for mode in modes}
    print(f"\n{WIDTH}×{HEIGHT}, ms per frame (first frame of a scene, build included, in brackets)")
    others = [m for m in modes if m != "raster"] if "raster" in modes else []
    print(f"{'scene':<22}" + "".join(f"{m:>26}" for m in modes) + "".join(f"{m + ' / raster':>26}" for m in others))
    for k, (name, _, _) in enumerate(scenes):
        cells = "".join(f"{times[m][k][0]:>14.1f} ({times[m][k][1]:>8.0f})" for m in modes)
        ratios = "".join(f"{times[m][k][0] / times['raster'][k][0]:>25.1f}×" for m in others)
        print(f"{name:<22}{cells}{ratios}")

    if "raster" in modes:
        split = raster_split(scenes, 3 * args.repeats)
        print("\nraster, ms per frame: at 8×6 (Python, draw calls, tone mapping: no rasterising to speak of) "
              "and the rest of a 320×240 frame (the rasteriser)")
        for k, (name, _, _) in enumerate(scenes):
            print(f"  {name:<22}{split[k]:>8.1f} + {times['raster'][k][0] - split[k]:>8.1f}")

    print("\nresident memory of one renderer (a worker's), a new scene every 2 frames, after malloc_trim")
    for mode in (m for m in modes if not m.endswith("+shadows")):
        frames = args.frames if mode == "raster" else args.pt_frames
        ks, rss = memory_run(mode, scenes, frames, args.samples)
        slope = np.polyfit(ks, rss, 1)[0] * 100 if len(ks) > 1 else 0.0
        print(f"  {mode}: after {ks[0]} frames {rss[0]:.0f} MiB, after {ks[-1]} frames {rss[-1]:.0f} MiB "
              f"({rss[-1] - rss[0]:+.0f}); over {len(ks)} samples {rss.min():.0f}–{rss.max():.0f} MiB, "
              f"trend {slope:+.2f} MiB per 100 frames")

    if args.figure is not None and BREAKFAST.exists():
        figure(args.figure, args.samples)


if __name__ == "__main__":
    main()
