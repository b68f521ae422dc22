"""What sampled views see, before and after the sampler of issue 12, in one run.

Per house and sampler: the views it accepted out of those requested, and per view (traced
at ``--size``, the same rule for every sampler: :class:`sceneforge.camera_sampler.ViewStats`) the
distinct labelled objects seen, the D3 coverage (pixels with an occluded second object)
and the median distance to the envelope (planar D5 depth), averaged over the views, with
the worst view's envelope distance; and the seconds and candidates the sampling took.

Samplers:

- ``before``: the sampler as it was at ``--baseline`` (a git revision), its
  ``sceneforge/cameras.py`` loaded from git into this process: the floor below a candidate
  had to be a ``floor`` instance, candidates came from every floor of the house by area,
  the first valid ones were kept.
- ``first valid``: today's rules (floors or rugs, rooms and levels, void/envelope checks)
  with ``pool_per_camera = 1``: the first valid candidates of each room, no choice.
- ``after``: today's defaults: the best-scoring of ``pool_per_camera`` valid candidates.

Houses: the bundled toy houses, the breakfast room (../shared/scenes, when present) and two
hard cases of real data built by ``tests/hard_houses.py``: a room whose rug covers 90 % of
its floor, and a two-level house.

    python benchmarks/bench_cameras.py [--views 8] [--seeds 2] [--size 160x120] [--baseline REV]
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from sceneforge.camera_sampler import CameraSamplerConfig, ViewStats, sample_cameras
from sceneforge.houses import BUNDLED_TOY, discover, load
from sceneforge.layers import frontal_layers
from sceneforge.raytrace import HouseTracer

ROOT = Path(__file__).resolve().parents[1]
BREAKFAST = ROOT.parent / "shared" / "scenes" / "breakfast_room" / "BreakfastRoom.gltf"
#: the commit before the sampler of issue 12
BASELINE = "cfd5940"


def baseline_sampler(rev: str):
    """``sample_cameras`` of ``sceneforge/cameras.py`` at git revision ``rev``, imported as a
    module of this sceneforge (its relative imports resolve to today's conventions, errors
    and ray tracer, which it only reads)."""
    source = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:sceneforge/cameras.py"],
                            check=True, capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / "cameras_baseline.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("sceneforge._cameras_baseline", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module.sample_cameras


def houses():
    """[(name, house)]: bundled toy houses, the breakfast room, the hard cases."""
    sys.path.insert(0, str(ROOT))
    from tests.hard_houses import rug_room, two_level_house

    out = [(s.id, load(s)) for s in discover(BUNDLED_TOY)]
    if BREAKFAST.exists():
        out.append(("breakfast_room", load(BREAKFAST)))
    out += [("rug 90 % (hard)", rug_room()), ("two levels (hard)", two_level_house())]
    return out


def measure(house, tracer, sampler, config, views: int, seeds: int, size):
    """Per-view statistics at ``size`` of the cameras ``sampler`` gives over ``seeds`` seeds,
    and the sampling's seconds and candidates per seed."""
    stats, seconds, candidates, accepted = [], 0.0, 0, 0
    for seed in range(seeds):
        start = time.perf_counter()
        cameras, report = sampler(house, views, np.random.default_rng(seed), config, tracer)
        seconds += time.perf_counter() - start
        candidates += report.candidates
        accepted += len(cameras)
        stats += [ViewStats.of(frontal_layers(house, c.resized(*size), tracer)) for c in cameras]
    return stats, seconds / seeds, candidates / seeds, accepted / seeds


def row(name: str, sampler: str, views: int, result) -> tuple[str, list]:
    stats, seconds, candidates, accepted = result
    if not stats:
        return (f"{name:20s} {sampler:12s} {accepted:5.1f}/{views:<3d} {'-':>7s} {'-':>6s} {'-':>8s} {'-':>8s} "
                f"{seconds:7.2f} {candidates:6.0f}"), []
    objects = np.mean([s.objects for s in stats])
    d3 = 100 * np.mean([s.d3_fraction for s in stats])
    env = np.array([s.envelope_distance for s in stats])
    return (f"{name:20s} {sampler:12s} {accepted:5.1f}/{views:<3d} {objects:7.2f} {d3:6.2f} "
            f"{np.nanmean(env):8.2f} {np.nanmin(env):8.2f} {seconds:7.2f} {candidates:6.0f}"), stats


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--views", type=int, default=8, help="cameras requested per house")
    parser.add_argument("--seeds", type=int, default=2, help="seeds per house (statistics pool over them)")
    parser.add_argument("--size", default="160x120", help="resolution of the statistics trace, WxH")
    parser.add_argument("--baseline", default=BASELINE, help="git revision of the 'before' sampler")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))

    before = baseline_sampler(args.baseline)
    after = CameraSamplerConfig()
    samplers = [("before", before, None), ("first valid", sample_cameras, replace(after, pool_per_camera=1)),
                ("after", sample_cameras, after)]
    print(f"{args.views} views per house, {args.seeds} seeds, statistics at {size[0]}×{size[1]}; "
          f"'before' = sceneforge/cameras.py at {args.baseline}")
    print(f"{'house':20s} {'sampler':12s} {'views':>9s} {'objects':>7s} {'D3 %':>6s} {'env m':>8s} "
          f"{'worst m':>8s} {'s/house':>7s} {'cands':>6s}")
    pooled = {name: [] for name, _, _ in samplers}
    totals = {name: [0.0, 0.0] for name, _, _ in samplers}
    for name, house in houses():
        tracer = HouseTracer(house)
        for label, sampler, config in samplers:
            result = measure(house, tracer, sampler, config, args.views, args.seeds, size)
            line, stats = row(name, label, args.views, result)
            print(line)
            pooled[label] += stats
            totals[label][0] += result[1]
            totals[label][1] += result[2]
    print("all houses, per view:")
    for label, _, _ in samplers:
        stats = pooled[label]
        env = np.array([s.envelope_distance for s in stats])
        print(f"  {label:12s} views {len(stats) / args.seeds:5.1f}  objects {np.mean([s.objects for s in stats]):5.2f}  "
              f"D3 {100 * np.mean([s.d3_fraction for s in stats]):5.2f} %  envelope {np.nanmean(env):5.2f} m "
              f"(median {np.nanmedian(env):5.2f}, worst {np.nanmin(env):5.2f})  "
              f"sampling {totals[label][0]:6.2f} s, {totals[label][1]:5.0f} candidates, "
              f"{1e3 * totals[label][0] / max(totals[label][1], 1):5.1f} ms per candidate")


if __name__ == "__main__":
    main()
