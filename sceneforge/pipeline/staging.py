"""Work in progress and resume: the run's files under ``OUT.zarr/_staging/``.

- ``run.json``: the run's identity (schema version, houses source, config, house ids),
  written when a run claims a destination; a run resumes only with the same identity;
- ``houses/<hash of the id>.json``: the planning record of a house (step 1), with the
  fingerprint of its input files (:mod:`.inputs`);
- ``created.json``: the per-view arrays exist for that many views (step 2);
- ``mesh/NNNNNN.npz``: the ground-truth meshes of shard N (step 3);
- ``done/NNNNNN.json``: the marker of shard N, written last, atomically: its views, the
  digest of their plan (:meth:`~.assign.Plan.digest`), the SHA-256 of every file it wrote and
  its failures. A shard is redone unless its marker is intact, its plan digest is the
  run's and its files still hash as recorded.

A re-run compares the houses found with those staged (or, for a complete store, those its
attributes record) and refuses when any changed, was added or removed, unless asked to
``update``: then exactly those houses are planned again, and the shards whose plan did not
change are kept (:func:`reopen` stages a complete store's shards as markers for that).

The store writer (:class:`~sceneforge.store.StoreWriter`) puts these files atomically; the
folder is removed when the run completes.
"""

from __future__ import annotations

import hashlib
import io
import json
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from ..config import DatasetConfig
from ..errors import DamagedStoreError, SceneforgeError
from ..store import MESH_KINDS, SCHEMA_VERSION, StoreWriter, array_specs, shard_key
from ..store.validate import FileDamage, file_damage
from .inputs import InputChanges, changes

#: staging folder inside the store, removed when the run completes
STAGING = "_staging"
RUN_KEY = f"{STAGING}/run.json"
CREATED_KEY = f"{STAGING}/created.json"


def house_key(house_id: str) -> str:
    # a house id can hold any character; its hash is a file name
    return f"{STAGING}/houses/{hashlib.sha256(house_id.encode()).hexdigest()[:24]}.json"


def marker_key(shard: int) -> str:
    return f"{STAGING}/done/{shard:06d}.json"


def mesh_key(shard: int) -> str:
    return f"{STAGING}/mesh/{shard:06d}.npz"


def identity(config: "DatasetConfig", houses: str) -> dict:
    """What makes two runs the same run (as the store's attributes record it)."""
    return {"schema_version": SCHEMA_VERSION, "houses_source": houses, "config": config.to_dict()}


def comparable(run_identity: dict) -> dict:
    """``run_identity`` with the paths in it absolute (the houses source, the config's files):
    a run records them so, but a store written before recorded them as given, relative to
    the folder it ran in; resolved from the folder this run runs in, such a store still
    resumes and updates where it used to."""
    from ..config import absolute_paths
    from ..store.location import resolve

    out = dict(run_identity)
    source = out.get("houses_source")
    if isinstance(source, str) and not source.startswith("bundled:"):
        out["houses_source"] = resolve(source)
    if isinstance(out.get("config"), dict):
        out["config"] = absolute_paths(DatasetConfig, out["config"])
    return out


def identity_differences(stored: dict, wanted: dict, limit: int = 3) -> str:
    """What differs between a stored run identity and this run's, for the refusal message:
    ``"config.width: 320 there, 64 here; houses_source: ..."`` (the first ``limit``
    differing leaves, dotted paths), or ``""`` when they are equal."""
    found: list[str] = []

    def walk(a, b, path: str) -> None:
        if isinstance(a, dict) and isinstance(b, dict):
            for key in sorted(set(a) | set(b), key=str):
                walk(a.get(key), b.get(key), f"{path}.{key}" if path else str(key))
        elif a != b:
            found.append(f"{path}: {json.dumps(a)} there, {json.dumps(b)} here")

    walk(stored, wanted, "")
    return "; ".join(found[:limit]) + (f"; and {len(found) - limit} more" if len(found) > limit else "")


@dataclass(frozen=True)
class Preparation:
    """What :func:`prepare` found: ``state`` ``"new"``, ``"resume"`` or ``"complete"``, the
    houses that changed since (planned again), the failed houses retried, and the files of
    a complete store that were not as written (``damaged``: rendered again; ``removed``:
    no run wrote them)."""

    state: str
    changes: InputChanges = InputChanges()
    retried: tuple[str, ...] = ()
    damaged: tuple[str, ...] = ()
    removed: tuple[str, ...] = ()


def prepare(writer: StoreWriter, run_identity: dict, house_ids: list[str], *, overwrite: bool = False,
            update: bool = False, retry_failed: bool = False) -> Preparation:
    """Check the destination and claim it.

    A run resumes an unfinished run, or completes a complete store, only with the same
    identity. When houses changed, were added or removed since (their input files hashed
    again), it refuses naming them unless ``update``: then those houses are planned again
    and the rest is kept. ``retry_failed`` plans the houses that failed again (and renders
    the shards of failed views again).
    """
    if overwrite and writer.exists():
        if not (writer.exists("zarr.json") or writer.exists(STAGING) or writer.is_empty()):
            raise SceneforgeError(f"{writer.url}: not a zarr store; refusing to delete it (--overwrite)")
        writer.rm("")
    started = writer.get_json(RUN_KEY)
    if started is not None:
        if comparable({k: started.get(k) for k in run_identity}) != comparable(run_identity):
            raise SceneforgeError(
                f"{writer.url}: holds an unfinished run with another config or houses; run that command "
                "again to finish it, or pass --overwrite to start over")
        records = {hid: writer.get_json(house_key(hid)) for hid in started["house_ids"]}
        found = changes([r or {"id": hid} for hid, r in records.items()], house_ids)
        _refuse_unless(found, update, writer, "this run started")
        failed = {hid for hid, r in records.items() if r is not None and "failure" in r} if retry_failed else set()
        for hid in found.redo | set(found.removed) | failed:
            writer.rm(house_key(hid))
        if retry_failed:
            _drop_markers_with_failures(writer)
        if found:
            writer.put_json(RUN_KEY, {**run_identity, "house_ids": house_ids})
        return Preparation("resume", found, tuple(sorted(failed)))
    if writer.exists("zarr.json"):
        attrs = writer.attrs()
        differs = identity_differences(comparable({k: attrs.get(k) for k in run_identity}), comparable(run_identity))
        if not attrs.get("complete") or differs:
            raise SceneforgeError(f"{writer.url}: holds another store ({differs or 'not marked complete'}); "
                                  "pass --overwrite to replace it, or choose another path")
        found = changes(attrs["houses"], house_ids)
        _refuse_unless(found, update, writer, "this store was rendered")
        failed = {f["house"] for f in attrs["failures"]} & set(house_ids) if retry_failed else set()
        stored = DatasetConfig.from_dict(attrs["config"], what=f"{writer.url} config", recorded=True)
        damage = file_damage(writer, attrs, stored)
        for key in damage.unexpected:  # no run wrote them: not this store's
            writer.rm(key)
        shards = damaged_shards(damage, attrs["views"], stored.store.views_per_shard)
        if not found and not failed and not shards:
            return Preparation("complete", removed=tuple(damage.unexpected))
        reopen(writer, attrs, run_identity, house_ids, found.redo | failed, shards)
        lost = tuple(damage.missing + damage.damaged) or ((damage.manifest,) if damage.manifest else ())
        return Preparation("resume", found, tuple(sorted(failed)), lost, tuple(damage.unexpected))
    if writer.is_file():
        raise SceneforgeError(f"{writer.url}: is a file, not a folder")
    if not writer.is_empty():
        raise SceneforgeError(f"{writer.url}: exists and is not empty; choose another path")
    writer.put_json(RUN_KEY, {**run_identity, "house_ids": house_ids})
    return Preparation("new")


def recorded_config(writer: StoreWriter) -> "DatasetConfig":
    """The config the store at ``writer`` (or the unfinished run there) was rendered with."""
    started = writer.get_json(RUN_KEY)
    if started is not None:
        doc = started["config"]
    elif writer.exists("zarr.json"):
        doc = writer.attrs().get("config")
    else:
        doc = None
    if doc is None:
        raise SceneforgeError(f"{writer.url}: no store that sceneforge render wrote, so nothing to repair")
    return DatasetConfig.from_dict(doc, what=f"{writer.url} config", recorded=True)


def _refuse_unless(found: InputChanges, update: bool, writer: StoreWriter, since: str) -> None:
    if found and not update:
        raise SceneforgeError(
            f"{writer.url}: the houses changed since {since} ({found.describe()}); pass --update to redo "
            "exactly these houses, or --overwrite to start over")


def _drop_markers_with_failures(writer: StoreWriter) -> None:
    done = writer.path(f"{STAGING}/done")
    if writer.fs.exists(done):
        for path in writer.fs.ls(done, detail=False):
            key = f"{STAGING}/done/{path.rsplit('/', 1)[1]}"
            marker = writer.get_json(key)
            if marker is None or marker["failures"]:
                writer.rm(key)


def damaged_shards(damage: FileDamage, n_views: int, per_shard: int) -> set[int]:
    """The shards to render again for the files ``damage`` found: those of the missing or
    damaged per-view shard files; every shard when the manifest or a mesh array's file is
    not as written (the mesh arrays are made from every shard's meshes)."""
    every = set(range(-(-n_views // per_shard)))
    if damage.manifest:
        return every
    shards = set()
    for key in damage.missing + damage.damaged:
        array, coords = key.rsplit("/c/", 1)
        if array.startswith("mesh/"):
            return every
        shards.add(int(coords.split("/")[0]))
    return shards


def reopen(writer: StoreWriter, attrs: dict, run_identity: dict, house_ids: list[str], redo: set[str],
           damaged: set[int] = frozenset()) -> None:
    """Turn the complete store of ``attrs`` back into a run to resume that plans the houses
    ``redo`` (and those of ``house_ids`` it does not have) again: the other houses' records
    are rebuilt from the store (provenance, failure log and cameras) and staged, and each
    shard of those houses only is staged with its marker and mesh part, as its run wrote
    them, so it is kept wherever the new plan puts the same views at the same indices.
    The shards ``damaged`` are not staged (rendered again); a house whose cameras are in a
    damaged shard is planned again (the same cameras: planning is seeded)."""
    from ..store import open_store
    from .assign import Plan

    store = open_store(writer.url, writer.storage_options or None)
    config = DatasetConfig.from_dict(attrs["config"], what=f"{writer.url} config", recorded=True)
    house_failures = {f["house"]: f for f in attrs["failures"] if f["view"] is None}
    camera_id, K, pose, lost = _stored_cameras(store, config.store.views_per_shard)
    redo = redo | {h["id"] for h in attrs["houses"] if h["status"] == "ok" and lost[slice(*h["views"])].any()}
    records = []
    for h in attrs["houses"]:
        rec = {k: v for k, v in h.items() if k not in ("status", "views")}
        if h["status"] == "failed":
            rec["failure"] = {k: v for k, v in house_failures[h["id"]].items() if k not in ("house", "view")}
        else:
            a, b = h["views"]
            rec.update(camera_id=camera_id[a:b].tolist(), K=K[a:b].tolist(), cam_to_world=pose[a:b].tolist())
        records.append(rec)
    old = Plan.from_records(records)
    kept = set(house_ids) - redo
    for rec in records:
        if rec["id"] in kept:
            writer.put_json(house_key(rec["id"]), rec)
    arrays = {spec.name: store.array(spec.name) for spec in array_specs(config, per_view=True)}
    for s, (a, b) in enumerate(old.shards(config.store.views_per_shard)):
        if s in damaged or any(old.houses[v.house]["id"] not in kept for v in old.views[a:b]):
            continue
        marker = {"shard": s, "views": [a, b], "plan": old.digest(a, b),
                  "files": {key: writer.sha256(key) for key in (shard_key(arr, s) for arr in arrays.values())},
                  "failures": [f for f in attrs["failures"] if f["view"] is not None and a <= f["view"] < b]}
        if config.view.with_mesh:
            part = _stored_mesh_part(store, a, b)
            marker["files"][mesh_key(s)] = put_mesh_part(writer, s, part)
            marker["mesh_counts"] = part["counts"].tolist()
        writer.put_json(marker_key(s), marker)
    writer.put_json(CREATED_KEY, {"views": attrs["views"]})
    writer.put_json(RUN_KEY, {**run_identity, "house_ids": house_ids})
    writer.mark_incomplete()


def _stored_cameras(store, per_shard: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``camera_id (N,)``, ``K (N, 3, 3)`` and ``cam_to_world (N, 4, 4)`` of a store, read
    shard by shard, and ``lost (N,) bool``: the views of the shards that cannot be read."""
    names = ("camera_id", "K", "cam_to_world")
    n = len(store)
    out = [np.zeros((n, *store.array(name).shape[1:]), store.array(name).dtype) for name in names]
    lost = np.zeros(n, bool)
    for a in range(0, n, per_shard):
        try:
            parts = [np.asarray(store.array(name)[a: a + per_shard]) for name in names]
        except DamagedStoreError:
            lost[a: a + per_shard] = True
            continue
        for array, part in zip(out, parts):
            array[a: a + per_shard] = part
    return (*out, lost)


def _stored_mesh_part(store, start: int, stop: int) -> dict[str, np.ndarray]:
    """The mesh part of views ``start:stop`` (:func:`~sceneforge.store.mesh_part`) read back
    from a store's ragged mesh arrays."""
    part, counts = {}, np.zeros((stop - start, 2, 2), np.int64)
    for k, kind in enumerate(MESH_KINDS):
        vo = np.asarray(store.array(f"mesh/{kind}/vertex_offsets")[start: stop + 1])
        fo = np.asarray(store.array(f"mesh/{kind}/face_offsets")[start: stop + 1])
        part[f"{kind}_vertices"] = np.asarray(store.array(f"mesh/{kind}/vertices")[vo[0]: vo[-1]])
        part[f"{kind}_faces"] = np.asarray(store.array(f"mesh/{kind}/faces")[fo[0]: fo[-1]])
        part[f"{kind}_instance"] = np.asarray(store.array(f"mesh/{kind}/instance")[fo[0]: fo[-1]])
        counts[:, k, 0], counts[:, k, 1] = np.diff(vo), np.diff(fo)
    part["counts"] = counts
    return part


def intact(writer: StoreWriter, marker: dict | None, views: tuple[int, int], plan_digest: str) -> bool:
    """The shard of ``views`` was written completely, from the plan of digest
    ``plan_digest``, and its files still hold what was written."""
    return (marker is not None and marker.get("views") == list(views) and marker.get("plan") == plan_digest
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
    """The one line for a write that failed: what failed, and what a re-run resumes."""
    try:
        done = len(writer.fs.ls(writer.path(f"{STAGING}/done"), detail=False))
    except OSError:
        done = 0
    where = f" {e.filename}" if e.filename and str(e.filename) != writer.root else ""
    kept = (f"; the {done} shard{'s' if done != 1 else ''} written so far {'are' if done != 1 else 'is'} intact"
            if done else "")
    return SceneforgeError(f"{writer.url}: cannot write{where} ({e.strerror or e}){kept}: fix the cause and run "
                           "the same command again to resume")
