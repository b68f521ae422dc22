"""Generic scenes written by suffix: glTF/GLB, OBJ or PLY, instances named by
:func:`~sceneforge.houses.formats.generic.tagged_name` so that the loader gives their
categories back."""

from __future__ import annotations

from pathlib import Path

from ..errors import SceneforgeError
from ..houses.formats.generic import SUFFIXES, tagged_name
from ..houses.model import House
from .gltf import write_gltf
from .obj import write_obj
from .ply import write_ply
from .textures import mesh_of


def write_house(house: House, path: str | Path, names: list[str] | None = None) -> Path:
    """Write ``house`` as ``.gltf``, ``.glb``, ``.obj`` (+ ``.mtl``) or ``.ply`` (by suffix).

    Every format keeps instances (one node / ``o`` object / PLY ``instance`` value each),
    categories (through :func:`tagged_name`, unless ``names`` gives every instance its name
    as written: :mod:`sceneforge.testing.scenes`) and geometry. glTF and OBJ keep base colours,
    textures, uv and emission; PLY keeps base colours (as face colours) and uv, not textures. Rooms
    are not kept. glTF stores positions as float32, relative to each instance's centre
    (about 6e-8 × the instance's size of error). Returns ``path``.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise SceneforgeError(
            f"{path}: cannot write a house as {suffix!r} (use one of {', '.join(SUFFIXES)})")
    path.parent.mkdir(parents=True, exist_ok=True)
    names = _unique([tagged_name(i) for i in house.instances] if names is None else list(names))
    if suffix in (".gltf", ".glb"):
        write_gltf(path, house, names)
    elif suffix == ".obj":
        write_obj(path, [mesh_of(i, name=name) for i, name in zip(house.instances, names, strict=True)],
                  comment=f"sceneforge house {house.id}: objects are named <nyu40 class>__<name>")
    else:
        write_ply(path, house, names)
    return path


def _unique(names: list[str]) -> list[str]:
    """Names made unique with ``.2``, ``.3``... (OBJ would merge equal names)."""
    seen: dict[str, int] = {}
    out = []
    for name in names:
        seen[name] = seen.get(name, 0) + 1
        out.append(name if seen[name] == 1 else f"{name}.{seen[name]}")
    return out
