"""Input fingerprints: which files a house was read from, and whether they changed since.

Planning a house (step 1) records the SHA-256 of every file its loader opened for reading
(:func:`reads`: a Python audit hook sees each ``open``, so every format is covered without
each listing its files: a glTF's buffers and textures, a SUNCG house's room and object
meshes, a name map) into the house's plan record as ``inputs`` ``{path: SHA-256 or
None}`` (None: the file was missing). A house whose files are chosen by listing its folder
(a scene folder: by names, by ``scene.json``'s patterns or with ``--format scene``) also
records that folder's listing (:func:`listing_key`, :func:`listing`), so a file added to
it or removed from it counts as a change. A re-run compares them with the files as they are now
(:func:`changes`) and names every house that changed, was added, was removed, or failed and
changed since.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

from ..errors import listed

#: the paths being recorded in this thread (None: not recording)
_recording = threading.local()
_hooked = False
#: files that are code, not input: what Python imports while a loader runs
_CODE_SUFFIXES = (".py", ".pyc", ".so", ".pyd", ".pth")


def _hook(event: str, args: tuple) -> None:
    if event != "open":
        return
    paths = getattr(_recording, "paths", None)
    if paths is None or not isinstance(args[0], (str, bytes, os.PathLike)):
        return
    mode, flags = args[1], args[2]
    reading = ("r" in mode and "+" not in mode) if isinstance(mode, str) else (
        mode is None and isinstance(flags, int) and flags & os.O_ACCMODE == os.O_RDONLY)
    if reading:
        paths.append(os.fsdecode(args[0]))


@contextlib.contextmanager
def reads() -> Iterator[list[str]]:
    """Record the files opened for reading in this thread while the block runs: yields the
    list, filled as they are opened (code Python imports meanwhile is left out later, by
    :func:`fingerprint`)."""
    global _hooked
    if not _hooked:
        sys.addaudithook(_hook)  # audit hooks stay for the life of the process: one, installed once
        _hooked = True
    outer = getattr(_recording, "paths", None)
    _recording.paths = paths = []
    try:
        yield paths
    finally:
        _recording.paths = outer
        if outer is not None:
            outer.extend(paths)


def _code_roots() -> tuple[str, ...]:
    """Folders whose files are software, not a house: Python's, installed packages' and
    sceneforge's own (bar its bundled data: toy houses, name maps)."""
    import sceneforge

    package = Path(sceneforge.__file__).resolve().parent
    roots = {sys.prefix, sys.base_prefix, sys.exec_prefix, str(package), str(package.parent / "schemas"),
             str(package.parent / "cli")}
    roots |= {p for p in sys.path if p and ("site-packages" in p or "dist-packages" in p)}
    return tuple(str(Path(r).resolve()) + os.sep for r in roots if r)


def _is_input(path: str, code: tuple[str, ...], data: str) -> bool:
    if path.startswith(data):
        return True
    return not (path.startswith(code) or path.endswith(_CODE_SUFFIXES) or f"{os.sep}__pycache__{os.sep}" in path)


def listing(folder: str | Path) -> list[str]:
    """The files under ``folder`` (recursively, hidden files and folders left out) as sorted
    POSIX paths relative to it."""
    root = Path(folder)
    out = []
    for here, dirs, files in os.walk(root):
        dirs[:] = [d for d in dirs if not d.startswith(".")]
        out += [(Path(here) / f).relative_to(root).as_posix() for f in files if not f.startswith(".")]
    return sorted(out)


def listing_key(folder: str | Path) -> str:
    """The ``inputs`` key of a folder's listing: its absolute path and a trailing separator
    (file keys never end in one)."""
    return str(Path(folder).absolute()) + os.sep


def file_digest(path: str) -> str | None:
    """SHA-256 (hex) of the file at ``path``, or, for a :func:`listing_key`, of the folder's
    :func:`listing`; None when there is none."""
    if path.endswith(os.sep):
        if not os.path.isdir(path):
            return None
        return hashlib.sha256("\n".join(listing(path)).encode()).hexdigest()
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    except (FileNotFoundError, NotADirectoryError, IsADirectoryError):
        return None
    return h.hexdigest()


def fingerprint(paths: Iterable[str]) -> dict[str, str | None]:
    """``{path: SHA-256 or None}`` of the input files among ``paths`` (absolute, sorted)."""
    from ..houses.categories import data_file

    code, data = _code_roots(), str(data_file("")) + os.sep
    files = sorted({str(Path(p).absolute()) for p in paths})
    return {p: file_digest(p) for p in files if _is_input(p, code, data)}


@dataclass(frozen=True)
class InputChanges:
    """How the houses found now differ from those a store (or an unfinished run) was made of.

    changed : houses whose input files changed (they had no failure)
    added   : houses found now that the store does not have
    removed : houses the store has that are not found now
    fixed   : houses that failed and whose input files changed since
    """

    changed: tuple[str, ...] = ()
    added: tuple[str, ...] = ()
    removed: tuple[str, ...] = ()
    fixed: tuple[str, ...] = ()

    def __bool__(self) -> bool:
        return bool(self.changed or self.added or self.removed or self.fixed)

    @property
    def redo(self) -> set[str]:
        """The houses found now that must be planned again."""
        return {*self.changed, *self.added, *self.fixed}

    def describe(self, most: int = 8) -> str:
        """One line: ``changed: a, b; added: c; ...`` (at most ``most`` names per kind)."""
        parts = []
        for label, ids in (("changed", self.changed), ("added", self.added), ("removed", self.removed),
                           ("failed before and changed since", self.fixed)):
            if ids:
                parts.append(f"{label}: {listed(ids, most)}")
        return "; ".join(parts)


def changes(before: list[dict], now: list[str]) -> InputChanges:
    """Compare houses recorded ``before`` (plan records or store provenance: ``id``,
    ``inputs``, and ``status: failed`` or ``failure`` for a house that failed) with the ids
    of the houses found ``now``, hashing the recorded files again. A record without
    ``inputs`` (a store written before fingerprints) counts as unchanged."""
    known = {r["id"]: r for r in before}
    digests: dict[str, str | None] = {}

    def moved(record: dict) -> bool:
        for path, digest in (record.get("inputs") or {}).items():
            if path not in digests:
                digests[path] = file_digest(path)
            if digests[path] != digest:
                return True
        return False

    changed, fixed = [], []
    for hid in now:
        record = known.get(hid)
        if record is not None and moved(record):
            failed = "failure" in record or record.get("status") == "failed"
            (fixed if failed else changed).append(hid)
    found = set(now)
    return InputChanges(tuple(changed), tuple(h for h in now if h not in known),
                        tuple(h for h in known if h not in found), tuple(fixed))


def house_path(record: dict) -> Path:
    """Where the house of a store's provenance ``record`` is: its recorded ``path``, which is
    relative to the folder render ran in when HOUSES was given so; from another folder, the
    same path inside the absolute paths its fingerprinted files were read from."""
    path = Path(record["path"])
    if path.is_absolute() or path.exists():
        return path
    tail = "/" + path.as_posix().strip("/")
    for read in record.get("inputs") or {}:
        read = Path(read).as_posix()
        at = (read + "/").find(tail + "/")
        if at >= 0:
            return Path(read[: at + len(tail)])
    return path
