"""A scale run of ``sceneforge render``: views/s and worker memory over time, store bytes, and
what 500k views would cost.

Makes toy houses with ``sceneforge toy-houses`` and renders them with ``sceneforge render``
(the commands a user runs, in a subprocess, with the default config: RGB raster, no
ground-truth meshes), while this process samples, every ``--sample`` seconds:

- the views done: the shard markers the run writes (``OUT.zarr/_staging/done/``, each naming
  its views) as they appear, and the houses planned (``_staging/houses/``);
- each worker process of the run (the render process's spawned children): resident memory
  (``VmRSS``) and CPU seconds (``utime + stime``), from ``/proc`` (Linux only).

It prints views/s for each tenth of the views and per minute, the workers' resident memory
at each tenth and its fitted trend over the rendering step (flat: the trend moves it by
less than 5 % of its mean over the run), the store's bytes (total and per view), and the
projected cost of 500k views on N cores, from the measured per-core rates (linear in
cores: no shared bottleneck, each core rendering at the rate measured here), and writes a
PNG of views/s and worker memory over time.

    python benchmarks/bench_scale.py [--houses 250] [--views-per-house 8] [--workers 2] [--plot PNG]
        [--sample 1.0] [--cores 2,16,64,256] [--keep DIR] [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: the target of the projection
TARGET_VIEWS = 500_000
#: a worker's memory is flat when its fitted trend over the run moves it by less than this
#: fraction of its mean
FLAT = 0.05
PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096
TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


# ---------------------------------------------------------------------------- sampling

@dataclass
class Sample:
    t: float  # seconds since the render started
    views: int  # views whose shard marker exists
    houses: int  # houses planned
    workers: dict[int, tuple[float, float]]  # pid -> (resident MiB, CPU seconds)
    main_cpu: float  # CPU seconds of the render process itself, when it is not a worker
    machine_cpu: float  # CPU seconds every process of the machine has used (/proc/stat)


@dataclass
class Sampler:
    """Samples the run's progress and its workers every ``interval`` seconds, in a thread."""

    render_pid: int
    store: Path
    interval: float
    in_process: bool = False  # one worker: the render process itself
    t0: float = field(default_factory=time.perf_counter)
    samples: list[Sample] = field(default_factory=list)
    rendering_from: float | None = None  # when the per-view arrays were created (step 2)
    _seen: dict[str, int] = field(default_factory=dict)
    _stop: threading.Event = field(default_factory=threading.Event)

    def start(self) -> "Sampler":
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def _loop(self) -> None:
        while not self._stop.is_set():
            self.samples.append(self._sample())
            self._stop.wait(self.interval)

    def _sample(self) -> Sample:
        t = time.perf_counter() - self.t0
        staging = self.store / "_staging"
        if self.rendering_from is None and (staging / "created.json").exists():
            self.rendering_from = t
        for marker in _listdir(staging / "done"):
            if marker not in self._seen:
                try:
                    a, b = json.loads((staging / "done" / marker).read_text())["views"]
                except (OSError, ValueError, KeyError):
                    continue  # being written, or the staging folder removed at the end
                self._seen[marker] = b - a
        houses = len(_listdir(staging / "houses"))
        if not houses and self.samples:
            houses = self.samples[-1].houses  # the staging folder is gone: the run is finishing
        # with one worker the render process renders itself (no pool)
        workers = [self.render_pid] if self.in_process else _workers(self.render_pid)
        return Sample(t, sum(self._seen.values()), houses, {p: _proc(p) for p in workers},
                      0.0 if self.in_process else _proc(self.render_pid)[1], _machine_cpu())


def _listdir(path: Path) -> list[str]:
    try:
        return os.listdir(path)
    except OSError:
        return []


def _workers(pid: int) -> list[int]:
    """The render process's worker processes: its children spawned by multiprocessing (not
    its resource tracker)."""
    out = []
    for entry in _listdir(Path("/proc")):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
            cmdline = Path(f"/proc/{entry}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        if ppid == pid and "spawn_main" in cmdline and "resource_tracker" not in cmdline:
            out.append(int(entry))
    return sorted(out)


def _machine_cpu() -> float:
    """CPU seconds the machine's cores have been busy since boot (user, nice, system, irq)."""
    fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]
    user, nice, system, _idle, _iowait, irq, softirq, steal = (int(x) for x in fields[:8])
    return (user + nice + system + irq + softirq + steal) / TICKS


def _proc(pid: int) -> tuple[float, float]:
    """(resident MiB, CPU seconds) of process ``pid``; NaN when it has ended."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        stat = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan"), float("nan")
    rss = next(int(line.split()[1]) for line in status.splitlines() if line.startswith("VmRSS:"))
    return rss / 1024, (int(stat[11]) + int(stat[12])) / TICKS


# ---------------------------------------------------------------------------- the run

def sceneforge(*args: str) -> list[str]:
    """The ``sceneforge`` command of this interpreter's environment."""
    exe = Path(sys.executable).with_name("sceneforge")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "sceneforge"]


def render(houses: Path, store: Path, args) -> tuple[Sampler, float, str]:
    """Run ``sceneforge render`` while sampling it; (sampler, wall seconds, its output)."""
    cmd = [*sceneforge(), "render", str(houses), str(store), "--workers", str(args.workers),
           "--views-per-house", str(args.views_per_house), "--resolution", args.resolution,
           *(["--rgb", args.rgb] if args.rgb else [])]
    print("$ sceneforge", " ".join(cmd[len(sceneforge()):]), flush=True)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    sampler = Sampler(proc.pid, store, args.sample, in_process=args.workers == 1, t0=t0).start()
    output, _ = proc.communicate()
    wall = time.perf_counter() - t0
    sampler.stop()
    if proc.returncode != 0:
        raise SystemExit(f"sceneforge render failed ({proc.returncode}):\n{output}")
    # the markers of the last moments are gone with the staging folder: the store has them all
    from sceneforge.store import open_store

    last = sampler.samples[-1]
    sampler.samples.append(Sample(wall, len(open_store(str(store))), last.houses, {}, last.main_cpu, _machine_cpu()))
    return sampler, wall, output


# ---------------------------------------------------------------------------- figures

def decile_rates(t: np.ndarray, views: np.ndarray, total: int, start: float) -> list[tuple[float, float, float]]:
    """[(start s, end s, views/s)] of each tenth of the views, from the sampled (t, views)
    and the rendering step's ``start``: each tenth from the first sample reaching it."""
    marks = [start] + [crossing(t, views, k * total / 10) for k in range(1, 11)]
    return [(a, b, total / 10 / (b - a) if b > a else float("nan")) for a, b in zip(marks[:-1], marks[1:])]


def crossing(t: np.ndarray, views: np.ndarray, x: float) -> float:
    """When the views done reached ``x``: linear between the samples either side."""
    i = int(np.flatnonzero(views >= x)[0])
    if i == 0 or views[i] == views[i - 1]:
        return float(t[i])
    return float(t[i - 1] + (x - views[i - 1]) * (t[i] - t[i - 1]) / (views[i] - views[i - 1]))


def minute_rates(t: np.ndarray, views: np.ndarray, start: float) -> list[tuple[float, float]]:
    """[(minute end s, views/s in that minute)] of the rendering step (the last minute
    partial)."""
    out = []
    edges = np.arange(start, t[-1] + 60, 60.0)
    for a, b in zip(edges[:-1], edges[1:]):
        b = min(b, float(t[-1]))
        if b <= a:
            break
        va, vb = (np.interp(x, t, views) for x in (a, b))
        out.append((b, (vb - va) / (b - a)))
    return out


def memory_trend(views: np.ndarray, rss: np.ndarray) -> tuple[float, float]:
    """(MiB per 1,000 views, mean MiB) of a least-squares line through the worker's resident
    memory against the views done."""
    keep = np.isfinite(rss)
    if keep.sum() < 3 or np.ptp(views[keep]) == 0:
        return float("nan"), float(np.nanmean(rss)) if keep.any() else float("nan")
    slope = np.polyfit(views[keep], rss[keep], 1)[0]
    return 1000 * slope, float(rss[keep].mean())


def store_bytes(store: Path) -> tuple[int, dict[str, int]]:
    """Total bytes of the store's files and bytes by array (metadata apart)."""
    by: dict[str, int] = {}
    for p in store.rglob("*"):
        if p.is_file():
            key = p.relative_to(store).as_posix()
            name = key.split("/c/")[0] if "/c/" in key else "metadata"
            by[name] = by.get(name, 0) + p.stat().st_size
    return sum(by.values()), by


def plot(path: Path, sampler: Sampler, t: np.ndarray, views: np.ndarray, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    window = max(1, int(round(10 / sampler.interval)))  # a 10-second moving rate
    if len(t) > window:
        rate = (views[window:] - views[:-window]) / (t[window:] - t[:-window])
        top.plot(t[window:], rate, lw=1, label="views/s over the last 10 s")
    start = sampler.rendering_from or 0.0
    done = np.flatnonzero(views >= views[-1])
    end = float(t[done[0]]) if len(done) else float(t[-1])
    top.axhline(views[-1] / (end - start), color="k", ls="--", lw=1, label="mean of the rendering step")
    for ax in (top, bottom):
        ax.axvspan(0, start, color="0.9", label="planning (cameras)" if ax is top else None)
    top.set_ylabel("views / s")
    top.set_ylim(bottom=0)
    top.legend(loc="lower right", fontsize=8)
    top.set_title(title, fontsize=9)
    pids = sorted({p for s in sampler.samples for p in s.workers})
    for k, pid in enumerate(pids):
        rss = [s.workers.get(pid, (np.nan, np.nan))[0] for s in sampler.samples]
        bottom.plot(t, rss, lw=1, label=f"worker {k + 1}")
    bottom.set_ylabel("resident memory, MiB")
    bottom.set_xlabel("seconds since render started")
    bottom.set_ylim(bottom=0)
    bottom.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--houses", type=int, default=250, help="toy houses (sceneforge toy-houses --count)")
    ap.add_argument("--views-per-house", type=int, default=8)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--resolution", default="320x240")
    ap.add_argument("--rgb", default=None, help="render's --rgb (default: render's default, raster)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the toy houses")
    ap.add_argument("--sample", type=float, default=1.0, help="seconds between samples")
    ap.add_argument("--cores", default="2,16,64,256", help="core counts of the 500k-view projection")
    ap.add_argument("--plot", default=str(Path(tempfile.gettempdir()) / "bench_scale.png"),
                    help="where the PNG goes (default: bench_scale.png in the temporary folder)")
    ap.add_argument("--keep", default=None, help="keep the houses and the store in this folder")
    ap.add_argument("--quick", action="store_true", help="12 houses x 4 views, a sample every 0.25 s (a smoke run)")
    args = ap.parse_args()
    if not Path("/proc/self/status").exists():
        raise SystemExit("bench_scale samples worker processes through /proc: Linux only")
    if args.quick:
        args.houses, args.views_per_house, args.sample = 12, 4, 0.25
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_scale_"))
    houses, store = work / "houses", work / "scale.zarr"
    try:
        shutil.rmtree(store, ignore_errors=True)
        print(f"{args.houses} toy houses x {args.views_per_house} views, {args.workers} workers, "
              f"{args.resolution}, {os.cpu_count()} CPUs, load average {' '.join(f'{x:.1f}' for x in os.getloadavg())}")
        t0 = time.perf_counter()
        if not houses.exists():
            subprocess.run([*sceneforge(), "toy-houses", str(houses), "--count", str(args.houses),
                            "--seed", str(args.seed)], check=True, stdout=subprocess.DEVNULL)
        print(f"toy-houses: {time.perf_counter() - t0:.1f} s")
        load_before = os.getloadavg()
        sampler, wall, output = render(houses, store, args)
        load_after = os.getloadavg()
        report(args, sampler, wall, output, store, load_before, load_after)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


def report(args, sampler: Sampler, wall: float, output: str, store: Path, load_before, load_after) -> None:
    samples = sampler.samples
    t = np.array([s.t for s in samples])
    views = np.array([s.views for s in samples], dtype=float)
    total = int(views[-1])
    start = sampler.rendering_from if sampler.rendering_from is not None else 0.0
    last = output.strip().splitlines()[-1] if output.strip() else ""
    print(f"render: {last}")
    print(f"load average (1 min) at the start {load_before[0]:.1f}, at the end {load_after[0]:.1f}")
    n_houses = max(s.houses for s in samples)
    print(f"planning (cameras of {n_houses} houses): {start:.1f} s; rendering {total} views: {wall - start:.1f} s; "
          f"whole run {wall:.1f} s = {total / wall:.2f} views/s end to end")

    print("\nviews/s by tenth of the views, with the run's CPU seconds per view (render process and workers) and the cores the "
          "machine's other processes kept busy meanwhile (a slower tenth with the same CPU per view was "
          "slowed from outside):")
    deciles = decile_rates(t, views, total, start)
    ours, last_cpu = [], {}
    for smp in samples:  # a worker's CPU seconds as last sampled (the final sample has no workers)
        last_cpu.update({p: c for p, (_, c) in smp.workers.items() if np.isfinite(c)})
        ours.append(sum(last_cpu.values()) + smp.main_cpu)
    ours = np.array(ours)
    machine = np.array([smp.machine_cpu for smp in samples])
    for k, (a, b, rate) in enumerate(deciles):
        used, busy = (np.interp(b, t, x) - np.interp(a, t, x) for x in (ours, machine))
        print(f"  {10 * k:>3}-{10 * (k + 1):<3}%  {a:7.1f}-{b:7.1f} s  {rate:6.2f} views/s  "
              f"{used / (total / 10):.3f} CPU s/view  others {(busy - used) / (b - a):.2f} cores")
    steady = [r for _, _, r in deciles[1:] if np.isfinite(r)]
    print(f"  first tenth {deciles[0][2]:.2f} views/s (workers starting); the other nine: "
          f"{min(steady):.2f}-{max(steady):.2f}, mean {total * 0.9 / (deciles[-1][1] - deciles[0][1]):.2f} views/s")
    print("views/s per minute of the rendering step: "
          + ", ".join(f"{r:.2f}" for _, r in minute_rates(t, views, start)))

    print("\nworker resident memory (MiB) at each tenth of the views:")
    live = [i for i, smp in enumerate(samples) if smp.workers]  # the final sample is the store's count
    lv = views[live]
    pids = sorted({p for smp in samples for p in smp.workers})
    at = [live[int(np.flatnonzero(lv >= min(k * total / 10, lv[-1]))[0])] for k in range(1, 11)]
    warm = (t >= start) & (views >= total / 10)  # the trend after the first tenth (first houses, first frames)
    flat_all, cpu_total = True, 0.0
    for k, pid in enumerate(pids):
        rss = np.array([smp.workers.get(pid, (np.nan, np.nan))[0] for smp in samples])
        cpu = np.array([smp.workers.get(pid, (np.nan, np.nan))[1] for smp in samples])
        slope, mean = memory_trend(views[warm], rss[warm])
        change = abs(slope) * total / 1000
        flat = bool(change < FLAT * mean)
        flat_all &= flat
        cpu_total += float(np.nanmax(cpu)) if np.isfinite(cpu).any() else 0.0
        print(f"  worker {k + 1}: " + " ".join(f"{rss[i]:.0f}" for i in at)
              + f"; peak {np.nanmax(rss):.0f}; trend after the first tenth {slope:+.1f} MiB per 1,000 views "
              f"({change:.0f} MiB over the run, {100 * change / mean:.1f} % of its mean {mean:.0f}): "
              + ("flat" if flat else "NOT flat"))
    print(f"  worker memory flat (trend < {FLAT:.0%} of the mean over the run): {'yes' if flat_all else 'NO'}")

    size, by = store_bytes(store)
    print(f"\nstore: {size / 1e6:.1f} MB, {size / total / 1e3:.1f} kB per view; largest arrays (kB per view): "
          + ", ".join(f"{k} {v / total / 1e3:.1f}" for k, v in sorted(by.items(), key=lambda kv: -kv[1])[:5]))

    cores = min(args.workers, os.cpu_count() or 1)
    houses_needed = TARGET_VIEWS / args.views_per_house
    # (a) wall: the cores this run had, for as long as it took; (b) CPU: what its processes
    # used (the render process and its workers), so another job sharing the machine is not counted
    plan_core_s = start * cores / n_houses
    view_core_s = cores * (wall - start) / total
    wall_hours = (houses_needed * plan_core_s + TARGET_VIEWS * view_core_s) / 3600
    cpu_per_view = (cpu_total + samples[-1].main_cpu) / total
    cpu_hours = TARGET_VIEWS * cpu_per_view / 3600
    print(f"\nprojection for {TARGET_VIEWS:,} views ({houses_needed:,.0f} houses x {args.views_per_house} views) "
          f"on N cores, linear in cores (each core renders at the rate measured here: no shared bottleneck, "
          f"the store is written shard by shard and no two workers write one file):")
    print(f"  (a) from this run's wall time on {cores} cores: {plan_core_s:.2f} core-s per house planning, "
          f"{view_core_s:.3f} core-s per view rendering -> {wall_hours:,.0f} core-hours")
    print(f"  (b) from the CPU time of the render process and its workers: {cpu_per_view:.3f} s per view, "
          f"planning included -> {cpu_hours:,.0f} core-hours (what the cores cost where nothing else runs)")
    print(f"  store: {TARGET_VIEWS * size / total / 1e9:,.0f} GB")
    print(f"  {'cores':>7}{'(a) hours':>11}{'(b) hours':>11}")
    for n in (int(c) for c in args.cores.split(",")):
        print(f"  {n:>7}{wall_hours / n:>11.1f}{cpu_hours / n:>11.1f}")

    plot(Path(args.plot), sampler, t, views,
         f"sceneforge render: {args.houses} toy houses x {args.views_per_house} views, {args.workers} workers, "
         f"{args.resolution}; load average {load_before[0]:.1f}")
    print(f"\nplot: {args.plot}")


if __name__ == "__main__":
    main()
