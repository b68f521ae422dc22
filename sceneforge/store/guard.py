"""What a command may write over: no command loses data it did not create.

Every command that writes checks its outputs here before it touches anything:

- an output is never one of the command's inputs, nor inside one, nor holding one
  (:func:`check_apart`): ``predict RUN gt.zarr gt.zarr`` is refused, so is a render into
  its own houses folder;
- nothing is written inside a store (:func:`enclosing_store`): a store's files are its
  writer's, listed in its manifest;
- a store is only written over by the command that makes its kind (:func:`store_kind`):
  ``render`` writes dataset stores, ``predict`` prediction stores; neither replaces the
  other's, ``--overwrite`` or not, nor a zarr store sceneforge did not write
  (:func:`check_store_output`).

Paths are compared resolved (symbolic links and ``..`` followed), URLs as written.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterable

from ..errors import SceneforgeError
from .location import errors, is_url, open_location, resolve

#: the kinds of store by the command that writes them
WRITERS = {"dataset": "sceneforge render", "prediction": "sceneforge predict"}
#: the file that makes a folder a zarr v3 group
GROUP_FILE = "zarr.json"
#: what an unfinished render keeps before its arrays exist (:mod:`sceneforge.pipeline.staging`)
RENDER_RUN_FILE = "_staging/run.json"


def _join(path: str, name: str) -> str:
    return f"{str(path).rstrip('/')}/{name}"


def _normal(path: str | os.PathLike) -> str:
    return resolve(str(path)).rstrip("/") or "/"


def store_kind(path: str | os.PathLike, storage_options: dict | None = None) -> str | None:
    """What is at ``path``: ``"dataset"`` (a store of ``sceneforge render``, or its
    unfinished run), ``"prediction"`` (of ``sceneforge predict``, finished or not),
    ``"zarr"`` (a zarr group sceneforge did not write) or None (no zarr group there)."""
    path = str(path)
    if not is_url(path) and not Path(path).is_dir():
        return None
    place = open_location(path, storage_options)

    def read(name: str) -> bytes | None:
        with errors(path):  # unreachable, no bucket, denied: one line naming the store
            try:
                return place.fs.cat_file(_join(place.root, name))
            except FileNotFoundError:
                return None

    data = read(GROUP_FILE)
    if data is None:
        return "dataset" if read(RENDER_RUN_FILE) is not None else None
    try:
        attrs = json.loads(data).get("attributes") or {}
    except (ValueError, AttributeError):
        return "zarr"
    if "schema_version" not in attrs:
        return "zarr"
    return "prediction" if "prediction" in attrs else "dataset"


def describe_kind(kind: str) -> str:
    """``"a dataset store (sceneforge render wrote it)"``, for refusals."""
    if kind == "zarr":
        return "a zarr store sceneforge did not write"
    return f"a {kind} store ({WRITERS[kind]} wrote it)"


def enclosing_store(path: str | os.PathLike) -> Path | None:
    """The (outermost) zarr store that ``path`` (a local path, existing or not) lies
    strictly inside, or None."""
    if is_url(str(path)):
        return None
    here = Path(resolve(str(path)))
    found = None
    for folder in here.parents:  # innermost first: an array of a store is a zarr node too
        if (folder / GROUP_FILE).is_file() or (folder / RENDER_RUN_FILE).is_file():
            found = folder
    return found


def check_not_in_store(path: str | os.PathLike | None, what: str) -> None:
    """Raise :class:`SceneforgeError` when ``what`` at ``path`` would be written inside a store."""
    if path is None:
        return
    store = enclosing_store(path)
    if store is not None:
        raise SceneforgeError(f"{path}: the {what} would be written inside the store {store}, whose files are "
                              "its own; choose a path outside it")


def check_apart(out: str | os.PathLike, what: str, inputs: Iterable[tuple[str, str | os.PathLike | None]]) -> None:
    """Raise :class:`SceneforgeError` when the output ``out`` (``what``) is one of
    ``inputs`` ((what, path) pairs; None paths are skipped), lies inside one or holds one."""
    mine = _normal(out)
    for name, path in inputs:
        if path is None or str(path).startswith("bundled:"):
            continue
        theirs = _normal(path)
        if mine == theirs:
            relation = "is"
        elif theirs.startswith(mine.rstrip("/") + "/"):
            relation = "holds"
        elif mine.startswith(theirs.rstrip("/") + "/"):
            relation = "is inside"
        else:
            continue
        raise SceneforgeError(f"{out}: the {what} {relation} the {name} {path}, an input of this command; "
                              f"write the {what} to another path")


def check_store_output(out: str, kind: str, *, overwrite: bool, storage_options: dict | None = None) -> None:
    """Raise :class:`SceneforgeError` unless the command that writes ``kind`` stores may
    write at ``out``: nothing there, an empty folder, or (resuming, or with ``overwrite``)
    a store of its own kind. Never a store of another kind or a zarr store sceneforge did
    not write; with ``overwrite``, nothing it cannot prove it made."""
    check_not_in_store(out, f"{kind} store")
    found = store_kind(out, storage_options)
    if found is not None and found != kind:
        raise SceneforgeError(f"{out}: holds {describe_kind(found)}; {WRITERS[kind]} writes {kind} stores and "
                              "never replaces another kind: choose another path")
    if found is None and overwrite and not is_url(out) and Path(out).is_dir() and any(Path(out).iterdir()):
        raise SceneforgeError(f"{out}: holds files that are not a sceneforge store; refusing to delete them "
                              "(--overwrite replaces only a store this command wrote): choose another path")
