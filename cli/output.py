"""What every command does with the files it writes: check the location before working
(so hours of work do not end on an unwritable path), write each file atomically (a
temporary file renamed into place: a reader, or a run cut short, never sees half a file),
and say counts in words ("1 house", "2 houses")."""

from __future__ import annotations

import contextlib
import errno
import os
import uuid
from pathlib import Path
from typing import Iterator

from sceneforge.errors import SceneforgeError, plural

__all__ = ["atomic_output", "check_output", "plural", "save_figure", "write_text"]


def _is_url(path: str) -> bool:
    return "://" in str(path)


def check_output(path: str | os.PathLike | None, what: str = "output", kind: str = "file") -> None:
    """Raise :class:`SceneforgeError` (one line) unless ``what`` can be written at ``path``:
    not inside a store (:func:`~sceneforge.store.guard.check_not_in_store`), and writable,
    checked by writing a probe file where it will go (and removing it). None and URLs (fsspec: the
    store writer checks those) pass.

    kind : ``"file"``; ``"folder"``, created now (e.g. the folder export writes files into);
           or ``"store"``, a folder the command itself creates or replaces (a store, a
           training run): its parent is probed and it is not created
    """
    if path is None or _is_url(str(path)):
        return
    from sceneforge.store.guard import check_not_in_store

    check_not_in_store(path, what)  # a store's files are its writer's alone
    path = Path(path)
    if kind != "file" and path.is_file():
        raise SceneforgeError(f"{path}: {what} is a file, not a folder")
    if kind == "file" and path.is_dir():
        raise SceneforgeError(f"{path}: {what} is a folder, not a file")
    home = path if kind == "folder" else path.parent
    probe = home / f".sceneforge-probe-{uuid.uuid4().hex}"
    try:
        home.mkdir(parents=True, exist_ok=True)
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        reason = e.strerror or str(e)
        if e.errno == errno.ENOTDIR or isinstance(e, FileExistsError):
            reason = "a part of the path is a file, not a folder"
        raise SceneforgeError(f"{path}: cannot write the {what} there ({reason})") from None


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix, so writers that go by it pick
    the format) and rename it to ``path`` when the block succeeds; remove it otherwise."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex[:8]}.partial{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically."""
    with atomic_output(path) as tmp:
        tmp.write_text(text)


def save_figure(fig, path: str | os.PathLike, dpi: int = 100) -> None:
    """Save a matplotlib figure to ``path`` atomically."""
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=dpi)
