"""The training input pipeline's own ceiling: steps/s of the learning check's data with a
near-zero-compute net, before and after batches were read at once, in one run.

The learning check (``benchmarks/learning_check.sh``, docs/spec.md §10.5) trains the depth,
seg and overhead stages on toy houses rendered at 80×60 (``benchmarks/learning/``). Here
``--houses`` of them (default 10, the fewest the default 0.1 / 0.1 house split takes; the
check renders 40) are rendered into a temporary folder with the check's render config,
or ``--store`` is read. For each stage, its batches (its sample fields and batch size as
the check's config sets them; the overhead stage reads its cached input, as the check
does) go through:

- **before**: the previous path, kept here: a dataset that reads each sample alone, one
  zarr read per array (``PreviousStoreDataset``), the DataLoader's default prefetch, and
  the loss read back (a host synchronisation) after every step;
- **after**: the library's (:func:`sceneforge.learn.trainer.make_loader`): whole batches
  read in the worker at once straight from the shard files, made channels-last there, 4
  batches prefetched per worker, the losses read once every ``log_every`` steps.

Both with DataLoader workers kept across epochs, each batch moved to the device as the
trainer does (:func:`~sceneforge.learn.trainer._to`; here the CPU, where making the images
channels-last is part of the pipeline), and an Adam step on a near-zero net (one 1×1
convolution of the input to one channel, the loss its mean): the nets, the losses and the
mirroring are the step's compute, not the pipeline's. steps/s over ``--steps`` steps after
the first batch, epochs in a row, the best of ``--rounds`` rounds of before then after
(the machine may be shared); the first batch (workers started, stores opened) is timed
apart. Stage start-up: the split (index the store, draw the house split), each frontal
stage's ``train()`` up to its training loop and through one step of its real net (the
CPU's compute, not the pipeline's), and the overhead stage's feature cache fill, its
reading before and after timed apart.

    python benchmarks/bench_input_pipeline.py [--store STORE] [--houses 10] [--workers 0 2]
                                              [--steps 100] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from sceneforge.evaluate.learning import seg_targets
from sceneforge.learn.cache import FeatureCache
from sceneforge.learn.dataset import (
    EMPTY,
    SAMPLE_FIELDS,
    StoreDataset,
    index_stores,
    normalize_rgb,
    segmentation_target,
)
from sceneforge.learn.split import SPLITS, fixed_split
from sceneforge.learn.stages import get_stage
from sceneforge.learn.train import TrainConfig, frontal_nets, train
from sceneforge.learn.trainer import (
    EpochSampler,
    _leave_interrupts_to_the_parent,
    _to,
    check_finite,
    end_workers,
    make_loader,
    worker_context,
)

RECIPE = Path(__file__).resolve().parent / "learning"
CPU = torch.device("cpu")


# ------------------------------------------------------------------ the previous path


class PreviousStoreDataset(StoreDataset):
    """:class:`StoreDataset` as it read before: each sample alone, one zarr read per array
    (``overhead_depth`` twice for the overhead targets), no ``__getitems__``."""

    __getitems__ = None  # the DataLoader asks for samples one by one

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        store = self._stores()[int(self.index.store[i])]
        v = int(self.index.view[i])
        read = lambda name: np.asarray(store.array(name)[v])  # noqa: E731
        out: dict[str, torch.Tensor] = {"index": torch.tensor(i, dtype=torch.int64)}
        if "rgb" in self.fields:
            out["rgb"] = torch.from_numpy(normalize_rgb(read("rgb")))
        if "depth" in self.fields:
            out["depth"] = torch.from_numpy(read("depth").astype(np.float32))
        if "seg" in self.fields:
            out["seg"] = torch.from_numpy(seg_targets(read("category")[None], read("depth")[None], EMPTY)[0])
        if "overhead_height" in self.fields:
            height = read("overhead_height").astype(np.float32)
            foreground = np.isfinite(height)
            floor = np.isfinite(read("overhead_depth")[4])
            out["overhead_height"] = torch.from_numpy(np.where(~foreground & floor, np.float32(0), height))
            out["overhead_foreground"] = torch.from_numpy(foreground)
        if "overhead_seg" in self.fields:
            nothing = np.isnan(read("overhead_depth")).all(axis=0)
            out["overhead_seg"] = torch.from_numpy(segmentation_target(read("overhead_category"), nothing))
        if "camera" in self.fields:
            for name in SAMPLE_FIELDS["camera"]:
                out[name] = torch.from_numpy(read(name).astype(np.float64))
        return out


class PreviousCachedDataset(torch.utils.data.Dataset):
    """The overhead stage's cached samples as they were read: targets sample by sample, the
    input (C, R, R) as the files held it then (now channels last: the view of one)."""

    def __init__(self, targets: PreviousStoreDataset, files: list[str]):
        self.targets, self.files = targets, files

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return {**self.targets[i], "overhead_input": torch.from_numpy(np.load(self.files[i])).permute(2, 0, 1)}


def previous_loader(dataset, workers: int, sampler) -> torch.utils.data.DataLoader:
    """``make_loader`` as it was: persistent workers, the DataLoader's default prefetch (2)."""
    kw = {"num_workers": workers, "pin_memory": False}
    if workers > 0:
        kw.update(multiprocessing_context=worker_context(), persistent_workers=True,
                  worker_init_fn=_leave_interrupts_to_the_parent)
    return torch.utils.data.DataLoader(dataset, batch_sampler=sampler, **kw)


# ------------------------------------------------------------------- near-zero net


class NearZeroNet(torch.nn.Module):
    """One 1×1 convolution of the stage's input (RGB, or the overhead stage's cached input)
    to one channel; the loss is its mean."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv = torch.nn.Conv2d(channels, 1, 1)

    def loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        # the cached input is float16: the overhead stage reads it as float32 too
        return self.conv(batch["overhead_input"].float() if "overhead_input" in batch else batch["rgb"]).mean()


def measure(loader, sampler: EpochSampler, net: NearZeroNet, steps: int, sync_every: int) -> tuple[float, float]:
    """(seconds to the first batch, steps/s of the ``steps`` steps after it), epochs in a row
    as training takes them; the losses read every ``sync_every`` steps."""
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-3)
    started, pending, n, epoch = time.perf_counter(), [], 0, 0
    first = timed_from = None
    while n <= steps:
        sampler.set_epoch(epoch)
        for batch in loader:
            if first is None:
                first = time.perf_counter() - started
                timed_from = time.perf_counter()
            loss = net.loss(_to(batch, CPU))
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            pending.append((n, loss.detach()))
            if len(pending) >= sync_every:
                check_finite(pending)
                pending = []
            n += 1
            if n > steps:
                break
        epoch += 1
    check_finite(pending)
    return first, steps / (time.perf_counter() - timed_from)


# -------------------------------------------------------------------------- set-up


def render_store(folder: Path, houses: int) -> tuple[str, float]:
    """The learning check's render of ``houses`` toy houses; (the store, seconds)."""
    sf = [sys.executable, "-m", "sceneforge"]
    subprocess.run([*sf, "toy-houses", str(folder / "houses"), "--count", str(houses), "--seed", "1"],
                   check=True, capture_output=True)
    started = time.perf_counter()
    store = folder / "gt.zarr"
    subprocess.run([*sf, "render", str(folder / "houses"), str(store), "--config", str(RECIPE / "render.json"),
                    "--workers", "2"], check=True, capture_output=True)
    return str(store), time.perf_counter() - started


def check_config(stage: str, store: str, split_file: str, **kw) -> TrainConfig:
    """The learning check's config of ``stage`` on ``store``, its split in ``split_file``."""
    data = json.loads((RECIPE / f"{stage}.json").read_text())
    config = TrainConfig.from_dict({**data, "stores": [store]}, what=f"{stage}.json")
    return replace(config, split=replace(config.split, file=split_file), **kw)


class _Clock:
    """A TrainProgress noting when the loop starts and when each step ends."""

    def __init__(self):
        self.at: list[float] = []

    def start(self, total: int, done: int) -> None:
        self.at.append(time.perf_counter())

    def step(self, step: int, loss: float) -> None:
        self.at.append(time.perf_counter())


def time_train(config: TrainConfig, run: Path) -> tuple[float, float, float]:
    """One step of the stage's real net through ``train()``: seconds to the loop's start
    (split, nets, feature cache), to the end of the first step, and the whole call."""
    clock, started = _Clock(), time.perf_counter()
    train(replace(config, max_steps=1), run, device="cpu", tensorboard=False, progress=clock)
    return clock.at[0] - started, clock.at[1] - started, time.perf_counter() - started


def read_all(loader) -> float:
    """Seconds to read every batch of ``loader``."""
    started = time.perf_counter()
    for _ in loader:
        pass
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--store", help="a store of the learning check's kind (default: render --houses)")
    parser.add_argument("--houses", type=int, default=10, help="toy houses to render (at least 10)")
    parser.add_argument("--workers", type=int, nargs="+", default=[0, 2], help="DataLoader workers to try")
    parser.add_argument("--steps", type=int, default=100, help="timed steps per measurement")
    parser.add_argument("--rounds", type=int, default=3, help="measurements of each path, the best kept")
    parser.add_argument("--stages", nargs="+", default=["depth", "seg", "overhead"],
                        choices=["depth", "seg", "overhead"])
    args = parser.parse_args()
    torch.set_num_threads(max(1, min(torch.get_num_threads(), len(os.sched_getaffinity(0)))))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if args.store:
            store, how = args.store, "given"
        else:
            store, seconds = render_store(tmp, args.houses)
            how = f"{args.houses} toy houses rendered in {seconds:.1f} s with benchmarks/learning/render.json"
        split_file = str(tmp / "split.json")

        started = time.perf_counter()
        index = index_stores([store])
        split = fixed_split(index.house, [store], check_config("depth", store, split_file).split)
        subsets = {s: index.subset(split.of(s)) for s in SPLITS}
        split_s = time.perf_counter() - started
        train_index = subsets["train"]
        print(f"store {store} ({how}): {len(index)} views of {len(set(index.house))} houses, "
              f"{index.shapes['W']}x{index.shapes['H']}, overhead {index.shapes['Wo']}; "
              f"{len(train_index)} training views")
        print(f"CPU: {len(os.sched_getaffinity(0))} cores, torch {torch.__version__}, "
              f"{torch.get_num_threads()} threads; load average {os.getloadavg()[0]:.1f}\n")
        print("stage start-up:")
        print(f"  split (index the store, draw the house split)          {split_s:6.2f} s")

        runs = {}
        for stage in ("depth", "seg"):
            if stage in args.stages or "overhead" in args.stages:
                runs[stage] = tmp / stage
                loop, first, whole = time_train(check_config(stage, store, split_file), runs[stage])
                print(f"  {stage:<8} train(): loop starts at {loop:5.2f} s, first step (the real net) done at "
                      f"{first:5.2f} s, call returns at {whole:5.2f} s")

        datasets = {}
        for name in args.stages:
            stage = get_stage(name)
            config = check_config(name, store, split_file, **({"depth_run": str(runs["depth"]),
                                                              "seg_run": str(runs["seg"])}
                                                             if name == "overhead" else {}))
            if name != "overhead":
                datasets[name] = (config, PreviousStoreDataset(train_index, stage.fields),
                                  StoreDataset(train_index, stage.fields), 3)
                continue
            from sceneforge.learn.eft import EpipolarFeatureTransformer

            frontal = frontal_nets(config)
            eft = EpipolarFeatureTransformer(config.eft, resolution=index.shapes["Wo"])
            cache = FeatureCache(tmp / "overhead", config, frontal, eft)
            full = StoreDataset(train_index, stage.fields)
            fill_loader = {"before": torch.utils.data.DataLoader(PreviousStoreDataset(train_index, stage.fields),
                                                                 batch_size=config.batch_size),
                           "after": torch.utils.data.DataLoader(full, batch_size=config.batch_size)}
            reading = {k: read_all(loader) for k, loader in fill_loader.items()}
            started = time.perf_counter()
            cache.fill(full, CPU)
            fill_s = time.perf_counter() - started
            print(f"  overhead feature cache fill, {len(full)} views: {fill_s:.2f} s (the frozen nets and the EFT "
                  f"on the CPU); its reading alone {reading['before']:.2f} s before, {reading['after']:.2f} s "
                  f"after ({reading['before'] / reading['after']:.1f}x)")
            files = cache.files(full)
            channels = np.load(files[0]).shape[-1]
            from sceneforge.learn.cache import CachedDataset

            datasets[name] = (config, PreviousCachedDataset(PreviousStoreDataset(train_index, stage.targets),
                                                                   files),
                              CachedDataset(StoreDataset(train_index, stage.targets), files), channels)

        print(f"\ninput pipeline, near-zero net (one 1x1 convolution), steps/s over {args.steps} steps after the "
              f"first batch, the best of {args.rounds} rounds (before, after, before, ...; the machine is shared):")
        print(f"  {'stage':<9}{'batch':>5}{'workers':>8}   {'first batch before/after':>24}   "
              f"{'steps/s before':>14}{'after':>9}{'ratio':>8}")
        for name, (config, before_set, after_set, channels) in datasets.items():
            for workers in args.workers:
                first, rate = {"before": [], "after": []}, {"before": [], "after": []}
                for _ in range(args.rounds):
                    for path, dataset in (("before", before_set), ("after", after_set)):
                        sampler = EpochSampler(len(dataset), config.seed, config.batch_size)
                        loader = (previous_loader(dataset, workers, sampler) if path == "before"
                                  else make_loader(dataset, CPU, workers, batch_sampler=sampler))
                        torch.manual_seed(0)
                        try:
                            f, r = measure(loader, sampler, NearZeroNet(channels), args.steps,
                                           1 if path == "before" else config.log_every)
                        finally:
                            end_workers(loader)
                        first[path].append(f)
                        rate[path].append(r)
                f0, f1, r0, r1 = min(first["before"]), min(first["after"]), max(rate["before"]), max(rate["after"])
                print(f"  {name:<9}{config.batch_size:>5}{workers:>8}   {f0:11.2f} s / {f1:5.2f} s   "
                      f"{r0:14.1f}{r1:9.1f}{r1 / r0:7.1f}x")
        print(f"load average at the end {os.getloadavg()[0]:.1f} (other jobs on this machine)")


if __name__ == "__main__":
    main()
