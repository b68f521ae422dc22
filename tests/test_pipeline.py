"""``sceneforge render``: determinism across executors, resume after SIGKILL, failures, errors."""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from sceneforge.cli.main import cli

from sceneforge.cameras import look_at_camera, write_pbrs_cameras
from sceneforge.config import load_config
from sceneforge.errors import EXIT_FAILURES, SceneforgeError
from sceneforge.houses.formats.native import write_house
from sceneforge.pipeline import executors, render_dataset
from sceneforge.store import array_digests, open_store, validate_store

#: tiny views, four per toy house, two per shard (a house's views span shards): 12 views in 6 shards
#: with the ground-truth meshes, whose parts the workers stage and the run concatenates
TINY = {"width": 32, "height": 24, "views_per_house": 4, "view": {"overhead": {"resolution": 16}},
        "store": {"views_per_shard": 2, "gt_mesh": "all"}}
COMMANDS = {"render": "render:render", "validate": "render:validate", "show": "render:show",
            "export": "render:export"}


@pytest.fixture(autouse=True)
def render_commands(monkeypatch):
    for name, target in COMMANDS.items():
        monkeypatch.setitem(cli.lazy, name, target)


def files_of(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` by relative path, with its bytes."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def config_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("config") / "tiny.json"
    path.write_text(json.dumps(TINY))
    return path


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """The store of an uninterrupted in-process run with one worker."""
    out = tmp_path_factory.mktemp("ref") / "ref.zarr"
    summary = render_dataset("bundled:toy", str(out), load_config(None, TINY))
    assert (summary.views, summary.houses, summary.failed_houses, summary.shards) == (12, 3, (), 6)
    return out


def test_reference_store_is_complete_and_valid(reference):
    files = files_of(reference)
    assert not any(name.startswith("_staging") or name.endswith(".partial") for name in files)
    assert validate_store(str(reference)) == []
    store = open_store(str(reference))
    assert len(store) == 12 and store.attrs["complete"]
    assert [str(store.view(i)["house_id"]) for i in range(12)] == ["toy_0_000"] * 4 + ["toy_0_001"] * 4 + \
        ["toy_0_002"] * 4
    assert [int(store.view(i)["camera_id"]) for i in range(12)] == [0, 1, 2, 3] * 3
    # one view per chunk, two per shard file: 6 shard files per per-view array
    assert sorted(n for n in files if n.startswith("depth/c/")) == [f"depth/c/{s}/0/0/0" for s in range(6)]


# Worker processes pay seconds of imports (open3d, and pyrender for RGB). These runs leave
# RGB out; the SIGKILL test below checks that RGB rendered in another process is identical.
NO_RGB = {**TINY, "rgb": {"enabled": False}}


@pytest.fixture(scope="module")
def reference_no_rgb(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ref") / "ref_no_rgb.zarr"
    render_dataset("bundled:toy", str(out), load_config(None, NO_RGB))
    return out


@pytest.mark.slow
def test_two_workers_write_the_same_bytes(reference_no_rgb, tmp_path):
    render_dataset("bundled:toy", str(tmp_path / "two.zarr"), load_config(None, NO_RGB), workers=2)
    assert files_of(tmp_path / "two.zarr") == files_of(reference_no_rgb)
    digests = array_digests(str(tmp_path / "two.zarr"))
    assert len(digests) == 25 and digests == array_digests(str(reference_no_rgb))  # 26 arrays less rgb


@pytest.mark.slow
def test_dask_local_cluster_writes_the_same_bytes(reference_no_rgb, tmp_path):
    render_dataset("bundled:toy", str(tmp_path / "dask.zarr"), load_config(None, NO_RGB), workers=2,
                   scheduler="local")
    assert files_of(tmp_path / "dask.zarr") == files_of(reference_no_rgb)


CHILD = "import sys; from sceneforge.cli.render import render; render.main(sys.argv[1:])"


def _start_and_kill(args, out: Path, staged: str) -> None:
    """Run ``sceneforge render args`` in a child process and SIGKILL it as soon as
    ``out/_staging/<staged>/`` holds a file."""
    proc = subprocess.Popen([sys.executable, "-c", CHILD, *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    folder = out / "_staging" / staged
    deadline = time.monotonic() + 120
    while not (folder.is_dir() and any(folder.glob("*.json"))):
        assert proc.poll() is None, f"the run ended (code {proc.returncode}) before anything was staged"
        assert time.monotonic() < deadline
        time.sleep(0.002)
    proc.send_signal(signal.SIGKILL)
    proc.wait()


@pytest.mark.slow
def test_sigkill_then_resume_gives_identical_bytes(reference, config_file, tmp_path):
    out = tmp_path / "killed.zarr"
    args = ["bundled:toy", str(out), "--config", str(config_file)]
    _start_and_kill(args, out, "houses")  # while planning houses
    _start_and_kill(args, out, "done")  # while rendering shards
    done = len(list((out / "_staging" / "done").glob("*.json"))) if (out / "_staging").is_dir() else "all"
    assert done != "all" and done < 6, f"the run was not interrupted: {done} of 6 shards done"
    with pytest.raises(SceneforgeError, match="incomplete"):
        open_store(str(out))
    res = CliRunner().invoke(cli, ["render", *args])
    assert res.exit_code == 0, res.output
    assert files_of(out) == files_of(reference)


def test_a_second_render_into_the_same_store_is_refused_and_the_first_completes(config_file, tmp_path):
    out = tmp_path / "busy.zarr"
    first = subprocess.Popen([sys.executable, "-c", CHILD, "bundled:toy", str(out), "--config", str(config_file)],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lock = tmp_path / "busy.zarr.lock"
    deadline = time.monotonic() + 120
    while not lock.exists():
        assert first.poll() is None and time.monotonic() < deadline, first.stderr.read()
        time.sleep(0.002)
    second = CliRunner().invoke(cli, ["render", "bundled:toy", str(out), "--config", str(config_file)])
    assert first.poll() is None, "the first run ended before the second one tried"
    assert second.exit_code == 1 and "Traceback" not in second.output
    assert second.output.strip().splitlines() == [
        f"error: {out}: another run is writing this store (pid {first.pid} on {socket.gethostname()}, since "
        f"{json.loads(lock.read_text())['since']}: -c bundled:toy {out} --config {config_file}); wait for it "
        "to end, or write elsewhere"]
    assert first.wait(timeout=300) == 0, first.stderr.read()
    assert not lock.exists()
    assert validate_store(str(out)) == []
    store = open_store(str(out))
    for i in range(len(store)):
        vertices, faces = store.mesh(i)["envelope"]
        assert len(faces) > 0 and np.abs(vertices).max() > 0


@pytest.mark.parametrize("executor", [["--workers", "2"], ["--workers", "2", "--scheduler", "local"]],
                         ids=["process pool", "LocalCluster"])
def test_workers_die_within_10_s_of_a_sigkilled_render(executor, small_house, tmp_path):
    psutil = pytest.importorskip("psutil")
    small_house.id = "one"
    write_house(small_house, tmp_path / "houses" / "one")
    render = subprocess.Popen([sys.executable, "-c", CHILD, str(tmp_path / "houses"), str(tmp_path / "out.zarr"),
                               "--resolution", "16x12", "--overhead-resolution", "8", "--views-per-house", "2",
                               "--no-rgb", *executor], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    workers = []
    while not workers:
        assert render.poll() is None and time.monotonic() < deadline, "the run ended before a worker started"
        workers = [p for p in psutil.Process(render.pid).children(recursive=True)
                   if "spawn_main" in " ".join(p.cmdline())]
        time.sleep(0.05)
    descendants = psutil.Process(render.pid).children(recursive=True)
    render.send_signal(signal.SIGKILL)
    render.wait()
    gone, alive = psutil.wait_procs(descendants, timeout=10)
    for p in alive:  # leave nothing behind, then fail
        p.kill()
    assert alive == [], f"alive 10 s after the run was killed: {[' '.join(p.cmdline())[:80] for p in alive]}"


def test_disk_full_is_one_error_and_resume_keeps_intact_shards_only(reference, tmp_path, monkeypatch):
    import sceneforge.store.writer

    real = sceneforge.store.writer.write_shard
    calls = []

    def fails_third_time(*args):
        calls.append(1)
        if len(calls) == 3:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(*args)

    monkeypatch.setattr(sceneforge.store.writer, "write_shard", fails_third_time)
    out = tmp_path / "full.zarr"
    with pytest.raises(SceneforgeError, match="No space left on device.*intact.*resume"):
        render_dataset("bundled:toy", str(out), load_config(None, TINY))
    assert sorted(p.name for p in (out / "_staging" / "done").iterdir()) == ["000000.json", "000001.json"]
    # a shard file torn after its marker was written (power loss before the data reached the disk)
    torn = out / "depth" / "c" / "0" / "0" / "0" / "0"
    torn.write_bytes(torn.read_bytes()[:10])
    monkeypatch.setattr(sceneforge.store.writer, "write_shard", real)
    summary = render_dataset("bundled:toy", str(out), load_config(None, TINY))
    assert summary.shards_run == 5  # shard 1 was kept; the torn shard 0 and shards 2..5 were written
    assert files_of(out) == files_of(reference)


def test_an_interrupted_run_names_an_added_house_and_update_takes_it_in(small_house, tmp_path, monkeypatch):
    import shutil

    import sceneforge.store.writer

    for name in ("a", "b"):
        small_house.id = name
        write_house(small_house, tmp_path / "houses" / name)
    config = load_config(None, {**NO_RGB, "views_per_house": 2})

    def disk_full(*args):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(sceneforge.store.writer, "write_shard", disk_full)
    with pytest.raises(SceneforgeError, match="No space left") as failed:
        render_dataset(str(tmp_path / "houses"), str(tmp_path / "out.zarr"), config)
    assert "intact" not in str(failed.value)  # no shard was written
    monkeypatch.undo()
    shutil.copytree(tmp_path / "houses" / "a", tmp_path / "houses" / "a2")
    with pytest.raises(SceneforgeError, match=r"houses changed since this run started \(added: a2\); pass --update"):
        render_dataset(str(tmp_path / "houses"), str(tmp_path / "out.zarr"), config)
    summary = render_dataset(str(tmp_path / "houses"), str(tmp_path / "out.zarr"), config, update=True)
    assert summary.changes.added == ("a2",) and summary.views == 6
    render_dataset(str(tmp_path / "houses"), str(tmp_path / "fresh.zarr"), config)
    assert array_digests(str(tmp_path / "out.zarr")) == array_digests(str(tmp_path / "fresh.zarr"))


def _moved(house, dx: float):
    """``house`` with every instance but the envelope moved ``dx`` m along x."""
    for inst in house.instances:
        if not inst.envelope:
            inst.vertices = inst.vertices + np.array([dx, 0.0, 0.0], dtype=inst.vertices.dtype)
    return house


def test_changed_added_removed_and_fixed_houses_are_named_and_update_equals_a_fresh_render(small_house, tmp_path):
    """A store of houses a, b, c and broken e; then b changes, c goes, d comes and e is fixed:
    a re-run names all four and refuses; --update redoes exactly those and ends with the
    arrays a fresh render of the new houses writes."""
    import copy

    houses, out = tmp_path / "houses", str(tmp_path / "out.zarr")
    for name in ("a", "b", "c", "e"):
        h = copy.deepcopy(small_house)
        h.id = name
        write_house(h, houses / name)
    (houses / "e" / "house.bin").write_bytes(b"\0" * 10)
    config = load_config(None, {**NO_RGB, "views_per_house": 3})  # 3 views per house, 2 per shard
    first = render_dataset(str(houses), out, config)
    assert first.failed_houses == ("e",) and first.views == 9

    b = _moved(copy.deepcopy(small_house), 0.3)
    b.id = "b"
    write_house(b, houses / "b")
    shutil.rmtree(houses / "c")
    d = _moved(copy.deepcopy(small_house), -0.2)
    d.id = "d"
    write_house(d, houses / "d")
    e = copy.deepcopy(small_house)
    e.id = "e"
    write_house(e, houses / "e")

    res = CliRunner().invoke(cli, ["render", str(houses), out, "--config", str(_config_of(config, tmp_path))])
    assert res.exit_code == 1 and "Traceback" not in res.output
    assert res.output.strip().splitlines() == [
        f"error: {out}: the houses changed since this store was rendered (changed: b; added: d; removed: c; "
        "failed before and changed since: e); pass --update to redo exactly these houses, or --overwrite to "
        "start over"]

    summary = render_dataset(str(houses), out, config, update=True)
    assert summary.changes.changed == ("b",) and summary.changes.added == ("d",)
    assert summary.changes.removed == ("c",) and summary.changes.fixed == ("e",)
    assert summary.failed_houses == () and summary.views == 12
    # a's shard 0 (views 0, 1) is kept; every shard from view 2 on holds other views now
    assert summary.shards_run == 5
    fresh = str(tmp_path / "fresh.zarr")
    render_dataset(str(houses), fresh, config)
    assert array_digests(out) == array_digests(fresh)
    assert validate_store(out) == []
    assert open_store(out).attrs["houses"] == open_store(fresh).attrs["houses"]
    assert render_dataset(str(houses), out, config).already_complete


def _config_of(config, tmp_path) -> Path:
    path = tmp_path / "config.json"
    path.write_text(json.dumps(config.to_dict()))
    return path


def test_retry_failed_retries_failed_houses_only(small_house, tmp_path, monkeypatch):
    import sceneforge.view

    houses, out = _houses_with_failures(small_house, tmp_path / "houses"), str(tmp_path / "out.zarr")
    config = load_config(None, {**NO_RGB, "views_per_house": 2})
    real = sceneforge.view.compute_view

    def flaky(house, camera, *args):
        if house.id == "good" and flaky.fail:
            raise MemoryError("out of memory")
        return real(house, camera, *args)

    flaky.fail = True
    monkeypatch.setattr(sceneforge.view, "compute_view", flaky)
    first = render_dataset(str(houses), out, config)
    assert first.failed_houses == ("corrupt", "good", "no_floor")
    assert render_dataset(str(houses), out, config).already_complete  # nothing changed: nothing to do
    flaky.fail = False
    summary = render_dataset(str(houses), out, config, retry_failed=True)
    assert summary.retried == ("corrupt", "good", "no_floor") and summary.shards_run == 1
    assert summary.failed_houses == ("corrupt", "no_floor")
    assert all(open_store(out).view(i)["valid"] for i in range(2))


def test_rerun_of_a_complete_store_does_nothing_and_other_config_is_refused(reference, tmp_path):
    import shutil

    out = tmp_path / "copy.zarr"
    shutil.copytree(reference, out)
    summary = render_dataset("bundled:toy", str(out), load_config(None, TINY))
    assert summary.already_complete and summary.views == 12
    # the refusal says what differs, not only that something does
    with pytest.raises(SceneforgeError, match=r"another store \(config\.seed: 0 there, 1 here\)"):
        render_dataset("bundled:toy", str(out), load_config(None, {**TINY, "seed": 1}))
    assert files_of(out) == files_of(reference)


def _houses_with_failures(small_house, root: Path) -> Path:
    """Three houses: ``good``, ``corrupt`` (its buffer missing) and ``no_floor`` (no camera)."""
    small_house.id = "good"
    write_house(small_house, root / "good")
    small_house.id = "corrupt"
    write_house(small_house, root / "corrupt")
    (root / "corrupt" / "house.bin").write_bytes(b"\0" * 10)
    small_house.id = "no_floor"
    small_house.instances = [i for i in small_house.instances if i.category_name != "floor"]
    write_house(small_house, root / "no_floor")
    return root


def test_failed_houses_are_logged_and_the_others_complete(small_house, tmp_path):
    houses = _houses_with_failures(small_house, tmp_path / "houses")
    out = tmp_path / "out.zarr"
    res = CliRunner().invoke(cli, ["render", str(houses), str(out), "--resolution", "32x24",
                                   "--overhead-resolution", "16", "--views-per-house", "2", "--no-rgb"])
    assert res.exit_code == EXIT_FAILURES, res.output
    assert "Traceback" not in res.output
    assert "2 houses failed" in res.output
    failed = [line for line in res.output.splitlines() if line.startswith("failed:")]
    assert len(failed) == 2 and "house corrupt (load)" in failed[0] and "house no_floor (cameras)" in failed[1]

    store = open_store(str(out))
    assert validate_store(str(out)) == []
    assert len(store) == 2 and {str(store.view(i)["house_id"]) for i in range(2)} == {"good"}
    log = store.attrs["failures"]
    assert [(f["house"], f["stage"]) for f in log] == [("corrupt", "load"), ("no_floor", "cameras")]
    assert "no horizontal floor surface" in log[1]["reason"]
    status = {h["id"]: (h["status"], h["views"]) for h in store.attrs["houses"]}
    assert status == {"corrupt": ("failed", [0, 0]), "good": ("ok", [0, 2]), "no_floor": ("failed", [2, 2])}


def test_a_view_that_fails_is_blank_and_logged(tmp_path, monkeypatch):
    import sceneforge.view

    real = sceneforge.view.compute_view

    def fails_on_camera(house, camera, *args):
        if house.id == "toy_0_001" and np.allclose(camera.cam_to_world, second_camera):
            raise FloatingPointError("a bug")
        return real(house, camera, *args)

    config = load_config(None, NO_RGB)
    out = tmp_path / "out.zarr"
    # a first run shows the cameras: view 5 is house toy_0_001's second one
    render_dataset("bundled:toy", str(out), config)
    second_camera = open_store(str(out)).view(5)["cam_to_world"]
    monkeypatch.setattr(sceneforge.view, "compute_view", fails_on_camera)
    summary = render_dataset("bundled:toy", str(out), config, overwrite=True)
    assert summary.failed_houses == ("toy_0_001",) and summary.views == 12
    assert summary.failures == [{"house": "toy_0_001", "stage": "view", "reason": "FloatingPointError: a bug",
                                 "view": 5}]
    store = open_store(str(out))
    assert validate_store(str(out)) == []
    v = store.view(5)
    assert not v["valid"] and np.isnan(v["depth"]).all() and (v["instance"] == -1).all()
    np.testing.assert_array_equal(v["cam_to_world"], second_camera)  # its camera is kept
    assert store.mesh(5)["objects"][0].shape == (0, 3)
    assert all(store.view(i)["valid"] for i in range(12) if i != 5)


def test_camera_files_are_used_in_order_with_their_line_numbers(small_house, tmp_path):
    small_house.id = "room"
    write_house(small_house, tmp_path / "houses" / "room")
    cams = [look_at_camera((1.0, 1.5, 1.5), (-1.0, -0.3, -1.0), width=32, height=24),
            look_at_camera((-1.5, 1.4, -1.0), (1.0, -0.2, 0.5), width=32, height=24)]
    path = tmp_path / "cams" / "room" / "room_camera.txt"
    path.parent.mkdir(parents=True)
    write_pbrs_cameras(path, cams)
    lines = path.read_text().splitlines()
    path.write_text("\n".join([lines[0], "", "# a comment", lines[1]]) + "\n")
    out = tmp_path / "out.zarr"
    config = load_config(None, {**TINY, "cameras": str(tmp_path / "cams"), "rgb": {"enabled": False},
                                "store": {**TINY["store"], "gt_mesh": "none"}})
    summary = render_dataset(str(tmp_path / "houses"), str(out), config)
    assert summary.failed_houses == ()
    assert validate_store(str(out)) == []
    store = open_store(str(out))
    assert [int(store.view(i)["camera_id"]) for i in range(len(store))] == [0, 3]
    for i, cam in enumerate(cams):
        np.testing.assert_allclose(store.view(i)["cam_to_world"], cam.cam_to_world, atol=1e-12)
        np.testing.assert_allclose(store.view(i)["K"], cam.K, atol=1e-9)
    assert store.attrs["houses"][0]["cameras"] == {"source": "file", "file": str(path), "requested": 2,
                                                   "accepted": 2}
    assert "rgb" not in store.view(0) and not store.has_mesh
    with pytest.raises(SceneforgeError, match="keeps no ground-truth meshes"):
        store.mesh(0)


def test_missing_camera_file_fails_that_house(small_house, tmp_path):
    for name in ("room", "other"):
        small_house.id = name
        write_house(small_house, tmp_path / "houses" / name)
    path = tmp_path / "cams" / "room" / "room_camera.txt"
    path.parent.mkdir(parents=True)
    write_pbrs_cameras(path, [look_at_camera((1.0, 1.5, 1.5), (-1.0, -0.3, -1.0), width=32, height=24)])
    config = load_config(None, {**TINY, "cameras": str(tmp_path / "cams"), "rgb": {"enabled": False},
                                "store": {**TINY["store"], "gt_mesh": "none"}})
    summary = render_dataset(str(tmp_path / "houses"), str(tmp_path / "out.zarr"), config)
    assert summary.failed_houses == ("other",) and summary.views == 1
    assert "no camera file" in summary.failures[0]["reason"]
    assert validate_store(str(tmp_path / "out.zarr")) == []


def test_a_cameras_folder_with_no_camera_file_is_refused(small_house, tmp_path):
    """A wrong folder would fail every house into a store of no views."""
    small_house.id = "room"
    write_house(small_house, tmp_path / "houses" / "room")
    (tmp_path / "cams").mkdir()
    config = load_config(None, {**TINY, "cameras": str(tmp_path / "cams"), "rgb": {"enabled": False},
                                "store": {**TINY["store"], "gt_mesh": "none"}})
    with pytest.raises(SceneforgeError, match=r"no camera file for any of the 1 house \(expected .*room_camera"):
        render_dataset(str(tmp_path / "houses"), str(tmp_path / "out.zarr"), config)
    assert not (tmp_path / "out.zarr").exists()


def test_the_store_can_live_on_an_fsspec_filesystem():
    url = "memory://sceneforge-test/store.zarr"
    summary = render_dataset("bundled:toy", url, load_config(None, {**NO_RGB, "views_per_house": 1}))
    assert summary.views == 3 and summary.failed_houses == ()
    assert validate_store(url) == []
    assert [str(open_store(url).view(i)["house_id"]) for i in range(3)] == ["toy_0_000", "toy_0_001", "toy_0_002"]


def test_unwritable_destination_is_one_red_line(tmp_path):
    (tmp_path / "file").write_text("not a folder")
    res = CliRunner().invoke(cli, ["render", "bundled:toy", str(tmp_path / "file" / "out.zarr"), "--no-rgb"])
    assert res.exit_code == 1
    lines = res.output.strip().splitlines()
    assert lines[-1].startswith("error: ") and "cannot write" in lines[-1] and "Traceback" not in res.output


def test_options_and_config_file_resolve_into_the_store(config_file, tmp_path):
    out = tmp_path / "cli.zarr"
    res = CliRunner().invoke(cli, ["render", "bundled:toy", str(out), "--config", str(config_file),
                                   "--views-per-house", "1", "--seed", "7", "--no-rgb", "--scale", "1"])
    assert res.exit_code == 0, res.output
    assert "3 views of 3 houses" in res.output
    config = open_store(str(out)).config
    assert (config.views_per_house, config.seed, config.width, config.store.views_per_shard) == (1, 7, 32, 2)
    assert not config.rgb.enabled
    res = CliRunner().invoke(cli, ["render", "bundled:toy", str(out), "--cameras", str(tmp_path),
                                   "--views-per-house", "2"])
    assert res.exit_code == 2 and "exclude each other" in res.output


def _allocator_settings(_):
    return {k: os.environ.get(k) for k in ("OPENBLAS_NUM_THREADS", *executors.MALLOC_THRESHOLDS)}


def test_worker_processes_get_single_threaded_blas_and_the_malloc_thresholds():
    """Spawned workers start with the environment glibc and OpenBLAS read at start-up; this
    process (the one-worker run) sets the thresholds through mallopt."""
    with executors.executor(2) as run:
        seen = list(run(_allocator_settings, range(2)))
    want = {"OPENBLAS_NUM_THREADS": "1", **{k: str(v) for k, v in executors.MALLOC_THRESHOLDS.items()}}
    assert seen == [want, want]
    assert not {k for k in executors.MALLOC_THRESHOLDS if k in os.environ}, "the parent's environment is restored"
    if sys.platform.startswith("linux"):
        assert executors.tune_allocator()


def test_render_uses_every_usable_core_by_default_but_no_idle_worker(monkeypatch):
    import os

    from sceneforge.pipeline.executors import default_workers

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3}, raising=False)
    assert [default_workers(t) for t in (0, 1, 3, 4, 100)] == [1, 1, 3, 4, 4]
