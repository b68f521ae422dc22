"""The Makefile's install: a different ``TORCH_INDEX`` reinstalls torch from it, and a later
``make`` keeps the index of the last install (run on a copy with a logging stand-in Python)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CPU = "https://download.pytorch.org/whl/cpu"

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="no make")


@pytest.fixture
def checkout(tmp_path) -> Path:
    """The Makefile and its prerequisites, with a stand-in ``.venv/bin/python`` that logs its
    arguments to ``calls.log`` and a no-op ``scripts/system-deps.sh``."""
    shutil.copy(ROOT / "Makefile", tmp_path / "Makefile")
    for name in ("pyproject.toml", "setup.py", "sceneforge/raytrace/_embree.cpp"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text("")
    (tmp_path / "scripts").mkdir()
    (tmp_path / "scripts" / "system-deps.sh").write_text("exit 0\n")
    python = tmp_path / ".venv" / "bin" / "python"
    python.parent.mkdir(parents=True)
    python.write_text(f'#!/bin/sh\necho "$*" >> {tmp_path / "calls.log"}\n')
    python.chmod(0o755)
    return tmp_path


def make(root: Path, *args: str) -> tuple[str, list[str]]:
    """Run ``make install ARGS`` in ``root``: its output and the stand-in Python's new calls."""
    log = root / "calls.log"
    before = log.read_text().splitlines() if log.exists() else []
    out = subprocess.run(["make", "install", *args], cwd=root, capture_output=True, text=True, check=True)
    after = log.read_text().splitlines() if log.exists() else []
    return out.stdout, after[len(before):]


def torch_calls(calls: list[str]) -> list[str]:
    return [c for c in calls if "torch" in c and "import" not in c]


def test_a_new_torch_index_reinstalls_torch_and_is_remembered(checkout):
    _, calls = make(checkout)
    assert torch_calls(calls)[-1] == "-m pip install --quiet torch==2.13.0"
    _, calls = make(checkout)
    assert calls == []  # nothing changed: nothing installed

    out, calls = make(checkout, f"TORCH_INDEX={CPU}")  # used to print "Nothing to be done"
    assert f"torch: installing from {CPU}" in out
    assert torch_calls(calls) == ["-m pip uninstall --quiet --yes torch",
                                  f"-m pip install --quiet torch==2.13.0 --index-url {CPU}"]
    assert make(checkout)[1] == []  # a later make keeps the CPU index: no reinstall

    _, calls = make(checkout, "TORCH_INDEX=")  # back to the default index
    assert torch_calls(calls)[-1] == "-m pip install --quiet torch==2.13.0"
