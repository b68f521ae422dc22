"""The lock that lets one run at a time write a store: a file beside it naming its holder."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import socket
import sys
import time
import uuid
from typing import TYPE_CHECKING

from ..errors import StoreLockedError

if TYPE_CHECKING:
    from .writer import StoreWriter

log = logging.getLogger(__name__)


class StoreLock:
    """The lock of a store: a file beside it (``OUT.zarr.lock``) naming the process that
    writes it (pid, host, process start time, command line).

    A lock whose process is gone (same host, and no process with that pid and start time:
    killed with SIGKILL, or the machine rebooted) is taken over with a warning on the
    ``sceneforge.store.lock`` logger. On a local filesystem the lock file is created atomically
    (a hard link that fails when the file exists); on other fsspec filesystems (object
    stores) it is checked, then written, which leaves a short window for two runs started
    at the same moment.
    """

    def __init__(self, writer: "StoreWriter"):
        self.writer = writer
        self.path = f"{writer.root}.lock"
        self.me = {"pid": os.getpid(), "host": socket.gethostname(), "started": _process_start(os.getpid()),
                   "since": time.strftime("%Y-%m-%d %H:%M:%S"),
                   "command": " ".join([os.path.basename(sys.argv[0]), *sys.argv[1:]])}

    def acquire(self) -> None:
        """Take the lock; raises :class:`StoreLockedError` while a live process holds it."""
        data = json.dumps(self.me).encode()
        for _ in range(5):
            if self._create(data):
                return
            holder = self._read()
            if holder is None:  # being written right now, or torn by a crash while written
                time.sleep(0.2)
                holder = self._read()
            if holder is not None and _alive(holder):
                elsewhere = "" if holder.get("host") == self.me["host"] else f"; if that run is gone, delete {self.path}"
                raise StoreLockedError(
                    f"{self.writer.url}: another run is writing this store ({_describe(holder)}); wait for it to "
                    f"end, or write elsewhere{elsewhere}")
            if self._take_over(holder):
                log.warning("%s: took over the lock of a run that is no longer running (%s)", self.writer.url,
                            "a torn lock file" if holder is None else _describe(holder))
        raise StoreLockedError(f"{self.writer.url}: cannot take the lock {self.path}: other runs keep taking it")

    def release(self) -> None:
        """Remove the lock file, if it is still this process's."""
        holder = self._read()
        if holder is not None and holder.get("pid") == self.me["pid"] and holder.get("host") == self.me["host"]:
            with contextlib.suppress(FileNotFoundError):
                self.writer.fs.rm(self.path)

    def _create(self, data: bytes) -> bool:
        fs = self.writer.fs
        fs.makedirs(self.path.rsplit("/", 1)[0] or "/", exist_ok=True)
        if not self.writer.local:
            if fs.exists(self.path):
                return False
            fs.pipe_file(self.path, data)
            return True
        tmp = f"{self.path}.{uuid.uuid4().hex}.partial"
        with open(tmp, "wb") as f:
            f.write(data)
        try:
            os.link(tmp, self.path)
            return True
        except FileExistsError:
            return False
        finally:
            os.unlink(tmp)

    def _read(self) -> dict | None:
        try:
            return json.loads(self.writer.fs.cat_file(self.path))
        except (FileNotFoundError, ValueError):
            return None

    def _take_over(self, stale: dict | None) -> bool:
        """Remove the stale lock ``stale`` unless another process replaced it meanwhile;
        True when it was removed (by this process or another)."""
        fs = self.writer.fs
        aside = f"{self.path}.{uuid.uuid4().hex}.stale"
        try:
            fs.mv(self.path, aside)
        except FileNotFoundError:
            return False
        try:
            moved = json.loads(fs.cat_file(aside))
        except ValueError:
            moved = None
        if moved != stale:  # a live run's fresh lock, taken between the read and the move: put it back
            fs.mv(aside, self.path)
            return False
        fs.rm(aside)
        return True


def _process_start(pid: int) -> str | None:
    """When process ``pid`` started, as an opaque string (boot id and start tick on Linux;
    None where /proc does not tell), so that a pid reused by a later process is not mistaken
    for the holder of a lock."""
    try:
        with open("/proc/sys/kernel/random/boot_id") as f:
            boot = f.read().strip()
        with open(f"/proc/{pid}/stat") as f:
            stat = f.read()
        return f"{boot}:{stat.rsplit(')', 1)[1].split()[19]}"
    except (OSError, IndexError):
        return None


def _alive(holder: dict) -> bool:
    """The process that wrote lock ``holder`` is still running (assumed so on another host)."""
    if holder.get("host") != socket.gethostname():
        return True
    pid = int(holder.get("pid", -1))
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # alive, another user's
    started = holder.get("started")
    return started is None or _process_start(pid) in (None, started)


def _describe(holder: dict) -> str:
    command = holder.get("command") or "?"
    return f"pid {holder.get('pid')} on {holder.get('host')}, since {holder.get('since')}: {command}"
