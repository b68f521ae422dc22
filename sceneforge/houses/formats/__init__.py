"""Input formats as a registry: one :class:`~.base.Format` per format, found by name.

Each format module says how to recognise its houses (``detect``), list those at a path
(``list``: one for a house file or folder, all of them for a SUNCG or 3D-FRONT root) and
read one (``load``):

============== ===================================== =========================================
name           module                                what is recognised
============== ===================================== =========================================
``sceneforge`` :mod:`.native`                        ``house.json`` with the format tag, or its folder
``gltf``       :mod:`.generic` (parser :mod:`.gltf`) ``.gltf`` / ``.glb`` file
``obj``        :mod:`.generic` (parser :mod:`.obj`)  ``.obj`` file
``ply``        :mod:`.generic` (parser :mod:`.ply`)  ``.ply`` file
``suncg``      :mod:`.suncg`                         SUNCG root, a house folder in one, its ``house.json``
``front3d``    :mod:`.front3d`                       folder holding ``3D-FRONT/``, scene JSON
``scene``      :mod:`.scene` (files read by          folder of per-object meshes: with a
               :mod:`.generic`)                      ``scene.json``, or named as one room's parts
============== ===================================== =========================================

:func:`find` searches a path with them; :func:`sceneforge.houses.discover` and
:func:`sceneforge.houses.load` are the entry points. Writers of the formats other than
sceneforge's own are test helpers (:mod:`sceneforge.testing`).
"""

from __future__ import annotations

import json
from pathlib import Path

from ...errors import UnknownFormatError
from . import front3d, generic, native, scene, suncg
from .base import Format, HouseSource, forget_json_document

__all__ = ["FOLDER_ORDER", "REGISTRY", "UNREADABLE", "Format", "HouseSource", "detect", "find"]

#: Every format by name, in the order ``--format`` lists them and files are recognised: a
#: sceneforge ``house.json`` also has SUNCG's keys, so sceneforge is asked first; a
#: ``scene.json`` holding a 3D-FRONT scene is 3D-FRONT's.
REGISTRY: dict[str, Format] = {
    f.name: f for f in (native.FORMAT, generic.GLTF, generic.OBJ, generic.PLY, suncg.FORMAT, front3d.FORMAT,
                        scene.FORMAT)
}
#: The formats a folder can be, in the order asked: SUNCG and 3D-FRONT by their folder layout
#: (whatever else the folder holds), then a sceneforge house folder by its ``house.json``,
#: then a folder of per-object meshes (a scene).
FOLDER_ORDER = ("suncg", "front3d", "sceneforge", "scene")


def detect(path: Path) -> Format | None:
    """The format of a house file, house folder or root: the first that recognises it."""
    names = FOLDER_ORDER if path.is_dir() else REGISTRY
    try:
        return next((REGISTRY[name] for name in names if REGISTRY[name].detect(path)), None)
    finally:
        forget_json_document()


#: a file of this name is a house whatever it holds: when no format reads it, it is reported
HOUSE_FILE_NAMES = ("house.json",)
#: the format of a :class:`HouseSource` found unreadable before any format could read it
UNREADABLE = "unreadable"


def find(path: Path, only: Format | None = None) -> list[HouseSource]:
    """Every house at ``path``, in a stable (sorted) order; with ``only``, of that format alone.

    A file is one house (of ``only`` whatever it looks like, when given). A folder that a
    format recognises (or, with ``only``, takes as a fallback: ``--format scene``, any folder
    of meshes) holds that format's houses; any other folder is searched, sorted, hidden
    names skipped, for recognised files and folders. A ``house.json`` no format
    recognises, and a JSON file given itself that is not JSON, are found as houses with a
    :attr:`HouseSource.problem` (the parser's message): they fail alone. Raises
    :class:`UnknownFormatError` for any other file in no format.
    """
    if path.is_file():
        fmt = only or detect(path)
        if fmt is not None:
            return fmt.sources(path)
        problem = unreadable_json(path, given=True)
        if problem is None:
            raise UnknownFormatError(f"{path}: not a house in any supported format")
        return [HouseSource(path.stem, UNREADABLE, path, problem)]
    fmt = detect(path) if only is None else (
        only if only.detect(path) or only.fallback is not None and only.fallback(path) else None)
    if fmt is not None:
        return fmt.sources(path)
    found: list[HouseSource] = []
    for child in sorted(path.iterdir()):
        if child.name.startswith("."):
            continue
        if child.is_dir():
            found += find(child, only)
            continue
        fmt = detect(child)
        if fmt is None and only is not None and only.fallback is not None and only.fallback(child):
            fmt = only
        if fmt is not None and (only is None or fmt is only):
            found += fmt.sources(child)
        elif fmt is None and only is None and (problem := unreadable_json(child, given=False)) is not None:
            found.append(HouseSource(child.stem, UNREADABLE, child, problem))
    return found


def unreadable_json(path: Path, given: bool) -> str | None:
    """Why a ``.json`` file that no format recognised is no house, or None when it is not
    one to report: a file named ``house.json`` always is, any JSON file when ``given``
    itself only when it does not parse."""
    if path.suffix.lower() != ".json":
        return None
    named = path.name.lower() in HOUSE_FILE_NAMES
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except OSError as e:
        return f"cannot read {path.name}: {e.strerror or e}"
    except UnicodeDecodeError as e:
        return f"cannot read {path.name}: not UTF-8 text ({e.reason} at byte {e.start})"
    except ValueError as e:
        return f"cannot read {path.name}: not JSON: {e}"
    if not named:
        return None
    keys = (", ".join(sorted(map(repr, doc))[:6]) or "no keys") if isinstance(doc, dict) else f"a {type(doc).__name__}"
    return (f"{path.name} is in no supported format: no sceneforge tag ('format': '{native.FORMAT_TAG}'), "
            f"no SUNCG 'levels', no 3D-FRONT 'furniture' and 'scene' (found {keys})")
