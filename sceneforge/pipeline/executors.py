"""Where a run's tasks execute: in this process, a pool of spawned local processes, or a
Dask distributed cluster, all behind one ``map(fn, items)`` that yields results as tasks
complete."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from typing import Callable, Iterable, Iterator

from ..errors import MissingDependencyError, SceneforgeError
from .worker import WORKER

#: glibc malloc thresholds for the processes that compute views (bytes): a view's arrays
#: are a few MB each, above glibc's default mmap threshold, so each was mapped fresh,
#: page-faulted in and unmapped again when freed, or the heap's top trimmed back to the
#: system after every view; kept in the heap, the next view reuses the memory. 8 of a toy
#: view's 74 ms (benchmarks/bench_ground_truth.py runs with them); resident memory stays
#: flat over 500 views.
MALLOC_THRESHOLDS = {"MALLOC_MMAP_THRESHOLD_": 256 << 20, "MALLOC_TRIM_THRESHOLD_": 512 << 20}
_MALLOPT = {"MALLOC_MMAP_THRESHOLD_": -3, "MALLOC_TRIM_THRESHOLD_": -1}  # M_MMAP_THRESHOLD, M_TRIM_THRESHOLD

#: environment of local worker processes: BLAS thread pools fight Open3D's for the cores
#: when each worker has its own; glibc reads the malloc thresholds at start-up
_WORKER_ENV = {"OPENBLAS_NUM_THREADS": "1", **{k: str(v) for k, v in MALLOC_THRESHOLDS.items()}}


def tune_allocator() -> bool:
    """Set :data:`MALLOC_THRESHOLDS` in this process (glibc's ``mallopt``), as worker
    processes get them from their environment; False where the C library has no mallopt."""
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    return all(mallopt(_MALLOPT[k], int(v)) == 1 for k, v in MALLOC_THRESHOLDS.items())


def default_workers(tasks: int) -> int:
    """``render --workers``'s default: a process per core this process may use, at most one
    per task (a house to plan, a shard to render): on 2 cores 2 workers render the toy
    houses 1.7× as fast as one (docs/benchmarks.md), and an idle worker only costs memory."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, tasks))


def _worker_env(workers: int) -> dict[str, str]:
    """Environment of ``workers`` local worker processes: single-threaded BLAS, and the
    cores shared out among the workers' ray tracers (Open3D would otherwise give each
    worker a thread per core: on 2 cores, 2 workers ran no faster than 1)."""
    from ..raytrace import THREADS_ENV

    return {**_WORKER_ENV, THREADS_ENV: str(max(1, (os.cpu_count() or 1) // workers))}


#: prctl(2) option: the signal the kernel sends this process when its parent ends
_PR_SET_PDEATHSIG = 1


def die_with_parent(parent: int, poll: float = 1.0) -> None:
    """Make this (worker) process end when process ``parent`` ends, however it ends (SIGKILL
    included): on Linux the kernel kills it at once (``PR_SET_PDEATHSIG``); everywhere a
    daemon thread also checks every ``poll`` seconds that its parent is still ``parent``.
    Without it a pool's workers outlive a killed run: each holds both ends of its pipes,
    so none sees the parent go."""
    if sys.platform.startswith("linux"):
        import ctypes

        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # the parent ended before the line above
        os._exit(1)

    def watch():
        while True:
            time.sleep(poll)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, name="die-with-parent", daemon=True).start()


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
    last house across tasks. They end with this process, whatever ends it
    (:func:`die_with_parent`; a LocalCluster's worker processes watch their nanny, which
    lives in this process, the same way).
    """
    if workers < 1:
        raise SceneforgeError(f"workers must be at least 1, got {workers}")
    if scheduler is not None:
        with _dask(workers, scheduler) as run:
            yield run
    elif workers == 1:
        tune_allocator()
        try:
            yield lambda fn, items: map(fn, items)
        finally:
            WORKER.close()
    else:
        with _process_pool(workers) as run:
            yield run


@contextlib.contextmanager
def _process_pool(workers: int):
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

    context = multiprocessing.get_context("spawn")
    with _environ(_worker_env(workers)), ProcessPoolExecutor(workers, context, initializer=die_with_parent,
                                                             initargs=(os.getpid(),)) as pool:
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
