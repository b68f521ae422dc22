"""Houses: the model, the input formats (a registry, :mod:`.formats`), the toy-house generator.

Every command that takes ``HOUSES`` goes through :func:`discover`, which turns a path
(one house file, a house folder, a folder of houses in any format, a SUNCG root or a
3D-FRONT root) into :class:`HouseSource` entries, and :func:`load`, which reads one.
Loading is lazy so that one broken house fails alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..errors import HouseError, SceneforgeError, UnknownFormatError
from .formats import REGISTRY, HouseSource, find
from .model import House, Instance, Level, Material, Room, make_instance

__all__ = [
    "BUNDLED_TOY", "FORMATS", "House", "HouseSource", "Instance", "Level", "LoadOptions", "Material", "Room",
    "discover", "iter_houses", "load", "make_instance",
]


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
        raise SceneforgeError(f"{path}: no such file or folder")
    if fmt is not None and fmt not in FORMATS:
        raise UnknownFormatError(f"unknown format {fmt!r}; choose one of {', '.join(FORMATS)}")
    found = find(path, None if fmt is None else REGISTRY[fmt])
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


def load(source: HouseSource | str | Path, options: LoadOptions | None = None) -> House:
    """Read one house. Expected problems raise :class:`HouseError` naming house and file."""
    options = options or LoadOptions()
    if not isinstance(source, HouseSource):
        found = discover(source, options.format)
        if len(found) != 1:
            raise SceneforgeError(f"{source}: holds {len(found)} houses, expected one")
        source = found[0]
    fmt = REGISTRY.get(source.format)
    if fmt is None:
        raise UnknownFormatError(f"unknown format {source.format!r}")
    try:
        return fmt.load(source, options)
    except SceneforgeError:
        raise
    except (OSError, ValueError, KeyError, IndexError, TypeError) as e:
        raise HouseError(source.id, source.path, f"{type(e).__name__}: {e}") from e


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
