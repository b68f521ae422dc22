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
   ever write the same file. Its ground-truth meshes (with ``store.gt_mesh: all``) go to a
   staged part; a marker listing the SHA-256 of every file it wrote is written last, atomically.
4. **Finalize** (main process, single writer): the mesh parts, if any, are concatenated in view
   order into the ragged mesh arrays, provenance and the failure log are written to the
   group attributes with ``complete: true``, and the staging folder is removed.

Work in progress lives in ``OUT.zarr/_staging/``. A killed run (SIGKILL, power loss)
restarted with the same command skips every house record and shard whose marker is intact
and whose files still hash as recorded, redoes the rest, and ends with the same bytes as an
uninterrupted run: nothing written depends on timing, worker count or scheduler.

One run writes a store at a time (the store's lock, :class:`~sceneforge.store.StoreLock`).
Each house's plan record holds the SHA-256 of the files it was read from: a re-run names the
houses that changed, were added or removed since and refuses, unless ``update`` (those
houses are planned and rendered again, the rest kept: the store ends as a fresh run on the
new houses would write it); ``retry_failed`` plans and renders the failed houses again.

Execution: in-process (``workers=1``), a pool of spawned processes (``workers=N``) or a Dask
distributed cluster (``scheduler="tcp://host:8786"``, or ``"local"`` for a LocalCluster).
Each worker process keeps one renderer and the last house it loaded.

One module per step: :mod:`.plan` (1), :mod:`.assign` (2), :mod:`.shards` (3),
:mod:`.finalize` (4); :mod:`.staging` keeps the work in progress and decides what resumes,
:mod:`.executors` runs the tasks, :mod:`.worker` is what a worker process keeps between them.
The store itself is written through :class:`~sceneforge.store.StoreWriter`. :mod:`.explain`
redoes a run's steps for one house up to the overhead camera, to show how it was chosen
(``sceneforge overhead-camera``); :mod:`.gt_mesh` makes the ground-truth meshes of a store's
views from its houses where the store keeps none (``store.gt_mesh: none``, the default).
"""

from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Protocol

from ..store import StoreWriter, location_errors
from ..store.guard import check_apart, check_store_output
from ..store.location import resolve
from .assign import Plan, ViewPlan
from .executors import default_workers, executor
from .finalize import finalize_store
from .inputs import InputChanges
from .plan import check_camera_folder, plan_house, plan_houses
from .shards import ShardTask, render_shard
from .staging import CREATED_KEY, STAGING, identity, intact, marker_key, prepare, recorded_config, write_error

if TYPE_CHECKING:
    from ..config import DatasetConfig
    from ..houses import HouseSource

__all__ = ["Plan", "Progress", "RenderSummary", "STAGING", "ShardTask", "ViewPlan", "executor", "plan_house",
           "render_dataset", "render_shard"]


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
    seconds  : wall time of the run; ``render_seconds``: of its rendering step alone
               (``views_rendered`` views), the rate the progress bar shows
    changes  : the houses that changed since the store (or the unfinished run) was made,
               redone with ``update``; ``retried``: the failed houses retried
    damaged  : the files of a complete store found not as written (their shards were
               rendered again); ``removed``: the files no run wrote, removed
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
    views_rendered: int = 0
    render_seconds: float = 0.0
    changes: InputChanges = InputChanges()
    retried: tuple[str, ...] = ()
    damaged: tuple[str, ...] = ()
    removed: tuple[str, ...] = ()


def render_dataset(
    houses: str,
    out: str,
    config: "DatasetConfig",
    *,
    workers: int | None = 1,
    scheduler: str | None = None,
    overwrite: bool = False,
    update: bool = False,
    retry_failed: bool = False,
    repair: bool = False,
    storage_options: dict | None = None,
    progress: Progress | None = None,
) -> RenderSummary:
    """Render every house under ``houses`` into the store at ``out`` (resuming it if a run with
    the same config and houses was interrupted there).

    houses       : anything :func:`~sceneforge.houses.discover` takes (a folder, ``bundled:toy``, ...)
    out          : local path or fsspec URL of the store
    workers      : processes (1: this one); None = one per usable core, at most one per house
                   or shard (:func:`~.executors.default_workers`)
    update       : when houses changed, were added or removed since the store (or the
                   unfinished run) was made, redo exactly those (else that is refused)
    retry_failed : plan and render the houses that failed again
    repair       : render with the config the store records (``config`` is not used). Any
                   re-run of a complete store hashes its files against its manifest and
                   renders again exactly the shards whose files are damaged or missing,
                   removing the files no run wrote, so that it ends as a clean render
    Raises :class:`SceneforgeError` for an unusable destination (one of the inputs, or
    holding anything but this command's own dataset store: :mod:`sceneforge.store.guard`),
    a store another run is writing, changed houses without ``update``, or a failed write; houses that fail are
    recorded in the store's failure log and the summary.
    """
    from ..houses import discover

    t_start = time.perf_counter()
    # recorded absolute, so that the store names its houses from any folder (messages keep HOUSES as given)
    source = str(houses) if str(houses).startswith("bundled:") else resolve(str(houses))
    check_apart(out, "store", [("houses", houses)])
    check_store_output(out, "dataset", overwrite=overwrite, storage_options=storage_options)
    writer = StoreWriter(out, storage_options)
    if repair:
        config = recorded_config(writer)
    check_apart(out, "store", [("camera folder", config.cameras)])
    sources = discover(houses, config.houses.format)
    if config.cameras is not None:
        check_camera_folder(config.cameras, [s.id for s in sources])
    if workers is None:
        shards = -(-len(sources) * config.views_per_house // config.store.views_per_shard)
        workers = default_workers(max(len(sources), shards))
    try:
        with writer, location_errors(writer.url):  # S3 gone mid-run: one line, as at the start
            prep = prepare(writer, identity(config, source), [s.id for s in sources], overwrite=overwrite,
                           update=update, retry_failed=retry_failed)
            if prep.state == "complete":
                writer.rm(STAGING)
                writer.remove_partials()
                attrs = writer.attrs()
                return _summary(writer, attrs["houses"], attrs["failures"], attrs["views"], config, t_start,
                                prep=prep, already_complete=True)
            with executor(workers, scheduler) as run:
                plan = Plan.from_records(plan_houses(writer, sources, config, run, progress))
                created = writer.get_json(CREATED_KEY)
                if created != {"views": len(plan.views)}:
                    if created is None:
                        writer.create(config, source, len(plan.views))
                    else:  # an update: the shards that keep their views stay
                        writer.resize(config, len(plan.views))
                    writer.put_json(CREATED_KEY, {"views": len(plan.views)})
                rendered = _render_shards(writer, plan, sources, config, run, progress)
            provenance, failures = finalize_store(writer, plan, config, source, rendered.markers)
    except OSError as e:
        raise write_error(writer, e) from None
    return _summary(writer, provenance, failures, len(plan.views), config, t_start, rendered, prep)


@dataclass
class _Rendered:
    """What step 3 did: every shard's marker in shard order, the shards and views rendered
    now, their wall seconds and their worker seconds per stage."""

    markers: list[dict]
    shards: int
    views: int
    seconds: float
    timings: dict[str, float]


def _render_shards(writer: StoreWriter, plan: Plan, sources: list["HouseSource"], config: "DatasetConfig",
                   run: Callable, progress: Progress | None) -> _Rendered:
    """Step 3 for every shard whose staged marker is not intact."""
    shards = plan.shards(config.store.views_per_shard)
    digests = [plan.digest(a, b) for a, b in shards]
    markers = {s: writer.get_json(marker_key(s)) for s in range(len(shards))}
    todo = [s for s, m in markers.items() if not intact(writer, m, shards[s], digests[s])]
    views = sum(shards[s][1] - shards[s][0] for s in todo)
    if progress:
        progress.start("rendering views", len(plan.views), "views", done=len(plan.views) - views)
    tasks = [ShardTask(writer.zarr_url, writer.storage_options, s, plan.views[a:b],
                       {v.house: sources[v.house] for v in plan.views[a:b]}, config, digests[s])
             for s, (a, b) in enumerate(shards) if s in set(todo)]
    timings = Counter()
    t0 = time.perf_counter()
    for marker in run(render_shard, tasks):
        timings.update(marker.pop("timings"))
        markers[marker["shard"]] = marker
        if progress:
            progress.advance(marker["views"][1] - marker["views"][0])
    return _Rendered([markers[s] for s in range(len(shards))], len(tasks), views, time.perf_counter() - t0,
                     dict(timings))


def _summary(writer, houses, failures, n_views, config, t_start, rendered: _Rendered | None = None,
             prep=None, already_complete=False) -> RenderSummary:
    failed = tuple(dict.fromkeys(f["house"] for f in failures))
    return RenderSummary(
        path=writer.url, views=n_views, houses=sum(h["status"] == "ok" for h in houses),
        failed_houses=failed, failures=failures, shards=math.ceil(n_views / config.store.views_per_shard),
        shards_run=rendered.shards if rendered else 0, seconds=time.perf_counter() - t_start,
        timings=rendered.timings if rendered else {}, already_complete=already_complete,
        views_rendered=rendered.views if rendered else 0, render_seconds=rendered.seconds if rendered else 0.0,
        changes=prep.changes if prep else InputChanges(), retried=prep.retried if prep else (),
        damaged=prep.damaged if prep else (), removed=prep.removed if prep else (),
    )
