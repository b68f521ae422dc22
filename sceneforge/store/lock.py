"""The lock that lets one run at a time write a store: a file beside it naming its holder."""

from __future__ import annotations

import json
import logging
import os
import socket
import sys
import time
from typing import TYPE_CHECKING

from ..errors import StoreLockedError

if TYPE_CHECKING:
    from .writer import StoreWriter

log = logging.getLogger(__name__)


class StoreLock:
    """The lock of a store: a file beside it (``OUT.zarr.lock``) naming the process that
    writes it (pid, host, process start time, command line).

    It is created only where none is, and a stale one is replaced only while it is still
    the one read, both by the store's place (:class:`~.location.Location`): on local files
    (a hard link) and on S3 (conditional PUTs, so also for runs on two machines) two runs
    cannot both hold it, nor both take over the same stale one. A lock whose process is gone (same host, and no process
    with that pid and start time: killed with SIGKILL, or the machine rebooted) is taken
    over with a warning on the ``sceneforge.store.lock`` logger; one held on another host
    is taken as alive (the message says which file to delete if that run is gone).
    """

    def __init__(self, writer: "StoreWriter"):
        self.writer = writer
        self.location = writer.location
        self.path = f"{writer.root}.lock"
        self.me = {"pid": os.getpid(), "host": socket.gethostname(), "started": _process_start(os.getpid()),
                   "since": time.strftime("%Y-%m-%d %H:%M:%S"),
                   "command": " ".join([os.path.basename(sys.argv[0]), *sys.argv[1:]])}

    def acquire(self) -> None:
        """Take the lock; raises :class:`StoreLockedError` while a live process holds it."""
        data = json.dumps(self.me).encode()
        for _ in range(5):
            if self.location.create(self.path, data):
                return
            found = self._read()
            if found is not None and found[0] is None:  # being written right now, or torn by a crash
                time.sleep(0.2)
                found = self._read()
            if found is None:  # released meanwhile
                continue
            holder, version = found
            if holder is not None and _alive(holder):
                elsewhere = ("" if holder.get("host") == self.me["host"] else
                             f"; if that run is gone, delete {self.location.url_of(self.path)}")
                raise StoreLockedError(
                    f"{self.writer.url}: another run is writing this store ({_describe(holder)}); wait for it to "
                    f"end, or write elsewhere{elsewhere}")
            if self.location.replace(self.path, data, version):
                log.warning("%s: took over the lock of a run that is no longer running (%s)", self.writer.url,
                            "a torn lock file" if holder is None else _describe(holder))
                return
        raise StoreLockedError(f"{self.writer.url}: cannot take the lock {self.location.url_of(self.path)}: other "
                               "runs keep taking it")

    def release(self) -> None:
        """Remove the lock file, if it is still this process's."""
        found = self._read()
        holder = found and found[0]
        if holder and holder.get("pid") == self.me["pid"] and holder.get("host") == self.me["host"]:
            self.location.remove(self.path)

    def _read(self) -> tuple[dict | None, object] | None:
        """The holder named by the lock file (None when it is not JSON) and the file's
        version; None when there is no lock file."""
        found = self.location.read(self.path)
        if found is None:
            return None
        data, version = found
        try:
            holder = json.loads(data)
        except ValueError:
            holder = None
        return (holder if isinstance(holder, dict) else None), version


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
