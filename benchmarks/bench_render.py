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

    python benchmarks/bench_render.py [--views 3] [--frames 500] [--pt-frames 20] [--samples 64]
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import time
from pathlib import Path

import numpy as np

from sceneforge.camera_sampler import CameraSamplerConfig, sample_cameras
from sceneforge.cameras import look_at_camera
from sceneforge.houses import BUNDLED_TOY, House, Material, Room, discover, load, make_instance
from sceneforge.raytrace import HouseTracer
from sceneforge.render import RenderConfig, open_renderer

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
    args = parser.parse_args()
    modes = args.modes.split(",")

    scenes = scenes_and_cameras(args.views)
    with open_renderer("raster", 8, 8) as probe:
        info = probe.gl_info()
        print(f"raster: EGL device {probe.device.index} ({probe.device.kind}), {info['renderer']}")
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
