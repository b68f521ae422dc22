"""Batches of toy houses written in sceneforge's format, and the bundled set.

Regenerate the bundled houses with ``python -m sceneforge.houses.toy --bundle``.
"""

from __future__ import annotations

import os
import shutil
import uuid
from pathlib import Path

import numpy as np

from ...errors import SceneforgeError
from .. import bundled_toy_dir
from .hard_cases import ToyOptions
from .house import check_seed, generate_house

#: the bundled houses are ``toy_0_000`` .. ``toy_0_002``
BUNDLE_SEED = 0
BUNDLE_COUNT = 3


def house_seed(seed: int, index: int) -> int:
    """Seed of house ``index`` of a batch generated with ``seed`` (independent streams)."""
    return int(np.random.SeedSequence(seed, spawn_key=(index,)).generate_state(1, np.uint64)[0])


def toy_house_id(seed: int, index: int) -> str:
    return f"toy_{seed}_{index:03d}"


def write_toy_houses(out: str | Path, count: int, seed: int, progress=None,
                     options: ToyOptions | None = None, *, replace: bool = False) -> list[Path]:
    """Write ``count`` toy houses into ``out/<id>/`` in sceneforge's format; return the folders.

    House ``i`` has id ``toy_<seed>_<i:03d>`` and seed :func:`house_seed` ``(seed, i)``, and
    the hard cases ``options`` asks for (:class:`~.hard_cases.ToyOptions`; None: none).
    ``progress(house, folder)`` is called after each house is written. Each house is written
    into a hidden folder beside its own and renamed into place when complete, so a killed
    run leaves whole houses only (house discovery skips hidden names). A folder of the
    house's id already there is kept when it holds the same bytes (the same seed and options
    wrote it) and refused otherwise: it is not this house, and nothing here made it
    (``replace``: replaced, for the package's own bundle after the generator changed).
    """
    from ..formats.native import write_house

    seed = check_seed(seed)
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
        raise SceneforgeError(f"toy houses: count must be a positive integer, got {count!r}")
    folders = []
    for i in range(count):
        house = generate_house(house_seed(seed, i), toy_house_id(seed, i), options)
        folder = Path(out) / house.id
        partial = folder.with_name(f".{house.id}.{uuid.uuid4().hex[:8]}.partial")
        try:
            if folder.exists() and not folder.is_dir():
                raise NotADirectoryError(f"{folder} is a file")
            write_house(house, partial)
            if folder.exists() and replace:
                shutil.rmtree(folder)
            if not folder.exists():
                os.replace(partial, folder)
            elif not _same_files(partial, folder):
                raise SceneforgeError(f"{folder}: holds another house than {house.id} of seed {seed} with "
                                      "these options; write the toy houses to another folder")
        except OSError as e:
            raise SceneforgeError(f"toy houses: cannot write {folder}: {e.strerror or e}") from None
        finally:
            shutil.rmtree(partial, ignore_errors=True)
        folders.append(folder)
        if progress is not None:
            progress(house, folder)
    return folders


def _same_files(a: Path, b: Path) -> bool:
    """The folders ``a`` and ``b`` hold the same files with the same bytes."""
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    if files != sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file()):
        return False
    return all((a / f).read_bytes() == (b / f).read_bytes() for f in files)


def write_bundle(out: str | Path | None = None) -> list[Path]:
    """(Re)write the bundled toy houses (into the package unless ``out`` is given)."""
    return write_toy_houses(out or bundled_toy_dir(), BUNDLE_COUNT, BUNDLE_SEED, replace=True)
