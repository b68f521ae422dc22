"""What a format is: the :class:`Format` record every format module fills in, and the
:class:`HouseSource` that discovery finds and :func:`~sceneforge.houses.load` reads."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .. import LoadOptions
    from ..model import House


@dataclass(frozen=True)
class HouseSource:
    """A house that :func:`~sceneforge.houses.load` can read: its id, format and path.

    ``problem`` says why a house that discovery found cannot be read (a ``house.json``
    that is not JSON, an id two houses share); loading it raises
    :class:`~sceneforge.errors.HouseError` with that message, so the house fails alone.
    """

    id: str
    format: str
    path: Path
    problem: str | None = None


@dataclass(frozen=True)
class Format:
    """One input format: how to recognise its houses, list them and read one.

    :data:`sceneforge.houses.formats.REGISTRY` holds every format by name. ``detect`` and
    ``list`` are asked about paths that exist; ``load`` raises
    :class:`~sceneforge.errors.HouseError` for a house it cannot read.
    """

    #: the name ``--format`` takes and :attr:`HouseSource.format` holds
    name: str
    #: ``detect(path)``: True for a house file, a house folder or a root of this format
    detect: Callable[[Path], bool]
    #: ``load(source, options)``: the house ``source`` names
    load: Callable[[HouseSource, LoadOptions], House]
    #: ``list(path)``: the houses at a path this format detected or was asked for (all the
    #: houses of a root); None: the path is one house file, its id the file's stem
    list: Callable[[Path], list[HouseSource]] | None = None
    #: ``fallback(path)``: True for a file or folder no format recognises that this one takes
    #: when it is asked for by name; None: such files are skipped
    fallback: Callable[[Path], bool] | None = None

    def sources(self, path: Path) -> list[HouseSource]:
        """The houses at ``path``, a file or folder of this format."""
        return self.list(path) if self.list is not None else [HouseSource(path.stem, self.name, path)]


def json_document(path: Path):
    """The parsed content of a ``.json`` file, or None when it is not one or cannot be read.

    Formats recognised by a JSON file's keys ask about the same file in turn, so the last
    document read is kept (keyed by path, modification time and size) until
    :func:`forget_json_document`.
    """
    if path.suffix.lower() != ".json":
        return None
    try:
        stat = path.stat()
    except OSError:
        return None
    return _parsed_json(str(path), stat.st_mtime_ns, stat.st_size)


@lru_cache(maxsize=1)
def _parsed_json(path: str, mtime_ns: int, size: int):
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


def forget_json_document() -> None:
    """Drop the document :func:`json_document` keeps."""
    _parsed_json.cache_clear()
