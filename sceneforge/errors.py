"""Expected failures. The CLI prints these as one red line; anything else is a bug."""

from __future__ import annotations


class SceneforgeError(Exception):
    """Base class of every error a user can cause (bad input, missing dependency, ...)."""


class HouseError(SceneforgeError):
    """A house cannot be loaded. Names the house, the file and the problem."""

    def __init__(self, house: str, file: str | None, problem: str):
        self.house, self.file, self.problem = str(house), file and str(file), problem
        where = f"house {self.house}" + (f": {self.file}" if self.file else "")
        super().__init__(f"{where}: {problem}")


class UnknownFormatError(SceneforgeError):
    """A path is not a house in any supported format."""


class MissingDependencyError(SceneforgeError):
    """An optional dependency is needed for the feature that was used."""

    def __init__(self, package: str, feature: str, install: str):
        super().__init__(f"{feature} needs {package}: install it with `{install}`")


class DamagedStoreError(SceneforgeError):
    """A store's file cannot be read as written (truncated, changed or deleted since):
    names the array, the views and the shard file, and the command that says how to repair it."""


class StoreLockedError(SceneforgeError):
    """Another live process holds the lock of a store (a second writer is refused)."""


class Interrupted(KeyboardInterrupt):
    """Ctrl-C (or SIGTERM) stopped a command that knows how to go on: ``hint`` says what to
    run next, as the CLI prints it after "interrupted: "."""

    def __init__(self, hint: str):
        super().__init__(hint)
        self.hint = hint


#: Exit codes of the ``sceneforge`` command, defined once (README "Exit codes").
EXIT_OK = 0
#: an expected error (bad input, unwritable output, full disk, a store another run holds):
#: one red line; what was written before it is kept
EXIT_ERROR = 1
#: a bad option or argument (Click's own code)
EXIT_USAGE = 2
#: the command finished, but some of its work failed: houses or views that failed (render,
#: houses inspect), problems found in a store (validate), checks that failed (doctor)
EXIT_FAILURES = 3
#: interrupted by Ctrl-C (128 + SIGINT, as shells report it)
EXIT_INTERRUPTED = 130


def listed(items, shown: int = 5) -> str:
    """``"a, b, c and 4 more"``: the first ``shown`` of ``items`` (strings) and how many
    are left out, for messages naming many files, houses or views."""
    items = list(items)
    more = f" and {len(items) - shown} more" if len(items) > shown else ""
    return ", ".join(items[:shown]) + more


def no_such_path(path, known: tuple[str, ...] = ()) -> str:
    """``"PATH: no such file or folder"``, with the closest names that do exist beside it
    (or among ``known``, e.g. ``bundled:toy``) as a suggestion: a typo gets its fix."""
    import difflib
    from pathlib import Path

    text = str(path)
    close = difflib.get_close_matches(text, known, n=1) if known else []
    if not close:
        parent = Path(text).parent
        try:
            names = sorted(p.name for p in parent.iterdir()) if parent.is_dir() else []
        except OSError:
            names = []
        close = [str(parent / n) if str(parent) != "." else n
                 for n in difflib.get_close_matches(Path(text).name, names, n=2)]
    hint = f" (did you mean {' or '.join(close)}?)" if close else ""
    return f"{text}: no such file or folder{hint}"


def plural(n: int, word: str, many: str | None = None) -> str:
    """``"1 house"``, ``"2 houses"`` (``many``: the plural when it is not ``word + "s"``):
    counts in messages, library and CLI alike."""
    return f"{n} {word if n == 1 else many or word + 's'}"
