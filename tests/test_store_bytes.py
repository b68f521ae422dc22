"""Bytes per view: the default store (no meshes, per-array codecs) against the old defaults
(meshes kept, every array byte-shuffled) on a toy and a real-style house, the same values in
both; ``benchmarks/bench_store_bytes.py`` prints the whole table."""

from __future__ import annotations

from pathlib import Path

import pytest
import zarr

from sceneforge.config import load_config
from sceneforge.houses import BUNDLED_TOY
from sceneforge.pipeline import render_dataset
from sceneforge.store import array_digests, check_store

from .conftest import BREAKFAST_ROOM, needs_shared

#: the old defaults, still selectable
OLD = {"store": {"gt_mesh": "all", "codec": "blosc-zstd"}}


def shard_bytes_per_view(store: Path, views: int) -> float:
    """The bytes of the store's arrays (their chunk files) per view."""
    return sum(p.stat().st_size for p in store.rglob("*") if p.is_file() and "/c/" in p.as_posix()) / views


@pytest.mark.slow
@pytest.mark.parametrize("houses", [BUNDLED_TOY, pytest.param(BREAKFAST_ROOM, marks=needs_shared(BREAKFAST_ROOM))],
                         ids=["toy", "breakfast_room"])
def test_the_default_store_is_a_fraction_of_the_old_with_the_same_values(houses, tmp_path):
    stores = {}
    for name, overrides in (("old", OLD), ("new", {})):
        stores[name] = tmp_path / f"{name}.zarr"
        summary = render_dataset(str(houses), str(stores[name]), load_config(None, {"views_per_house": 1, **overrides}))
        assert summary.failed_houses == () and check_store(str(stores[name])).valid
    views = summary.views
    old, new = (shard_bytes_per_view(stores[k], views) for k in ("old", "new"))
    assert new < 0.2 * old
    if houses == BUNDLED_TOY:
        assert new <= 0.5e6  # 320x240, RGB on
    old_digests, new_digests = array_digests(str(stores["old"])), array_digests(str(stores["new"]))
    assert new_digests == {k: v for k, v in old_digests.items() if not k.startswith("mesh/")}
    depth = zarr.open_group(str(stores["new"]), mode="r")["depth"].metadata.codecs[0].codecs[-1].to_dict()
    assert depth["configuration"]["shuffle"] == "shuffle" and depth["configuration"]["blocksize"] == 5 * 240 * 320 * 4
