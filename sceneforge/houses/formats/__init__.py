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
============== ===================================== =========================================

:func:`find` searches a path with them; :func:`sceneforge.houses.discover` and
:func:`sceneforge.houses.load` are the entry points. Writers of the formats other than
sceneforge's own are test helpers (:mod:`sceneforge.testing`).
"""

from __future__ import annotations

from pathlib import Path

from ...errors import UnknownFormatError
from . import front3d, generic, native, suncg
from .base import Format, HouseSource, forget_json_document

__all__ = ["FOLDER_ORDER", "REGISTRY", "Format", "HouseSource", "detect", "find"]

#: Every format by name, in the order ``--format`` lists them and files are recognised: a
#: sceneforge ``house.json`` also has SUNCG's keys, so sceneforge is asked first.
REGISTRY: dict[str, Format] = {
    f.name: f for f in (native.FORMAT, generic.GLTF, generic.OBJ, generic.PLY, suncg.FORMAT, front3d.FORMAT)
}
#: The formats a folder can be, in the order asked: SUNCG and 3D-FRONT by their folder layout
#: (whatever else the folder holds), then a sceneforge house folder by its ``house.json``.
FOLDER_ORDER = ("suncg", "front3d", "sceneforge")


def detect(path: Path) -> Format | None:
    """The format of a house file, house folder or root: the first that recognises it."""
    names = FOLDER_ORDER if path.is_dir() else REGISTRY
    try:
        return next((REGISTRY[name] for name in names if REGISTRY[name].detect(path)), None)
    finally:
        forget_json_document()


def find(path: Path, only: Format | None = None) -> list[HouseSource]:
    """Every house at ``path``, in a stable (sorted) order; with ``only``, of that format alone.

    A file is one house (of ``only`` whatever it looks like, when given). A folder that a
    format recognises holds that format's houses; any other folder is searched, sorted,
    hidden names skipped, for recognised files and folders. Raises
    :class:`UnknownFormatError` for a file in no format.
    """
    if path.is_file():
        fmt = only or detect(path)
        if fmt is None:
            raise UnknownFormatError(f"{path}: not a house in any supported format")
        return fmt.sources(path)
    fmt = detect(path) if only is None else (only if only.detect(path) else None)
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
    return found
