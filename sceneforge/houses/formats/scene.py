"""One scene in many files: a folder of per-object meshes read as one house, named after
the folder (``room/Floor.obj``, ``room/Walls.obj``, ``room/Chair.001.obj``, ... → ``room``).

Modelling tools export a scene one file per object as readily as one file for all; each of
those files alone has no floor to stand a camera on. A folder is such a scene
(:func:`detect`) when

- it holds a **manifest** ``scene.json`` (:data:`MANIFEST`; ``schemas/scene.schema.json``)
  and mesh files or a ``files`` entry: ``{"files": ["*.obj"]}``, plus, if needed,
  ``"up_axis"``, ``"scale"`` (they replace ``--up-axis`` and ``--scale`` for this house:
  the folder knows its own axes and units) and ``"name_map"`` (a name map file in the
  folder, its rules tried before ``--name-map``'s). ``files`` lists paths or glob
  patterns inside the folder, read in that order (a pattern's files sorted, each file once);
- or, without a manifest, its mesh files (:data:`~.generic.SUFFIXES`, directly in it, at
  least two) are named as the parts of one room (:func:`named_as_objects`): by the bundled
  name map, one file's name is a floor (or a merged shell), one a wall, ceiling or shell,
  and one an object (a chair, a lamp, ...);
- or it is asked for by name (``--format scene``): any folder holding mesh files.

The files are read as :func:`~.generic.load_house` reads one file, every mesh an instance;
a mesh whose name says nothing (``default``, ``Mesh``, ``Object001``:
:data:`~.generic.GENERIC_NAME`) is named after its file. The up axis is decided once, for
all the files together. Every file read is an input of the house: a changed file is noticed
by a re-run's fingerprints (:mod:`sceneforge.pipeline.inputs`).
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from ...conventions import NYU40_IDS, is_envelope
from ...errors import HouseError, SceneforgeError
from ..model import House
from ..names import SHELL, NameMap, read_rules
from .base import Format, HouseSource, json_document
from .generic import SUFFIXES, load_house

if TYPE_CHECKING:
    from .. import LoadOptions

__all__ = ["FORMAT", "MANIFEST", "detect", "mesh_files", "named_as_objects", "read_manifest"]

#: the manifest's file name
MANIFEST = "scene.json"


def mesh_files(folder: Path) -> list[Path]:
    """The mesh files directly in ``folder`` (hidden ones left out), sorted by name."""
    try:
        children = sorted(folder.iterdir())
    except OSError:
        return []
    return [p for p in children
            if p.suffix.lower() in SUFFIXES and not p.name.startswith(".") and p.is_file()]


def named_as_objects(files: list[Path]) -> bool:
    """True when the files' names, by the bundled name map, are the parts of one room: one
    names a floor (or a shell), one a wall, a ceiling (or a shell) and one an object."""
    if len(files) < 2:
        return False
    names = NameMap.bundled()
    kinds: set[str] = set()
    for f in files:
        target = names.lookup(f.stem)
        if target == SHELL:
            kinds |= {"floor", "envelope"}
        elif target == NYU40_IDS["floor"]:
            kinds.add("floor")
        elif target in (NYU40_IDS["wall"], NYU40_IDS["ceiling"]):
            kinds.add("envelope")
        elif isinstance(target, int) and target and not is_envelope(target):
            kinds.add("object")
    return kinds == {"floor", "envelope", "object"}


def _has_manifest(folder: Path) -> bool:
    """A ``scene.json`` that is this folder's manifest: the folder holds mesh files or the
    file lists some (a scene.json of another kind in a folder of no meshes is not one)."""
    path = folder / MANIFEST
    if not path.is_file():
        return False
    doc = json_document(path)
    return isinstance(doc, dict) and "files" in doc or bool(mesh_files(folder))


def detect(path: Path) -> bool:
    """True for a scene folder (module doc) or its manifest."""
    if path.is_file():
        return path.name == MANIFEST and _has_manifest(path.parent)
    return path.is_dir() and (_has_manifest(path) or named_as_objects(mesh_files(path)))


def _folder(path: Path) -> Path:
    return path.parent if path.name == MANIFEST and not path.is_dir() else path


def _list(path: Path) -> list[HouseSource]:
    folder = _folder(path)
    return [HouseSource(folder.name, "scene", folder)]


def read_manifest(folder: Path, house_id: str) -> dict | None:
    """The checked manifest of ``folder`` (None without one): ``files`` as paths, and
    ``up_axis``, ``scale``, ``name_map`` (a path) when given. Raises :class:`HouseError`,
    one line naming the manifest, for one that is not JSON, breaks the schema, or names
    files outside the folder, no mesh file or a missing name map."""
    from sceneforge.schemas import validate_or_raise

    path = folder / MANIFEST
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise HouseError(house_id, path, f"cannot read the scene manifest: {e}") from None
    try:
        validate_or_raise(doc, "scene", what="scene manifest")
    except SceneforgeError as e:
        raise HouseError(house_id, path, str(e)) from None
    files: list[Path] = []
    for entry in doc["files"]:
        if Path(entry).is_absolute() or ".." in Path(entry).parts:
            raise HouseError(house_id, path,
                             f"files: {entry!r} is outside the folder (give paths relative to it)")
        found = sorted(p for p in folder.glob(entry) if p.is_file() and p.suffix.lower() in SUFFIXES)
        if not found:
            raise HouseError(house_id, path, f"files: {entry!r} names no mesh file in {folder} "
                                             f"(expected {', '.join(SUFFIXES)})")
        files += [p for p in found if p not in files]
    out = {"files": files, **{k: doc[k] for k in ("up_axis", "scale") if k in doc}}
    if "name_map" in doc:
        out["name_map"] = folder / doc["name_map"]
    return out


def load_scene(folder: str | Path, options: LoadOptions | None = None, house_id: str | None = None) -> House:
    """Read the scene folder ``folder`` (or its manifest) as one house (module doc)."""
    from .. import LoadOptions

    folder = _folder(Path(folder))
    options = options or LoadOptions()
    house_id = house_id or folder.name
    if not folder.is_dir():
        raise HouseError(house_id, folder, "a scene is a folder of mesh files: give the folder")
    manifest = read_manifest(folder, house_id)
    rules = ()
    if manifest is None:
        files = mesh_files(folder)
        if not files:
            raise HouseError(house_id, folder, f"no mesh file ({', '.join(SUFFIXES)}) in the folder")
    else:
        files = manifest["files"]
        options = replace(options, **{k: manifest[k] for k in ("up_axis", "scale") if k in manifest})
        if "name_map" in manifest:
            try:
                rules = read_rules(manifest["name_map"])
            except SceneforgeError as e:
                raise HouseError(house_id, folder / MANIFEST, str(e)) from None
    return load_house(folder, options, house_id, files=files, rules=rules)


def _load(source: HouseSource, options: LoadOptions) -> House:
    return load_scene(source.path, options, source.id)


FORMAT = Format("scene", detect=detect, load=_load, list=_list,
                # asked for by name (--format scene), any folder of mesh files is one scene
                fallback=lambda path: path.is_dir() and bool(mesh_files(path)))
