"""Stores on S3, against a real S3 API served on this machine (moto's server, started here
in a subprocess: :func:`sceneforge.testing.s3.local_s3`), through s3fs as users reach S3:
the endpoint and credentials in ``AWS_ENDPOINT_URL``, ``AWS_ACCESS_KEY_ID``, ...

A render to ``s3://`` is whole, valid and holds a local render's arrays; its lock is a
conditional write (create-only ``If-None-Match: *``; a stale one taken over with
``If-Match`` on its ETag), so a second render is refused and two runs never both hold it;
a SIGKILLed render resumes to the same arrays; an unreachable endpoint, a missing bucket
and denied credentials are one red line each; and every command that reads a store reads
one there.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from click.testing import CliRunner

pytest.importorskip("moto.server", reason="the test extra (moto[server]) is not installed")
s3fs = pytest.importorskip("s3fs", reason="the s3 extra (s3fs) is not installed")

from sceneforge.cli.main import cli  # noqa: E402

from sceneforge.config import load_config  # noqa: E402
from sceneforge.errors import EXIT_FAILURES, SceneforgeError, StoreLockedError  # noqa: E402
from sceneforge.pipeline import render_dataset  # noqa: E402
from sceneforge.store import StoreWriter, array_digests, open_store, validate_store  # noqa: E402
from sceneforge.store.location import open_location  # noqa: E402
from sceneforge.testing.s3 import FOREIGN, free_port, local_s3  # noqa: E402

BUCKET = "bucket"
#: 3 toy houses × 2 views of 64×48 (the nets' smallest input), one shard per house
CONFIG = {"width": 64, "height": 48, "views_per_house": 2, "view": {"overhead": {"resolution": 32}},
          "store": {"views_per_shard": 2}}


@pytest.fixture(scope="module")
def s3():
    """A moto server with the bucket ``bucket``; this process's (and its children's)
    environment points at it. Yields an s3fs filesystem on it."""
    with local_s3() as server, pytest.MonkeyPatch.context() as mp:
        for name in FOREIGN:
            mp.delenv(name, raising=False)
        for name, value in server.env.items():
            mp.setenv(name, value)
        # fsspec caches filesystems by their options, not by the environment they read: none
        # made for another server (this module's fixture again, after other modules' tests) serves
        s3fs.S3FileSystem.clear_instance_cache()
        fs = s3fs.S3FileSystem(skip_instance_cache=True)
        fs.mkdir(BUCKET)
        yield fs
    s3fs.S3FileSystem.clear_instance_cache()


@pytest.fixture(scope="module")
def config_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("config") / "s3.json"
    path.write_text(json.dumps(CONFIG))
    return path


@pytest.fixture(scope="module")
def local_digests(tmp_path_factory) -> dict[str, str]:
    out = tmp_path_factory.mktemp("local") / "toy.zarr"
    render_dataset("bundled:toy", str(out), load_config(None, CONFIG))
    return array_digests(str(out))


@pytest.fixture(scope="module")
def store(s3) -> str:
    url = f"s3://{BUCKET}/toy.zarr"
    summary = render_dataset("bundled:toy", url, load_config(None, CONFIG))
    assert (summary.views, summary.houses, summary.shards, summary.failed_houses) == (6, 3, 3, ())
    return url


def run(*args):
    return CliRunner().invoke(cli, list(map(str, args)))


def keys(fs, prefix: str) -> list[str]:
    fs.invalidate_cache()
    return sorted(fs.find(f"{BUCKET}/{prefix}"))


# ------------------------------------------------------------------------------ a render


def test_a_render_to_s3_is_whole_valid_and_holds_the_local_arrays(s3, store, local_digests):
    res = run("validate", store)
    assert res.exit_code == 0 and res.output.strip() == f"{store}: valid (dataset store, 6 views)"
    digests = array_digests(store)
    assert {"rgb", "depth", "overhead_height"} <= digests.keys() and digests == local_digests
    opened = open_store(store)  # whole views read from the shard objects by byte range, as zarr reads them
    for name in ("depth", "category", "K"):
        array = opened.array(name)
        np.testing.assert_array_equal(array.views([5, 0, 3]), np.stack([array[5], array[0], array[3]]))
        assert array._reader is not None
    files = keys(s3, "toy.zarr")
    assert files and not any("/_staging/" in k or k.endswith(".partial") for k in files)
    assert not s3.exists(f"{BUCKET}/toy.zarr.lock")  # released


# ------------------------------------------------------------------------------ the lock


def test_the_lock_is_created_only_where_none_is_and_replaced_only_while_unchanged(s3):
    place = open_location(f"s3://{BUCKET}/race.zarr")
    path = f"{BUCKET}/race.zarr.lock"
    # eight writers at once, as on eight machines: one creates the lock
    barrier, won = threading.Barrier(8), []

    def create(i):
        barrier.wait()
        if place.create(path, json.dumps({"host": f"machine{i}"}).encode()):
            won.append(i)

    threads = [threading.Thread(target=create, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    data, etag = place.read(path)
    assert len(won) == 1 and json.loads(data) == {"host": f"machine{won[0]}"}
    # two runs that both found it stale: the first replace wins, the second's ETag is gone
    assert place.replace(path, b'{"host": "taker1"}', etag)
    assert not place.replace(path, b'{"host": "taker2"}', etag)
    assert json.loads(place.read(path)[0]) == {"host": "taker1"}
    place.remove(path)
    assert place.read(path) is None and not place.replace(path, b"{}", etag)


def test_a_conditional_write_in_conflict_has_lost(s3, monkeypatch):
    """S3 answers 409 ConditionalRequestConflict to a conditional write racing another one
    (moto never does): that writer did not get the lock, as with 412."""
    from botocore.exceptions import ClientError
    from s3fs.errors import translate_boto_error

    place = open_location(f"s3://{BUCKET}/conflict.zarr")

    def conflict(*args, **kwargs):
        raise translate_boto_error(ClientError({"Error": {"Code": "ConditionalRequestConflict"}}, "PutObject"))

    monkeypatch.setattr(place.fs, "pipe_file", conflict)
    assert not place.create(f"{BUCKET}/conflict.zarr.lock", b"{}")
    assert not place.replace(f"{BUCKET}/conflict.zarr.lock", b"{}", '"etag"')


def test_a_dead_runs_lock_is_taken_over_and_another_hosts_is_not(s3, caplog):
    url = f"s3://{BUCKET}/stale.zarr"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = {"pid": dead.pid, "host": socket.gethostname(), "started": "boot:1", "since": "2024-01-01 00:00:00",
             "command": "sceneforge render a b"}
    s3.pipe_file(f"{BUCKET}/stale.zarr.lock", json.dumps(stale).encode())
    with caplog.at_level("WARNING", logger="sceneforge.store"):
        with StoreWriter(url):
            assert json.loads(s3.cat_file(f"{BUCKET}/stale.zarr.lock"))["pid"] == os.getpid()
    assert f"took over the lock of a run that is no longer running (pid {dead.pid} on" in caplog.text
    assert not s3.exists(f"{BUCKET}/stale.zarr.lock")
    elsewhere = {**stale, "host": "another-machine"}
    s3.pipe_file(f"{BUCKET}/stale.zarr.lock", json.dumps(elsewhere).encode())
    with pytest.raises(StoreLockedError, match=rf"on another-machine.*if that run is gone, delete "
                                               rf"s3://{BUCKET}/stale.zarr.lock$"):
        with StoreWriter(url):
            pass


def _start_render(url: str, config_file, until: str, s3) -> subprocess.Popen:
    """``sceneforge render bundled:toy URL`` in a child process, returned once ``until``
    (a key under the bucket, or a prefix ending in ``/``) exists."""
    proc = subprocess.Popen([sys.executable, "-m", "sceneforge", "render", "bundled:toy", url, "--config",
                             str(config_file)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not keys(s3, until):
        assert proc.poll() is None, f"the run ended (code {proc.returncode}) first: {proc.stderr.read()}"
        assert time.monotonic() < deadline
        time.sleep(0.02)
    return proc


def test_a_second_render_of_the_same_url_is_refused_in_one_line(s3, config_file):
    url = f"s3://{BUCKET}/busy.zarr"
    first = _start_render(url, config_file, "busy.zarr.lock", s3)
    try:
        second = run("render", "bundled:toy", url, "--config", config_file)
        assert first.poll() is None, "the first run ended before the second one tried"
        holder = json.loads(s3.cat_file(f"{BUCKET}/busy.zarr.lock"))
    finally:
        first.kill()
        first.wait()
    assert second.exit_code == 1 and "Traceback" not in second.output
    assert second.output.strip().splitlines() == [
        f"error: {url}: another run is writing this store (pid {first.pid} on {socket.gethostname()}, since "
        f"{holder['since']}: __main__.py render bundled:toy {url} --config {config_file}); wait for it to end, "
        "or write elsewhere"]


def test_a_killed_render_resumes_to_the_local_arrays(s3, config_file, local_digests):
    url = f"s3://{BUCKET}/killed.zarr"
    proc = _start_render(url, config_file, "killed.zarr/_staging/done/", s3)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = len(keys(s3, "killed.zarr/_staging/done/"))
    assert 1 <= done < 3, f"the run was not killed mid-way: {done} of 3 shards done"
    with pytest.raises(SceneforgeError, match="incomplete"):
        open_store(url)
    assert run("validate", url).exit_code == EXIT_FAILURES
    res = run("render", "bundled:toy", url, "--config", config_file)
    assert res.exit_code == 0, res.output
    lines = " ".join(res.output.split())
    assert f"took over the lock of a run that is no longer running (pid {proc.pid} on" in lines
    assert f"6 views of 3 houses in 3 shards ({3 - done} written now)" in lines
    assert validate_store(url) == [] and array_digests(url) == local_digests


# ---------------------------------------------------------------------------- a cluster


def test_a_dask_clusters_workers_write_one_store_on_s3(s3, local_digests, tmp_path):
    """docs/store.md "On a cluster": a scheduler and two worker processes of their own, each reaching
    S3 through its own environment as on other machines, and `render --scheduler ADDRESS`:
    the workers write their shards into the bucket, and the store holds a local render's
    arrays (RGB left out: the workers would each start a renderer)."""
    pytest.importorskip("distributed", reason="the store extra (dask[distributed]) is not installed")
    config = tmp_path / "no_rgb.json"
    config.write_text(json.dumps({**CONFIG, "rgb": {"enabled": False}}))
    address = f"tcp://127.0.0.1:{free_port()}"
    dask = [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port",
            address.rsplit(":", 1)[1], "--no-dashboard"]
    workers = [sys.executable, "-m", "distributed.cli.dask_worker", address, "--nworkers", "2", "--nthreads", "1",
               "--no-dashboard"]
    started = [subprocess.Popen(dask, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL),
               subprocess.Popen(workers, env={**os.environ, "SCENEFORGE_TRACE_THREADS": "1"},
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    url = f"s3://{BUCKET}/cluster.zarr"
    try:
        res = run("render", "bundled:toy", url, "--config", config, "--scheduler", address)
    finally:
        for proc in reversed(started):
            proc.terminate()
            proc.wait(timeout=60)
    assert res.exit_code == 0 and "6 views of 3 houses in 3 shards (3 written now)" in res.output, res.output
    assert validate_store(url) == []
    assert array_digests(url) == {k: v for k, v in local_digests.items() if k != "rgb"}


# ------------------------------------------------------------------------------ bad input


def _render_in_a_child(url: str, env: dict) -> subprocess.CompletedProcess:
    """A render in a fresh process (its S3 clients see ``env`` alone), of one tiny view per
    house; its stderr without the blank line the progress bar leaves."""
    done = subprocess.run([sys.executable, "-m", "sceneforge", "render", "bundled:toy", url, "--views-per-house",
                           "1", "--resolution", "16x12", "--overhead-resolution", "8", "--no-rgb"],
                          env={**os.environ, **env, "NO_COLOR": "1"}, capture_output=True, text=True, timeout=300)
    done.stderr = done.stderr.strip()
    return done


def test_the_endpoint_and_credentials_may_come_from_fsspecs_configuration(s3):
    """FSSPEC_S3_* (or ~/.config/fsspec/s3.json) instead of AWS_*: the writer and zarr both
    take them."""
    env = {name: "" for name in ("AWS_ENDPOINT_URL", "AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY")}
    env.update(FSSPEC_S3_ENDPOINT_URL=os.environ["AWS_ENDPOINT_URL"], FSSPEC_S3_KEY="testing",
               FSSPEC_S3_SECRET="testing")
    done = _render_in_a_child(f"s3://{BUCKET}/configured.zarr", env)
    assert done.returncode == 0, done.stderr
    assert f"s3://{BUCKET}/configured.zarr: 3 views of 3 houses" in done.stderr


def test_an_unreachable_endpoint_is_one_red_line(s3):
    port = free_port()  # nothing listens there
    # one attempt (the standard variable): botocore would retry for ~10 s
    done = _render_in_a_child(f"s3://{BUCKET}/toy.zarr", {"AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}",
                                                          "AWS_MAX_ATTEMPTS": "1"})
    assert done.returncode == 1 and done.stdout == ""
    assert done.stderr.splitlines() == [
        f'error: s3://{BUCKET}/toy.zarr: cannot reach S3 (Could not connect to the endpoint URL: '
        f'"http://127.0.0.1:{port}/{BUCKET}/toy.zarr/zarr.json"); check the endpoint (AWS_ENDPOINT_URL) and the '
        'network']  # the first request: what is at OUT (sceneforge.store.guard)


def test_a_missing_bucket_is_one_red_line_and_not_created(s3):
    done = _render_in_a_child("s3://no-such-bucket/toy.zarr", {})
    assert done.returncode == 1 and done.stdout == ""
    assert done.stderr.splitlines() == [
        "error: s3://no-such-bucket/toy.zarr: no bucket 'no-such-bucket' at that endpoint; create it first "
        "(sceneforge writes into an existing bucket)"]
    assert not s3.exists("no-such-bucket")
    res = run("validate", "s3://no-such-bucket/toy.zarr")
    assert res.exit_code == 1 and res.output.strip().splitlines() == [done.stderr.strip()]


def test_denied_credentials_are_one_red_line():
    with local_s3(deny_all=True) as denying:
        done = _render_in_a_child(f"s3://{BUCKET}/toy.zarr", denying.env)
    assert done.returncode == 1 and done.stdout == ""
    assert done.stderr.splitlines() == [
        f"error: s3://{BUCKET}/toy.zarr: access denied (InvalidAccessKeyId The AWS Access Key Id you provided "
        "does not exist in our records.); check the credentials (AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, "
        "AWS_PROFILE) and the bucket's permissions"]


# ------------------------------------------------------------------------- every reader


def test_every_command_reads_a_store_on_s3(s3, store, tmp_path):
    assert run("show", store, "--view", 1, "-o", tmp_path / "panel.png").exit_code == 0
    assert (tmp_path / "panel.png").stat().st_size > 1000
    res = run("export", store, tmp_path / "exr")
    assert res.exit_code == 0 and len(list((tmp_path / "exr").glob("view_*.exr"))) == 6, res.output
    # 2 training houses, 1 test house; the split is saved beside the store, on S3; a
    # DataLoader worker (a forked process) reads the store too
    res = run("train", store, "--stage", "depth", "--run", tmp_path / "run", "--max-steps", 2, "--batch-size", 2,
              "--width", 0.125, "--val-fraction", 0, "--test-fraction", 0.34, "--device", "cpu", "--no-tensorboard", "--workers", 1)
    assert res.exit_code == 0 and "2 steps" in " ".join(res.output.split()), res.output
    split = json.loads(s3.cat_file(f"{BUCKET}/toy.split.json"))
    assert (len(split["train"]), len(split["test"])) == (2, 1)
    pred = f"s3://{BUCKET}/pred.zarr"
    res = run("predict", tmp_path / "run", store, pred, "--device", "cpu")
    assert res.exit_code == 0 and "2 of 6 views predicted (depth)" in " ".join(res.output.split()), res.output
    assert validate_store(pred) == []
    res = run("evaluate", "predictions", pred, store, "--density", 100, "--plot", tmp_path / "p.png")
    assert res.exit_code == 0 and "split: test (2 views of 1 house)" in res.output, res.output
