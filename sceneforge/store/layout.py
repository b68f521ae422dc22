"""The store's layout, read from ``schemas/store.schema.json`` (every array's path, dtype,
shape, fill value, source and meaning), and what follows from it: the arrays a config's
store holds, their sizes, the group attributes a store starts with, and a view's entries
of the per-view arrays. Writer, reader and validator all take the layout from here.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from types import SimpleNamespace
from typing import TYPE_CHECKING

import numpy as np

from .. import conventions
from ..conventions import nyu40_table
from ..frustum import mesh_provenance

if TYPE_CHECKING:
    from ..cameras import Camera
    from ..config import DatasetConfig
    from ..view import ViewGroundTruth

SCHEMA_VERSION = "1.1"  # 1.1: the envelope mesh is the D5 surface (docs/spec.md §5.2), not envelope polygons
#: the two ground-truth meshes of a view, in the order the store keeps them
MESH_KINDS: tuple[str, ...] = ("objects", "envelope")
#: ragged mesh arrays: rows per chunk, and chunks per shard
MESH_CHUNK_ROWS = 1 << 16
MESH_SHARD_CHUNKS = 16
#: the manifest of a complete store: ``{"files": {key: SHA-256 or null}}`` of every shard
#: file (null: zarr wrote no file, every value is the fill value), written by ``finalize``
MANIFEST = "manifest.json"


@dataclass(frozen=True)
class ArraySpec:
    """One array of the layout (an entry of ``schemas/store.schema.json``).

    name        : path in the group, e.g. ``depth`` or ``mesh/objects/faces``
    dims        : symbolic shape: ``N`` views, ``H``/``W`` frontal image, ``Ho``/``Wo``
                  overhead image, ``L`` ray-intersection layers (``view.layers.intersections``), ``V``/``F`` mesh rows, ``N+1`` offsets, or a fixed size
    dtype       : numpy dtype name, or ``string`` for variable-length UTF-8
    fill        : value of a view that was not computed (per-view arrays)
    per_view    : the first axis is the view index (one view per chunk, sharded)
    optional    : the config field that switches the array on (``config.store.normals``), or
                  ``field=value`` when it has that value (``config.store.gt_mesh=all``); None
                  when always present
    description : what it holds
    source      : per-view arrays: where a written view's values come from, an attribute
                  path on :func:`view_arrays`' arguments (``gt.layers.depth``, ``house_id``)
    shuffle     : Blosc's shuffle for the array under the ``blosc-zstd-per-array`` codec:
                  ``shuffle`` (bytes), ``bitshuffle`` or ``noshuffle``, chosen by measurement
    """

    name: str
    dims: tuple
    dtype: str
    fill: object
    per_view: bool
    optional: str | None
    description: str
    source: str | None = None
    shuffle: str = "shuffle"

    def shape(self, sizes: dict[str, int]) -> tuple[int, ...]:
        """The concrete shape for ``sizes`` (``{"N": .., "H": .., ...}``)."""
        return tuple(d if isinstance(d, int) else sizes[d] for d in self.dims)

    @property
    def numpy_dtype(self):
        return np.dtypes.StringDType() if self.dtype == "string" else np.dtype(self.dtype)

    @property
    def fill_value(self):
        """The fill value as a Python scalar (NaN for ``"NaN"``)."""
        return float("nan") if self.fill == "NaN" else self.fill

    def blank(self, sizes: dict[str, int]) -> np.ndarray:
        """One view of fill values: shape ``dims[1:]``."""
        return np.full(self.shape(sizes)[1:], self.fill_value, dtype=self.numpy_dtype)


@lru_cache(maxsize=None)
def layout() -> dict[str, ArraySpec]:
    """Every array of the store layout, by path, in schema order."""
    from sceneforge import schemas

    props = schemas.load("store")["properties"]["arrays"]["properties"]
    return {
        name: ArraySpec(
            name=name,
            dims=tuple(p["x-dims"]),
            dtype=p["properties"]["dtype"]["const"],
            fill=p.get("x-fill"),
            per_view=p["$ref"].endswith("/per_view"),
            optional=p.get("x-optional"),
            description=p["description"],
            source=p.get("x-source"),
            shuffle=p.get("x-shuffle", "shuffle"),
        )
        for name, p in props.items()
    }


def _flag(config: "DatasetConfig", optional: str) -> bool:
    path, _, wanted = optional.partition("=")
    value = config
    for part in path.split(".")[1:]:
        value = getattr(value, part)
    return value == wanted if wanted else bool(value)


def array_specs(config: "DatasetConfig", per_view: bool | None = None) -> list[ArraySpec]:
    """The arrays a store written with ``config`` holds (``per_view`` filters on that kind)."""
    return [
        s for s in layout().values()
        if (s.optional is None or _flag(config, s.optional)) and (per_view is None or s.per_view == per_view)
    ]


def sizes_of(config: "DatasetConfig", n_views: int) -> dict[str, int]:
    """The symbolic dimensions of :class:`ArraySpec` for ``config`` and ``n_views`` views."""
    r = config.view.overhead.resolution
    return {"N": n_views, "N+1": n_views + 1, "H": config.height, "W": config.width, "Ho": r, "Wo": r,
            "L": config.view.layers.intersections}


def conventions_attrs() -> dict:
    """The conventions a store's arrays follow (docs/spec.md §1), as recorded in its attributes:
    :func:`sceneforge.conventions.record`, built from the constants that define them."""
    return conventions.record()


def base_attrs(config: "DatasetConfig", houses_source: str, n_views: int) -> dict:
    """Group attributes known when a store is created (``complete`` false, no houses yet)."""
    from sceneforge import __version__

    return {
        "schema_version": SCHEMA_VERSION,
        "package_version": __version__,
        "complete": False,
        "views": n_views,
        "houses_source": houses_source,
        "seed": config.seed,
        "config": config.to_dict(),
        "conventions": conventions_attrs(),
        "nyu40": nyu40_table(),
        # the rules of the views' ground-truth meshes, whether the store keeps them or not
        "ground_truth_mesh": mesh_provenance(config.view.mesh, config.width, config.height),
        "houses": [],
        "failures": [],
    }


def _source(root, path: str):
    """The value at attribute ``path`` (an :attr:`ArraySpec.source`) of ``root``; None when absent."""
    for part in path.split("."):
        root = getattr(root, part, None)
    return root


def view_arrays(gt: "ViewGroundTruth", rgb: np.ndarray | None, house_id: str, camera_id: int,
                config: "DatasetConfig") -> dict[str, np.ndarray]:
    """One view's entries of every per-view array (shapes without the view axis), each taken
    from where its layout entry's ``source`` says."""
    view = SimpleNamespace(gt=gt, rgb=rgb, house_id=house_id, camera_id=camera_id, valid=True)
    out = {}
    for spec in array_specs(config, per_view=True):
        value = _source(view, spec.source)
        if value is None:
            raise ValueError(f"{spec.name}: the view has no {spec.source}")
        out[spec.name] = np.asarray(value, dtype=spec.numpy_dtype)
    return out


def blank_view(camera: "Camera", house_id: str, camera_id: int, config: "DatasetConfig") -> dict[str, np.ndarray]:
    """The entries of a view whose ground truth failed: fill values, except what is known
    without it (the frontal camera and the ids)."""
    known = SimpleNamespace(gt=SimpleNamespace(camera=camera), house_id=house_id, camera_id=camera_id)
    sizes = sizes_of(config, 1)
    out = {}
    for spec in array_specs(config, per_view=True):
        value = _source(known, spec.source)
        out[spec.name] = spec.blank(sizes) if value is None else np.asarray(value, dtype=spec.numpy_dtype)
    return out
