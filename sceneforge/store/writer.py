"""The one writer of a store (:class:`StoreWriter`): per-view arrays created from the layout
and filled shard by shard, the ragged mesh arrays, the manifest and the final attributes,
and a run's own files (atomic ``put``), under the store's lock (:mod:`.lock`).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
from typing import TYPE_CHECKING, Iterable

import numpy as np

from ..errors import MissingDependencyError
from .layout import (
    MANIFEST,
    MESH_CHUNK_ROWS,
    MESH_KINDS,
    MESH_SHARD_CHUNKS,
    ArraySpec,
    array_specs,
    base_attrs,
    layout,
    sizes_of,
)
from .location import errors, open_location, options_for
from .lock import StoreLock

if TYPE_CHECKING:
    import zarr

    from ..config import DatasetConfig


def array_compressor(config: "DatasetConfig", spec: ArraySpec, chunk_shape: tuple[int, ...]):
    """The compressor of array ``spec`` with chunks of ``chunk_shape``, by ``config.store.codec``:

    - ``blosc-zstd-per-array``: Blosc + zstd with the array's own shuffle (the layout's
      ``x-shuffle``) and one Blosc block per chunk (Blosc's default splits a view into blocks
      of a few hundred kB, each compressed alone: 16 % more bytes for a toy view's depth);
      both chosen by measurement, ``benchmarks/bench_store_bytes.py``;
    - ``blosc-zstd``: Blosc + zstd, every array byte-shuffled, Blosc's default blocks (the
      stores written before per-array codecs);
    - ``zstd``: plain zstd, for readers without Blosc.

    Blosc shuffles by the array's item size (zarr sets it from the dtype).
    """
    from zarr.codecs import BloscCodec, ZstdCodec

    level = config.store.compression_level
    if config.store.codec == "zstd":
        return ZstdCodec(level=level)
    if config.store.codec == "blosc-zstd":
        return BloscCodec(cname="zstd", clevel=level, shuffle="shuffle")
    block = int(np.prod(chunk_shape)) * spec.numpy_dtype.itemsize if spec.dtype != "string" else 0
    return BloscCodec(cname="zstd", clevel=level, shuffle=spec.shuffle, blocksize=block)


def create_arrays(group: "zarr.Group", config: "DatasetConfig", n_views: int) -> None:
    """(Re)create every per-view array of a store of ``n_views`` views, empty."""
    sizes = sizes_of(config, n_views)
    per_shard = config.store.views_per_shard
    for spec in array_specs(config, per_view=True):
        shape = spec.shape(sizes)
        chunks = (1, *shape[1:])
        group.create_array(
            spec.name, shape=shape, dtype=spec.numpy_dtype, chunks=chunks, shards=(per_shard, *shape[1:]),
            compressors=array_compressor(config, spec, chunks), fill_value=spec.fill_value, overwrite=True,
        )


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
            spec = specs[f"mesh/{kind}/{name}"]
            group.create_array(spec.name, data=offsets[:, j].astype(spec.dtype), chunks=(MESH_CHUNK_ROWS,),
                               compressors=array_compressor(config, spec, (MESH_CHUNK_ROWS,)), overwrite=True)
        for name in ("vertices", "faces", "instance"):
            spec = specs[f"mesh/{kind}/{name}"]
            shape = spec.shape(rows)
            chunks = (MESH_CHUNK_ROWS, *shape[1:])
            array = group.create_array(
                spec.name, shape=shape, dtype=spec.dtype, chunks=chunks,
                shards=(MESH_CHUNK_ROWS * MESH_SHARD_CHUNKS, *shape[1:]),
                compressors=array_compressor(config, spec, chunks), overwrite=True)
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
    into place on local files, one PUT on an object store: :class:`~.location.Location`),
    so readers see all of a file or nothing.

    One run writes a store at a time: ``with StoreWriter(url) as writer:`` takes the store's
    lock (:class:`StoreLock`, a conditional write where the store lives) for the block and releases it on any exit, exceptions and
    Ctrl-C included; a second run is refused with :class:`StoreLockedError` naming the
    holder. The writers of shard tasks in worker processes write under their run's lock
    and are not entered.

    url             : a local path or an fsspec URL (``memory://...``, ``s3://...``)
    storage_options : passed to fsspec and zarr, over the defaults of the store's kind of
                      place (:func:`~.location.options_for`); credentials otherwise come
                      from where the filesystem package looks (``AWS_*`` for S3)
    """

    def __init__(self, url: str, storage_options: dict | None = None):
        self.url = str(url)
        self.storage_options = options_for(self.url, storage_options)
        #: where the store lives and what that place guarantees (atomic files, the lock's writes)
        self.location = open_location(self.url, self.storage_options)
        self.fs, self.root, self.local = self.location.fs, self.location.root, self.location.local
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
        with errors(self.url):  # the first request: an unreachable endpoint, no bucket, denied
            self._lock.acquire()
        return self

    def __exit__(self, *exc) -> None:
        lock, self._lock = self._lock, None
        if lock is not None:
            lock.release()

    # ------------------------------------------------------------------------ the arrays

    def create(self, config: "DatasetConfig", houses_source: str, n_views: int, *, replace: bool = False,
               **extra) -> None:
        """(Re)create every per-view array of ``n_views`` views, empty, and the attributes
        known so far (:func:`base_attrs`, ``complete`` false, and ``extra``, e.g. ``prediction``).

        replace : first remove whatever the location holds (else arrays are recreated in place)
        """
        group = self._open("w" if replace else "a")
        create_arrays(group, config, n_views)
        group.attrs.put({**base_attrs(config, houses_source, n_views), **extra})
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
            self.location.remove(self.path(key))
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
        self.location.put(self.path(key), data)

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
