"""Object names → NYU40 classes for generic scenes (glTF/OBJ/PLY), and what to do with a name.

A rule is ``[regex, target]``, matched case-insensitively; a target is

- an NYU40 class name (or an alias, ``rug``, ``tv``, ...): the instance gets that class;
- ``"drop"`` (:data:`DROP`): the instance is left out (plants, persons, helper geometry);
- ``"shell"`` (:data:`SHELL`): the mesh is a merged room envelope, split by face orientation
  and height into wall, floor and ceiling (:func:`sceneforge.houses.shell.split_shell`).

The order a name is looked up in (:meth:`NameMap.match`):

1. the ``<nyu40 name>__`` tag that sceneforge's own writers put on every name
   (:func:`~sceneforge.houses.formats.generic.tagged_name`), so written scenes load back with
   the classes they had, whatever a map says;
2. the user's rules (``--name-map FILE``) on the whole name as written (``re.search``), in
   file order: the first that matches wins, whatever the bundled rules would say (and a
   mesh they name is never taken for a room box after loading,
   :mod:`sceneforge.houses.cleanup`);
3. the bundled rules (``sceneforge/data/name_patterns.json``) by **head word**, below;
4. a name that is itself an NYU40 class name (``chair``).

A name nothing matches is unknown: void with a warning (an error with ``--strict``).
A user map therefore only lists what it adds or changes: one rule is a valid map.

The head-word rule (:func:`head_match`), because names are compounds whose words say different
things (``CeilingLampshade`` is a lamp, not the ceiling): the bundled rules are matched
against the name's words (:func:`words`: split at camelCase, digits, ``_``, ``-``, ``.`` and
spaces, lower case, joined by single spaces), and of their matches the one ending right-most
wins (the head of a compound comes last: ``TableLamp``, ``CoffeeTable``) — except that an
object class beats a room-envelope class (:func:`~sceneforge.conventions.is_envelope`: wall,
floor, ceiling, door, window, curtain, picture, ...), which in a name only says where the
object is (``Lamp_Ceiling``, ``WallLight``, ``Kitchen_Cabinet_Door``), and ``drop`` beats
both (``Plant_Pot``, ``Chair_Collider``). Part words (the bundled file's ``parts``: ``frame``,
``shade``, ``glass``, ``seat``, ``cushion``) name a piece or the material of what the rest of
the name names, so they count only when no other word matches (``WindowFrame`` is a window,
``LightShade`` a lamp, ``Toilet_Seat`` a toilet; ``Frame`` alone is a picture).
"""

from __future__ import annotations

import json
import re
from bisect import bisect_right
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from ..conventions import NYU40_NAMES, is_envelope, nyu40_id
from ..errors import SceneforgeError
from .categories import data_file

__all__ = ["BUNDLED_MAP", "DROP", "SHELL", "TAG", "NameMap", "Rule", "head_match", "words"]

#: the target that leaves an instance out
DROP = "drop"
#: the target that splits a merged envelope mesh into wall, floor and ceiling
SHELL = "shell"
#: the bundled rules, tried after the user's
BUNDLED_MAP = "name_patterns.json"
#: the ``<nyu40 name>__`` tag of sceneforge's writers at the start of a name
TAG = re.compile(r"^(" + "|".join(map(re.escape, NYU40_NAMES)) + r")__(?=.)")

# runs of letters (digits, "_" and every other character separate words), then camelCase
# humps inside a run: "TVStand" → TV, Stand; "LightShade" → Light, Shade
_LETTERS = re.compile(r"[^\W\d_]+")
_HUMP = re.compile(r"(?<=[a-z])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])")


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
    """The rules of one lookup (module doc): ``user`` rules first match on the whole name,
    then the ``bundled`` rules by head word, with ``parts`` the words that name a piece."""

    user: tuple[Rule, ...]
    bundled_rules: tuple[Rule, ...]
    parts: frozenset[str]

    @classmethod
    def bundled(cls) -> "NameMap":
        """The bundled rules alone."""
        return _bundled()

    @classmethod
    def with_user_rules(cls, path: str | Path | None) -> "NameMap":
        """The rules of the user's map file ``path`` (none when None), then the bundled ones."""
        bundled = cls.bundled()
        if path is None:
            return bundled
        return cls(read_rules(path), bundled.bundled_rules, bundled.parts)

    def match(self, name: str) -> tuple[int | str | None, Rule | None]:
        """``(target, rule)`` for a node name: the tag's class, the first matching user rule's
        target, the bundled rules' head-word target, or the class a bare NYU40 name stands
        for; ``(None, None)`` when unknown."""
        tag = TAG.match(name)
        if tag is not None:
            return nyu40_id(tag.group(1)), None
        rule = self.user_rule(name)
        if rule is None:
            rule = head_match(self.bundled_rules, self.parts, name)
        if rule is not None:
            return rule.target, rule
        return nyu40_id(name), None

    def lookup(self, name: str) -> int | str | None:
        """The target of a node name (:meth:`match` without the rule)."""
        return self.match(name)[0]

    def user_rule(self, name: str) -> Rule | None:
        """The first of the user's rules that matches ``name``, or None: a name the user's map
        decides, which no later guess (bundled rules, geometry) overrides."""
        return next((rule for rule in self.user if rule.pattern.search(name)), None)


def words(name: str) -> list[str]:
    """The words of a name, lower case: ``"CeilingLampshade.001"`` → ``["ceiling", "lampshade"]``,
    ``"TV_Stand"`` → ``["tv", "stand"]`` (module doc)."""
    return [w.lower() for run in _LETTERS.findall(name) for w in _HUMP.split(run) if w]


def head_match(rules: tuple[Rule, ...], parts: frozenset[str], name: str) -> Rule | None:
    """The rule of ``name``'s head word among ``rules`` (module doc), or None when none matches.

    Each rule is searched in the name's words joined by single spaces; a match ranks by its
    target (``drop`` > an object class > an envelope class or ``shell``), then by where it
    ends (right-most first), then by the rule's order. Matches ending in a word of ``parts``
    are left out while a match ends in any other word.
    """
    ws = words(name)
    text = " ".join(ws)
    starts = [0]
    for w in ws[:-1]:
        starts.append(starts[-1] + len(w) + 1)
    found = []  # (rank, end, -order, in a part word, rule)
    for order, rule in enumerate(rules):
        for m in rule.pattern.finditer(text):
            if m.end() > m.start():
                word = ws[bisect_right(starts, m.end() - 1) - 1]
                found.append((_rank(rule.target), m.end(), -order, word in parts, rule))
    whole = [f for f in found if not f[3]]
    return max(whole or found, key=lambda f: f[:3])[4] if found else None


def _rank(target: int | str) -> int:
    """How strongly a target claims a name: leaving it out, then an object, then the envelope."""
    if target == DROP:
        return 2
    return 0 if target == SHELL or is_envelope(target) else 1


def read_rules(path: str | Path) -> tuple[Rule, ...]:
    """The rules of a map file: ``{"patterns": [[regex, target], ...]}`` or the bare list.

    Raises :class:`SceneforgeError` naming the file and the rule for anything unreadable.
    """
    path = Path(path)
    return _rules(_read(path), path)


def _rules(doc, path: Path) -> tuple[Rule, ...]:
    """The rules of the map ``doc`` read from ``path`` (:func:`read_rules`)."""
    items = doc.get("patterns") if isinstance(doc, dict) else doc
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


def _read(path: Path):
    """The JSON document of a map file; :class:`SceneforgeError` when it cannot be read."""
    try:
        return json.loads(path.read_text())
    except OSError as e:
        raise SceneforgeError(f"cannot read name map {path}: {e.strerror or e}") from None
    except ValueError as e:
        raise SceneforgeError(f"cannot read name map {path}: {e}") from None


@lru_cache(maxsize=1)
def _bundled() -> NameMap:
    path = data_file(BUNDLED_MAP)
    doc = _read(path)
    return NameMap((), _rules(doc, path), frozenset(doc["parts"]))
