"""Step 3 of a run: one task per shard computes its views (ground truth and RGB) and writes
that shard of every per-view array, so no two tasks ever write the same file."""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..errors import SceneforgeError
from ..store import StoreWriter
from .assign import ViewPlan
from .staging import marker_key, mesh_key, put_mesh_part
from .worker import WORKER

if TYPE_CHECKING:
    from ..config import DatasetConfig
    from ..houses import HouseSource


@dataclass(frozen=True)
class ShardTask:
    """Everything a worker needs to compute and write one shard."""

    url: str  # the store as a writer in another process opens it (StoreWriter.zarr_url)
    storage_options: dict
    shard: int
    views: tuple[ViewPlan, ...]
    houses: dict[int, "HouseSource"]  # the views' houses by index
    config: "DatasetConfig"
    plan: str  # the digest of the shard's plan (Plan.digest), kept in its marker


def render_shard(task: ShardTask) -> dict:
    """Compute the views of one shard and write them (step 3). Returns the shard's marker
    (see :mod:`~sceneforge.pipeline.staging`) plus ``timings``, this task's worker seconds
    per stage.

    A view whose ground truth or RGB fails is written as fill values with ``valid`` false
    and listed in the marker's failures; failing to start the renderer raises
    :class:`SceneforgeError`, failing to write the :class:`OSError` (the run names the store
    and what resumes).
    """
    try:
        views, meshes, failures, timings = _compute_views(task)
        t0 = time.perf_counter()
        marker = _write(task, views, meshes, failures)
    except SceneforgeError as e:
        # subclasses with their own constructor arguments do not survive pickling back
        # from a worker process; the message is what the user needs
        raise SceneforgeError(str(e)) from None
    timings["write"] = time.perf_counter() - t0
    return {**marker, "timings": dict(timings)}


def _compute_views(task: ShardTask) -> tuple[list[dict], list, list[dict], Counter]:
    """The shard's views as :func:`~sceneforge.store.view_arrays` entries, their meshes
    (None for a failed view), the failures and the seconds spent per stage."""
    from ..cameras import Camera
    from ..store import blank_view, view_arrays
    from ..view import compute_view

    config = task.config
    timings = Counter()
    renderer = WORKER.renderer_for(config) if config.rgb.enabled else None
    views, meshes, failures = [], [], []
    for v in task.views:
        source = task.houses[v.house]
        house_id = source.id
        camera = Camera(v.K, v.cam_to_world, config.width, config.height)
        try:
            t0 = time.perf_counter()
            house = WORKER.load(source, config)
            tracer = WORKER.tracer_of(house)
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
    return views, meshes, failures, timings


def _write(task: ShardTask, views: list[dict], meshes: list, failures: list[dict]) -> dict:
    """Write the shard, stage its meshes, then its marker (last: it vouches for the rest)."""
    from ..store import mesh_part

    writer = StoreWriter(task.url, task.storage_options)
    writer.write_shard(task.shard, views)
    files = dict(writer.files)
    marker = {"shard": task.shard, "views": [task.views[0].index, task.views[-1].index + 1], "plan": task.plan,
              "files": files, "failures": failures}
    if task.config.view.with_mesh:
        part = mesh_part(meshes)
        files[mesh_key(task.shard)] = put_mesh_part(writer, task.shard, part)
        marker["mesh_counts"] = part["counts"].tolist()
    writer.put_json(marker_key(task.shard), marker)
    return marker
