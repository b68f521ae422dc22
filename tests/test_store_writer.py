"""The store writer: create, write shards in any order, meshes, finalize, read back exactly;
its atomic files; the array digests; its lock; and that no other module writes a store
with zarr."""

from __future__ import annotations

import ast
import json
import os
import socket
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("zarr", reason="the store extra (zarr) is not installed")

from sceneforge.config import load_config  # noqa: E402
from sceneforge.errors import SceneforgeError  # noqa: E402
from sceneforge.store import (  # noqa: E402
    MESH_KINDS,
    StoreWriter,
    array_digests,
    array_specs,
    layout,
    mesh_part,
    open_store,
    sizes_of,
)

ROOT = Path(__file__).resolve().parents[1]
#: 7 views of 8 x 6 pixels, 4 x 4 overhead, 3 views per shard: shards of 3, 3 and 1 views
N = 7
SMALL = {"width": 8, "height": 6, "view": {"overhead": {"resolution": 4}},
         "store": {"views_per_shard": 3, "gt_mesh": "all"}}


def random_views(config, rng: np.random.Generator) -> list[dict[str, np.ndarray]]:
    """N views of random values of every per-view array of ``config``."""
    sizes = sizes_of(config, 1)
    views = []
    for i in range(N):
        view = {}
        for spec in array_specs(config, per_view=True):
            shape = spec.shape(sizes)[1:]
            if spec.dtype == "string":
                view[spec.name] = np.array(f"house_{i // 3}", dtype=spec.numpy_dtype)
            elif spec.dtype == "bool":
                view[spec.name] = np.asarray(rng.random(shape) < 0.5)
            elif np.issubdtype(spec.numpy_dtype, np.integer):
                view[spec.name] = rng.integers(0, 40, shape).astype(spec.numpy_dtype)
            else:
                view[spec.name] = rng.normal(size=shape).astype(spec.numpy_dtype)
        views.append(view)
    return views


def random_meshes(rng: np.random.Generator) -> list:
    """N views' ground-truth meshes (as :func:`mesh_part` reads them); view 2 has none."""
    def mesh(v, f):
        return SimpleNamespace(vertices=rng.normal(size=(v, 3)), faces=rng.integers(0, v, (f, 3)),
                               instance=rng.integers(0, 5, f))

    return [None if i == 2 else SimpleNamespace(objects=mesh(3 + i, 2 * i), envelope=mesh(4, 2)) for i in range(N)]


def shards_of(views: list) -> list[tuple[int, list]]:
    return [(s, views[s * 3: s * 3 + 3]) for s in range((N + 2) // 3)]


def write_store(url: str, config, views: list, meshes: list | None, order=(2, 0, 1)) -> StoreWriter:
    writer = StoreWriter(url)
    writer.create(config, "houses/", N)
    shards = shards_of(views)
    for s in order:
        writer.write_shard(*shards[s])
    houses = [{"id": f"house_{h}", "format": "native", "path": f"houses/{h}", "status": "ok",
               "views": [3 * h, min(3 * h + 3, N)]} for h in range(3)]
    if meshes is not None:
        parts = [mesh_part(meshes[s * 3: s * 3 + 3]) for s, _ in shards]
        writer.write_meshes(config, np.concatenate([p.pop("counts") for p in parts]), parts)
    writer.finalize(config, "houses/", N, houses=houses, failures=[], note="written by a test")
    return writer


def test_shards_written_out_of_order_read_back_exactly(tmp_path):
    config = load_config(None, SMALL)
    rng = np.random.default_rng(0)
    views, meshes = random_views(config, rng), random_meshes(rng)
    url = str(tmp_path / "s.zarr")
    write_store(url, config, views, meshes)
    store = open_store(url)
    assert len(store) == N and store.attrs["complete"] and store.attrs["note"] == "written by a test"
    assert store.config == config and [h["id"] for h in store.attrs["houses"]] == ["house_0", "house_1", "house_2"]
    assert set(store.names) == {s.name for s in array_specs(config, per_view=True)}
    for i, view in enumerate(views):
        got = store.view(i)
        for name, value in view.items():
            if name == "house_id":
                assert str(got[name]) == str(value)
            else:
                np.testing.assert_array_equal(got[name], value, err_msg=f"view {i}: {name}")
        for kind in MESH_KINDS:
            v, f = store.mesh(i)[kind]
            m = None if meshes[i] is None else getattr(meshes[i], kind)
            np.testing.assert_array_equal(v, np.zeros((0, 3)) if m is None else m.vertices.astype(np.float32))
            np.testing.assert_array_equal(f, np.zeros((0, 3)) if m is None else m.faces)
    assert not list(tmp_path.rglob("*.partial"))


def test_a_store_is_incomplete_until_finalized(tmp_path):
    config = load_config(None, {**SMALL, "store": {**SMALL["store"], "gt_mesh": "none"}})
    url = str(tmp_path / "s.zarr")
    writer = StoreWriter(url)
    writer.create(config, "houses/", N)
    for s, views in shards_of(random_views(config, np.random.default_rng(1))):
        writer.write_shard(s, views)
    with pytest.raises(SceneforgeError, match="incomplete"):
        open_store(url)
    assert len(open_store(url, allow_incomplete=True)) == N
    assert not open_store(url, allow_incomplete=True).has_mesh


def test_a_shard_written_again_is_replaced(tmp_path):
    config = load_config(None, {**SMALL, "store": {**SMALL["store"], "gt_mesh": "none"}})
    first, second = (random_views(config, np.random.default_rng(seed)) for seed in (2, 3))
    writer = StoreWriter(str(tmp_path / "s.zarr"))
    writer.create(config, "houses/", N)
    writer.write_shard(1, first[3:6])
    keys = writer.write_shard(1, second[3:6])
    assert sorted(keys) == sorted("/".join([s.name, "c", "1", *"0" * (len(s.dims) - 1)])
                                  for s in array_specs(config, per_view=True))
    store = open_store(str(tmp_path / "s.zarr"), allow_incomplete=True)
    np.testing.assert_array_equal(store.array("depth")[3:6], np.stack([v["depth"] for v in second[3:6]]))


def test_files_are_put_atomically_and_torn_json_reads_as_missing():
    writer = StoreWriter("memory://sceneforge-writer-test/s.zarr")
    assert writer.is_empty() and not writer.is_file()
    writer.put_json("_staging/a.json", {"x": 1})
    assert writer.get_json("_staging/a.json") == {"x": 1} and not writer.is_empty()
    writer.put("_staging/b.json", b'{"x": ')
    assert writer.get_json("_staging/b.json") is None and writer.get("_staging/c.json") is None
    assert writer.sha256("_staging/a.json") is not None and writer.sha256("_staging/c.json") is None
    assert [p for p in writer.fs.find(writer.root) if p.endswith(".partial")] == []
    writer.rm("")
    assert not writer.exists()


def test_digests_follow_values_not_chunk_layout(tmp_path):
    config = load_config(None, SMALL)
    rng = np.random.default_rng(4)
    views, meshes = random_views(config, rng), random_meshes(rng)
    write_store(str(tmp_path / "a.zarr"), config, views, meshes)
    regrouped = load_config(None, {**SMALL, "store": {"views_per_shard": 1}})
    writer = StoreWriter(str(tmp_path / "b.zarr"))
    writer.create(regrouped, "houses/", N)
    for i in reversed(range(N)):
        writer.write_shard(i, views[i: i + 1])
    parts = [mesh_part(meshes)]
    writer.write_meshes(regrouped, parts[0].pop("counts"), parts)
    writer.finalize(regrouped, "houses/", N, houses=[], failures=[])
    a, b = array_digests(str(tmp_path / "a.zarr")), array_digests(str(tmp_path / "b.zarr"))
    assert set(a) == {s.name for s in array_specs(config)} and a == b

    views[5]["depth"][0, 0, 0] += 1
    write_store(str(tmp_path / "c.zarr"), config, views, meshes)
    c = array_digests(str(tmp_path / "c.zarr"))
    assert [name for name in a if a[name] != c[name]] == ["depth"]


def test_every_per_view_array_has_a_source():
    assert all(s.source for s in layout().values() if s.per_view)


def _imports_zarr(path: Path) -> bool:
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
            [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0 else []
        if any(n == "zarr" or n.startswith("zarr.") for n in names):
            return True
    return False


def test_only_the_store_package_imports_zarr():
    files = sorted((ROOT / "sceneforge").rglob("*.py")) + sorted((ROOT / "cli").rglob("*.py"))
    assert ROOT / "sceneforge" / "store" / "writer.py" in files and len(files) > 20
    importers = {str(p.relative_to(ROOT)) for p in files if _imports_zarr(p)}
    assert importers and all(p.startswith("sceneforge/store/") for p in importers), sorted(importers)


# ------------------------------------------------------------------------------- the lock


def test_a_second_writer_is_refused_naming_the_holder_and_the_lock_goes_with_the_run(tmp_path):
    from sceneforge.errors import StoreLockedError

    url = str(tmp_path / "s.zarr")
    with StoreWriter(url):
        assert (tmp_path / "s.zarr.lock").is_file()
        with pytest.raises(StoreLockedError, match=rf"another run is writing this store \(pid {os.getpid()} on "):
            with StoreWriter(url):
                pass
    assert not (tmp_path / "s.zarr.lock").exists()
    with pytest.raises(KeyboardInterrupt):  # released on Ctrl-C too
        with StoreWriter(url):
            raise KeyboardInterrupt
    assert not (tmp_path / "s.zarr.lock").exists()


def test_the_lock_of_a_dead_process_is_taken_over_with_a_warning(tmp_path, caplog):
    import subprocess
    import sys

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    lock = tmp_path / "s.zarr.lock"
    lock.write_text(json.dumps({"pid": dead.pid, "host": socket.gethostname(), "started": "boot:1",
                                "since": "2024-01-01 00:00:00", "command": "sceneforge render a b"}))
    with caplog.at_level("WARNING", logger="sceneforge.store"):
        with StoreWriter(str(tmp_path / "s.zarr")):
            assert json.loads(lock.read_text())["pid"] == os.getpid()
    assert f"took over the lock of a run that is no longer running (pid {dead.pid} on" in caplog.text
    # a live pid whose start time is not the recorded one is a reused pid: taken over too
    lock.write_text(json.dumps({"pid": os.getppid(), "host": socket.gethostname(), "started": "another boot:1"}))
    with StoreWriter(str(tmp_path / "s.zarr")):
        pass
    assert not lock.exists()
