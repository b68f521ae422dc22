"""Houses: the model, the input formats (a registry, :mod:`.formats`), the toy-house generator.

Every command that takes ``HOUSES`` goes through :func:`discover`, which turns a path
(one house file, a house folder, a folder of houses in any format, a SUNCG root, a
3D-FRONT root or a scene folder of per-object meshes) into :class:`HouseSource` entries,
and :func:`load`, which reads one. Loading is lazy so that one broken house fails alone.

House ids (:func:`house_ids`, the README's "Your own data"):

1. a house file's id is its name without the suffix (``kitchen.glb`` → ``kitchen``);
   sceneforge and SUNCG houses and scene folders are named by their folder, 3D-FRONT scenes
   by their file;
2. where a file's name says nothing — it is generic (:data:`GENERIC_STEMS`: ``scene.gltf``,
   ``house.obj``, ``model.ply``, ...) or several houses of the scan share it — the id is the
   name of the folder holding it (``a/scene.gltf`` → ``a``);
3. where folder names are shared too, the folder's path under the folder scanned
   (``set1/a/scene.gltf`` → ``set1/a``);
4. houses whose ids still collide fail, each naming the other files; the others go on.
"""

from __future__ import annotations

import typing
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path

from ..errors import HouseError, SceneforgeError, UnknownFormatError, no_such_path
from .formats import REGISTRY, UNREADABLE, HouseSource, find
from .model import House, Instance, Level, Material, Room, make_instance

__all__ = [
    "BUNDLED_TOY", "FORMATS", "House", "HouseSource", "Instance", "Level", "LoadOptions", "Material", "Room",
    "discover", "house_ids", "iter_houses", "load", "make_instance",
]

#: file names (without suffix, any case) that say nothing about the house: such a house is
#: named after its folder
GENERIC_STEMS = frozenset({
    "scene", "house", "model", "mesh", "untitled", "export", "output", "main", "default",
    "textured", "textured_output", "scene_mesh", "mesh_textured",
})


@dataclass(frozen=True)
class LoadOptions:
    """How to read houses. Field docs double as CLI help."""

    #: source format; None = detect from the path
    format: str | None = None
    #: fail on unknown categories instead of mapping them to void
    strict: bool = False
    #: generic meshes: multiply coordinates by this to get metres
    scale: float = 1.0
    #: generic meshes: the source's up axis, converted to +Y up: y, z, or auto (told from the
    #: geometry and the names of floors; glTF is y unless clearly z; `houses inspect` says why)
    up_axis: typing.Literal["auto", "y", "z"] = "auto"
    #: generic meshes: JSON name map whose rules are tried before the bundled ones (targets: NYU40 names, drop, shell)
    name_map: str | None = None
    #: 3D-FRONT: folder of 3D-FUTURE models (default: found beside the scene files)
    future_dir: str | None = None
    #: SUNCG: what a material with both a colour (Kd) and a texture (map_Kd) shows: replace (the
    #: texture alone, as PBRS's Mitsuba renders SUNCG) or multiply (Kd × texture, OpenGL's modulate)
    suncg_textures: typing.Literal["replace", "multiply"] = "replace"


#: Names accepted by ``--format``, in the registry's order.
FORMATS = tuple(REGISTRY)


#: Stands for the toy houses bundled with the package wherever a houses path is taken.
BUNDLED_TOY = "bundled:toy"


def bundled_toy_dir() -> Path:
    """Folder of the toy houses shipped with the package."""
    from .categories import data_file

    return data_file("toy_houses")


def discover(path: str | Path, fmt: str | None = None) -> list[HouseSource]:
    """All houses under ``path``, in a stable (sorted) order.

    ``path`` may be :data:`BUNDLED_TOY` for the bundled toy houses. Raises
    :class:`UnknownFormatError` when ``path`` holds nothing readable and
    :class:`SceneforgeError` when it does not exist.
    """
    path = bundled_toy_dir() if str(path) == BUNDLED_TOY else Path(path)
    if not path.exists():
        raise SceneforgeError(no_such_path(path, (BUNDLED_TOY,)))
    if fmt is not None and fmt not in FORMATS:
        raise UnknownFormatError(f"unknown format {fmt!r}; choose one of {', '.join(FORMATS)}")
    found = find(path, None if fmt is None else REGISTRY[fmt])
    if not found and fmt is not None:
        formats = sorted({s.format for s in _find_any(path)} - {UNREADABLE})
        if formats:
            raise UnknownFormatError(
                f"{path}: no {fmt} house found (--format {fmt}); it holds {' and '.join(formats)} houses: "
                f"pass --format {formats[0]} or leave --format out")
    if not found:
        raise UnknownFormatError(
            f"{path}: no house found (supported: sceneforge house.json, glTF/GLB, OBJ, PLY, "
            "SUNCG root or house, 3D-FRONT root or scene JSON, a folder of per-object meshes with a "
            "scene.json)"
        )
    return house_ids(found, path)


def _find_any(path: Path) -> list[HouseSource]:
    """What :func:`find` recognises at ``path`` in any format (nothing where it raises)."""
    try:
        return find(path)
    except UnknownFormatError:
        return []


def house_ids(sources: list[HouseSource], scanned: Path) -> list[HouseSource]:
    """``sources`` (found under ``scanned``) with the ids of the module doc's rule; houses
    whose ids collide get a :attr:`HouseSource.problem` naming the other files."""
    base = scanned if scanned.is_dir() else scanned.parent
    named_by_file = [s.path.is_file() and s.id == s.path.stem for s in sources]
    stems = Counter(s.id for s, by_file in zip(sources, named_by_file) if by_file)
    ids, by_folder = [], []
    for s, by_file in zip(sources, named_by_file):
        generic = by_file and (s.id.lower() in GENERIC_STEMS or stems[s.id] > 1)
        ids.append(s.path.parent.name if generic else s.id)
        by_folder.append(generic or not by_file)
    counts = Counter(ids)
    for k, s in enumerate(sources):
        folder = s.path.parent if named_by_file[k] else s.path if s.path.is_dir() else s.path.parent
        if by_folder[k] and counts[ids[k]] > 1 and folder != base and folder.is_relative_to(base):
            ids[k] = folder.relative_to(base).as_posix()
    files: dict[str, list[Path]] = {}
    for i, s in zip(ids, sources):
        files.setdefault(i, []).append(s.path)
    out = []
    for i, s in zip(ids, sources):
        problem = s.problem
        if len(files[i]) > 1:
            others = ", ".join(str(f) for f in files[i] if f != s.path)
            problem = (f"id {i!r} is also the id of {others}: rename one of the files or folders, "
                       "or read them separately")
        out.append(replace(s, id=i, problem=problem))
    return out


def load(source: HouseSource | str | Path, options: LoadOptions | None = None) -> House:
    """Read one house. Expected problems raise :class:`HouseError` naming house and file."""
    options = options or LoadOptions()
    if not isinstance(source, HouseSource):
        found = discover(source, options.format)
        if len(found) != 1:
            raise SceneforgeError(f"{source}: holds {len(found)} houses, expected one")
        source = found[0]
    if source.problem is not None:
        raise HouseError(source.id, source.path, source.problem)
    fmt = REGISTRY.get(source.format)
    if fmt is None:
        raise UnknownFormatError(f"unknown format {source.format!r}")
    try:
        house = fmt.load(source, options)
    except HouseError as e:
        if e.house == source.id:
            raise
        raise HouseError(source.id, e.file, e.problem) from e  # the id discovery gave it
    except SceneforgeError:
        raise
    except (OSError, ValueError, KeyError, IndexError, TypeError) as e:
        raise HouseError(source.id, source.path, f"{type(e).__name__}: {e}") from e
    house.id = source.id
    return house


def iter_houses(path: str | Path, options: LoadOptions | None = None):
    """Yield ``(source, house, error)`` for every house under ``path``.

    Exactly one of ``house`` and ``error`` is None: a house that fails to load is reported
    with its :class:`HouseError` and the others still load. Unexpected exceptions are
    reported too, wrapped with the house and file they came from.
    """
    options = options or LoadOptions()
    for source in discover(path, options.format):
        try:
            yield source, load(source, options), None
        except SceneforgeError as e:
            yield source, None, e
        except Exception as e:  # a bug or a library choking on bad bytes: still only this house
            yield source, None, HouseError(source.id, source.path, f"{type(e).__name__}: {e}")
