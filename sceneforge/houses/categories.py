"""Mapping source category names to NYU40 ids.

Two kinds of map, both plain JSON files a user can copy and edit:

- a **name-pattern map** for generic scenes (glTF/OBJ/PLY): ordered ``[regex, nyu40 name]``
  rules matched against node/object names, first match wins;
- a **category table** for datasets with their own vocabulary (3D-FRONT): exact
  category name → NYU40 name.

Unknown names map to void with a warning on the house, or raise with ``strict``.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from ..conventions import NYU40_NAMES, nyu40_id
from ..errors import HouseError, SceneforgeError
from .model import House


def data_file(name: str) -> Path:
    """Path of a data file shipped inside the package (``sceneforge/data``)."""
    return Path(__file__).resolve().parents[1] / "data" / name


@dataclass(frozen=True)
class PatternMap:
    """Ordered ``(compiled regex, NYU40 id)`` rules; the first rule that matches wins."""

    rules: tuple[tuple[re.Pattern, int], ...]
    source: str

    @classmethod
    def from_file(cls, path: str | Path) -> "PatternMap":
        path = Path(path)
        try:
            raw = json.loads(path.read_text())
            items = raw["patterns"] if isinstance(raw, dict) else raw
            rules = []
            for pattern, name in items:
                cid = nyu40_id(name)
                if cid is None:
                    raise SceneforgeError(
                        f"{path}: {name!r} is not an NYU40 class name (one of {', '.join(NYU40_NAMES[1:])})"
                    )
                rules.append((re.compile(pattern, re.IGNORECASE), cid))
        except (OSError, ValueError, KeyError, TypeError, re.error) as e:
            raise SceneforgeError(f"cannot read name-pattern map {path}: {e}") from None
        return cls(tuple(rules), str(path))

    @classmethod
    def default(cls) -> "PatternMap":
        return _default_pattern_map()

    def lookup(self, name: str) -> int | None:
        """NYU40 id for a node name, or None when no rule matches."""
        direct = nyu40_id(name)
        for pattern, cid in self.rules:
            if pattern.search(name):
                return cid
        return direct


@lru_cache(maxsize=1)
def _default_pattern_map() -> PatternMap:
    return PatternMap.from_file(data_file("name_patterns.json"))


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
    msg = f"unknown category {label!r} mapped to void"
    if msg not in house.warnings:
        house.warnings.append(msg)
    return 0
