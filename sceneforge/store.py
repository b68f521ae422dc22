"""The dataset store: a zarr v3 group written by ``sceneforge render`` (SPEC §9).

The layout is defined once, in ``schemas/store.schema.json``: every array's path, dtype,
shape (``x-dims``), fill value, source (``x-source``) and meaning. This module reads that
table (:func:`layout`) to create, fill, read and check stores, so writer, reader and
validator cannot disagree.

- **Per-view arrays** have the view index first, one view per chunk, and
  ``config.store.views_per_shard`` views per shard file (zarr's sharding codec), each chunk
  compressed (Blosc + zstd by default). ``depth (N, 5, H, W) float32`` holds D1..D5 with NaN = no surface.
- **Ground-truth meshes** (objects and envelope apart) are ragged: the vertices, faces and
  face instances of all views concatenated in view order, with ``vertex_offsets`` and
  ``face_offsets (N + 1,)``; faces index the view's own vertex rows.
- **Group attributes** hold the schema and package versions, the resolved config, the seed,
  the conventions, the NYU40 table, per-house provenance and the failure log.

This module is the only one that touches zarr. :class:`StoreWriter` writes a store (``sceneforge
render`` and ``sceneforge predict`` both go through it), holding its lock (:class:`StoreLock`)
for the run, and records a manifest of every shard file's SHA-256 when it completes it;
:func:`open_store` reads one with numpy only (no PyTorch); :func:`check_store` (and
:func:`validate_store`) checks one against the schema, its manifest and for internal
consistency; :func:`array_digests` fingerprints its contents.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import socket
import sys
import time
import uuid
import warnings
from dataclasses import dataclass
from functools import lru_cache
from types import SimpleNamespace
from typing import TYPE_CHECKING, Iterable, Iterator

import numpy as np

from . import conventions
from .conventions import LAYER_NAMES, NYU40_NAMES, nyu40_table, tol
from .errors import MissingDependencyError, SceneforgeError, StoreLockedError
from .frustum import mesh_provenance

log = logging.getLogger(__name__)

if TYPE_CHECKING:
    import zarr

    from .cameras import Camera
    from .config import DatasetConfig
    from .view import ViewGroundTruth

SCHEMA_VERSION = "1.1"  # 1.1: the envelope mesh is the D5 surface (SPEC §5), not envelope polygons
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
                  overhead image, ``V``/``F`` mesh rows, ``N+1`` offsets, or a fixed size
    dtype       : numpy dtype name, or ``string`` for variable-length UTF-8
    fill        : value of a view that was not computed (per-view arrays)
    per_view    : the first axis is the view index (one view per chunk, sharded)
    optional    : the config flag that switches the array on, or None when always present
    description : what it holds
    source      : per-view arrays: where a written view's values come from, an attribute
                  path on :func:`view_arrays`' arguments (``gt.layers.depth``, ``house_id``)
    """

    name: str
    dims: tuple
    dtype: str
    fill: object
    per_view: bool
    optional: str | None
    description: str
    source: str | None = None

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
        )
        for name, p in props.items()
    }


def _flag(config: "DatasetConfig", path: str) -> bool:
    value = config
    for part in path.split(".")[1:]:
        value = getattr(value, part)
    return bool(value)


def array_specs(config: "DatasetConfig", per_view: bool | None = None) -> list[ArraySpec]:
    """The arrays a store written with ``config`` holds (``per_view`` filters on that kind)."""
    return [
        s for s in layout().values()
        if (s.optional is None or _flag(config, s.optional)) and (per_view is None or s.per_view == per_view)
    ]


def sizes_of(config: "DatasetConfig", n_views: int) -> dict[str, int]:
    """The symbolic dimensions of :class:`ArraySpec` for ``config`` and ``n_views`` views."""
    r = config.view.overhead.resolution
    return {"N": n_views, "N+1": n_views + 1, "H": config.height, "W": config.width, "Ho": r, "Wo": r}


def conventions_attrs() -> dict:
    """The conventions a store's arrays follow (SPEC §1), as recorded in its attributes:
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
        "ground_truth_mesh": (mesh_provenance(config.view.mesh, config.width, config.height)
                              if config.view.with_mesh else None),
        "houses": [],
        "failures": [],
    }


# ----------------------------------------------------------------------------- writing


def _compressor(config: "DatasetConfig"):
    """The configured compressor. Blosc shuffles by the array's item size (zarr sets it from
    the dtype), so single-byte arrays (RGB, masks) are compressed as plain zstd would."""
    from zarr.codecs import BloscCodec, ZstdCodec

    level = config.store.compression_level
    if config.store.codec == "zstd":
        return ZstdCodec(level=level)
    return BloscCodec(cname="zstd", clevel=level, shuffle="shuffle")


def create_arrays(group: "zarr.Group", config: "DatasetConfig", n_views: int) -> None:
    """(Re)create every per-view array of a store of ``n_views`` views, empty."""
    sizes = sizes_of(config, n_views)
    per_shard = config.store.views_per_shard
    for spec in array_specs(config, per_view=True):
        shape = spec.shape(sizes)
        group.create_array(
            spec.name, shape=shape, dtype=spec.numpy_dtype,
            chunks=(1, *shape[1:]), shards=(per_shard, *shape[1:]),
            compressors=_compressor(config), fill_value=spec.fill_value, overwrite=True,
        )


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


def shard_key(array: "zarr.Array", shard: int) -> str:
    """Store key of the object holding shard ``shard`` of a per-view array."""
    coords = (shard,) + (0,) * (array.ndim - 1)
    return f"{array.path}/{array.metadata.chunk_key_encoding.encode_chunk_key(coords)}"


def write_shard(arrays: dict[str, "zarr.Array"], start: int, views: list[dict[str, np.ndarray]]) -> None:
    """Write consecutive views ``start, start + 1, ...`` (whole shards) into the per-view arrays."""
    stop = start + len(views)
    for name, array in arrays.items():
        array[start:stop] = np.stack([v[name] for v in views])


class RowWriter:
    """Appends rows to a ragged array, writing each shard once, when it is full."""

    def __init__(self, array: "zarr.Array"):
        self.array, self.rows = array, array.shards[0]
        self.pending: list[np.ndarray] = []
        self.n_pending = 0
        self.written = 0

    def append(self, rows: np.ndarray) -> None:
        self.pending.append(rows)
        self.n_pending += len(rows)
        while self.n_pending >= self.rows:
            block = np.concatenate(self.pending)
            self._write(block[: self.rows])
            rest = block[self.rows:]
            self.pending, self.n_pending = [rest], len(rest)

    def close(self) -> None:
        if self.n_pending:
            self._write(np.concatenate(self.pending))
        if self.written != self.array.shape[0]:
            raise AssertionError(f"{self.array.path}: wrote {self.written} of {self.array.shape[0]} rows")

    def _write(self, block: np.ndarray) -> None:
        self.array[self.written: self.written + len(block)] = block
        self.written += len(block)


def write_meshes(group: "zarr.Group", config: "DatasetConfig", counts: np.ndarray,
                 parts: Iterable[dict[str, np.ndarray]]) -> None:
    """(Re)create the ragged mesh arrays and fill them from per-shard parts, in view order.

    counts : (N, 2, 2) int64  per view, per kind (objects, envelope): vertex and face counts
    parts  : dicts with ``<kind>_vertices (v, 3)``, ``<kind>_faces (f, 3)`` and
             ``<kind>_instance (f,)`` of consecutive views, concatenated
    """
    specs = layout()
    writers = {}
    for k, kind in enumerate(MESH_KINDS):
        offsets = np.zeros((len(counts) + 1, 2), dtype=np.int64)
        np.cumsum(counts[:, k], axis=0, out=offsets[1:])
        rows = {"V": int(offsets[-1, 0]), "F": int(offsets[-1, 1])}
        for j, name in enumerate(("vertex_offsets", "face_offsets")):
            group.create_array(f"mesh/{kind}/{name}", data=offsets[:, j].astype(specs[f"mesh/{kind}/{name}"].dtype),
                               chunks=(MESH_CHUNK_ROWS,), compressors=_compressor(config), overwrite=True)
        for name in ("vertices", "faces", "instance"):
            spec = specs[f"mesh/{kind}/{name}"]
            shape = spec.shape(rows)
            array = group.create_array(
                spec.name, shape=shape, dtype=spec.dtype, chunks=(MESH_CHUNK_ROWS, *shape[1:]),
                shards=(MESH_CHUNK_ROWS * MESH_SHARD_CHUNKS, *shape[1:]), compressors=_compressor(config),
                overwrite=True)
            writers[f"{kind}_{name}"] = RowWriter(array)
    for part in parts:
        for key, writer in writers.items():
            writer.append(part[key].astype(writer.array.dtype, copy=False))
    for writer in writers.values():
        writer.close()


def mesh_part(meshes: list) -> dict[str, np.ndarray]:
    """Concatenate the ground-truth meshes (:class:`~sceneforge.frustum.ViewMesh` or None for
    a failed view) of consecutive views into one part for :func:`write_meshes`.

    Returns the part plus ``counts (n, 2, 2) int64`` (per view, per kind: vertices, faces).
    """
    part: dict[str, list] = {f"{k}_{n}": [] for k in MESH_KINDS for n in ("vertices", "faces", "instance")}
    counts = np.zeros((len(meshes), 2, 2), dtype=np.int64)
    for i, mesh in enumerate(meshes):
        for k, kind in enumerate(MESH_KINDS):
            m = getattr(mesh, kind) if mesh is not None else None
            v = np.zeros((0, 3), np.float32) if m is None else np.asarray(m.vertices, np.float32)
            f = np.zeros((0, 3), np.int32) if m is None else np.asarray(m.faces, np.int32)
            inst = np.zeros(0, np.int32) if m is None else np.asarray(m.instance, np.int32)
            part[f"{kind}_vertices"].append(v)
            part[f"{kind}_faces"].append(f)
            part[f"{kind}_instance"].append(inst)
            counts[i, k] = len(v), len(f)
    out = {key: np.concatenate(arrays) for key, arrays in part.items()}
    out["counts"] = counts
    return out


class StoreWriter:
    """The one writer of a store, at a local path or an fsspec URL.

    ``create`` lays out the empty per-view arrays from the layout, ``write_shard`` fills one
    shard of them (one writer per shard: shards can be written in any order, by any
    process), ``write_meshes`` the ragged mesh arrays, and ``finalize`` records provenance
    with ``complete: true``; :func:`open_store` reads the result.

    Besides the arrays, a run may keep its own files in the store (``put``/``get`` by key,
    e.g. the render pipeline's staging folder): ``put`` is atomic (a temporary file renamed
    into place), so readers see all of a file or nothing.

    One run writes a store at a time: ``with StoreWriter(url) as writer:`` takes the store's
    lock (:class:`StoreLock`) for the block and releases it on any exit, exceptions and
    Ctrl-C included; a second run is refused with :class:`StoreLockedError` naming the
    holder. The writers of shard tasks in worker processes write under their run's lock
    and are not entered.

    url             : a local path or an fsspec URL (``memory://...``, ``s3://...``)
    storage_options : passed to fsspec and zarr
    """

    def __init__(self, url: str, storage_options: dict | None = None):
        try:
            import fsspec
        except ImportError as e:
            raise MissingDependencyError("fsspec", "the dataset store", "pip install sceneforge[store]") from e

        self.url = str(url)
        self.storage_options = storage_options or {}
        self.fs, root = fsspec.core.url_to_fs(self.url, **self.storage_options)
        self.root = root.rstrip("/")
        self.local = "file" in _protocols(self.fs)
        #: what zarr opens, and what a writer in another process is given: an absolute path
        #: for local files (zarr's LocalStore creates folders and writes atomically), else the URL
        self.zarr_url = self.root if self.local else self.url
        self._group = None
        self._arrays: dict[str, "zarr.Array"] = {}
        self._lock: StoreLock | None = None
        #: SHA-256 (hex, None for no file) of every shard file written through this writer
        self.files: dict[str, str | None] = {}

    def __repr__(self) -> str:
        return f"StoreWriter({self.url!r})"

    def __enter__(self) -> "StoreWriter":
        self._lock = StoreLock(self)
        self._lock.acquire()
        return self

    def __exit__(self, *exc) -> None:
        lock, self._lock = self._lock, None
        if lock is not None:
            lock.release()

    # ------------------------------------------------------------------------ the arrays

    def create(self, config: "DatasetConfig", houses_source: str, n_views: int, *, replace: bool = False) -> None:
        """(Re)create every per-view array of ``n_views`` views, empty, and the attributes
        known so far (:func:`base_attrs`, ``complete`` false).

        replace : first remove whatever the location holds (else arrays are recreated in place)
        """
        group = self._open("w" if replace else "a")
        create_arrays(group, config, n_views)
        group.attrs.put(base_attrs(config, houses_source, n_views))
        self._group, self._arrays = group, {}

    def write_shard(self, shard: int, views: list[dict[str, np.ndarray]]) -> list[str]:
        """Write the views of shard ``shard`` (views ``shard * views_per_shard, ...``, as
        :func:`view_arrays` gives them) into every per-view array they hold.

        The shard's files are removed first, so a shard torn by a kill is replaced, never
        patched. Returns the keys of those files (for :meth:`sha256`).
        """
        arrays = {name: self._array(name) for name in views[0]}
        keys = [shard_key(array, shard) for array in arrays.values()]
        for key in keys:
            self.rm(key)
        start = shard * next(iter(arrays.values())).shards[0]
        write_shard(arrays, start, views)
        self.files.update({key: self.sha256(key) for key in keys})
        return keys

    def resize(self, config: "DatasetConfig", n_views: int) -> None:
        """Give every per-view array ``n_views`` views, keeping the shards inside (a run
        that updates some houses of a store rewrites the shards whose views moved)."""
        sizes = sizes_of(config, n_views)
        for spec in array_specs(config, per_view=True):
            self._array(spec.name).resize(spec.shape(sizes))

    def write_meshes(self, config: "DatasetConfig", counts: np.ndarray, parts: Iterable[dict[str, np.ndarray]]) -> None:
        """(Re)create and fill the ragged mesh arrays (see :func:`write_meshes`)."""
        write_meshes(self._group_rw(), config, counts, parts)

    def finalize(self, config: "DatasetConfig", houses_source: str, n_views: int, *, houses: list[dict],
                 failures: list[dict], files: dict[str, str | None] | None = None, **extra) -> None:
        """Mark the store complete: :func:`base_attrs` with ``complete: true``, the houses'
        provenance, the failure log and ``extra`` attributes (e.g. ``prediction``), after
        writing the manifest (:data:`MANIFEST`): the SHA-256 of every shard file, as written
        (``files``: those written by other processes, e.g. the render pipeline's workers;
        with those written through this writer and the mesh arrays' files), so that
        :func:`validate_store` finds a file damaged, missing or left over later. Then remove
        the temporary files of writes cut short."""
        manifest = {**self.files, **(files or {})}
        for spec in array_specs(config, per_view=False):
            for key in self._chunk_files(spec.name):
                manifest[key] = self.sha256(key)
        data = json.dumps({"files": dict(sorted(manifest.items()))}, indent=0).encode()
        self.put(MANIFEST, data)
        attrs = base_attrs(config, houses_source, n_views)
        attrs.update(complete=True, houses=houses, failures=failures, **extra,
                     manifest={"file": MANIFEST, "files": len(manifest), "sha256": hashlib.sha256(data).hexdigest()})
        self._group_rw().attrs.put(attrs)
        self.remove_partials()

    def _chunk_files(self, name: str) -> list[str]:
        """Keys of the chunk (or shard) files array ``name`` has now."""
        prefix = self.path(f"{name}/c")
        if not self.fs.exists(prefix):
            return []
        return sorted(p[len(self.root) + 1:] for p in self.fs.find(prefix))

    def mark_incomplete(self) -> None:
        """Set ``complete`` false (a run starts changing a complete store)."""
        self._group_rw().attrs["complete"] = False

    def attrs(self) -> dict:
        """The group attributes of the store there now."""
        return self._open("r").attrs.asdict()

    def _open(self, mode: str) -> "zarr.Group":
        try:
            import zarr
        except ImportError as e:
            raise MissingDependencyError("zarr", "the dataset store", "pip install sceneforge[store]") from e
        return zarr.open_group(self.zarr_url, mode=mode,
                               storage_options=None if self.local else self.storage_options or None)

    def _group_rw(self) -> "zarr.Group":
        if self._group is None:
            self._group = self._open("r+")
        return self._group

    def _array(self, name: str) -> "zarr.Array":
        if name not in self._arrays:
            self._arrays[name] = self._group_rw()[name]
        return self._arrays[name]

    # ------------------------------------------------------------------------- the files

    def path(self, key: str) -> str:
        return f"{self.root}/{key}"

    def exists(self, key: str = "") -> bool:
        """Something is at ``key`` (at the store's location when ``key`` is empty)."""
        return self.fs.exists(self.path(key) if key else self.root)

    def is_file(self) -> bool:
        """The store's location is a file (not a folder)."""
        return self.exists() and self.fs.isfile(self.root)

    def is_empty(self) -> bool:
        """Nothing is at the store's location, or an empty folder."""
        return not self.exists() or (not self.fs.isfile(self.root) and not self.fs.ls(self.root))

    def put(self, key: str, data: bytes) -> None:
        """Write ``data`` to ``key`` so that readers see all of it or nothing."""
        path = self.path(key)
        tmp = f"{path}.{uuid.uuid4().hex}.partial"
        self.fs.makedirs(path.rsplit("/", 1)[0], exist_ok=True)
        self.fs.pipe_file(tmp, data)
        self.fs.mv(tmp, path)

    def get(self, key: str) -> bytes | None:
        """The bytes at ``key``, or None when there is no such file."""
        try:
            return self.fs.cat_file(self.path(key))
        except FileNotFoundError:
            return None

    def put_json(self, key: str, doc) -> None:
        self.put(key, json.dumps(doc).encode())

    def get_json(self, key: str):
        """The JSON at ``key``, or None when it is missing or torn (a write cut by power loss)."""
        data = self.get(key)
        if data is None:
            return None
        try:
            return json.loads(data)
        except ValueError:
            return None

    def sha256(self, key: str) -> str | None:
        """SHA-256 of the file at ``key`` (hex), or None when there is none."""
        data = self.get(key)
        return None if data is None else hashlib.sha256(data).hexdigest()

    def rm(self, key: str) -> None:
        """Remove ``key`` and everything under it (the whole store when ``key`` is empty)."""
        with contextlib.suppress(FileNotFoundError):
            self.fs.rm(self.path(key), recursive=True)

    def remove_partials(self) -> None:
        """Remove the temporary files of writes cut short (:meth:`put`'s and zarr's LocalStore's)."""
        if self.local:
            for path in self.fs.find(self.root):
                if path.endswith(".partial"):
                    self.fs.rm(path)


class StoreLock:
    """The lock of a store: a file beside it (``OUT.zarr.lock``) naming the process that
    writes it (pid, host, process start time, command line).

    A lock whose process is gone (same host, and no process with that pid and start time:
    killed with SIGKILL, or the machine rebooted) is taken over with a warning on the
    ``sceneforge.store`` logger. On a local filesystem the lock file is created atomically
    (a hard link that fails when the file exists); on other fsspec filesystems (object
    stores) it is checked, then written, which leaves a short window for two runs started
    at the same moment.
    """

    def __init__(self, writer: "StoreWriter"):
        self.writer = writer
        self.path = f"{writer.root}.lock"
        self.me = {"pid": os.getpid(), "host": socket.gethostname(), "started": _process_start(os.getpid()),
                   "since": time.strftime("%Y-%m-%d %H:%M:%S"),
                   "command": " ".join([os.path.basename(sys.argv[0]), *sys.argv[1:]])}

    def acquire(self) -> None:
        """Take the lock; raises :class:`StoreLockedError` while a live process holds it."""
        data = json.dumps(self.me).encode()
        for _ in range(5):
            if self._create(data):
                return
            holder = self._read()
            if holder is None:  # being written right now, or torn by a crash while written
                time.sleep(0.2)
                holder = self._read()
            if holder is not None and _alive(holder):
                elsewhere = "" if holder.get("host") == self.me["host"] else f"; if that run is gone, delete {self.path}"
                raise StoreLockedError(
                    f"{self.writer.url}: another run is writing this store ({_describe(holder)}); wait for it to "
                    f"end, or write elsewhere{elsewhere}")
            if self._take_over(holder):
                log.warning("%s: took over the lock of a run that is no longer running (%s)", self.writer.url,
                            "a torn lock file" if holder is None else _describe(holder))
        raise StoreLockedError(f"{self.writer.url}: cannot take the lock {self.path}: other runs keep taking it")

    def release(self) -> None:
        """Remove the lock file, if it is still this process's."""
        holder = self._read()
        if holder is not None and holder.get("pid") == self.me["pid"] and holder.get("host") == self.me["host"]:
            with contextlib.suppress(FileNotFoundError):
                self.writer.fs.rm(self.path)

    def _create(self, data: bytes) -> bool:
        fs = self.writer.fs
        fs.makedirs(self.path.rsplit("/", 1)[0] or "/", exist_ok=True)
        if not self.writer.local:
            if fs.exists(self.path):
                return False
            fs.pipe_file(self.path, data)
            return True
        tmp = f"{self.path}.{uuid.uuid4().hex}.partial"
        with open(tmp, "wb") as f:
            f.write(data)
        try:
            os.link(tmp, self.path)
            return True
        except FileExistsError:
            return False
        finally:
            os.unlink(tmp)

    def _read(self) -> dict | None:
        try:
            return json.loads(self.writer.fs.cat_file(self.path))
        except (FileNotFoundError, ValueError):
            return None

    def _take_over(self, stale: dict | None) -> bool:
        """Remove the stale lock ``stale`` unless another process replaced it meanwhile;
        True when it was removed (by this process or another)."""
        fs = self.writer.fs
        aside = f"{self.path}.{uuid.uuid4().hex}.stale"
        try:
            fs.mv(self.path, aside)
        except FileNotFoundError:
            return False
        try:
            moved = json.loads(fs.cat_file(aside))
        except ValueError:
            moved = None
        if moved != stale:  # a live run's fresh lock, taken between the read and the move: put it back
            fs.mv(aside, self.path)
            return False
        fs.rm(aside)
        return True


def _process_start(pid: int) -> str | None:
    """When process ``pid`` started, as an opaque string (boot id and start tick on Linux;
    None where /proc does not tell), so that a pid reused by a later process is not mistaken
    for the holder of a lock."""
    try:
        with open("/proc/sys/kernel/random/boot_id") as f:
            boot = f.read().strip()
        with open(f"/proc/{pid}/stat") as f:
            stat = f.read()
        return f"{boot}:{stat.rsplit(')', 1)[1].split()[19]}"
    except (OSError, IndexError):
        return None


def _alive(holder: dict) -> bool:
    """The process that wrote lock ``holder`` is still running (assumed so on another host)."""
    if holder.get("host") != socket.gethostname():
        return True
    pid = int(holder.get("pid", -1))
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # alive, another user's
    started = holder.get("started")
    return started is None or _process_start(pid) in (None, started)


def _describe(holder: dict) -> str:
    command = holder.get("command") or "?"
    return f"pid {holder.get('pid')} on {holder.get('host')}, since {holder.get('since')}: {command}"


def _protocols(fs) -> tuple[str, ...]:
    p = fs.protocol
    return (p,) if isinstance(p, str) else tuple(p)



# ----------------------------------------------------------------------------- reading


def _open_group(path: str, mode: str = "r", storage_options: dict | None = None) -> "zarr.Group":
    try:
        import zarr
    except ImportError as e:
        raise MissingDependencyError("zarr", "the dataset store", "pip install sceneforge[store]") from e
    try:
        return zarr.open_group(str(path), mode=mode, storage_options=storage_options)
    except (FileNotFoundError, zarr.errors.GroupNotFoundError, NotADirectoryError):
        raise SceneforgeError(f"{path}: no zarr store there") from None


class SceneStore:
    """A store opened for reading; numpy arrays out, no PyTorch.

    ``store.view(i)`` gives one view's entries of every per-view array (``rgb (H, W, 3)
    uint8``, ``depth (5, H, W) float32``, ..., ``house_id`` and ``camera_id`` as 0-d
    arrays); ``store.mesh(i)`` its ground-truth meshes; ``store.array(name)`` a lazily sliced
    zarr array; ``store.attrs`` the group attributes (config, provenance, failure log).
    """

    def __init__(self, group: "zarr.Group"):
        self.group = group
        self.attrs: dict = group.attrs.asdict()
        self._arrays: dict[str, "zarr.Array"] = {}
        present = {name for name, _ in _arrays_of(group)}
        self.names: tuple[str, ...] = tuple(s.name for s in layout().values() if s.per_view and s.name in present)
        self.has_mesh = all(f"mesh/{k}/vertices" in present for k in MESH_KINDS)

    def __len__(self) -> int:
        return int(self.attrs["views"])

    def __repr__(self) -> str:
        return f"SceneStore({self.group.store}, {len(self)} views)"

    @property
    def config(self) -> "DatasetConfig":
        """The resolved config the store was written with."""
        from .config import DatasetConfig

        return DatasetConfig.from_dict(self.attrs["config"], what=f"{self.group.store} config", recorded=True)

    def array(self, name: str) -> "zarr.Array":
        """The zarr array ``name`` (e.g. ``depth`` or ``mesh/objects/vertices``), for lazy slicing."""
        if name not in self._arrays:
            if name not in layout():
                raise KeyError(f"no array {name!r} in the store layout; per-view arrays: {', '.join(self.names)}")
            self._arrays[name] = self.group[name]
        return self._arrays[name]

    def _index(self, i: int) -> int:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"view {i} out of range for a store of {n} views")
        return int(i) % n

    def view(self, i: int) -> dict[str, np.ndarray]:
        """Every per-view array's entry for view ``i``."""
        i = self._index(i)
        out = {name: np.asarray(self.array(name)[i]) for name in self.names}
        out["house_id"] = np.asarray(str(out["house_id"]))
        return out

    def mesh(self, i: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """View ``i``'s ground-truth meshes: ``{"objects": (vertices (v, 3) float32,
        faces (f, 3) int32), "envelope": (...)}``, faces indexing those vertices."""
        if not self.has_mesh:
            raise SceneforgeError("this store has no ground-truth meshes (config view.with_mesh was false)")
        i = self._index(i)
        out = {}
        for kind in MESH_KINDS:
            v0, v1 = self.array(f"mesh/{kind}/vertex_offsets")[i: i + 2]
            f0, f1 = self.array(f"mesh/{kind}/face_offsets")[i: i + 2]
            out[kind] = (self.array(f"mesh/{kind}/vertices")[v0:v1], self.array(f"mesh/{kind}/faces")[f0:f1])
        return out


@contextlib.contextmanager
def _own_files_ignored() -> Iterator[None]:
    """Listing a group's members: the store's own files (the manifest, the staging folder
    of a run in progress) are not zarr nodes, which zarr warns about."""
    import zarr

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", zarr.errors.ZarrUserWarning)
        yield


def _arrays_of(group: "zarr.Group") -> Iterator[tuple[str, "zarr.Array"]]:
    import zarr

    with _own_files_ignored():
        members = list(group.members(max_depth=None))
    for path, node in members:
        if isinstance(node, zarr.Array):
            yield path, node


def reads_survive_fork() -> bool:
    """Whether a process forked from one that has read a store can read stores itself: zarr
    drops its IO thread's event loop in a forked child (``reset_resources_after_fork``, zarr
    3.0.x on); before, the child waits for ever on the parent's loop, whose thread it lacks."""
    try:
        from zarr.core import sync
    except ImportError:
        return False
    return hasattr(sync, "reset_resources_after_fork")


def open_store(path: str, storage_options: dict | None = None, *, allow_incomplete: bool = False) -> SceneStore:
    """Open the store at ``path`` (a local path or an fsspec URL) for reading.

    Raises :class:`SceneforgeError` when there is no sceneforge store there, or when the run
    that writes it has not finished (unless ``allow_incomplete``).
    """
    group = _open_group(path, "r", storage_options)
    if "schema_version" not in group.attrs:
        raise SceneforgeError(f"{path}: not a sceneforge store (no schema_version attribute)")
    if not group.attrs.get("complete") and not allow_incomplete:
        raise SceneforgeError(
            f"{path}: the store is incomplete (a render run is in progress or was interrupted); "
            "run the same command again to finish it"
        )
    return SceneStore(group)


# ---------------------------------------------------------------------------- checking


def describe(group: "zarr.Group") -> dict:
    """The document ``schemas/store.schema.json`` validates: attributes and array metadata."""
    arrays = {}
    for path, array in _arrays_of(group):
        codecs = []
        for codec in array.metadata.codecs:
            codecs.append(codec.to_dict()["name"])
            codecs += [c.to_dict()["name"] for c in getattr(codec, "codecs", ())]
        arrays[path] = {
            "shape": list(array.shape),
            "dtype": array.metadata.data_type.to_json(zarr_format=3),
            "chunks": list(array.chunks),
            "shards": list(array.shards) if array.shards else None,
            "codecs": codecs,
        }
    return {"attributes": group.attrs.asdict(), "arrays": arrays}


@dataclass
class StoreCheck:
    """What :func:`check_store` found.

    kind     : ``"dataset"`` (written by render) or ``"prediction"`` (by predict)
    problems : one line each, most telling first (empty: valid)
    notes    : what was not checked, and why
    """

    path: str
    kind: str
    views: int
    complete: bool
    problems: list[str]
    notes: list[str]

    @property
    def valid(self) -> bool:
        return not self.problems

    def summary(self) -> str:
        """One line: valid, incomplete, or how many problems."""
        if not self.complete:
            return (f"{self.path}: incomplete: a run writing it is in progress or was interrupted; run the same "
                    "command again to finish it")
        what = f"{self.kind} store, {self.views} view{'s' if self.views != 1 else ''}"
        if self.valid:
            return f"{self.path}: valid ({what})"
        n = len(self.problems)
        return f"{self.path}: invalid, {n} problem{'s' if n != 1 else ''} ({what})"


def validate_store(path: str, storage_options: dict | None = None) -> list[str]:
    """Every problem of the store at ``path`` (empty = valid): :func:`check_store`'s."""
    return check_store(path, storage_options).problems


def check_store(path: str, storage_options: dict | None = None) -> StoreCheck:
    """Check the store at ``path`` for what a reader relies on.

    - the schema and layout (arrays, shapes, chunks, attributes), and that it is complete
      (an incomplete store is reported as that one problem);
    - its files: every file of the manifest present with the SHA-256 recorded when it was
      written (a shard that is all fill values has no file, which the manifest records),
      none that the run did not write, no staging folder or temporary files left;
    - every shard decodable;
    - the attributes consistent with the arrays (view ranges, ids, the failure log);
    - content: cameras finite and rigid, classes in 0..40, failed views blank; in a dataset
      store also the ground-truth rules (M1 = M2, M3 = M4, D3 only after D1, depths
      ordered and >= 0, classes and instances set exactly where a layer is), which a
      prediction store does not follow (noted, not checked);
    - meshes: offsets from 0 to the row counts, faces within their view's vertices,
      non-empty, non-degenerate meshes where the view has layers.
    Raises :class:`SceneforgeError` when there is no store at ``path``.
    """
    from sceneforge import schemas

    from .config import DatasetConfig

    group = _open_group(path, "r", storage_options)
    doc = describe(group)
    attrs = doc["attributes"]
    kind = "prediction" if "prediction" in attrs else "dataset"
    n = attrs.get("views", 0) if isinstance(attrs.get("views"), int) else 0
    check = StoreCheck(str(path), kind, n, bool(attrs.get("complete", True)), [], [])
    check.problems += schemas.errors(doc, "store")
    if check.problems:
        return check
    if not check.complete:
        check.problems.append("incomplete: a run writing it is in progress or was interrupted; run the same "
                              "command again to finish it")
        return check
    try:
        config = DatasetConfig.from_dict(attrs["config"], what="config attribute", recorded=True)
    except SceneforgeError as e:
        check.problems.append(str(e))
        return check
    check.problems += _check_layout(doc["arrays"], config, n)
    check.problems += _check_attrs(attrs, n)
    if check.problems:
        return check
    files = StoreWriter(str(path), storage_options)
    check.problems += _check_files(files, attrs, config, check.notes)
    store = SceneStore(group)
    problems, layers = _check_views(store, config, kind == "prediction", check.notes)
    check.problems += problems
    if store.has_mesh:
        check.problems += _check_meshes(store, layers)
    return check


def _check_files(files: "StoreWriter", attrs: dict, config: "DatasetConfig", notes: list[str]) -> list[str]:
    """The store's files against its manifest; what a run leaves behind."""
    problems = []
    if files.exists("_staging"):
        problems.append("_staging/: a run's staging folder is left in a complete store (a second run wrote "
                        "into it, or it was copied while a run was writing)")
    if files.local:
        partial = [p for p in files.fs.find(files.root) if p.endswith(".partial")]
        if partial:
            problems.append(f"{len(partial)} temporary file(s) of writes cut short (*.partial)")
    record = attrs.get("manifest")
    if record is None:
        notes.append("no manifest (a store written before sceneforge recorded one): file hashes not checked")
        return problems
    data = files.get(record["file"])
    if data is None or hashlib.sha256(data).hexdigest() != record["sha256"]:
        return problems + [f"{record['file']}: {'missing' if data is None else 'not the one written with the store'}"]
    manifest = json.loads(data)["files"]
    missing, damaged, unexpected = [], [], []
    for key, digest in manifest.items():
        now = files.sha256(key)
        if now != digest:
            (missing if now is None else unexpected if digest is None else damaged).append(key)
    listed = set(manifest)
    for spec in array_specs(config):
        unexpected += [key for key in files._chunk_files(spec.name) if key not in listed]
    for what, keys in (("missing (written by the run, gone since)", missing),
                       ("damaged (not the bytes written: truncated or changed)", damaged),
                       ("not written by the run", unexpected)):
        if keys:
            shown = ", ".join(sorted(keys)[:5]) + (f" and {len(keys) - 5} more" if len(keys) > 5 else "")
            problems.append(f"{len(keys)} file(s) {what}: {shown}")
    return problems


def _check_layout(arrays: dict, config: "DatasetConfig", n: int) -> list[str]:
    problems = []
    sizes = sizes_of(config, n)
    expected = {s.name: s for s in array_specs(config)}
    for name in sorted(set(arrays) - set(expected)):
        problems.append(f"{name}: not expected with this config")
    for name, spec in expected.items():
        meta = arrays.get(name)
        if meta is None:
            problems.append(f"{name}: missing")
            continue
        shape = tuple(meta["shape"])
        if spec.per_view:
            want = spec.shape(sizes)
            if shape != want:
                problems.append(f"{name}: shape {shape}, expected {want} {spec.dims}")
            if tuple(meta["chunks"]) != (1, *want[1:]):
                problems.append(f"{name}: chunks {meta['chunks']}, expected one view per chunk")
            if meta["shards"][0] != config.store.views_per_shard:
                problems.append(f"{name}: {meta['shards'][0]} views per shard, config says "
                                f"{config.store.views_per_shard}")
        elif spec.dims == ("N+1",) and shape != (n + 1,):
            problems.append(f"{name}: shape {shape}, expected ({n + 1},)")
        elif len(shape) != len(spec.dims) or any(isinstance(d, int) and d != s for d, s in zip(spec.dims, shape)):
            problems.append(f"{name}: shape {shape} does not match {spec.dims}")
    return problems


def _check_attrs(attrs: dict, n: int) -> list[str]:
    problems = []
    if attrs["nyu40"] != nyu40_table():
        problems.append("nyu40: the label table differs from this sceneforge's")
    spans = [tuple(h["views"]) for h in attrs["houses"] if h["status"] == "ok"]
    covered = sum(b - a for a, b in spans)
    if sorted(spans) != spans or any(a2 != b1 for (_, b1), (a2, _) in zip(spans, spans[1:])) or covered != n:
        problems.append(f"houses: view ranges {spans} do not tile the {n} views in order")
    ids = {h["id"] for h in attrs["houses"]}
    for f in attrs["failures"]:
        if f["house"] not in ids:
            problems.append(f"failures: house {f['house']!r} is not in the houses list")
    return problems


def _rigid_problems(T: np.ndarray) -> np.ndarray:
    """(n,) bool: the (n, 4, 4) poses that are not finite rigid transforms."""
    R = T[:, :3, :3]
    bad = ~np.isfinite(T).all(axis=(1, 2))
    with np.errstate(invalid="ignore"):
        bad |= ~np.isclose(np.einsum("nji,njk->nik", R, R), np.eye(3), atol=tol.rotation).all(axis=(1, 2))
        bad |= np.linalg.det(np.where(np.isfinite(R), R, 0)) < 0
    bad |= ~(T[:, 3] == [0, 0, 0, 1]).all(axis=1)
    return bad


def _per_view(mask: np.ndarray) -> np.ndarray:
    """(n,) bool: the views of an (n, ...) mask with any pixel set."""
    return mask.reshape(len(mask), -1).any(axis=1)


class _Findings:
    """Views found breaking each rule, reported as one line per rule over the whole store."""

    def __init__(self):
        self.views: dict[str, list[int]] = {}

    def add(self, rule: str, bad: np.ndarray, start: int) -> None:
        hits = np.flatnonzero(bad)
        if len(hits):
            self.views.setdefault(rule, []).extend(int(start + i) for i in hits)

    def lines(self) -> list[str]:
        out = []
        for rule, views in self.views.items():
            shown = ", ".join(map(str, views[:5])) + (", ..." if len(views) > 5 else "")
            out.append(f"{rule}: {len(views)} view{'s' if len(views) != 1 else ''} ({shown})")
        return out


def _check_views(store: SceneStore, config: "DatasetConfig", prediction: bool,
                 notes: list[str]) -> tuple[list[str], np.ndarray | None]:
    """The problems of the per-view arrays, and per view whether D1 and D5 are set
    (``(n, 2) bool``, what :func:`_check_meshes` expects meshes for; None for predictions
    or when a shard cannot be read)."""
    problems, layers = [], []
    spans = {h["id"]: h["views"] for h in store.attrs["houses"] if h["status"] == "ok"}
    failed_views = {f["view"] for f in store.attrs["failures"] if f["stage"] == "view"}
    step = config.store.views_per_shard
    n_classes = len(NYU40_NAMES)
    found = _Findings()
    report = found.add
    if prediction:
        notes.append("a prediction store: the ground-truth rules (layer masks and order, instances) do not "
                     "apply and were not checked")

    for start in range(0, len(store), step):
        stop = min(start + step, len(store))
        a, broken = {}, False
        for name in store.names:
            try:
                a[name] = store.array(name)[start:stop]
            except Exception as e:  # a damaged shard: zarr's codecs raise many kinds
                problems.append(f"{name}: shard {start // step} (views {start}-{stop - 1}) cannot be decoded "
                                f"({type(e).__name__}: {e})")
                broken = True
        if broken:
            layers.append(np.zeros((stop - start, 2), bool))  # unknown: no mesh required
            continue
        valid = a["valid"]
        owners = np.array([(span := spans.get(str(hid))) is None or not span[0] <= start + i < span[1]
                           for i, hid in enumerate(a["house_id"])])
        report("house_id is not the house whose view range holds the view", owners, start)
        logged = np.array([(start + i) in failed_views for i in range(stop - start)])
        report("valid disagrees with the failure log", valid.astype(bool) == logged, start)
        report("camera_id < 0", a["camera_id"] < 0, start)
        K = a["K"]
        report("K is not finite with positive focal lengths",
               ~np.isfinite(K).all(axis=(1, 2)) | ~(K[:, 0, 0] > 0) | ~(K[:, 1, 1] > 0), start)
        report("cam_to_world is not a rigid transform", _rigid_problems(a["cam_to_world"]), start)
        v = valid.astype(bool)
        report("overhead_cam_to_world is not a rigid transform", v & _rigid_problems(a["overhead_cam_to_world"]),
               start)
        report("overhead_extent is not > 0", v & ~(a["overhead_extent"] > 0), start)
        d, cat = a["depth"], a["category"]
        f = np.isfinite(d)
        report("a class outside 0..40", _per_view(cat >= n_classes) | _per_view(a["overhead_category"] >= n_classes),
               start)
        od = a["overhead_depth"]
        fo = np.isfinite(od)
        report("a failed view holds data", ~v & (_per_view(f) | _per_view(fo)), start)
        if "rgb" in a:
            report("a failed view holds an RGB image", ~v & _per_view(a["rgb"] != 0), start)
        if prediction:
            continue
        inst = a["instance"]
        report("D1 and D2 are not set on the same pixels (M1 != M2)", _per_view(f[:, 0] != f[:, 1]), start)
        report("D3 and D4 are not set on the same pixels (M3 != M4)", _per_view(f[:, 2] != f[:, 3]), start)
        report("D3 is set where D1 is not", _per_view(f[:, 2] & ~f[:, 0]), start)
        with np.errstate(invalid="ignore"):
            report("negative depth", _per_view(d < 0), start)
            report("D2 before D1", _per_view(d[:, 1] < d[:, 0] - tol.stored_depth), start)
            report("D4 before D3", _per_view(d[:, 3] < d[:, 2] - tol.stored_depth), start)
            report("D3 before D2", _per_view(d[:, 2] < d[:, 1] - tol.same_instance_hit - tol.stored_depth), start)
            report("an object layer behind D5", _per_view(d[:, :4] > d[:, 4:] + tol.envelope_slack + tol.stored_depth),
                   start)
        for k, layer in ((0, 0), (1, 2), (2, 4)):
            report(f"category of {LAYER_NAMES[layer]} set where {LAYER_NAMES[layer]} is NaN",
                   _per_view(~f[:, layer] & (cat[:, k] != 0)), start)
        for k, layer in ((0, 0), (1, 2)):
            report(f"instance of {LAYER_NAMES[layer]} is not set exactly where {LAYER_NAMES[layer]} is",
                   _per_view(f[:, layer] != (inst[:, k] >= 0)), start)
        report("overhead: D1 and D2 are not set on the same pixels", _per_view(fo[:, 0] != fo[:, 1]), start)
        report("overhead_height is not set exactly where overhead D1 is",
               _per_view(np.isfinite(a["overhead_height"]) != fo[:, 0]), start)
        # what a ground-truth mesh must hold: objects wherever D1 is, the envelope wherever D5 is
        layers.append(np.stack([_per_view(f[:, 0]), _per_view(f[:, 4])], axis=1))
    complete = not prediction and sum(map(len, layers)) == len(store)
    return problems + found.lines(), np.concatenate(layers) if complete and layers else None


def _check_meshes(store: SceneStore, layers: np.ndarray | None) -> list[str]:
    problems = []
    found = _Findings()
    for kind in MESH_KINDS:
        try:
            vo = store.array(f"mesh/{kind}/vertex_offsets")[:]
            fo = store.array(f"mesh/{kind}/face_offsets")[:]
        except Exception as e:
            problems.append(f"mesh/{kind}: the offsets cannot be decoded ({type(e).__name__}: {e})")
            continue
        nv, nf = store.array(f"mesh/{kind}/vertices").shape[0], store.array(f"mesh/{kind}/faces").shape[0]
        bad_offsets = False
        for name, off, total in (("vertex_offsets", vo, nv), ("face_offsets", fo, nf)):
            if off[0] != 0 or off[-1] != total or (np.diff(off) < 0).any():
                problems.append(f"mesh/{kind}/{name}: not non-decreasing from 0 to {total}")
                bad_offsets = True
        if bad_offsets:
            continue
        vertices, faces = store.array(f"mesh/{kind}/vertices"), store.array(f"mesh/{kind}/faces")
        for start in range(0, len(store), 4096):
            stop = min(start + 4096, len(store))
            try:
                f = np.asarray(faces[fo[start]:fo[stop]])
                v = np.asarray(vertices[vo[start]:vo[stop]])
            except Exception as e:
                problems.append(f"mesh/{kind}: views {start}-{stop - 1} cannot be decoded ({type(e).__name__}: {e})")
                continue
            owner = np.repeat(np.arange(start, stop), np.diff(fo[start:stop + 1]))
            limit = (vo[owner + 1] - vo[owner])[:, None]
            outside = ((f < 0) | (f >= limit)).any(axis=1)
            found.add(f"mesh/{kind}/faces: face indices outside the view's vertices",
                      np.bincount(owner[outside] - start, minlength=stop - start) > 0, start)
            if layers is None:
                continue
            # faces index their view's rows: shift them to rows of this block's vertices
            rows = np.where(outside[:, None], 0, f + (vo[owner] - vo[start])[:, None])
            tri = v[rows] if len(v) else np.zeros((len(f), 3, 3), np.float32)
            area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
            solid = np.bincount(owner[area2 > 0] - start, minlength=stop - start) > 0
            what = "D1" if kind == "objects" else "D5"
            found.add(f"mesh/{kind}: empty or degenerate (zero-area faces only) in a view whose {what} is set",
                      layers[start:stop, 0 if kind == "objects" else 1] & ~solid, start)
        try:
            negative = (store.array(f"mesh/{kind}/instance")[:] < 0).any()
        except Exception as e:
            problems.append(f"mesh/{kind}/instance: cannot be decoded ({type(e).__name__}: {e})")
            continue
        if negative:
            problems.append(f"mesh/{kind}/instance: negative instance index")
    return problems + found.lines()


def array_digests(path: str, storage_options: dict | None = None) -> dict[str, str]:
    """SHA-256 (hex) of every array of the store at ``path``, meshes included, by path in the
    group: of its decoded values with their dtype and shape, so equal digests mean equal
    contents however zarr laid out the chunks. Attributes are left out (they hold the
    package version)."""
    return _digests(_open_group(path, "r", storage_options))


def _digests(group: "zarr.Group") -> dict[str, str]:
    out = {}
    with _own_files_ignored():
        arrays, groups = sorted(group.arrays()), sorted(group.groups())
    for name, array in arrays:
        data = np.asarray(array[...])
        h = hashlib.sha256()
        h.update(f"{data.dtype.str}{data.shape}".encode())
        h.update(np.ascontiguousarray(data).tobytes() if data.dtype != object else repr(data.tolist()).encode())
        out[name] = h.hexdigest()
    for name, sub in groups:
        out.update({f"{name}/{key}": digest for key, digest in _digests(sub).items()})
    return out


# ----------------------------------------------------------------------------- export


def _srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    c = rgb.astype(np.float32) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def export_exr(store: SceneStore, index: int, path) -> None:
    """Write view ``index`` as a two-part OpenEXR file (OpenEXR >= 3.2 Python API).

    Part ``frontal`` (H × W): float channels ``D1``..``D5`` (planar depth, metres, NaN = no
    surface) and, with RGB, linear ``R``, ``G``, ``B``. Part ``overhead`` (Ho × Wo):
    ``height`` and ``D1``..``D5``. Headers carry ``K`` (3×3), ``cam_to_world`` (4×4, OpenCV
    axes), ``house_id``, ``camera_id`` and ``view``; the overhead part also
    ``overhead_cam_to_world``, ``overhead_extent`` and ``tx ty tz theta sigma``.
    """
    try:
        import OpenEXR
    except ImportError as e:
        raise MissingDependencyError("OpenEXR", "EXR export", "pip install sceneforge[store]") from e

    v = store.view(index)
    H, W = v["depth"].shape[1:]
    Ho, Wo = v["overhead_height"].shape
    # parts of one file share the display window; each keeps its own data window
    display = (np.array([0, 0], np.int32), np.array([max(W, Wo) - 1, max(H, Ho) - 1], np.int32))
    common = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, "displayWindow": display,
              "house_id": str(v["house_id"]), "camera_id": int(v["camera_id"]), "view": int(index) % len(store),
              "K": v["K"].astype(np.float64), "cam_to_world": v["cam_to_world"].astype(np.float64)}
    frontal = {name: np.ascontiguousarray(v["depth"][k]) for k, name in enumerate(LAYER_NAMES)}
    if "rgb" in v:
        lin = _srgb_to_linear(v["rgb"])
        frontal.update({c: np.ascontiguousarray(lin[..., k]) for k, c in enumerate("RGB")})
    overhead = {name: np.ascontiguousarray(v["overhead_depth"][k]) for k, name in enumerate(LAYER_NAMES)}
    overhead["height"] = np.ascontiguousarray(v["overhead_height"])
    params = dict(zip(("tx", "ty", "tz", "theta", "sigma"), map(float, v["overhead_params"])))
    top = {**common, "overhead_cam_to_world": v["overhead_cam_to_world"].astype(np.float64),
           "overhead_extent": float(v["overhead_extent"]), **params}
    parts = [OpenEXR.Part(common, frontal, name="frontal"), OpenEXR.Part(top, overhead, name="overhead")]
    OpenEXR.File(parts).write(str(path))
