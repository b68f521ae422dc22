"""The built wheel carries the CLI, the schemas and the bundled houses, and works outside the repo."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    # build from a clean copy: setuptools would reuse a stale build/ folder of the work tree
    src = tmp_path_factory.mktemp("src") / "sceneforge"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        ".git", ".venv", "build", "dist", "*.egg-info", "__pycache__", "demo", "*.zarr", ".ruff_cache", ".pytest_cache"))
    res = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(out), str(src)],
        check=True, capture_output=True, text=True,
    )
    (out / "build.log").write_text(res.stdout + res.stderr)
    return next(out.glob("sceneforge-*.whl"))


def test_the_build_says_nothing_but_what_matters(wheel):
    # setuptools warned ~200 lines per install about the data folders it was not told of and
    # the license table; a quiet build leaves only a missing Embree worth saying
    log = (wheel.parent / "build.log").read_text()
    assert "Warning" not in log and "warn" not in log, log[:2000]


def test_wheel_contents(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    # every module of the source tree ships (pyproject lists packages explicitly)
    for folder, prefix in ((ROOT / "sceneforge", "sceneforge"), (ROOT / "cli", "sceneforge/cli")):
        for module in folder.rglob("*.py"):
            assert f"{prefix}/{module.relative_to(folder).as_posix()}" in names, module
    for needed in ("sceneforge/cli/main.py", "sceneforge/schemas/house.schema.json",
                   "sceneforge/data/name_patterns.json"):
        assert needed in names
    assert any(n.startswith("sceneforge/data/toy_houses/") and n.endswith("house.json") for n in names)


def test_installed_package_works_outside_the_repo(wheel, tmp_path):
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    code = (
        "import sceneforge, sceneforge.schemas as s; from sceneforge.houses import discover, load, BUNDLED_TOY;"
        "assert str(sceneforge.__file__).startswith(%r);" % str(site)
        + "srcs = discover(BUNDLED_TOY); h = load(srcs[0]); s.load('house');"
        "print(len(srcs), len(h.instances))"
    )
    res = subprocess.run([sys.executable, "-I", "-c", f"import sys; sys.path.insert(0, {str(site)!r}); {code}"],
                         cwd=tmp_path, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    n_houses, n_instances = map(int, res.stdout.split())
    assert n_houses == 3 and n_instances > 10
