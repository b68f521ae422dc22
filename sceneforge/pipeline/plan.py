"""Step 1 of a run: plan each house (load it, choose its cameras), resuming from the
records an interrupted run staged."""

from __future__ import annotations

import zlib
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from ..errors import SceneforgeError, plural
from .inputs import file_digest, fingerprint, listing_key, reads
from .staging import house_key
from .worker import WORKER

if TYPE_CHECKING:
    from ..config import DatasetConfig
    from ..houses import HouseSource
    from ..store import StoreWriter
    from . import Progress


def house_rng(seed: int, house_id: str) -> np.random.Generator:
    """The camera sampler's generator for a house: depends on the seed and the house id
    only, so a house gets the same cameras whatever other houses are in the run."""
    return np.random.default_rng([seed, zlib.crc32(house_id.encode())])


def sample_house_cameras(house, config: "DatasetConfig", tracer=None):
    """The cameras ``sceneforge render`` samples for ``house`` with ``config`` and the
    sampler's report (:class:`~sceneforge.camera_sampler.SamplerReport`): the same generator
    (seed and house id), so ``houses inspect --cameras`` shows what render will choose."""
    from ..camera_sampler import sample_cameras

    return sample_cameras(house, config.views_per_house, house_rng(config.seed, house.id), config.sampler, tracer)


def _load_recording_inputs(source: "HouseSource", config: "DatasetConfig", record: dict):
    """Load ``source`` afresh, recording the files its loader read in ``record["inputs"]``
    (:mod:`.inputs`), whether the load succeeds or raises."""
    WORKER.forget_house()  # a house cached by an earlier task would be read from no file
    with reads() as paths:
        try:
            return WORKER.load(source, config)
        finally:
            inputs = fingerprint(paths)
            if source.format == "scene":  # its files are what its folder (its path) holds
                key = listing_key(source.path)
                inputs[key] = file_digest(key)
            record["inputs"] = dict(sorted(inputs.items()))


def check_camera_folder(cameras: str, house_ids: list[str]) -> None:
    """Refuse a ``--cameras`` folder that holds a camera file for none of the houses (a
    wrong folder would otherwise fail every house and leave a store of no views)."""
    folder = Path(cameras)
    if not folder.is_dir():
        raise SceneforgeError(f"--cameras {cameras}: no such folder")
    if house_ids and not any((folder / hid / "room_camera.txt").is_file() for hid in house_ids):
        raise SceneforgeError(
            f"--cameras {cameras}: no camera file for any of the {plural(len(house_ids), 'house')} (expected "
            f"{folder / house_ids[0] / 'room_camera.txt'}, one folder per house id)")


def _file_cameras(source: "HouseSource", config: "DatasetConfig"):
    """Cameras of ``<cameras>/<house id>/room_camera.txt`` and their 0-based line numbers."""
    from ..cameras import read_pbrs_cameras

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
    loader ``notes`` when there are any (the up axis detected), ``cameras`` (how they were
    chosen), ``camera_id``, ``K`` and ``cam_to_world`` per camera; or ``failure``
    (``stage``, ``reason``) when the house cannot be used.
    """
    record = {"id": source.id, "format": source.format, "path": str(Path(source.path).absolute())}
    stage = "load"
    try:
        house = _load_recording_inputs(source, config, record)
        record.update(instances=len(house.instances), triangles=house.triangle_count, rooms=len(house.rooms),
                      warnings=list(house.warnings))
        if house.notes:
            record["notes"] = list(house.notes)
        stage = "cameras"
        if config.cameras is not None:
            cameras, ids, info = _file_cameras(source, config)
        else:
            cameras, report = sample_house_cameras(house, config, WORKER.tracer_of(house))
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


def plan_houses(writer: "StoreWriter", sources: list["HouseSource"], config: "DatasetConfig", run: Callable,
                progress: "Progress | None") -> list[dict]:
    """Step 1 for every house, in parallel through ``run``; a house whose record is staged
    already (an interrupted run) is not planned again. Returns the records in ``sources`` order."""
    records = {i: writer.get_json(house_key(s.id)) for i, s in enumerate(sources)}
    todo = [i for i, r in records.items() if r is None]
    if progress:
        progress.start("planning houses", len(sources), "houses", done=len(sources) - len(todo))
    for i, record in run(_plan_indexed, [(i, sources[i], config) for i in todo]):
        writer.put_json(house_key(sources[i].id), record)
        records[i] = record
        if progress:
            progress.advance(1)
    return [records[i] for i in range(len(sources))]


def _plan_indexed(args) -> tuple[int, dict]:
    i, source, config = args
    return i, plan_house(source, config)
