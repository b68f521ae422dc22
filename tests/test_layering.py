"""Imports run downward only: no import cycles, and every module imports from its
own layer or those below, in the layer order docs/architecture.md states.

Every import that runs counts, function-level ones included; those under
``if TYPE_CHECKING:`` do not (they never run). A module importing its own package's
``__init__`` (or a parent's) is not counted, as Python runs that before the module anyway.
The rules are ``../shared/tools/import_cycles.py``'s, and that checker runs too where it is.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import SHARED, needs_shared

ROOT = Path(__file__).resolve().parents[1]
#: the installed package names of the source folders (pyproject.toml's ``package-dir``)
FOLDERS = {"sceneforge": "sceneforge", "sceneforge.cli": "cli", "sceneforge.schemas": "schemas"}
CHECKER = SHARED / "tools" / "import_cycles.py"


def modules(root: Path, folders: dict[str, str]) -> dict[str, Path]:
    """Module name → file, for every ``.py`` under the folders (a package's ``__init__`` is
    the package's own module)."""
    out = {}
    for package, folder in folders.items():
        for path in sorted((root / folder).rglob("*.py")):
            parts = [*package.split("."), *path.relative_to(root / folder).with_suffix("").parts]
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


class _Imports(ast.NodeVisitor):
    """The modules of ``known`` that the code of ``module`` imports when it runs."""

    def __init__(self, module: str, is_package: bool, known: dict[str, Path]):
        self.module, self.is_package, self.known, self.found = module, is_package, known, set()

    def _resolve(self, name: str) -> str | None:
        while name and name not in self.known:
            name = name.rpartition(".")[0]
        return name or None

    def _add(self, name: str) -> None:
        target = self._resolve(name)
        if target is not None:
            self.found.add(target)

    def visit_If(self, node: ast.If) -> None:
        test = node.test
        if (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
                isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"):
            for child in node.orelse:
                self.visit(child)
            return
        self.generic_visit(node)

    def visit_Import(self, node: ast.Import) -> None:
        for alias in node.names:
            self._add(alias.name)

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        if node.level:
            base = self.module.split(".")
            if not self.is_package:
                base = base[:-1]
            base = base[: len(base) - (node.level - 1)]
            name = ".".join([*base, *([node.module] if node.module else [])])
        else:
            name = node.module or ""
        for alias in node.names:  # ``from . import x`` names the submodule x
            sub = f"{name}.{alias.name}"
            self._add(sub if sub in self.known else name)


def import_graph(known: dict[str, Path]) -> dict[str, set[str]]:
    """Module → the modules it imports (not itself, nor its own packages)."""
    graph = {}
    for module, path in known.items():
        visitor = _Imports(module, path.name == "__init__.py", known)
        visitor.visit(ast.parse(path.read_text(), str(path)))
        graph[module] = {t for t in visitor.found if t != module and not module.startswith(t + ".")}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of two or more modules (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 10 * len(graph) + 100))
    try:
        for v in sorted(graph):
            if v not in index:
                visit(v)
    finally:
        sys.setrecursionlimit(limit)
    return found


def layer_order(readme: Path = ROOT / "docs" / "architecture.md") -> list[list[str]]:
    """docs/architecture.md's numbered layer list, bottom first: per layer, the module names
    (``__init__`` is the ``sceneforge`` package's own module)."""
    section = re.split(r"^#{1,2} Architecture\n", readme.read_text(), maxsplit=1, flags=re.M)[1].split("\n## ", 1)[0]
    layers = []
    for line in section.splitlines():
        match = re.match(r"(\d+)\. ((?:`[\w.]+`(?:, )?)+):", line)
        if match:
            assert int(match.group(1)) == len(layers) + 1, line
            names = re.findall(r"`([\w.]+)`", match.group(2))
            layers.append(["sceneforge" if n == "__init__" else f"sceneforge.{n}" for n in names])
    return layers


def layer_of(module: str, layers: list[list[str]]) -> int | None:
    """The index of the layer that names ``module`` or a package holding it (the longest name wins)."""
    best = None
    for i, names in enumerate(layers):
        for name in names:
            if module == name or (name != "sceneforge" and module.startswith(name + ".")):
                if best is None or len(name) > len(best[1]):
                    best = (i, name)
    return None if best is None else best[0]


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return import_graph(modules(ROOT, FOLDERS))


def test_no_import_cycles(graph):
    assert len(graph) > 80
    assert cycles(graph) == []


def test_every_module_imports_only_its_own_layer_or_below(graph):
    layers = layer_order()
    assert len(layers) >= 8, "docs/architecture.md lists the layers as '1. `name`, ...: what'"
    unplaced = sorted(m for m in graph if layer_of(m, layers) is None)
    assert unplaced == [], "modules in no layer of docs/architecture.md's list"
    upward = sorted(f"{m} (layer {layer_of(m, layers) + 1}) imports {t} (layer {layer_of(t, layers) + 1})"
                    for m, targets in graph.items() for t in targets if layer_of(t, layers) > layer_of(m, layers))
    assert upward == []


def _plant(tmp_path: Path, files: dict[str, str]) -> dict[str, set[str]]:
    for name, text in files.items():
        path = tmp_path / "pkg" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return import_graph(modules(tmp_path, {"pkg": "pkg"}))


def test_a_function_level_import_upward_is_a_cycle_and_a_type_checking_one_is_not(tmp_path):
    graph = _plant(tmp_path, {
        "__init__.py": "",
        "low.py": "def f():\n    from .high import g\n    return g\n",
        "high.py": "from . import low\n",
        "typed.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .high import g\nelse:\n"
                    "    import pkg.low\n",
        "sub/__init__.py": "from .. import typed\n",
        "sub/leaf.py": "from .. import sub\nimport pkg\n",
    })
    assert graph["pkg.low"] == {"pkg.high"} and graph["pkg.high"] == {"pkg.low"}
    assert graph["pkg.typed"] == {"pkg.low"}  # TYPE_CHECKING imports never run; its else branch does
    assert graph["pkg.sub"] == {"pkg.typed"} and graph["pkg.sub.leaf"] == set()  # own packages: not counted
    assert cycles(graph) == [["pkg.high", "pkg.low"]]


def test_an_upward_import_breaks_the_layer_order(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text("# x\n\n## Architecture\n\n1. `errors`: shared\n2. `store`, `cli`: the rest\n\n## Next\n")
    layers = layer_order(readme)
    assert layers == [["sceneforge.errors"], ["sceneforge.store", "sceneforge.cli"]]
    assert layer_of("sceneforge.store.writer", layers) == 1 and layer_of("sceneforge.errors", layers) == 0
    assert layer_of("sceneforge.houses", layers) is None


@needs_shared(CHECKER)  # where it is absent, test_no_import_cycles still applies the same rules
def test_the_shared_checker_counts_no_cycles():
    """``../shared/tools/import_cycles.py``, where the checkout has it beside the repo (CI's
    clone does), agrees: 0 cycles."""
    out = subprocess.run([sys.executable, str(CHECKER), str(ROOT), "sceneforge"], capture_output=True, text=True,
                         check=True).stdout
    assert out.splitlines()[-1].startswith("0 import cycles"), out
