"""The house split of a set of stores: fixed once, saved, read by every stage, by
``predict`` and by ``evaluate`` (docs/spec.md §10.1). No PyTorch: the evaluation reads it.

A split belongs to the data, not to a run: houses are assigned to ``train``, ``val`` and
``test`` with the split's own seed (:class:`~sceneforge.learn.config.SplitConfig`, not the
training seed), the first time any stage trains on the stores, and written to a split file
(:func:`default_split_file`, named by the stores and beside the first, unless another is
given: ``/data/a.split.json`` for ``/data/a.zarr``)::

    {"version": 1, "val_fraction": 0.1, "test_fraction": 0.1, "seed": 0,
     "stores": ["/data/a.zarr"], "train": ["h0", ...], "val": [...], "test": [...]}

Every later stage on the same stores reads that file instead of splitting again, so an
overhead run never validates on its frozen nets' training houses, and ``predict`` and
``evaluate`` score the test houses only (``split="test"`` by default; ``"all"``: every view).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import SceneforgeError
from ..store.location import beside, is_url, read_file, resolve, write_file
from .config import SplitConfig

#: the splits of the houses
SPLITS: tuple[str, ...] = ("train", "val", "test")
#: what ``predict --split`` and ``evaluate --split`` take: a split or every view
SPLIT_CHOICES: tuple[str, ...] = (*SPLITS, "all")
#: the split file of earlier versions, one per folder: read only for the stores it records
LEGACY_SPLIT_FILE = "split.json"
_VERSION = 1
_OPTION = {"val": "--val-fraction", "test": "--test-fraction"}
_WHAT = {"val": "validation", "test": "test"}


def split_houses(house_ids: Sequence[str], config: SplitConfig | None = None) -> dict[str, list[str]]:
    """Assign houses to ``train``, ``val`` and ``test``: sorted ids shuffled with the seed,
    then the first ⌊val·n⌋ to val, the next ⌊test·n⌋ to test, the rest to train. The same
    houses and seed always give the same split."""
    config = config or SplitConfig()
    ids = sorted(set(map(str, house_ids)))
    order = [ids[i] for i in np.random.default_rng(config.seed).permutation(len(ids))]
    n_val, n_test = int(config.val_fraction * len(ids)), int(config.test_fraction * len(ids))
    return {"val": sorted(order[:n_val]), "test": sorted(order[n_val:n_val + n_test]),
            "train": sorted(order[n_val + n_test:])}


def split_file_name(stores: Sequence[str]) -> str:
    """The name of the split file of ``stores``: ``a.split.json`` for the one store
    ``a.zarr`` (``.zarr`` dropped); for several, the first's name, ``+`` the number of the
    others and 8 hex digits of the SHA-256 of the list (``a+2.5f3c0e1d.split.json``), so no
    other list of stores shares the file. The list is hashed as the stores' paths relative
    to the first store's folder (URLs as written): the name stays when that folder moves
    with its stores."""
    first = str(stores[0]).rstrip("/")
    name = first.rsplit("/", 1)[-1] if is_url(first) else Path(resolve(first)).name
    name = name.removesuffix(".zarr")
    if len(stores) == 1:
        return f"{name}.split.json"
    home = None if is_url(first) else str(Path(resolve(first)).parent)
    paths = [s if home is None or is_url(s) else os.path.relpath(s, home) for s in map(resolve, stores)]
    digest = hashlib.sha256("\n".join(paths).encode()).hexdigest()[:8]
    return f"{name}+{len(stores) - 1}.{digest}.split.json"


def default_split_file(stores: Sequence[str]) -> str:
    """The split file of ``stores`` when none is given: :func:`split_file_name` beside the
    first store (absolute; on its filesystem: ``s3://bucket/a.split.json`` for
    ``s3://bucket/a.zarr``). Until that file exists, a :data:`LEGACY_SPLIT_FILE` there that
    records exactly these stores is theirs (the runs and predictions of earlier versions
    keep their split); one of other stores is never read."""
    path = beside(stores[0], split_file_name(stores))
    if read_file(path) is not None:
        return path
    legacy = beside(stores[0], LEGACY_SPLIT_FILE)
    try:
        recorded = read_split(legacy).stores
    except SceneforgeError:  # none there, or a file of that name that is not a split
        return path
    return legacy if list(map(resolve, recorded)) == list(map(resolve, stores)) else path


@dataclass(frozen=True)
class HouseSplit:
    """The houses of each split and how they were drawn.

    houses : split name → sorted house ids
    config : the fractions and seed that drew them (``config.file``: where it is saved)
    stores : the stores it was drawn for
    """

    houses: dict[str, tuple[str, ...]]
    config: SplitConfig
    stores: tuple[str, ...]

    @property
    def path(self) -> str | None:
        """Where the split is saved: an absolute path or a URL."""
        return self.config.file

    def of(self, split: str) -> frozenset[str] | None:
        """The houses of ``split`` (``all``: None, i.e. every house)."""
        if split not in SPLIT_CHOICES:
            raise SceneforgeError(f"unknown split {split!r}; known: {', '.join(SPLIT_CHOICES)}")
        return None if split == "all" else frozenset(self.houses[split])

    def to_dict(self) -> dict:
        c = self.config
        return {"version": _VERSION, "val_fraction": c.val_fraction, "test_fraction": c.test_fraction,
                "seed": c.seed, "stores": list(self.stores), **{s: list(self.houses[s]) for s in SPLITS}}


def draw_split(house_ids: Sequence[str], config: SplitConfig, stores: Sequence[str] = ()) -> HouseSplit:
    """A new split of ``house_ids`` (nothing saved).

    Raises :class:`SceneforgeError` when a non-zero validation or test fraction gives no
    house, naming the smallest fraction that would (training keeps at least one house: the
    fractions sum below 1 and are rounded down).
    """
    ids = sorted(set(map(str, house_ids)))
    houses = split_houses(ids, config)
    for split in ("val", "test"):
        fraction = getattr(config, f"{split}_fraction")
        if fraction > 0 and not houses[split]:
            least = math.ceil(100 / len(ids)) / 100 if ids else 1.0
            raise SceneforgeError(
                f"{len(ids)} houses cannot give a {fraction:g} {_WHAT[split]} split: use {_OPTION[split]} "
                f">= {least:g} (or 0 for none) or more houses")
    return HouseSplit({s: tuple(houses[s]) for s in SPLITS}, config, tuple(map(str, stores)))


def read_split(path: str | Path) -> HouseSplit:
    """The split saved in ``path`` (a local path or a URL); :class:`SceneforgeError` when it
    is missing or not a split file."""
    path = str(path)
    try:
        data = read_file(path)
        if data is None:
            raise SceneforgeError(f"no split file {path}: train a run on these stores first (it writes the "
                                  "split), give --split-file, or use --split all")
        data = json.loads(data)
        config = SplitConfig(data["val_fraction"], data["test_fraction"], data["seed"], resolve(path))
        houses = {s: tuple(map(str, data[s])) for s in SPLITS}
        stores = tuple(map(str, data.get("stores", ())))
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise SceneforgeError(f"{path}: not a split file ({e})") from None
    return HouseSplit(houses, config, stores)


def fixed_split(house_ids: Sequence[str], stores: Sequence[str], config: SplitConfig) -> HouseSplit:
    """The split of the stores' houses saved in ``config.file`` (default:
    :func:`default_split_file`), drawn and written there if the file does not exist yet.

    Raises :class:`SceneforgeError` when the saved split was drawn with other fractions or
    another seed than ``config`` asks for, or does not hold every one of the houses.
    """
    path = resolve(config.file) if config.file is not None else default_split_file(stores)
    if read_file(path) is None:
        split = draw_split(house_ids, SplitConfig(config.val_fraction, config.test_fraction, config.seed, path),
                           stores)
        write_file(path, (json.dumps(split.to_dict(), indent=1) + "\n").encode())
        return split
    split = read_split(path)
    saved = split.config
    if (saved.val_fraction, saved.test_fraction, saved.seed) != (config.val_fraction, config.test_fraction,
                                                                 config.seed):
        raise SceneforgeError(
            f"{path} holds the split of these stores drawn with --val-fraction {saved.val_fraction:g} "
            f"--test-fraction {saved.test_fraction:g} --split-seed {saved.seed}: pass the same, or "
            "--split-file NEW.json for a new split")
    known = {h for s in SPLITS for h in split.houses[s]}
    missing = sorted(set(map(str, house_ids)) - known)
    if missing:
        raise SceneforgeError(f"{path} splits other stores: {len(missing)} houses ({', '.join(missing[:3])}"
                              f"{', ...' if len(missing) > 3 else ''}) are in none of its splits; give "
                              "--split-file NEW.json for these stores")
    return split
