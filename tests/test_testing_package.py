"""sceneforge.testing (writers only tests need) stays out of the runtime: nothing outside it imports it."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def imported_modules(source: str, module: str, is_package: bool) -> set[str]:
    """Absolute names of every module ``source`` (the code of ``module``) imports, relative ones resolved."""
    package = module.split(".") if is_package else module.split(".")[:-1]
    names = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            parent = ".".join([*base, *([node.module] if node.module else [])])
            names.add(parent)
            names |= {f"{parent}.{alias.name}" for alias in node.names}  # `from . import testing`
    return names


def runtime_modules():
    """(file, module name, is package) of every module the installed package runs: sceneforge/
    outside sceneforge/testing, and cli/ (installed as sceneforge.cli)."""
    for top, name in (("sceneforge", "sceneforge"), ("cli", "sceneforge.cli")):
        for file in sorted((ROOT / top).rglob("*.py")):
            rel = file.relative_to(ROOT / top)
            if top == "sceneforge" and rel.parts[0] == "testing":
                continue
            parts = [name, *rel.with_suffix("").parts]
            is_package = parts[-1] == "__init__"
            yield file, ".".join(parts[:-1] if is_package else parts), is_package


def test_no_runtime_module_imports_sceneforge_testing():
    offenders = [
        f"{file.relative_to(ROOT)} imports {name}"
        for file, module, is_package in runtime_modules()
        for name in imported_modules(file.read_text(), module, is_package)
        if name == "sceneforge.testing" or name.startswith("sceneforge.testing.")
    ]
    assert not offenders, offenders


def test_the_check_sees_relative_and_absolute_imports():
    modules = {m for _, m, _ in runtime_modules()}
    assert {"sceneforge.houses.formats", "sceneforge.cli.options"} <= modules
    assert not any(m.startswith("sceneforge.testing") for m in modules)
    for source in ("from ...testing import suncg", "from ... import testing", "import sceneforge.testing.gltf",
                   "from sceneforge.testing.obj import write_obj"):
        found = imported_modules(source, "sceneforge.houses.formats.suncg", is_package=False)
        assert any(n.startswith("sceneforge.testing") for n in found), source
    assert "sceneforge.testing" in imported_modules("from .. import testing", "sceneforge.houses", True)
    assert not any(n.startswith("sceneforge.testing")
                   for n in imported_modules("from ..houses import testing_tools", "sceneforge.cli.x", False))
