"""``sceneforge render``: houses in, a sharded zarr store out, on one machine or a Dask cluster.

A run goes through four steps, each resumable:

1. **Plan houses** (parallel, one task per house): load the house and choose its cameras
   (sampled with a seed derived from ``config.seed`` and the house id, or read from a PBRS
   camera file). A house that cannot be loaded or given a camera is recorded as failed.
2. **Assign views** (main process): views are numbered house by house in the order
   :func:`~sceneforge.houses.discover` lists the houses, cameras in order within a house.
   The per-view arrays are created with that many views.
3. **Render shards** (parallel, one task per shard): a task computes the views of one shard
   (ground truth and RGB) and writes that shard of every per-view array, so no two tasks
   ever write the same file. Its ground-truth meshes go to a staged part; a marker listing
   the SHA-256 of every file it wrote is written last, atomically.
4. **Finalize** (main process, single writer): the mesh parts are concatenated in view
   order into the ragged mesh arrays, provenance and the failure log are written to the
   group attributes with ``complete: true``, and the staging folder is removed.

Work in progress lives in ``OUT.zarr/_staging/``. A killed run (SIGKILL, power loss)
restarted with the same command skips every house record and shard whose marker is intact
and whose files still hash as recorded, redoes the rest, and ends with the same bytes as an
uninterrupted run: nothing written depends on timing, worker count or scheduler.

Execution: in-process (``workers=1``), a pool of spawned processes (``workers=N``) or a Dask
distributed cluster (``scheduler="tcp://host:8786"``, or ``"local"`` for a LocalCluster).
Each worker process keeps one renderer and the last house it loaded.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
import os
import time
import uuid
import zlib
from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Iterable, Iterator, Protocol

import numpy as np

from .errors import MissingDependencyError, SceneforgeError

if TYPE_CHECKING:
    from .config import DatasetConfig
    from .houses import HouseSource

#: staging folder inside the store, removed when the run completes
STAGING = "_staging"
#: environment of local worker processes: BLAS thread pools fight Open3D's for the cores
#: when each worker has its own
_WORKER_ENV = {"OPENBLAS_NUM_THREADS": "1"}


def _worker_env(workers: int) -> dict[str, str]:
    """Environment of ``workers`` local worker processes: single-threaded BLAS, and the
    cores shared out among the workers' ray tracers (Open3D would otherwise give each
    worker a thread per core: on 2 cores, 2 workers ran no faster than 1)."""
    from .raytrace import THREADS_ENV

    return {**_WORKER_ENV, THREADS_ENV: str(max(1, (os.cpu_count() or 1) // workers))}


class Progress(Protocol):
    """Receives progress: ``start`` once per step, then ``advance`` as work completes."""

    def start(self, step: str, total: int, unit: str, done: int = 0) -> None: ...

    def advance(self, n: int) -> None: ...


@dataclass
class RenderSummary:
    """What a run did.

    failures : the store's failure log (``house``, ``stage``, ``reason``, ``view``)
    timings  : worker seconds spent this run per stage (``load``, ``ground_truth``,
               ``render``, ``write``), summed over views
    """

    path: str
    views: int
    houses: int
    failed_houses: tuple[str, ...]
    failures: list[dict]
    shards: int
    shards_run: int
    seconds: float
    timings: dict[str, float] = field(default_factory=dict)
    already_complete: bool = False


# ------------------------------------------------------------------------------ staging


class Destination:
    """The store's location: a local path or an fsspec URL, plus atomic staging files."""

    def __init__(self, url: str, storage_options: dict | None = None):
        import fsspec

        self.url = str(url)
        self.storage_options = storage_options or {}
        self.fs, root = fsspec.core.url_to_fs(self.url, **self.storage_options)
        self.root = root.rstrip("/")
        self.local = "file" in _protocols(self.fs)
        #: what zarr opens: a plain path for local files (zarr's LocalStore creates folders
        #: and writes atomically), else the URL
        self.zarr_url = self.root if self.local else self.url

    def open_group(self, mode: str):
        """The store's zarr group."""
        import zarr

        return zarr.open_group(self.zarr_url, mode=mode,
                               storage_options=None if self.local else self.storage_options or None)

    def path(self, key: str) -> str:
        return f"{self.root}/{key}"

    def exists(self, key: str = "") -> bool:
        return self.fs.exists(self.path(key) if key else self.root)

    def put(self, key: str, data: bytes) -> None:
        """Write ``data`` to ``key`` so that readers see all of it or nothing."""
        path = self.path(key)
        tmp = f"{path}.{uuid.uuid4().hex}.partial"
        self.fs.makedirs(path.rsplit("/", 1)[0], exist_ok=True)
        self.fs.pipe_file(tmp, data)
        self.fs.mv(tmp, path)

    def get(self, key: str) -> bytes | None:
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
        data = self.get(key)
        return None if data is None else hashlib.sha256(data).hexdigest()

    def rm(self, key: str) -> None:
        with contextlib.suppress(FileNotFoundError):
            self.fs.rm(self.path(key), recursive=True)

    def remove_partials(self) -> None:
        """Remove the temporary files of writes cut short (this module's and zarr's LocalStore's)."""
        if self.local:
            for path in self.fs.find(self.root):
                if path.endswith(".partial"):
                    self.fs.rm(path)


def _protocols(fs) -> tuple[str, ...]:
    p = fs.protocol
    return (p,) if isinstance(p, str) else tuple(p)


def _write_error(dest: Destination, e: OSError) -> SceneforgeError:
    return SceneforgeError(
        f"{dest.url}: cannot write ({e.strerror or e}); the shards written so far are intact: "
        "fix the cause and run the same command again to resume"
    )


# ------------------------------------------------------------------------- worker state


class _Worker:
    """What a worker process keeps between tasks: the last house it loaded and its tracer,
    and one RGB renderer."""

    def __init__(self):
        self.house_key = None
        self.house = self.tracer = None
        self.renderer_key = None
        self.renderer = None

    def load(self, source: "HouseSource", config: "DatasetConfig"):
        from .houses import load

        key = (source, config.houses)
        if key != self.house_key:
            self.house_key = None  # a load that raises leaves no stale house behind
            self.house, self.tracer = load(source, config.houses), None
            self.house_key = key
        return self.house

    def tracer_of(self, house):
        from .raytrace import HouseTracer

        if self.tracer is None:
            self.tracer = HouseTracer(house)
        return self.tracer

    def renderer_for(self, config: "DatasetConfig"):
        key = (config.width, config.height, config.rgb)
        if key != self.renderer_key:
            if self.renderer is not None:
                self.renderer.close()
            self.renderer = self.renderer_key = None
            try:
                from .render import Renderer
            except ImportError as e:
                raise MissingDependencyError("pyrender", "RGB rendering", "pip install sceneforge[render]") from e
            self.renderer = Renderer(config.width, config.height, antialias=config.rgb.antialias,
                                     config=config.rgb.lighting)
            self.renderer_key = key
        return self.renderer

    def close(self) -> None:
        """Free the renderer and forget the house (the in-process executor calls this at its end)."""
        if self.renderer is not None:
            self.renderer.close()
        self.renderer = self.renderer_key = None
        self.house_key = self.house = self.tracer = None


#: the state of this process when it works as a worker (one per process by construction)
_WORKER = _Worker()


# ------------------------------------------------------------------------ 1. plan houses


def _house_rng(seed: int, house_id: str) -> np.random.Generator:
    """The camera sampler's generator for a house: depends on the seed and the house id
    only, so a house gets the same cameras whatever other houses are in the run."""
    return np.random.default_rng([seed, zlib.crc32(house_id.encode())])


def _file_cameras(source: "HouseSource", config: "DatasetConfig"):
    """Cameras of ``<cameras>/<house id>/room_camera.txt`` and their 0-based line numbers."""
    from pathlib import Path

    from .cameras import read_pbrs_cameras

    path = Path(config.cameras) / source.id / "room_camera.txt"
    if not path.is_file():
        raise SceneforgeError(f"no camera file {path}")
    cameras = read_pbrs_cameras(path, config.width, config.height)
    lines = [i for i, line in enumerate(path.read_text().splitlines()) if line.split("#", 1)[0].strip()]
    return cameras, lines, {"source": "file", "file": str(path), "requested": len(cameras),
                            "accepted": len(cameras)}


def plan_house(source: "HouseSource", config: "DatasetConfig") -> dict:
    """Load one house and choose its cameras (step 1).

    Returns a JSON-ready record: ``id``, ``format``, ``path``, counts, loader warnings,
    ``cameras`` (how they were chosen), ``camera_id``, ``K`` and ``cam_to_world`` per
    camera; or ``failure`` (``stage``, ``reason``) when the house cannot be used.
    """
    from .cameras import sample_cameras

    record = {"id": source.id, "format": source.format, "path": str(source.path)}
    stage = "load"
    try:
        house = _WORKER.load(source, config)
        record.update(instances=len(house.instances), triangles=house.triangle_count, rooms=len(house.rooms),
                      warnings=list(house.warnings))
        stage = "cameras"
        if config.cameras is not None:
            cameras, ids, info = _file_cameras(source, config)
        else:
            cameras, report = sample_cameras(house, config.views_per_house, _house_rng(config.seed, source.id),
                                             config.sampler, _WORKER.tracer_of(house))
            ids = list(range(len(cameras)))
            info = {"source": "sampled", **report.to_dict()}
        record["cameras"] = info
        if not cameras:
            raise SceneforgeError(f"no valid camera ({_no_camera_reason(info)})")
    except Exception as e:  # a broken house must not stop the others; bugs are logged too
        reason = str(e) if isinstance(e, SceneforgeError) else f"{type(e).__name__}: {e}"
        return {**record, "failure": {"stage": stage, "reason": reason}}
    record.update(camera_id=ids, K=[c.K.tolist() for c in cameras],
                  cam_to_world=[c.cam_to_world.tolist() for c in cameras])
    return record


def _no_camera_reason(info: dict) -> str:
    if info["source"] == "file":
        return f"{info['file']} lists none"
    rejected = ", ".join(f"{k} {v}" for k, v in info["rejected"].items() if v)
    return f"all {info['candidates']} candidates rejected: {rejected}"


# ----------------------------------------------------------------------- 2. assign views


@dataclass(frozen=True)
class ViewPlan:
    """One view to compute: its index, house and camera."""

    index: int
    house: int
    camera_id: int
    K: np.ndarray
    cam_to_world: np.ndarray


@dataclass(frozen=True)
class Plan:
    """Every view of a run in order, and the houses they come from (records of step 1)."""

    houses: tuple[dict, ...]
    views: tuple[ViewPlan, ...]

    @classmethod
    def from_records(cls, records: list[dict]) -> "Plan":
        views, houses = [], []
        for h, rec in enumerate(records):
            start = len(views)
            if "failure" not in rec:
                for cid, K, pose in zip(rec["camera_id"], rec["K"], rec["cam_to_world"]):
                    views.append(ViewPlan(len(views), h, cid, np.array(K), np.array(pose)))
            houses.append({**rec, "views": [start, len(views)]})
        return cls(tuple(houses), tuple(views))

    def shards(self, per_shard: int) -> list[tuple[int, int]]:
        n = len(self.views)
        return [(s, min(s + per_shard, n)) for s in range(0, n, per_shard)]


# ----------------------------------------------------------------------- 3. render shards


@dataclass(frozen=True)
class ShardTask:
    """Everything a worker needs to compute and write one shard."""

    url: str  # what zarr opens (Destination.zarr_url)
    storage_options: dict
    shard: int
    views: tuple[ViewPlan, ...]
    houses: dict[int, "HouseSource"]  # the views' houses by index
    config: "DatasetConfig"


def _marker_key(shard: int) -> str:
    return f"{STAGING}/done/{shard:06d}.json"


def _mesh_key(shard: int) -> str:
    return f"{STAGING}/mesh/{shard:06d}.npz"


def render_shard(task: ShardTask) -> dict:
    """Compute the views of one shard and write them (step 3). Returns the shard's marker.

    A view whose ground truth or RGB fails is written as fill values with ``valid`` false
    and listed in the marker's failures; failing to write, or to start the renderer, raises
    :class:`SceneforgeError`.
    """
    try:
        return _render_shard(task)
    except SceneforgeError as e:
        # subclasses with their own constructor arguments do not survive pickling back
        # from a worker process; the message is what the user needs
        raise SceneforgeError(str(e)) from None


def _render_shard(task: ShardTask) -> dict:

    from .cameras import Camera
    from .store import blank_view, mesh_part, shard_key, view_arrays, write_shard
    from .view import compute_view

    config = task.config
    timings = Counter()
    renderer = _WORKER.renderer_for(config) if config.rgb.enabled else None
    views, meshes, failures = [], [], []
    for v in task.views:
        source = task.houses[v.house]
        house_id = source.id
        camera = Camera(v.K, v.cam_to_world, config.width, config.height)
        try:
            t0 = time.perf_counter()
            house = _WORKER.load(source, config)
            tracer = _WORKER.tracer_of(house)
            t1 = time.perf_counter()
            gt = compute_view(house, camera, config.view, tracer)
            t2 = time.perf_counter()
            rgb = renderer.render(house, camera) if renderer is not None else None
            t3 = time.perf_counter()
            timings.update(load=t1 - t0, ground_truth=t2 - t1, render=t3 - t2)
            views.append(view_arrays(gt, rgb, house_id, v.camera_id, config))
            meshes.append(gt.mesh)
        except Exception as e:  # one bad view must not stop the run; bugs are logged too
            reason = str(e) if isinstance(e, SceneforgeError) else f"{type(e).__name__}: {e}"
            failures.append({"house": house_id, "stage": "view", "reason": reason, "view": v.index})
            views.append(blank_view(camera, house_id, v.camera_id, config))
            meshes.append(None)

    t0 = time.perf_counter()
    dest = Destination(task.url, task.storage_options)
    try:
        group = dest.open_group("r+")
        arrays = {name: group[name] for name in views[0]}
        keys = {name: shard_key(array, task.shard) for name, array in arrays.items()}
        for key in keys.values():
            dest.rm(key)  # a shard torn by a kill is replaced, never patched
        write_shard(arrays, task.views[0].index, views)
        files = {key: dest.sha256(key) for key in keys.values()}
        marker = {"shard": task.shard, "views": [task.views[0].index, task.views[-1].index + 1],
                  "files": files, "failures": failures}
        if config.view.with_mesh:
            part = mesh_part(meshes)
            buf = io.BytesIO()
            np.savez(buf, **part)
            dest.put(_mesh_key(task.shard), buf.getvalue())
            files[_mesh_key(task.shard)] = hashlib.sha256(buf.getvalue()).hexdigest()
            marker["mesh_counts"] = part["counts"].tolist()
        dest.put_json(_marker_key(task.shard), marker)
    except OSError as e:
        raise _write_error(dest, e) from None
    timings["write"] = time.perf_counter() - t0
    return {**marker, "timings": dict(timings)}


def _intact(dest: Destination, marker: dict | None, views: tuple[int, int]) -> bool:
    """The shard of ``views`` was written completely and its files still hold what was written."""
    return (marker is not None and marker.get("views") == list(views)
            and all(dest.sha256(key) == digest for key, digest in marker["files"].items()))


# ---------------------------------------------------------------------------- execution


@contextlib.contextmanager
def _environ(variables: dict[str, str]) -> Iterator[None]:
    """Set the unset ``variables`` while the block runs (worker processes started in it
    inherit them), then restore the environment."""
    added = [k for k in variables if k not in os.environ]
    os.environ.update({k: variables[k] for k in added})
    try:
        yield
    finally:
        for k in added:
            os.environ.pop(k, None)


@contextlib.contextmanager
def executor(workers: int = 1, scheduler: str | None = None) -> Iterator[Callable[[Callable, Iterable], Iterator]]:
    """A ``map(fn, items)`` that yields results as tasks complete.

    workers   : processes (or Dask workers for ``scheduler="local"``); 1 runs in this process
    scheduler : None for local processes, ``"local"`` for a Dask LocalCluster, or the
                address of a Dask scheduler (``tcp://host:8786``)

    Local processes are started with ``spawn`` (forking a process that holds an OpenGL or
    Open3D context is unsafe) and live as long as the block, so each keeps its renderer and
    last house across tasks.
    """
    if workers < 1:
        raise SceneforgeError(f"workers must be at least 1, got {workers}")
    if scheduler is not None:
        with _dask(workers, scheduler) as run:
            yield run
    elif workers == 1:
        try:
            yield lambda fn, items: map(fn, items)
        finally:
            _WORKER.close()
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed
        from concurrent.futures.process import BrokenProcessPool

        def run(fn, items):
            futures = [pool.submit(fn, item) for item in items]
            try:
                for future in as_completed(futures):
                    yield future.result()
            except BrokenProcessPool:
                raise SceneforgeError("a worker process died (out of memory or a crash in a native library); "
                                      "run the same command again to resume") from None
            finally:
                for future in futures:
                    future.cancel()

        with _environ(_worker_env(workers)), ProcessPoolExecutor(workers, multiprocessing.get_context("spawn")) as pool:
            yield run


@contextlib.contextmanager
def _dask(workers: int, scheduler: str):
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError as e:
        raise MissingDependencyError("dask[distributed]", "--scheduler", "pip install sceneforge[store]") from e
    cluster = None
    if scheduler == "local":
        # its nannies start workers with single-threaded BLAS (Dask's pre-spawn environment);
        # the workers inherit the tracers' share of the cores
        with _environ(_worker_env(workers)):
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None)
    try:
        client = Client(cluster if cluster is not None else scheduler, timeout="30s")
    except (OSError, TimeoutError) as e:
        raise SceneforgeError(f"cannot reach the Dask scheduler {scheduler}: {e}") from None

    def run(fn, items):
        futures = client.map(fn, list(items), pure=False)
        try:
            for future in as_completed(futures):
                yield future.result()
        finally:
            client.cancel(futures)

    try:
        yield run
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


# -------------------------------------------------------------------------------- a run


def _identity(config: "DatasetConfig", houses: str) -> dict:
    """What makes two runs the same run (as the store's attributes record it)."""
    from .store import SCHEMA_VERSION

    return {"schema_version": SCHEMA_VERSION, "houses_source": houses, "config": config.to_dict()}


def _prepare(dest: Destination, identity: dict, house_ids: list[str], overwrite: bool) -> str:
    """Check the destination and claim it: ``"new"``, ``"resume"`` or ``"complete"``.

    A run resumes only with the same identity and the same houses found (view indices
    depend on them).
    """
    if overwrite and dest.exists():
        if not (dest.exists("zarr.json") or dest.exists(STAGING) or not dest.fs.ls(dest.root)):
            raise SceneforgeError(f"{dest.url}: not a zarr store; refusing to delete it (--overwrite)")
        dest.rm("")
    started = dest.get_json(f"{STAGING}/run.json")
    if started is not None:
        if started != {**identity, "house_ids": house_ids}:
            raise SceneforgeError(
                f"{dest.url}: holds an unfinished run with another config or houses; run that command "
                "again to finish it, or pass --overwrite to start over")
        return "resume"
    if dest.exists("zarr.json"):
        attrs = dest.open_group("r").attrs
        if attrs.get("complete") and {k: attrs.get(k) for k in identity} == identity:
            return "complete"
        raise SceneforgeError(f"{dest.url}: holds another store; pass --overwrite to replace it, or choose "
                              "another path")
    if dest.exists() and dest.fs.isfile(dest.root):
        raise SceneforgeError(f"{dest.url}: is a file, not a folder")
    if dest.exists() and dest.fs.ls(dest.root):
        raise SceneforgeError(f"{dest.url}: exists and is not empty; choose another path")
    dest.put_json(f"{STAGING}/run.json", {**identity, "house_ids": house_ids})
    return "new"


def _house_key(index: int) -> str:
    return f"{STAGING}/houses/{index:06d}.json"


def _plan_houses(dest, sources, config, run, progress) -> list[dict]:
    records = {i: dest.get_json(_house_key(i)) for i in range(len(sources))}
    todo = [i for i, r in records.items() if r is None]
    if progress:
        progress.start("planning houses", len(sources), "houses", done=len(sources) - len(todo))
    for i, record in run(_plan_indexed, [(i, sources[i], config) for i in todo]):
        dest.put_json(_house_key(i), record)
        records[i] = record
        if progress:
            progress.advance(1)
    return [records[i] for i in range(len(sources))]


def _plan_indexed(args) -> tuple[int, dict]:
    i, source, config = args
    return i, plan_house(source, config)


def _finalize(dest: Destination, plan: Plan, config: "DatasetConfig", houses: str,
              markers: list[dict]) -> tuple[list[dict], list[dict]]:
    """Step 4: meshes, attributes, cleanup. Returns the houses' provenance and the failure log."""
    from .store import base_attrs, write_meshes

    view_failures = {}
    for m in markers:
        for f in m["failures"]:
            view_failures.setdefault(f["house"], []).append(f)
    failures, provenance = [], []
    for rec in plan.houses:
        entry = {k: rec[k] for k in ("id", "format", "path", "views", "instances", "triangles", "rooms",
                                     "warnings", "cameras") if k in rec}
        entry["status"] = "failed" if "failure" in rec else "ok"
        provenance.append(entry)
        if "failure" in rec:
            failures.append({"house": rec["id"], **rec["failure"], "view": None})
        failures += view_failures.get(rec["id"], [])

    group = dest.open_group("r+")
    if config.view.with_mesh:
        counts = np.concatenate([np.array(m["mesh_counts"], dtype=np.int64).reshape(-1, 2, 2) for m in markers]
                                or [np.zeros((0, 2, 2), np.int64)])

        def parts():
            for m in markers:
                with np.load(io.BytesIO(dest.get(_mesh_key(m["shard"])))) as part:
                    yield dict(part)

        write_meshes(group, config, counts, parts())
    attrs = base_attrs(config, houses, len(plan.views))
    attrs.update(complete=True, houses=provenance, failures=failures)
    group.attrs.put(attrs)
    dest.rm(STAGING)
    dest.remove_partials()
    return provenance, failures


def render_dataset(
    houses: str,
    out: str,
    config: "DatasetConfig",
    *,
    workers: int = 1,
    scheduler: str | None = None,
    overwrite: bool = False,
    storage_options: dict | None = None,
    progress: Progress | None = None,
) -> RenderSummary:
    """Render every house under ``houses`` into the store at ``out`` (resuming it if a run with
    the same config and houses was interrupted there).

    houses : anything :func:`~sceneforge.houses.discover` takes (a folder, ``bundled:toy``, ...)
    out    : local path or fsspec URL of the store
    Raises :class:`SceneforgeError` for an unusable destination or a failed write; houses that
    fail are recorded in the store's failure log and the summary.
    """
    from .houses import discover
    from .store import base_attrs, create_arrays

    t_start = time.perf_counter()
    sources = discover(houses, config.houses.format)
    identity = _identity(config, str(houses))
    dest = Destination(out, storage_options)
    try:
        state = _prepare(dest, identity, [s.id for s in sources], overwrite)
    except OSError as e:
        raise _write_error(dest, e) from None
    if state == "complete":
        dest.rm(STAGING)
        dest.remove_partials()
        attrs = dest.open_group("r").attrs.asdict()
        return _summary(dest, attrs["houses"], attrs["failures"], attrs["views"], config, 0, t_start, {},
                        already_complete=True)

    timings = Counter()
    try:
        with executor(workers, scheduler) as run:
            plan = Plan.from_records(_plan_houses(dest, sources, config, run, progress))
            if dest.get_json(f"{STAGING}/created.json") != {"views": len(plan.views)}:
                group = dest.open_group("a")
                create_arrays(group, config, len(plan.views))
                group.attrs.put(base_attrs(config, str(houses), len(plan.views)))
                dest.put_json(f"{STAGING}/created.json", {"views": len(plan.views)})

            shards = plan.shards(config.store.views_per_shard)
            markers = {s: dest.get_json(_marker_key(s)) for s in range(len(shards))}
            todo = [s for s, m in markers.items() if not _intact(dest, m, shards[s])]
            if progress:
                progress.start("rendering views", len(plan.views), "views",
                               done=sum(b - a for s, (a, b) in enumerate(shards) if s not in todo))
            tasks = [ShardTask(dest.zarr_url, dest.storage_options, s, plan.views[a:b],
                               {v.house: sources[v.house] for v in plan.views[a:b]}, config)
                     for s, (a, b) in enumerate(shards) if s in todo]
            for marker in run(render_shard, tasks):
                timings.update(marker.pop("timings"))
                markers[marker["shard"]] = marker
                if progress:
                    progress.advance(marker["views"][1] - marker["views"][0])
        provenance, failures = _finalize(dest, plan, config, str(houses), [markers[s] for s in range(len(shards))])
    except OSError as e:
        raise _write_error(dest, e) from None
    return _summary(dest, provenance, failures, len(plan.views), config, len(tasks), t_start, dict(timings))


def _summary(dest, houses, failures, n_views, config, shards_run, t_start, timings, already_complete=False):
    failed = tuple(dict.fromkeys(f["house"] for f in failures))
    return RenderSummary(
        path=dest.url, views=n_views, houses=sum(h["status"] == "ok" for h in houses),
        failed_houses=failed, failures=failures, shards=math.ceil(n_views / config.store.views_per_shard),
        shards_run=shards_run, seconds=time.perf_counter() - t_start, timings=timings,
        already_complete=already_complete,
    )
