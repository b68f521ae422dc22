"""Object names → NYU40 classes for generic scenes (glTF/OBJ/PLY), and what to do with a name.

A :class:`NameMap` is an ordered list of ``[regex, target]`` rules matched (case-insensitive,
``re.search``) against node/object names; the first rule that matches wins. A target is

- an NYU40 class name (or an alias, ``rug``, ``tv``, ...): the instance gets that class;
- ``"drop"`` (:data:`DROP`): the instance is left out (plants, persons, helper geometry);
- ``"shell"`` (:data:`SHELL`): the mesh is a merged room envelope, split by face orientation
  and height into wall, floor and ceiling (:func:`sceneforge.houses.shell.split_shell`).

The order a name is looked up in:

1. the ``<nyu40 name>__`` tag that sceneforge's own writers put on every name
   (:func:`~sceneforge.houses.formats.generic.tagged_name`), so written scenes load back with
   the classes they had, whatever a map says;
2. the user's rules (``--name-map FILE``), in file order;
3. the bundled rules (``sceneforge/data/name_patterns.json``), in file order;
4. a name that is itself an NYU40 class name (``chair``).

A name nothing matches is unknown: void with a warning (an error with ``--strict``).
A user map therefore only lists what it adds or changes: one rule is a valid map.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from ..conventions import NYU40_NAMES, nyu40_id
from ..errors import SceneforgeError
from .categories import data_file

__all__ = ["BUNDLED_MAP", "DROP", "SHELL", "TAG", "NameMap", "Rule"]

#: the target that leaves an instance out
DROP = "drop"
#: the target that splits a merged envelope mesh into wall, floor and ceiling
SHELL = "shell"
#: the bundled rules, tried after the user's
BUNDLED_MAP = "name_patterns.json"
#: the ``<nyu40 name>__`` tag of sceneforge's writers at the start of a name
TAG = re.compile(r"^(" + "|".join(map(re.escape, NYU40_NAMES)) + r")__(?=.)")


@dataclass(frozen=True)
class Rule:
    """One rule: a name matching ``pattern`` gets ``target`` (an NYU40 id, :data:`DROP` or
    :data:`SHELL`). ``source`` names the map file and the rule's position, for messages."""

    pattern: re.Pattern
    target: int | str
    source: str

    def describe(self) -> str:
        """``name_patterns.json #2 ('plant|leaves|leaf|bran…')``"""
        text = self.pattern.pattern
        return f"{self.source} ({(text if len(text) <= 24 else text[:23] + '…')!r})"


@dataclass(frozen=True)
class NameMap:
    """The rules of one lookup, user rules first (module doc)."""

    rules: tuple[Rule, ...]

    @classmethod
    def bundled(cls) -> "NameMap":
        """The bundled rules alone."""
        return _bundled()

    @classmethod
    def with_user_rules(cls, path: str | Path | None) -> "NameMap":
        """The rules of the user's map file ``path`` (none when None), then the bundled ones."""
        if path is None:
            return cls.bundled()
        return cls(read_rules(path) + cls.bundled().rules)

    def match(self, name: str) -> tuple[int | str | None, Rule | None]:
        """``(target, rule)`` for a node name: the tag's class, the first matching rule's
        target, or the class a bare NYU40 name stands for; ``(None, None)`` when unknown."""
        tag = TAG.match(name)
        if tag is not None:
            return nyu40_id(tag.group(1)), None
        for rule in self.rules:
            if rule.pattern.search(name):
                return rule.target, rule
        return nyu40_id(name), None

    def lookup(self, name: str) -> int | str | None:
        """The target of a node name (:meth:`match` without the rule)."""
        return self.match(name)[0]


def read_rules(path: str | Path) -> tuple[Rule, ...]:
    """The rules of a map file: ``{"patterns": [[regex, target], ...]}`` or the bare list.

    Raises :class:`SceneforgeError` naming the file and the rule for anything unreadable.
    """
    path = Path(path)
    try:
        raw = json.loads(path.read_text())
    except OSError as e:
        raise SceneforgeError(f"cannot read name map {path}: {e.strerror or e}") from None
    except ValueError as e:
        raise SceneforgeError(f"cannot read name map {path}: {e}") from None
    items = raw.get("patterns") if isinstance(raw, dict) else raw
    if not isinstance(items, list):
        raise SceneforgeError(f"name map {path}: expected a list of [regex, target] rules under 'patterns'")
    rules = []
    for k, item in enumerate(items):
        where = f"name map {path}, rule {k + 1}"
        if not (isinstance(item, list) and len(item) == 2 and all(isinstance(x, str) for x in item)):
            raise SceneforgeError(f"{where}: expected [regex, target], got {item!r}")
        pattern, target = item
        try:
            compiled = re.compile(pattern, re.IGNORECASE)
        except re.error as e:
            raise SceneforgeError(f"{where}: bad regex {pattern!r}: {e}") from None
        key = target.strip().lower()
        cid = key if key in (DROP, SHELL) else nyu40_id(target)
        if cid is None:
            raise SceneforgeError(
                f"{where}: {target!r} is not a target (an NYU40 class name, {DROP!r} or {SHELL!r}; "
                f"classes: {', '.join(NYU40_NAMES[1:])})"
            )
        rules.append(Rule(compiled, cid, f"{path.name} #{k + 1}"))
    return tuple(rules)


@lru_cache(maxsize=1)
def _bundled() -> NameMap:
    return NameMap(read_rules(data_file(BUNDLED_MAP)))
