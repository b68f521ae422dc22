"""``needs_shared`` (tests/conftest.py): where ``../shared`` is absent, as on a user's clone,
the tests that read it skip naming what they need as ``../shared/...``, and the run ends with
a line counting them, under xdist (``make test``'s ``-n 2``) as without."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

CONFTEST = Path(__file__).with_name("conftest.py")

SAMPLE = '''
import pytest

from .conftest import SHARED, needs_shared


@needs_shared(SHARED / "scenes" / "room.gltf")
def test_reads_a_scene():
    assert (SHARED / "scenes" / "room.gltf").read_text() == "room"


@pytest.mark.parametrize("name", ["toy", pytest.param("tool", marks=needs_shared(SHARED / "tools" / "tool.py"))])
def test_a_parameter_reads_a_tool(name):
    assert name == "toy" or (SHARED / "tools" / "tool.py").is_file()


def test_reads_nothing_shared():
    pass
'''


@pytest.mark.slow
@pytest.mark.parametrize("present", [False, True], ids=["users_clone", "ci"])
def test_what_needs_shared_skips_by_its_relative_name_and_is_counted(tmp_path, present):
    repo = tmp_path / "repo"
    (repo / "tests").mkdir(parents=True)
    (repo / "pytest.ini").write_text("[pytest]\n")  # the rootdir: no settings from the folders above
    shutil.copy(CONFTEST, repo / "tests" / "conftest.py")
    (repo / "tests" / "__init__.py").touch()
    (repo / "tests" / "test_sample.py").write_text(SAMPLE)
    if present:
        for name, text in (("scenes/room.gltf", "room"), ("tools/tool.py", "")):
            (tmp_path / "shared" / name).parent.mkdir(parents=True, exist_ok=True)
            (tmp_path / "shared" / name).write_text(text)
    # this run's own settings (PYTEST_ADDOPTS, xdist's worker variables) stay out of the inner one
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_")}
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-ra", "-n", "2", "-p", "no:cacheprovider",
                           "-p", "no:dash"], cwd=repo, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    lines = done.stdout.splitlines()
    skips = sorted(line.split(": ", 1)[1] for line in lines if line.startswith("SKIPPED"))
    if present:
        assert "tests that need ../shared: 2 ran, 0 skipped (../shared present)" in lines, done.stdout
        assert skips == [] and "4 passed" in lines[-1]
    else:
        assert "tests that need ../shared: 0 ran, 2 skipped (../shared absent: a user's clone)" in lines, done.stdout
        assert skips == [f"needs ../shared/{name} (CI checks ../shared out beside the repo; a user's clone has none)"
                         for name in ("scenes/room.gltf", "tools/tool.py")]
        assert "2 passed, 2 skipped" in lines[-1] and str(tmp_path) not in done.stdout
