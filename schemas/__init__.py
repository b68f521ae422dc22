"""The JSON Schemas of sceneforge's on-disk contracts (house format, scene manifest, the
configs of render, train, predict and evaluate, store layout).

Installed as ``sceneforge.schemas`` so that the schemas travel with the package.
"""

from __future__ import annotations

import difflib
import json
from functools import lru_cache
from pathlib import Path

from sceneforge.errors import SceneforgeError

NAMES = ("house", "scene", "config", "train", "predict", "evaluate", "store")


@lru_cache(maxsize=None)
def load(name: str) -> dict:
    """The parsed JSON Schema ``schemas/<name>.schema.json``."""
    if name not in NAMES:
        raise KeyError(f"no schema {name!r}; known: {', '.join(NAMES)}")
    return json.loads((Path(__file__).parent / f"{name}.schema.json").read_text())


def errors(doc, name: str) -> list[str]:
    """Every way ``doc`` breaks schema ``name``, as ``path: message`` strings (empty = valid)."""
    import jsonschema

    validator = jsonschema.Draft202012Validator(load(name))
    return [
        f"{'/'.join(str(p) for p in e.absolute_path) or '(top)'}: {e.message}"
        for e in sorted(validator.iter_errors(doc), key=lambda e: list(map(str, e.absolute_path)))
    ]


def unknown_keys(doc, name: str) -> list[tuple[str, list[str]]]:
    """The keys of ``doc`` that schema ``name`` does not know, as (dotted key, the keys
    allowed beside it) pairs, sorted by key."""
    import jsonschema

    found = []
    for e in jsonschema.Draft202012Validator(load(name)).iter_errors(doc):
        if e.validator != "additionalProperties" or not isinstance(e.instance, dict):
            continue
        known = list(e.schema.get("properties", {}))
        where = [str(p) for p in e.absolute_path]
        found += [(".".join([*where, key]), known) for key in e.instance if key not in known]
    return sorted(found)


def validate_or_raise(doc, name: str, *, what: str) -> None:
    """Raise :class:`SceneforgeError` naming ``what`` and the first problems when invalid;
    an unknown key is named first, with the nearest known key when one is close."""
    unknown = unknown_keys(doc, name)
    if unknown:
        keys = ", ".join(repr(key) for key, _ in unknown)
        hint = ""
        if len(unknown) == 1:
            key, known = unknown[0]
            near = difflib.get_close_matches(key.rsplit(".", 1)[-1], known, n=1)
            hint = f"; did you mean {near[0]!r}?" if near else ""
        raise SceneforgeError(f"{what}: unknown key{'s' if len(unknown) > 1 else ''} {keys}: Additional properties "
                              f"are not allowed by the {name} schema{hint}")
    problems = errors(doc, name)
    if problems:
        more = f" (and {len(problems) - 3} more)" if len(problems) > 3 else ""
        raise SceneforgeError(f"{what}: does not match the {name} schema: {'; '.join(problems[:3])}{more}")
