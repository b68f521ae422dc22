"""Milliseconds per rendered frame and resident memory over a long run (SPEC §8).

In one run on the same houses and cameras:

- ms per RGB frame at 320×240 and 640×480, single-sampled (sceneforge's default) and with
  pyrender's 4× multisampling (the baseline), and their ratio. Frames are rendered house by
  house, as the pipeline does; the scene build (lighting, upload) per house is timed apart.
- resident memory of the process after 10 and after ``--frames`` frames of one renderer
  cycling through the houses (a new house every 2 frames, so the scene is rebuilt and the
  previous one freed every other frame): over the toy houses, then over all houses with
  the big textured one, where the heap layout alone moves RSS by tens of MiB between two
  samples, so the trend over all samples is the leak figure.

Houses: the bundled toy houses plus generated ones (and the textured breakfast room when
../shared/scenes is present).

    python benchmarks/bench_render.py [--houses 6] [--views 4] [--frames 500] [--gpu N]
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import time
from pathlib import Path

import numpy as np

from sceneforge.cameras import CameraSamplerConfig, sample_cameras
from sceneforge.houses import BUNDLED_TOY, discover, load
from sceneforge.houses.toy import generate_house, house_seed
from sceneforge.raytrace import HouseTracer
from sceneforge.render import Renderer

BREAKFAST = Path(__file__).resolve().parents[2] / "shared" / "scenes" / "breakfast_room" / "BreakfastRoom.gltf"


def rss_mb(trim: bool = False) -> float:
    """Resident set size of this process, MiB (Linux /proc). With ``trim``, first hand the
    heap pages that glibc keeps after frees back to the system (``malloc_trim``): without it
    RSS swings by tens of MiB with the size of the last scene built, leak or no leak."""
    if trim:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def houses_and_cameras(n_houses: int, views: int):
    """[(house, [camera, ...])] with ``views`` sampled 320×240 cameras per house."""
    houses = [load(s) for s in discover(BUNDLED_TOY)]
    houses += [generate_house(house_seed(1, i), f"toy_1_{i:03d}") for i in range(max(0, n_houses - len(houses)))]
    if BREAKFAST.exists():
        houses.append(load(BREAKFAST))
    loose = CameraSamplerConfig(max_escape_fraction=0.5)
    out = []
    for house in houses:
        cameras, _ = sample_cameras(house, views, np.random.default_rng(0), loose, HouseTracer(house))
        if cameras:
            out.append((house, cameras))
    return out


def time_frames(views, width: int, height: int, antialias: bool, gpu, repeats: int) -> list[tuple[float, float]]:
    """Per house: (ms per frame with its scene cached, best of ``repeats`` passes over its views;
    ms to build its scene), for one renderer setting."""
    out = []
    with Renderer(width, height, gpu=gpu, antialias=antialias) as r:
        house, cameras = views[0]
        r.render(house, cameras[0].resized(width, height))  # shader compilation
        for house, cameras in views:
            cams = [c.resized(width, height) for c in cameras]
            start = time.perf_counter()
            r.render(house, cams[0])
            build = time.perf_counter() - start
            best = float("inf")  # the least disturbed pass: the machine is shared
            for _ in range(repeats):
                start = time.perf_counter()
                for c in cams:
                    r.render(house, c)
                best = min(best, time.perf_counter() - start)
            out.append((1e3 * best / len(cams), 1e3 * build))
    return out


def memory_run(views, frames: int, gpu) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame counts (k,) and RSS MiB (k,), untrimmed and trimmed, of one 320×240 renderer that
    gets a new house every 2 frames, after one warm-up frame per house (every scene built once).
    Sampled after frame 10, after the last frame and every 7 frames in between."""
    ks, raw, trimmed = [], [], []
    with Renderer(320, 240, gpu=gpu) as r:
        for house, cameras in views:
            r.render(house, cameras[0])
        for k in range(1, frames + 1):
            house, cameras = views[(k - 1) // 2 % len(views)]
            r.render(house, cameras[(k - 1) % len(cameras)])
            if k == 10 or k == frames or (k > 10 and k % 7 == 3):
                gc.collect()
                ks.append(k)
                raw.append(rss_mb())
                trimmed.append(rss_mb(trim=True))
    return np.array(ks), np.array(raw), np.array(trimmed)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--houses", type=int, default=6, help="toy houses (bundled first, then generated)")
    parser.add_argument("--views", type=int, default=4, help="cameras per house")
    parser.add_argument("--repeats", type=int, default=3, help="times each view is rendered in the timing runs")
    parser.add_argument("--frames", type=int, default=500, help="frames of the memory run")
    parser.add_argument("--gpu", type=int, default=None, help="EGL device index (default: automatic)")
    args = parser.parse_args()

    views = houses_and_cameras(args.houses, args.views)
    with Renderer(8, 8, gpu=args.gpu) as probe:
        info = probe.gl_info()
        print(f"device: EGL {probe.device.index} ({probe.device.kind}), {info['renderer']}, {info['version']}")
    tris = [h.triangle_count for h, _ in views]
    print(f"houses: {len(views)} ({min(tris):,}–{max(tris):,} triangles), {sum(len(c) for _, c in views)} views, "
          f"each rendered {args.repeats}×\n")

    groups: dict[str, list[int]] = {}
    for i, (house, _) in enumerate(views):
        groups.setdefault("toy" if house.id.startswith("toy") else house.id, []).append(i)
    print(f"{'size':>9}  {'houses':<14}  {'1 sample ms':>11}  {'4× MSAA ms':>10}  {'MSAA / 1':>8}  {'scene build ms':>14}")
    for width, height in ((320, 240), (640, 480)):
        single = time_frames(views, width, height, False, args.gpu, args.repeats)
        msaa = time_frames(views, width, height, True, args.gpu, args.repeats)
        for name, index in groups.items():
            if index:
                one, four = (float(np.mean([t[i][0] for i in index])) for t in (single, msaa))
                build = float(np.mean([single[i][1] for i in index]))
                print(f"{width:>4}×{height:<4}  {name:<14}  {one:>11.2f}  {four:>10.2f}  {four / one:>7.2f}×  {build:>14.1f}")

    print("\nresident memory of one 320×240 renderer, a new house every 2 frames after a warm-up frame per house;"
          "\ntrimmed = after glibc's malloc_trim")
    runs = {"toy houses": [v for v in views if v[0].id.startswith("toy")], "all houses": views}
    for name, run in runs.items():
        if name == "all houses" and len(run) == len(runs["toy houses"]):
            continue
        ks, raw, trimmed = memory_run(run, args.frames, args.gpu)
        # a single sample depends on the heap layout of its moment (tens of MiB with a big
        # house); a leak shows as a trend over all samples
        slope = np.polyfit(ks, trimmed, 1)[0] * 100
        print(f"  {name}: after {ks[0]} frames {raw[0]:.1f} MiB (trimmed {trimmed[0]:.1f}), after {ks[-1]} frames "
              f"{raw[-1]:.1f} MiB (trimmed {trimmed[-1]:.1f}): growth {raw[-1] - raw[0]:+.1f} MiB "
              f"(trimmed {trimmed[-1] - trimmed[0]:+.1f});\n    trimmed over {len(ks)} samples "
              f"{trimmed.min():.1f}–{trimmed.max():.1f} MiB, trend {slope:+.2f} MiB per 100 frames")


if __name__ == "__main__":
    main()
