"""Houses: the model, one loader (and writer) module per format, the toy-house generator.

Every command that takes ``HOUSES`` goes through :func:`discover`, which turns a path
(one house file, a house folder, a folder of houses in any format, a SUNCG root or a
3D-FRONT root) into :class:`HouseSource` entries, and :func:`load`, which reads one.
Loading is lazy so that one broken house fails alone.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from ..errors import HouseError, SceneforgeError, UnknownFormatError
from .model import House, Instance, Level, Material, Room, make_instance

__all__ = [
    "BUNDLED_TOY", "FORMATS", "House", "HouseSource", "Instance", "Level", "LoadOptions", "Material", "Room",
    "discover", "iter_houses", "load", "make_instance",
]

#: Names accepted by ``--format``.
FORMATS = ("sceneforge", "gltf", "obj", "ply", "suncg", "front3d")
#: file suffix of a generic scene → its format name
MESH_SUFFIXES = {".gltf": "gltf", ".glb": "gltf", ".obj": "obj", ".ply": "ply"}


@dataclass(frozen=True)
class LoadOptions:
    """How to read houses. Field docs double as CLI help."""

    #: source format; None = detect from the path
    format: str | None = None
    #: fail on unknown categories instead of mapping them to void
    strict: bool = False
    #: generic meshes: multiply coordinates by this to get metres
    scale: float = 1.0
    #: generic meshes: the source's up axis ("y" or "z"); z-up is converted to +Y up
    up_axis: str = "y"
    #: generic meshes: JSON name-pattern map replacing the bundled one
    name_map: str | None = None
    #: 3D-FRONT: folder of 3D-FUTURE models (default: found beside the scene files)
    future_dir: str | None = None


@dataclass(frozen=True)
class HouseSource:
    """A house that :func:`load` can read: its id, format and path."""

    id: str
    format: str
    path: Path


def _suncg_root_of(path: Path) -> Path | None:
    """The SUNCG root of ``path`` (root, ``house/<id>/`` or its ``house.json``), if it is one."""
    for cand in (path, *path.parents[:3]):
        if (cand / "house").is_dir() and (cand / "object").is_dir():
            return cand
    return None


def _json_kind(path: Path) -> str | None:
    from .formats.native import is_native

    if is_native(path):
        return "sceneforge"
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if isinstance(doc, dict):
        if "levels" in doc and ("version" in doc or "up" in doc):
            return "suncg"
        if "furniture" in doc and "scene" in doc:
            return "front3d"
    return None


def _detect_file(path: Path) -> str | None:
    if path.suffix.lower() in MESH_SUFFIXES:
        return MESH_SUFFIXES[path.suffix.lower()]
    if path.suffix.lower() == ".json":
        return _json_kind(path)
    return None


def _source(path: Path, fmt: str) -> HouseSource:
    if fmt == "sceneforge":
        house_dir = path.parent if path.is_file() else path
        return HouseSource(house_dir.name, fmt, house_dir)
    if fmt == "suncg":
        house_dir = path.parent if path.is_file() else path
        return HouseSource(house_dir.name, fmt, house_dir / "house.json")
    return HouseSource(path.stem, fmt, path)


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
        raise SceneforgeError(f"{path}: no such file or folder")
    if fmt is not None and fmt not in FORMATS:
        raise UnknownFormatError(f"unknown format {fmt!r}; choose one of {', '.join(FORMATS)}")
    found = _discover(path, fmt)
    if not found:
        raise UnknownFormatError(
            f"{path}: no house found (supported: sceneforge house.json, glTF/GLB, OBJ, PLY, "
            "SUNCG root or house, 3D-FRONT root or scene JSON)"
        )
    ids = [s.id for s in found]
    dupes = sorted({i for i in ids if ids.count(i) > 1})
    if dupes:
        raise SceneforgeError(f"{path}: several houses share the id(s) {', '.join(dupes)}")
    return found


def _discover(path: Path, fmt: str | None) -> list[HouseSource]:
    if path.is_file():
        kind = fmt or _detect_file(path)
        if kind is None:
            raise UnknownFormatError(f"{path}: not a house in any supported format")
        return [_source(path, kind)]
    if fmt in (None, "suncg") and _suncg_root_of(path) == path:
        return [
            HouseSource(d.name, "suncg", d / "house.json")
            for d in sorted((path / "house").iterdir())
            if (d / "house.json").is_file()
        ]
    if fmt in (None, "suncg") and (path / "house.json").is_file() and _suncg_root_of(path):
        return [_source(path, "suncg")]
    if fmt in (None, "front3d") and (path / "3D-FRONT").is_dir():
        return _discover(path / "3D-FRONT", "front3d")
    if fmt in (None, "sceneforge") and (path / "house.json").is_file():
        from .formats.native import is_native

        if is_native(path):
            return [_source(path, "sceneforge")]
    found: list[HouseSource] = []
    for child in sorted(path.iterdir()):
        if child.name.startswith("."):
            continue
        if child.is_dir():
            found += _discover(child, fmt)
        else:
            kind = _detect_file(child)
            if kind is not None and (fmt is None or kind == fmt):
                found.append(_source(child, kind))
            elif fmt is not None and kind is None and child.suffix.lower() == ".json" and fmt == "front3d":
                found.append(_source(child, fmt))
    return found


def load(source: HouseSource | str | Path, options: LoadOptions | None = None) -> House:
    """Read one house. Expected problems raise :class:`HouseError` naming house and file."""
    options = options or LoadOptions()
    if not isinstance(source, HouseSource):
        found = discover(source, options.format)
        if len(found) != 1:
            raise SceneforgeError(f"{source}: holds {len(found)} houses, expected one")
        source = found[0]
    try:
        if source.format == "sceneforge":
            from .formats.native import load_house

            return load_house(source.path, strict=options.strict)
        if source.format in ("gltf", "obj", "ply"):
            from .formats.generic import load_house

            return load_house(source.path, options)
        if source.format == "suncg":
            from .formats.suncg import load_house

            return load_house(source.path, options)
        if source.format == "front3d":
            from .formats.front3d import load_house

            return load_house(source.path, options)
    except SceneforgeError:
        raise
    except (OSError, ValueError, KeyError, IndexError, TypeError) as e:
        raise HouseError(source.id, source.path, f"{type(e).__name__}: {e}") from e
    raise UnknownFormatError(f"unknown format {source.format!r}")


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
