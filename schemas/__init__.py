"""The JSON Schemas of sceneforge's on-disk contracts (house format, config, store layout).

Installed as ``sceneforge.schemas`` so that the schemas travel with the package.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

from sceneforge.errors import SceneforgeError

NAMES = ("house", "config", "store")


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


def validate_or_raise(doc, name: str, *, what: str) -> None:
    """Raise :class:`SceneforgeError` naming ``what`` and the first problems when invalid."""
    problems = errors(doc, name)
    if problems:
        more = f" (and {len(problems) - 3} more)" if len(problems) > 3 else ""
        raise SceneforgeError(f"{what}: does not match the {name} schema: {'; '.join(problems[:3])}{more}")
