"""Mapping source category names to NYU40 ids.

Two kinds of map, both plain JSON files a user can copy and edit:

- a **name map** for generic scenes (glTF/OBJ/PLY): ordered ``[regex, target]`` rules
  matched against node/object names, the user's before the bundled ones
  (:mod:`sceneforge.houses.names`);
- a **category table** for datasets with their own vocabulary (3D-FRONT): exact
  category name → NYU40 name.

Unknown names map to void with a warning on the house, or raise with ``strict``.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import HouseError
from .model import House

#: how the warning for a name mapped to void starts (``houses inspect`` lists those names itself)
UNKNOWN = "unknown category"


def data_file(name: str) -> Path:
    """Path of a data file shipped inside the package (``sceneforge/data``)."""
    return Path(__file__).resolve().parents[1] / "data" / name


def resolve(
    house: House, label: str, category: int | None, *, strict: bool, file: str | Path | None = None
) -> int:
    """The NYU40 id to use for an instance whose lookup gave ``category`` (None = unknown).

    Unknown categories become void (0) with a warning, or raise :class:`HouseError` when
    ``strict``.
    """
    if category is not None:
        return category
    if strict:
        raise HouseError(house.id, file, f"unknown category {label!r} (--strict)")
    msg = f"{UNKNOWN} {label!r} mapped to void"
    if msg not in house.warnings:
        house.warnings.append(msg)
    return 0
