"""Training samples from one or more stores (docs/spec.md §9 → §10.1).

- **Lazy reads**: a :class:`StoreDataset` keeps only view indices; a batch (a DataLoader
  worker's whole batch, ``__getitems__``) reads the chunks of its views of each array it
  needs at once, straight from the shard files, and makes its targets in one go. Stores
  are opened on first use in each process and never pickled, so any number of DataLoader
  workers can read at once.
- **House-level split** (:mod:`.split`): every view of a house falls in the same split,
  fixed once per set of stores, so validation and test views show houses the networks
  never saw.
- **Input normalisation** *(ref)*: ``(rgb − mean) / 255`` with the mean colour of the PBRS
  images, :data:`RGB_MEAN`.
- **Segmentation targets** (:func:`segmentation_target`): 40 classes per layer; class
  ``c > 0`` is the NYU40 object class ``c + 1``, class 0 (:data:`BACKGROUND`, the slot of
  "wall") is background: no object in that layer or any room-envelope class merged into
  one *(paper appendix)*; :data:`EMPTY` marks pixels where the ray hits nothing at all
  (void), which the loss ignores by default *(ref)*.
- **Overhead height targets**: the store's object heights, 0 where only the floor is seen,
  NaN where nothing is; ``overhead_foreground`` marks the object pixels, the only ones the
  paper supervises (``floor_as_zero`` supervises the floor too).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Collection, Sequence

import numpy as np
import torch

from .. import conventions
from ..errors import SceneforgeError
from ..evaluate.learning import seg_targets
from .config import SplitConfig  # noqa: F401  (defined without torch, for the CLI and the schema)
from .split import SPLITS, split_houses  # noqa: F401  (re-exported: the split needs no torch)

#: mean RGB colour (0..255) subtracted from every input image *(ref: PBRS renderings)*
RGB_MEAN = (178.1781, 158.5039, 142.5141)
#: segmentation classes per layer (frontal layers 1 and 3, and the overhead view)
SEG_CLASSES = conventions.SEG_CLASSES
#: the background class: no object, and every room-envelope class
BACKGROUND = conventions.SEG_BACKGROUND
#: the target of a pixel where the ray hits nothing (PyTorch's ignore index)
EMPTY = -100

#: sample keys → the store arrays they are made from
SAMPLE_FIELDS: dict[str, tuple[str, ...]] = {
    "rgb": ("rgb",),
    "depth": ("depth",),
    "seg": ("category", "depth"),
    "overhead_height": ("overhead_height", "overhead_depth"),
    "overhead_seg": ("overhead_category", "overhead_depth"),
    "camera": ("K", "cam_to_world", "overhead_cam_to_world", "overhead_extent", "overhead_params"),
    "intersections": ("intersections/depth",),
    "intersection_labels": ("intersections/instance", "intersections/category"),
    "intersection_normal": ("intersections/normal",),
    "intersection_front_facing": ("intersections/front_facing",),
}


def normalize_rgb(rgb: np.ndarray) -> np.ndarray:
    """(..., H, W, 3) uint8 → (..., 3, H, W) float32 network input, ``(rgb − RGB_MEAN) / 255``."""
    x = np.moveaxis(np.asarray(rgb, dtype=np.float32), -1, -3)
    return (x - np.asarray(RGB_MEAN, dtype=np.float32)[:, None, None]) / 255.0


#: NYU40 id → segmentation class
NYU40_TO_CLASS = np.asarray(conventions.NYU40_TO_SEG, dtype=np.int64)
#: segmentation class → NYU40 id (0 for background)
CLASS_TO_NYU40 = np.asarray(conventions.SEG_TO_NYU40, dtype=np.int64)


def segmentation_target(category: np.ndarray, empty: np.ndarray | None = None) -> np.ndarray:
    """NYU40 ids (any shape, uint8) → segmentation classes (same shape, int64), :data:`EMPTY`
    where ``empty`` (bool, same shape) is set."""
    classes = NYU40_TO_CLASS[np.asarray(category, dtype=np.int64)]
    return classes if empty is None else np.where(empty, EMPTY, classes)


def batch_tensor(shape: tuple[int, ...], dtype) -> torch.Tensor:
    """An empty tensor of a batch: in a DataLoader worker, in shared memory, which the
    batch crosses to the training process in without another copy (as the default
    collation stacks samples into)."""
    out = torch.empty(shape, dtype=torch.from_numpy(np.empty(0, dtype=dtype)).dtype)
    return out.share_memory_() if torch.utils.data.get_worker_info() is not None else out


class Samples(list):
    """The samples of a batch read at once (a dataset's ``__getitems__``), each a dict of
    views of ``batch``, and the batch itself: the trainer's loaders take ``batch`` as it is
    (:func:`sceneforge.learn.trainer.collate`), any other collation stacks the samples."""

    def __init__(self, batch: dict[str, torch.Tensor]):
        super().__init__({k: v[j] for k, v in batch.items()} for j in range(len(batch["index"])))
        self.batch = batch


@dataclass(frozen=True)
class ViewIndex:
    """The usable views of a list of stores.

    stores : the store paths, in order
    store  : (n,) int64  which store a view is in
    view   : (n,) int64  its index in that store
    house  : (n,) str    its house id
    shapes : sizes of the stores' images: ``{"H", "W", "Ho", "Wo"}`` (equal in every store)
    """

    stores: tuple[str, ...]
    store: np.ndarray
    view: np.ndarray
    house: np.ndarray
    shapes: dict

    def subset(self, houses: Collection[str] | None) -> "ViewIndex":
        """The views of ``houses`` (None: every view)."""
        if houses is None:
            return self
        keep = np.isin(self.house, np.asarray(list(houses), dtype=self.house.dtype))
        return ViewIndex(self.stores, self.store[keep], self.view[keep], self.house[keep], self.shapes)

    def take(self, rows: Sequence[int]) -> "ViewIndex":
        """The views at positions ``rows`` of this index."""
        rows = np.asarray(rows, dtype=np.int64)
        return ViewIndex(self.stores, self.store[rows], self.view[rows], self.house[rows], self.shapes)

    def __len__(self) -> int:
        return len(self.view)


def index_stores(paths: Sequence[str]) -> ViewIndex:
    """Open every store once and list its valid views (failed views are left out).

    Raises :class:`SceneforgeError` when a store cannot be opened, holds no RGB, or its image
    sizes differ from the first store's.
    """
    from sceneforge.store import open_store

    stores, views, houses, shapes = [], [], [], None
    for k, path in enumerate(paths):
        store = open_store(str(path))
        if "rgb" not in store.names:
            raise SceneforgeError(f"{path}: the store has no RGB images (rendered with rgb.enabled false)")
        depth, top = store.array("depth"), store.array("overhead_height")
        these = {"H": depth.shape[2], "W": depth.shape[3], "Ho": top.shape[1], "Wo": top.shape[2]}
        if shapes is not None and these != shapes:
            raise SceneforgeError(f"{path}: images of {these} differ from {paths[0]}'s {shapes}")
        shapes = these
        valid = np.flatnonzero(np.asarray(store.array("valid")[:], dtype=bool))
        stores.append(str(path))
        views.append(np.stack([np.full(len(valid), k), valid], axis=1))
        houses.append(np.array([str(h) for h in store.array("house_id")[:]])[valid])
    if not stores:
        raise SceneforgeError("no store given")
    v = np.concatenate(views).astype(np.int64)
    return ViewIndex(tuple(stores), v[:, 0], v[:, 1], np.concatenate(houses), shapes)


class StoreDataset(torch.utils.data.Dataset):
    """Samples of the views of a :class:`ViewIndex` as dicts of tensors.

    fields : sample keys (:data:`SAMPLE_FIELDS`) to read:

    - ``rgb``: (3, H, W) float32 normalised input
    - ``depth``: (5, H, W) float32 D1..D5 metres, NaN = none
    - ``seg``: (2, H, W) int64 classes of layers 1 and 3, :data:`EMPTY` where the ray
      hits nothing (neither the layer nor the envelope D5)
    - ``overhead_height``: (Ho, Wo) float32 height above the floor, 0 where only the floor
      is hit, NaN where nothing is; and ``overhead_foreground`` (Ho, Wo) bool: an object is hit
    - ``overhead_seg``: (Ho, Wo) int64 class of the first object seen from above,
      :data:`EMPTY` where nothing (not even the floor) is hit
    - ``camera``: ``K`` (3, 3), ``cam_to_world``, ``overhead_cam_to_world`` (4, 4),
      ``overhead_extent`` () and ``overhead_params`` (5,) float64

    The K ray-intersection layers (docs/spec.md §4.7), of stores rendered with
    ``--intersections K`` (L = K; another store raises :class:`SceneforgeError`), each
    layer k the k-th surface along the pixel's ray, past the ray's last surface the fill
    value given:

    - ``intersections``: ``intersection_depth`` (L, H, W) float32 planar depth, metres
      (NaN: kept, as in ``depth``), and ``intersection_valid`` (L, H, W) bool, where it is
      finite: the mask to take a loss over
    - ``intersection_labels``: ``intersection_instance`` (L, H, W) int64 house instance
      (−1) and ``intersection_category`` (L, H, W) int64 NYU40 class (0)
    - ``intersection_normal``: (L, 3, H, W) float32 unit winding normal of the face, camera
      frame, not turned to face the camera (NaN)
    - ``intersection_front_facing``: (L, H, W) bool, the ray meets the face's front (false)

    Every sample also has ``index`` (its position in the dataset) int64. :meth:`batch`
    gives a batch of samples stacked; ``__getitems__`` (what a DataLoader calls with a
    batch's indices) the same as a list of samples.
    """

    def __init__(self, index: ViewIndex, fields: Sequence[str]):
        unknown = set(fields) - set(SAMPLE_FIELDS)
        if unknown:
            raise ValueError(f"unknown sample fields {sorted(unknown)}; known: {sorted(SAMPLE_FIELDS)}")
        self.index = index
        self.fields = tuple(fields)
        self._open: tuple[int, list] | None = None

    def __len__(self) -> int:
        return len(self.index)

    def __getstate__(self):
        # zarr handles stay in the process that opened them; workers reopen lazily
        return {**self.__dict__, "_open": None}

    def _stores(self) -> list:
        if self._open is None or self._open[0] != os.getpid():
            from sceneforge.store import open_store

            self._open = (os.getpid(), [open_store(p) for p in self.index.stores])
        return self._open[1]

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return self.__getitems__([i])[0]

    def __getitems__(self, indices: Sequence[int]) -> Samples:
        """The samples ``indices``, each as ``dataset[i]`` gives it: the batch a DataLoader's
        (batch) sampler asks for, read at once (:meth:`batch`)."""
        return Samples(self.batch(indices))

    def batch(self, indices: Sequence[int]) -> dict[str, torch.Tensor]:
        """The samples ``indices`` stacked, (B, ...) per key: what the default collation of
        ``[dataset[i] for i in indices]`` gives. Each array the fields need is read once
        for the whole batch, one chunk per view straight from the shard files
        (:meth:`~sceneforge.store.reader.CheckedArray.views`), and the targets are made for
        the batch at once. The images (``rgb``) are channels-last in memory, as the nets
        read them."""
        indices = np.asarray(indices, dtype=np.int64).reshape(-1)
        stores = self.index.store[indices]
        parts = []
        for k in np.unique(stores):
            at = np.flatnonzero(stores == k)
            parts.append((at, self._read(self._stores()[int(k)], self.index.view[indices[at]])))
        if len(parts) == 1:
            out = parts[0][1]
        else:  # views of several stores: each store's rows back in the batch's order
            out = {}
            for key, first in parts[0][1].items():
                out[key] = np.empty((len(indices), *first.shape[1:]), dtype=first.dtype)
                for at, part in parts:
                    out[key][at] = part[key]
        return {"index": torch.from_numpy(indices), **{k: torch.from_numpy(v) for k, v in out.items()}}

    def _read(self, store, views: np.ndarray) -> dict[str, np.ndarray]:
        """The fields of ``views`` of one store as numpy arrays (B, ...)."""
        missing = [name for field in self.fields for name in SAMPLE_FIELDS[field] if name not in store.names]
        if missing:  # only the optional intersection layers can be: the index checked the rest
            raise SceneforgeError(f"{store.where}: the store has no {', '.join(missing)}, which the sample fields "
                                  f"{', '.join(self.fields)} read; render it with --intersections K")
        arrays: dict[str, np.ndarray] = {}

        def read(name: str) -> np.ndarray:  # each array once, whichever fields need it
            if name not in arrays:
                arrays[name] = store.array(name).views(views)
            return arrays[name]

        out: dict[str, np.ndarray] = {}
        if "rgb" in self.fields:
            out["rgb"] = normalize_rgb(read("rgb"))
        if "depth" in self.fields:
            out["depth"] = read("depth").astype(np.float32, copy=False)
        if "seg" in self.fields:
            out["seg"] = seg_targets(read("category"), read("depth"), EMPTY)
        if "overhead_height" in self.fields:
            height = read("overhead_height").astype(np.float32, copy=False)
            foreground = np.isfinite(height)
            # the overhead D5 is the floor: where it alone is hit, the height is 0
            floor = np.isfinite(read("overhead_depth")[:, 4])
            out["overhead_height"] = np.where(~foreground & floor, np.float32(0), height)
            out["overhead_foreground"] = foreground
        if "overhead_seg" in self.fields:
            nothing = np.isnan(read("overhead_depth")).all(axis=1)
            out["overhead_seg"] = segmentation_target(read("overhead_category"), nothing)
        if "camera" in self.fields:
            for name in SAMPLE_FIELDS["camera"]:
                out[name] = read(name).astype(np.float64, copy=False)
        if "intersections" in self.fields:
            depth = read("intersections/depth").astype(np.float32, copy=False)
            out["intersection_depth"] = depth
            out["intersection_valid"] = np.isfinite(depth)
        if "intersection_labels" in self.fields:
            out["intersection_instance"] = read("intersections/instance").astype(np.int64)
            out["intersection_category"] = read("intersections/category").astype(np.int64)
        if "intersection_normal" in self.fields:
            out["intersection_normal"] = read("intersections/normal").astype(np.float32, copy=False)
        if "intersection_front_facing" in self.fields:
            out["intersection_front_facing"] = read("intersections/front_facing").astype(bool, copy=False)
        return out
