"""Work in progress and resume: the run's files under ``OUT.zarr/_staging/``.

- ``run.json``: the run's identity (schema version, houses source, config, house ids),
  written when a run claims a destination; a run resumes only with the same identity;
- ``houses/NNNNNN.json``: the planning record of house N (step 1);
- ``created.json``: the per-view arrays exist for that many views (step 2);
- ``mesh/NNNNNN.npz``: the ground-truth meshes of shard N (step 3);
- ``done/NNNNNN.json``: the marker of shard N, written last, atomically: its views, the
  SHA-256 of every file it wrote and its failures. A shard is redone unless its marker is
  intact and its files still hash as recorded.

The store writer (:class:`~sceneforge.store.StoreWriter`) puts these files atomically; the
folder is removed when the run completes.
"""

from __future__ import annotations

import hashlib
import io
from typing import TYPE_CHECKING, Iterator

import numpy as np

from ..errors import SceneforgeError
from ..store import SCHEMA_VERSION, StoreWriter

if TYPE_CHECKING:
    from ..config import DatasetConfig

#: staging folder inside the store, removed when the run completes
STAGING = "_staging"
RUN_KEY = f"{STAGING}/run.json"
CREATED_KEY = f"{STAGING}/created.json"


def house_key(index: int) -> str:
    return f"{STAGING}/houses/{index:06d}.json"


def marker_key(shard: int) -> str:
    return f"{STAGING}/done/{shard:06d}.json"


def mesh_key(shard: int) -> str:
    return f"{STAGING}/mesh/{shard:06d}.npz"


def identity(config: "DatasetConfig", houses: str) -> dict:
    """What makes two runs the same run (as the store's attributes record it)."""
    return {"schema_version": SCHEMA_VERSION, "houses_source": houses, "config": config.to_dict()}


def prepare(writer: StoreWriter, run_identity: dict, house_ids: list[str], overwrite: bool) -> str:
    """Check the destination and claim it: ``"new"``, ``"resume"`` or ``"complete"``.

    A run resumes only with the same identity and the same houses found (view indices
    depend on them).
    """
    if overwrite and writer.exists():
        if not (writer.exists("zarr.json") or writer.exists(STAGING) or writer.is_empty()):
            raise SceneforgeError(f"{writer.url}: not a zarr store; refusing to delete it (--overwrite)")
        writer.rm("")
    started = writer.get_json(RUN_KEY)
    if started is not None:
        if started != {**run_identity, "house_ids": house_ids}:
            raise SceneforgeError(
                f"{writer.url}: holds an unfinished run with another config or houses; run that command "
                "again to finish it, or pass --overwrite to start over")
        return "resume"
    if writer.exists("zarr.json"):
        attrs = writer.attrs()
        if attrs.get("complete") and {k: attrs.get(k) for k in run_identity} == run_identity:
            return "complete"
        raise SceneforgeError(f"{writer.url}: holds another store; pass --overwrite to replace it, or choose "
                              "another path")
    if writer.is_file():
        raise SceneforgeError(f"{writer.url}: is a file, not a folder")
    if not writer.is_empty():
        raise SceneforgeError(f"{writer.url}: exists and is not empty; choose another path")
    writer.put_json(RUN_KEY, {**run_identity, "house_ids": house_ids})
    return "new"


def intact(writer: StoreWriter, marker: dict | None, views: tuple[int, int]) -> bool:
    """The shard of ``views`` was written completely and its files still hold what was written."""
    return (marker is not None and marker.get("views") == list(views)
            and all(writer.sha256(key) == digest for key, digest in marker["files"].items()))


def put_mesh_part(writer: StoreWriter, shard: int, part: dict[str, np.ndarray]) -> str:
    """Stage the mesh part of ``shard`` (:func:`~sceneforge.store.mesh_part`); returns its SHA-256."""
    buf = io.BytesIO()
    np.savez(buf, **part)
    writer.put(mesh_key(shard), buf.getvalue())
    return hashlib.sha256(buf.getvalue()).hexdigest()


def mesh_parts(writer: StoreWriter, markers: list[dict]) -> Iterator[dict[str, np.ndarray]]:
    """The staged mesh parts of the shards of ``markers``, in their order, one at a time."""
    for m in markers:
        with np.load(io.BytesIO(writer.get(mesh_key(m["shard"])))) as part:
            yield dict(part)


def write_error(writer: StoreWriter, e: OSError) -> SceneforgeError:
    return SceneforgeError(
        f"{writer.url}: cannot write ({e.strerror or e}); the shards written so far are intact: "
        "fix the cause and run the same command again to resume"
    )
