"""The ground-truth meshes of a store's views (docs/spec.md §5.3) where the store keeps none: made on
demand from the houses the store records, and cached beside it.

Training never reads the meshes, so a store keeps them only when rendered with
``store.gt_mesh: all``. For the others, :class:`GroundTruthMeshes` makes a view's meshes
when they are asked for (``evaluate`` asks for the views it scores), exactly as the render
would have: the house is read the way the run read it (its recorded path and format, the
store's ``houses`` options), the objects are cut out by the view's *stored* D5 and
instance layers, the envelope is its D5 traced afresh at the store's mesh rules, and the
vertices are rounded to float32 as the store rounds them.

A house is read from its recorded path (a relative one also from another folder, through
its fingerprinted files' absolute paths: :func:`~.inputs.house_path`) and used only if every input
file the run fingerprinted still hashes as recorded (:mod:`.inputs`); otherwise the meshes
would be those of another house, and a score of them wrong, so that is a
:class:`SceneforgeError` naming the house and its first changed file.

Made meshes are cached in ``STORE.gt_mesh/`` (:func:`cache_folder`), one file per view,
keyed by everything they are made from: the house's fingerprints, the read options, the
mesh rules, the camera, the view's layers and the sceneforge version; a file whose key
differs is made again and replaced.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import SceneforgeError
from ..store import MESH_KINDS
from .inputs import file_digest, house_path

if TYPE_CHECKING:
    from ..houses import House
    from ..raytrace import HouseTracer
    from ..store import SceneStore

#: the cache folder of a store is the store's path with this suffix
CACHE_SUFFIX = ".gt_mesh"

Meshes = dict[str, tuple[np.ndarray, np.ndarray]]


def cache_folder(path: str) -> Path | None:
    """Where the meshes made for the store at ``path`` are cached: ``STORE.gt_mesh/`` beside
    a local store; None (no cache) for a URL."""
    if "://" in str(path):
        return None
    return Path(str(path).rstrip("/\\") + CACHE_SUFFIX)


class GroundTruthMeshes:
    """The ground-truth meshes of the views of ``store``: :meth:`mesh` gives view ``i``'s as
    :meth:`~sceneforge.store.SceneStore.mesh` does, the store's own when it keeps them, else
    made from its house (see the module doc).

    store : an opened store (:func:`sceneforge.store.open_store`)
    cache : the folder made meshes are kept in (created when first needed), or None
    """

    def __init__(self, store: "SceneStore", cache: str | Path | None = None):
        self.store = store
        self.cache = None if cache is None else Path(cache)
        self._house: tuple[str, "House", "HouseTracer"] | None = None
        self._checked: set[str] = set()

    def __repr__(self) -> str:
        return f"GroundTruthMeshes({self.store!r}, cache={str(self.cache) if self.cache else None!r})"

    def mesh(self, i: int) -> Meshes:
        """View ``i``'s meshes: ``{"objects": (vertices (v, 3) float32, faces (f, 3) int32),
        "envelope": (...)}``, faces indexing those vertices.

        Raises :class:`SceneforgeError` for a view whose ground truth failed, or whose house
        changed, moved or cannot be read since the store was rendered.
        """
        if self.store.has_mesh:
            return self.store.mesh(i)
        if "prediction" in self.store.attrs:
            raise SceneforgeError("a store of predictions has no ground-truth meshes: they come from the store of "
                                  "ground truth it was predicted from")
        view = self.store.view(i)
        i = int(i) % len(self.store)
        house_id = str(view["house_id"])
        if not view["valid"]:
            raise SceneforgeError(f"view {i} (house {house_id}) failed when it was rendered: it has no ground truth")
        record = self._record(house_id)
        key = self._key(record, view)
        cached = self._read(i, key)
        if cached is not None:
            return cached
        meshes = self._make(record, view)
        self._write(i, key, meshes)
        return meshes

    # ------------------------------------------------------------------------ making

    def _record(self, house_id: str) -> dict:
        record = next((h for h in self.store.attrs["houses"] if h["id"] == house_id), None)
        if record is None:
            raise SceneforgeError(f"house {house_id}: not in the store's houses attribute")
        return record

    def _check(self, record: dict) -> None:
        """Refuse a house whose input files are not those the store was rendered from."""
        if record["id"] in self._checked:
            return
        inputs = record.get("inputs")
        if not inputs:
            raise SceneforgeError(f"house {record['id']}: the store records no fingerprints of its files, so "
                                  "meshes made from them could be another house's; render it with --gt-mesh all")
        for path, digest in sorted(inputs.items()):
            now = file_digest(path)
            if now != digest:
                what = "is missing" if now is None else "changed"
                raise SceneforgeError(
                    f"house {record['id']}: {path} {what} since the store was rendered, so its ground-truth "
                    "meshes cannot be made (render the store again, with --update, or with --gt-mesh all)")
        self._checked.add(record["id"])

    def _house_of(self, record: dict) -> tuple["House", "HouseTracer"]:
        """The house of ``record``, read as the run read it, and its tracer (the last kept)."""
        from ..houses import HouseSource, load
        from ..raytrace import HouseTracer

        if self._house is None or self._house[0] != record["id"]:
            self._house = None
            house = load(HouseSource(record["id"], record["format"], house_path(record)), self.store.config.houses)
            self._house = (record["id"], house, HouseTracer(house))
        return self._house[1], self._house[2]

    def _make(self, record: dict, view: dict) -> Meshes:
        from ..cameras import Camera
        from ..frustum import view_mesh
        from ..layers import Layers

        self._check(record)
        house, tracer = self._house_of(record)
        config = self.store.config
        camera = Camera(view["K"], view["cam_to_world"], config.width, config.height)
        # the mesh rules read D5 and the layer instances: the stored ones, as the render had them
        normal = view.get("normal", np.full((3, config.height, config.width), np.nan, np.float32))
        layers = Layers(view["depth"], view["category"], view["instance"], normal)
        made = view_mesh(house, camera, layers, config.view.mesh, tracer)
        return {kind: (np.asarray(getattr(made, kind).vertices, np.float32),
                       np.asarray(getattr(made, kind).faces, np.int32)) for kind in MESH_KINDS}

    def _key(self, record: dict, view: dict) -> str:
        """SHA-256 of everything the view's meshes are made from."""
        from sceneforge import __version__

        config = self.store.config
        h = hashlib.sha256(json.dumps({
            "version": __version__, "house": record["id"], "inputs": record.get("inputs"),
            "houses": config.to_dict()["houses"], "mesh": config.to_dict()["view"]["mesh"],
            "size": [config.width, config.height],
        }, sort_keys=True).encode())
        for name in ("K", "cam_to_world", "depth", "instance"):
            h.update(np.ascontiguousarray(view[name]).tobytes())
        return h.hexdigest()

    # ------------------------------------------------------------------------ the cache

    def _path(self, i: int) -> Path:
        return self.cache / f"view_{i:06d}.npz"

    def _read(self, i: int, key: str) -> Meshes | None:
        if self.cache is None:
            return None
        try:
            with np.load(self._path(i)) as f:
                if str(f["key"]) != key:
                    return None
                return {kind: (f[f"{kind}_vertices"], f[f"{kind}_faces"]) for kind in MESH_KINDS}
        except (OSError, ValueError, KeyError):  # none yet, or torn: made again
            return None

    def _write(self, i: int, key: str, meshes: Meshes) -> None:
        """Cache the meshes: an ``.npz`` file (deflate level 1: a third of the bytes, a third
        of ``np.savez_compressed``'s time), written atomically (a temporary file renamed into
        place); a folder that cannot be written leaves them uncached."""
        if self.cache is None:
            return
        arrays = {"key": np.array(key), **{f"{kind}_{part}": array for kind, (v, f) in meshes.items()
                                           for part, array in (("vertices", v), ("faces", f))}}
        tmp = None
        try:
            self.cache.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=self.cache, suffix=".partial")
            with os.fdopen(fd, "wb") as file, zipfile.ZipFile(file, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as z:
                for name, array in arrays.items():
                    with z.open(f"{name}.npy", "w", force_zip64=True) as out:
                        np.lib.format.write_array(out, array, allow_pickle=False)
            os.replace(tmp, self._path(i))
        except OSError:
            if tmp is not None:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)


def ground_truth_meshes(path: str, storage_options: dict | None = None) -> GroundTruthMeshes:
    """The ground-truth meshes of the views of the store at ``path``, cached in
    :func:`cache_folder` (``STORE.gt_mesh/``) when it is local."""
    from ..store import open_store

    return GroundTruthMeshes(open_store(path, storage_options), cache_folder(path))
