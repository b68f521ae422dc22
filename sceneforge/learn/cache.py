"""The overhead stage's input computed once per view and read back from disk (docs/spec.md §10.5).

The overhead nets read the EFT of the frozen frontal nets' outputs (232 channels at the
overhead resolution at the paper's widths). That input depends only on the view (its RGB,
its cameras and, with ``eft_layers="truth"``, its layers: the dataset has no augmentation),
on the frozen nets (in eval mode: BatchNorm uses its running statistics) and on the EFT's
settings, so the overhead stage computes it once per view, before its first step, and
every step of every epoch (validation too) reads it back instead of running the frozen
nets and the EFT again.

Layout, under the run folder::

    RUN/feature_cache/KEY/STORE-VIEW.npy     (R, R, C) float16 or float32, one per view
                                             (channels last: the memory layout of the
                                             overhead nets' input, so a batch of them
                                             is one stack, no transpose)

- ``KEY`` digests everything the features depend on besides the view: the frozen nets'
  weights and buffers (their content, as loaded from the frozen runs' checkpoints) and
  architectures, the EFT config, ``eft_layers``, the stored dtype, this module's
  :data:`FORMAT` and the sceneforge version. A retrained frozen run gives another key; the
  folders of other keys are stale and removed.
- ``STORE`` digests the store's manifest (the SHA-256 of every shard file, written when the
  store is completed), so a re-rendered store is not read from an old cache; a store without
  one is named by its absolute path and attributes.
- Files are written whole or not at all (a temporary file moved into place), so an
  interrupted run resumes with the views it had cached.

``float16`` (the default) halves the disk and rounds every value to 11 significant bits
(relative error ≤ 2⁻¹¹ ≈ 4.9e-4; a view whose values overflow float16 is stored in float32);
``float32`` stores the features exactly. ``feature_cache_gib`` bounds the disk used: a split
(training, validation) whose views do not fit in what is left is not cached and is
recomputed every step, as with ``feature_cache="off"``; so is one whose files cannot be
written (a full disk: a warning says so).

Under DistributedDataParallel every process fills the cache itself (the files are written
whole, so they may share the folder, at the cost of computing every view once per process).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from .. import __version__
from .config import TrainConfig
from .dataset import Samples, StoreDataset, batch_tensor
from .eft import EpipolarFeatureTransformer

log = logging.getLogger(__name__)

#: the folder of a run that holds its feature caches
CACHE_DIR = "feature_cache"
#: the layout and meaning of the cached files; a change makes every older cache stale
#: (2: channels last)
FORMAT = 2
DTYPES = {"float16": torch.float16, "float32": torch.float32}


def net_digest(net: nn.Module) -> str:
    """SHA-256 (hex) of a net's class, config and every tensor of its state (name, dtype,
    shape and bytes): equal digests compute equal features."""
    h = hashlib.sha256(f"{type(net).__qualname__}\n{getattr(net, 'config', None)!r}\n".encode())
    for name, t in net.state_dict().items():
        t = t.detach().cpu().contiguous()
        h.update(f"{name} {t.dtype} {tuple(t.shape)}\n".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def cache_key(config: TrainConfig, frontal: dict[str, nn.Module], eft: EpipolarFeatureTransformer) -> str:
    """The name of the cache of the features ``frontal`` and ``eft`` give under ``config``
    (what goes into it: module docstring)."""
    doc = {"format": FORMAT, "sceneforge": __version__, "dtype": config.feature_cache,
           "nets": {name: net_digest(net) for name, net in sorted(frontal.items())},
           "eft": asdict(eft.config), "resolution": eft.resolution, "eft_layers": config.eft_layers}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:24]


def store_key(path: str) -> str:
    """A store's name in the cache: a digest of its manifest (its shard files' SHA-256) or,
    for a store without one, of its absolute path and attributes."""
    from sceneforge.store import open_store

    attrs = open_store(str(path)).attrs
    manifest = (attrs.get("manifest") or {}).get("sha256")
    doc = {"manifest": manifest} if manifest else {"path": str(Path(path).resolve()), "attrs": attrs}
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()[:16]


class CachedDataset(torch.utils.data.Dataset):
    """The samples of a :class:`StoreDataset` of the overhead stage with the overhead nets'
    input read from the cache: its target fields plus ``overhead_input`` (C, R, R) float16
    or float32 (as stored; channels-last in memory), and ``index``."""

    def __init__(self, targets: StoreDataset, files: list[str]):
        assert len(targets) == len(files)
        self.targets, self.files = targets, files

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, i: int) -> dict[str, Tensor]:
        return self.__getitems__([i])[0]

    def __getitems__(self, indices) -> Samples:
        """The samples ``indices``, their targets read as one batch (:meth:`StoreDataset.batch`)."""
        batch = self.targets.batch(indices)
        views = [np.load(self.files[int(i)], mmap_mode="r") for i in indices]
        # a view stored in float32 (beyond float16's range) makes the batch float32, as stacking tensors does
        stacked = batch_tensor((len(views), *views[0].shape), np.result_type(*views))  # (B, R, R, C)
        np.stack(views, out=stacked.numpy())  # from the page cache straight into the batch: one copy
        batch["overhead_input"] = stacked.permute(0, 3, 1, 2)
        return Samples(batch)


class FeatureCache:
    """The cached overhead inputs of one run (``RUN/feature_cache/KEY``).

    frontal, eft : the frozen nets and the EFT the features come from
    """

    def __init__(self, run: str | Path, config: TrainConfig, frontal: dict[str, nn.Module],
                 eft: EpipolarFeatureTransformer):
        self.config, self.frontal, self.eft = config, frontal, eft
        self.dtype = DTYPES[config.feature_cache]
        self.root = Path(run) / CACHE_DIR
        self.folder = self.root / cache_key(config, frontal, eft)
        self._stores: dict[str, str] = {}

    def view_bytes(self) -> int:
        """Disk bytes of one view's features (the float16 ones; a few may be stored in float32)."""
        c = EpipolarFeatureTransformer.out_channels(self.frontal["depth"].feature_channels,
                                                    self.frontal["seg"].feature_channels)
        return c * self.eft.resolution ** 2 * self.dtype.itemsize

    def files(self, dataset: StoreDataset) -> list[str]:
        """The cache file of every view of ``dataset``, in its order."""
        index = dataset.index
        for path in index.stores:
            if path not in self._stores:
                self._stores[path] = store_key(path)
        names = [self._stores[index.stores[s]] for s in index.store]
        return [str(self.folder / f"{name}-{int(v)}.npy") for name, v in zip(names, index.view)]

    def remove_stale(self) -> None:
        """Remove the caches of other keys (older frozen nets or settings) of this run."""
        if self.root.is_dir():
            for other in self.root.iterdir():
                if other != self.folder:
                    log.info("removing the stale feature cache %s", other)
                    shutil.rmtree(other, ignore_errors=True)

    def fill(self, dataset: StoreDataset, device: torch.device) -> int:
        """Compute and write the features of the views of ``dataset`` not cached yet (in
        batches of ``config.batch_size``; read in this process, which the frozen nets keep
        busy far longer); the number of views computed. Raises OSError when a file cannot
        be written (e.g. the disk is full)."""
        from .stages import overhead_input

        files = self.files(dataset)
        missing = [i for i, f in enumerate(files) if not os.path.exists(f)]
        if not missing:
            return 0
        self.folder.mkdir(parents=True, exist_ok=True)
        log.info("feature cache: computing %d views into %s", len(missing), self.folder)
        loader = torch.utils.data.DataLoader(torch.utils.data.Subset(dataset, missing),
                                             batch_size=self.config.batch_size)
        truth = self.config.eft_layers == "truth"
        done = 0
        for batch in loader:
            batch = {k: v.to(device) for k, v in batch.items()}
            x = overhead_input(self.frontal, self.eft, batch, truth)[0]
            for features, k in zip(x, batch["index"].tolist()):
                self._write(files[k], features)
            done += len(x)
        return done

    def _write(self, path: str, features: Tensor) -> None:
        stored = features.to(self.dtype)
        if not torch.isfinite(stored).all():  # beyond float16's range: keep this view exact
            stored = features.float()
        tmp = f"{path}.{os.getpid()}.tmp.npy"
        try:
            np.save(tmp, stored.cpu().permute(1, 2, 0).contiguous().numpy())
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.remove(tmp)


def cached_datasets(config: TrainConfig, run: str | Path, frontal: dict[str, nn.Module],
                    eft: EpipolarFeatureTransformer, device: torch.device, targets: tuple[str, ...],
                    *datasets: StoreDataset | None) -> list:
    """The overhead stage's datasets with their inputs cached (``config.feature_cache``).

    datasets : the training and validation sets (None: none), filled in this order while
               they fit in ``config.feature_cache_gib``; one that does not fit, and every
               one with ``feature_cache="off"``, is returned as it is
    targets  : the sample fields the stage's objective reads
    """
    if config.feature_cache == "off":
        return list(datasets)
    cache = FeatureCache(run, config, frontal, eft)
    cache.remove_stale()
    left = config.feature_cache_gib * 2 ** 30
    out = []
    for dataset in datasets:
        need = 0 if dataset is None else len(dataset) * cache.view_bytes()
        if dataset is None or need > left:
            if dataset is not None:
                log.warning("feature cache: %d views need %.1f GiB, more than the %.1f GiB left of "
                            "feature_cache_gib; recomputing them every step", len(dataset), need / 2 ** 30,
                            left / 2 ** 30)
            out.append(dataset)
            continue
        left -= need
        try:
            cache.fill(dataset, device)
        except OSError as e:
            log.warning("feature cache: cannot write %s (%s); recomputing the features every step",
                        cache.folder, e.strerror or e)
            out.append(dataset)
            continue
        out.append(CachedDataset(StoreDataset(dataset.index, targets), cache.files(dataset)))
    return out
