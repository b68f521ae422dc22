"""The dataset store: a zarr v3 group written by ``sceneforge render`` (docs/spec.md §9).

The layout is defined once, in ``schemas/store.schema.json``: every array's path, dtype,
shape (``x-dims``), fill value, source (``x-source``) and meaning. This package reads that
table (:func:`layout`) to create, fill, read and check stores, so writer, reader and
validator cannot disagree.

- **Per-view arrays** have the view index first, one view per chunk, and
  ``config.store.views_per_shard`` views per shard file (zarr's sharding codec), each chunk
  compressed (Blosc + zstd by default, each array's own shuffle, one Blosc block per chunk).
  ``depth (N, 5, H, W) float32`` holds D1..D5 with NaN = no surface.
- **Ground-truth meshes** (objects and envelope apart; only with ``store.gt_mesh: all``) are
  ragged: the vertices, faces and face instances of all views concatenated in view order,
  with ``vertex_offsets`` and ``face_offsets (N + 1,)``; faces index the view's own vertex rows.
- **Group attributes** hold the schema and package versions, the resolved config, the seed,
  the conventions, the NYU40 table, per-house provenance and the failure log.

This package is the only one that touches zarr, one module per concern:

- :mod:`.layout`: the layout table (:func:`layout`), the arrays and attributes of a
  config's store, a view's entries of the per-view arrays;
- :mod:`.writer`: :class:`StoreWriter` writes a store (``sceneforge render`` and
  ``sceneforge predict`` both go through it) and records a manifest of every shard file's
  SHA-256 when it completes it;
- :mod:`.location`: where a store lives (a local folder, an S3 bucket, any fsspec
  URL), what that kind of place guarantees (atomic files, the lock's create-only and
  replace-if-unchanged writes) and how its errors read (one line each);
- :mod:`.lock`: :class:`StoreLock`, which the writer holds for the run;
- :mod:`.reader`: :func:`open_store` reads one with numpy only (no PyTorch);
  :func:`array_digests` fingerprints its contents;
- :mod:`.shards`: whole views of a per-view array read straight from its shard files, as
  zarr's sharding codec lays them out (what training reads, batch by batch, through
  ``store.array(name).views(rows)``);
- :mod:`.validate`: :func:`check_store` (and :func:`validate_store`) checks one against
  the schema, its manifest and for internal consistency;
- :mod:`.export`: :func:`export_exr`, a view as an OpenEXR file.

The names below are the package's interface; ``from sceneforge.store import open_store``.
"""


from __future__ import annotations

from .export import export_exr
from .layout import (
    MANIFEST,
    MESH_KINDS,
    SCHEMA_VERSION,
    ArraySpec,
    array_specs,
    base_attrs,
    blank_view,
    conventions_attrs,
    layout,
    sizes_of,
    view_arrays,
)
from .location import errors as location_errors
from .lock import StoreLock
from .reader import SceneStore, array_digests, open_store, reads_survive_fork
from .validate import StoreCheck, check_store, describe, validate_store
from .writer import StoreWriter, mesh_part, shard_key

__all__ = ["MANIFEST", "MESH_KINDS", "SCHEMA_VERSION", "ArraySpec", "SceneStore", "StoreCheck", "StoreLock",
           "StoreWriter", "array_digests", "array_specs", "base_attrs", "blank_view", "check_store",
           "conventions_attrs", "describe", "export_exr", "layout", "location_errors", "mesh_part", "open_store",
           "reads_survive_fork", "shard_key", "sizes_of", "validate_store", "view_arrays"]
