"""Reading a store: :func:`open_store` gives a :class:`SceneStore`, numpy arrays out (no
PyTorch); :func:`array_digests` fingerprints a store's decoded contents.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import warnings
from typing import TYPE_CHECKING, Iterator

import numpy as np

from ..errors import DamagedStoreError, MissingDependencyError, SceneforgeError
from .layout import MESH_KINDS, layout
from .location import errors, open_location, options_for
from .shards import ShardDamage, ShardReader, fsspec_ranges, local_ranges

if TYPE_CHECKING:
    import zarr

    from ..config import DatasetConfig
    from .location import Location


def open_group(path: str, mode: str = "r", storage_options: dict | None = None) -> "zarr.Group":
    try:
        import zarr
    except ImportError as e:
        raise MissingDependencyError("zarr", "the dataset store", "pip install sceneforge[store]") from e
    place = open_location(str(path), storage_options)  # a filesystem package missing: one line
    try:
        with errors(place.url):  # an unreachable endpoint, no bucket, access denied: one line each
            options = None if place.local else options_for(place.url, storage_options)
            return zarr.open_group(place.url, mode=mode, storage_options=options)
    except (FileNotFoundError, zarr.errors.GroupNotFoundError, NotADirectoryError):
        raise place.missing() from None


class CheckedArray:
    """A zarr array of a store whose reads fail as one line (:class:`DamagedStoreError`)
    when a file is not as written: one that zarr cannot decode (truncated, zeroed, changed)
    or one the manifest lists that is gone (zarr would read fill values: garbage, silently).
    :meth:`views` reads whole views at once. Everything else is the zarr array's (``shape``,
    ``dtype``, ``shards``, ...)."""

    def __init__(self, array: "zarr.Array", store: "SceneStore"):
        self._array, self._store = array, store
        self._present: set[int] = set()  # shards whose file was found where the manifest lists one
        self._reader: ShardReader | None | bool = False  # False: not looked at yet

    def __getattr__(self, name):
        return getattr(self._array, name)

    def __len__(self) -> int:
        return len(self._array)

    @property
    def _per(self) -> int:
        """Rows per file along the first axis: a shard's (per-view arrays, mesh rows) or a
        chunk's (the unsharded mesh offsets)."""
        return self._array.shards[0] if self._array.shards else self._array.chunks[0]

    def __getitem__(self, selection):
        shards = self._shards(selection)
        try:
            out = self._array[selection]
        except (IndexError, TypeError, OSError):
            raise  # a bad selection is the caller's; an unreachable store says so itself
        except Exception as e:  # zarr's codecs raise ValueError, RuntimeError, ... for a torn file
            reason = str(e).split(". ")[0]  # zarr's checksum error goes on with the raw bytes
            raise self._damaged(self._first_broken(shards), f"cannot be decoded ({reason})") from None
        for shard in shards - self._present:
            if not self._store.file_present(self._key(shard)):
                raise self._damaged(shard, "is missing")
            self._present.add(shard)
        return out

    def views(self, rows) -> np.ndarray:
        """Whole rows ``rows`` (view indices, any order) along the first axis: ``(len(rows),
        *shape[1:])``, the values ``np.stack([self[r] for r in rows])`` gives, read straight
        from the shard files (:class:`~.shards.ShardReader`: a twentieth of zarr's time for a
        small view) where the array has the store writer's layout, else through zarr.
        Damage raises :class:`DamagedStoreError` as every read does."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        n = self._array.shape[0]
        if len(rows) and not (0 <= rows.min() and rows.max() < n):
            raise IndexError(f"rows {rows.min()}..{rows.max()} out of range for {n} rows")
        if self._reader is False:
            place = self._store.place
            read = local_ranges if place.local else fsspec_ranges(place.fs)
            self._reader = ShardReader.of(self._array, lambda shard: f"{place.root}/{self._key(shard)}", read,
                                          self._missing)
        if self._reader is None:
            out = np.empty((len(rows), *self._array.shape[1:]), dtype=self._array.dtype)
            for k, r in enumerate(rows):
                out[k] = self[int(r)]
            return out
        try:
            return self._reader(rows)
        except ShardDamage as e:
            raise self._damaged(e.shard, f"cannot be decoded ({e})") from None

    def _missing(self, shard: int) -> None:
        """A shard file that is not there: damage where the manifest lists it."""
        if not self._store.file_present(self._key(shard)):
            raise self._damaged(shard, "is missing")

    def _shards(self, selection) -> set[int]:
        """The shards (along the first axis) that ``selection`` reads."""
        n, per = self._array.shape[0], self._per
        first = selection[0] if isinstance(selection, tuple) and selection else selection
        if isinstance(first, (int, np.integer)):
            rows = range(int(first) % n, int(first) % n + 1) if n else range(0)
        elif isinstance(first, slice):
            rows = range(*first.indices(n))
        else:
            rows = range(n)
        if not rows:
            return set()
        return set(range(rows[0] // per, rows[-1] // per + 1)) if rows.step == 1 else {r // per for r in rows}

    def _key(self, shard: int) -> str:
        from .writer import shard_key

        return shard_key(self._array, shard)

    def _first_broken(self, shards: set[int]) -> int | None:
        for shard in sorted(shards):
            try:
                self._array[shard * self._per: (shard + 1) * self._per]
            except Exception:
                return shard
        return None

    def _damaged(self, shard: int | None, problem: str) -> DamagedStoreError:
        name, where = self._array.path, self._store.where
        if shard is None:
            return DamagedStoreError(f"{where}: {name} {problem}; run `sceneforge validate {where}`: it names the "
                                     "damaged files and how to repair them")
        a, b = shard * self._per, min((shard + 1) * self._per, self._array.shape[0]) - 1
        rows = "views" if self._array.path in layout() and layout()[self._array.path].per_view else "rows"
        return DamagedStoreError(f"{where}: {name} of {rows} {a}-{b}: the shard file {self._key(shard)} {problem}; "
                                 f"run `sceneforge validate {where}`: it names every damaged file and how to "
                                 "repair them")


class SceneStore:
    """A store opened for reading; numpy arrays out, no PyTorch.

    ``store.view(i)`` gives one view's entries of every per-view array (``rgb (H, W, 3)
    uint8``, ``depth (5, H, W) float32``, ..., ``house_id`` and ``camera_id`` as 0-d
    arrays); ``store.mesh(i)`` its ground-truth meshes; ``store.array(name)`` a lazily sliced
    zarr array; ``store.attrs`` the group attributes (config, provenance, failure log).

    Opened by :func:`open_store` (``place`` given), a read of a file that is not as written
    raises :class:`DamagedStoreError`, one line naming the array, views and shard file
    (:class:`CheckedArray`); without ``place`` (the validator, which reports every file
    itself) arrays are zarr's own.
    """

    def __init__(self, group: "zarr.Group", place: "Location | None" = None):
        self.group = group
        self.place = place
        #: how messages name the store: the path or URL it was opened with
        self.where = place.url if place is not None else str(group.store)
        self.attrs: dict = group.attrs.asdict()
        self._arrays: dict[str, "zarr.Array"] = {}
        self._manifest: dict[str, str | None] | None = None
        present = {name for name, _ in arrays_of(group)}
        self.names: tuple[str, ...] = tuple(s.name for s in layout().values() if s.per_view and s.name in present)
        self.has_mesh = all(f"mesh/{k}/vertices" in present for k in MESH_KINDS)

    def file_present(self, key: str) -> bool:
        """The file ``key`` is there, or the store's manifest records none (a shard of fill
        values only has no file; so do stores written before manifests)."""
        if self._manifest is None:
            record = self.attrs.get("manifest")
            data = record and self.place.fs.cat_file(f"{self.place.root}/{record['file']}")
            self._manifest = json.loads(data)["files"] if data else {}
        return self._manifest.get(key) is None or self.place.fs.exists(f"{self.place.root}/{key}")

    def __len__(self) -> int:
        return int(self.attrs["views"])

    def __repr__(self) -> str:
        return f"SceneStore({self.group.store}, {len(self)} views)"

    @property
    def config(self) -> "DatasetConfig":
        """The resolved config the store was written with."""
        from ..config import DatasetConfig

        return DatasetConfig.from_dict(self.attrs["config"], what=f"{self.group.store} config", recorded=True)

    def array(self, name: str) -> "zarr.Array":
        """The zarr array ``name`` (e.g. ``depth`` or ``mesh/objects/vertices``), for lazy slicing."""
        if name not in self._arrays:
            if name not in layout():
                raise KeyError(f"no array {name!r} in the store layout; per-view arrays: {', '.join(self.names)}")
            array = self.group[name]
            self._arrays[name] = array if self.place is None else CheckedArray(array, self)
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
            raise SceneforgeError("this store keeps no ground-truth meshes (config store.gt_mesh none): "
                                  "sceneforge.ground_truth_meshes(path).mesh(i) makes them from its houses")
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


def arrays_of(group: "zarr.Group") -> Iterator[tuple[str, "zarr.Array"]]:
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
    group = open_group(path, "r", storage_options)
    place = open_location(str(path), storage_options)
    if "schema_version" not in group.attrs:
        raise SceneforgeError(f"{path}: not a sceneforge store (no schema_version attribute)")
    if not group.attrs.get("complete") and not allow_incomplete:
        raise SceneforgeError(
            f"{path}: the store is incomplete (a render run is in progress or was interrupted); "
            "run the same command again to finish it"
        )
    return SceneStore(group, place)


def array_digests(path: str, storage_options: dict | None = None) -> dict[str, str]:
    """SHA-256 (hex) of every array of the store at ``path``, meshes included, by path in the
    group: of its decoded values with their dtype and shape, so equal digests mean equal
    contents however zarr laid out the chunks. Attributes are left out (they hold the
    package version)."""
    return _digests(open_group(path, "r", storage_options))


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
