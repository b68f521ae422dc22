"""Reading a store: :func:`open_store` gives a :class:`SceneStore`, numpy arrays out (no
PyTorch); :func:`array_digests` fingerprints a store's decoded contents.
"""

from __future__ import annotations

import contextlib
import hashlib
import warnings
from typing import TYPE_CHECKING, Iterator

import numpy as np

from ..errors import MissingDependencyError, SceneforgeError
from .layout import MESH_KINDS, layout
from .location import errors, open_location, options_for

if TYPE_CHECKING:
    import zarr

    from ..config import DatasetConfig


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
        present = {name for name, _ in arrays_of(group)}
        self.names: tuple[str, ...] = tuple(s.name for s in layout().values() if s.per_view and s.name in present)
        self.has_mesh = all(f"mesh/{k}/vertices" in present for k in MESH_KINDS)

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
    if "schema_version" not in group.attrs:
        raise SceneforgeError(f"{path}: not a sceneforge store (no schema_version attribute)")
    if not group.attrs.get("complete") and not allow_incomplete:
        raise SceneforgeError(
            f"{path}: the store is incomplete (a render run is in progress or was interrupted); "
            "run the same command again to finish it"
        )
    return SceneStore(group)


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
