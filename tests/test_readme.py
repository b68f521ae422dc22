"""The README's commands are tested code: a README that drifts from the code fails here.

Every ``bash``, ``console``, ``sh`` and ``python`` block of README.md and docs/*.md is run by
:func:`test_readme_walkthrough`, in order, in a fresh folder holding a copy of the tracked
files, and the outputs a ``console`` block shows are compared with what its commands print;
or it is marked as not run. Marks are HTML comments on the lines right above the fence:

``<!-- not run: REASON -->``
    the block is not run (GPU, hours, a cluster, an install); the reason is required.
``<!-- needs: PATH -->``
    run only where PATH (relative to the repository root) exists: a file of ``../shared``
    (e.g. the breakfast room), which CI checks out beside the repo and a user's clone lacks.
``<!-- compare: labels (REASON) -->``
    compare each output line only up to its first ``:`` (what a machine prints differently).
``<!-- s3: BUCKET -->``
    run against a local S3 API (moto's server, :func:`sceneforge.testing.s3.local_s3`)
    holding the bucket BUCKET, with ``AWS_ENDPOINT_URL`` and credentials pointing at it.

In a shown output, ``…`` stands for any text within a line and a line of ``…`` (or ``...``)
alone for any lines; timings (``9.5 s``, ``46.5 ms``, ``2.3 views/s``) and progress bars are
not compared. The blocks of :data:`NOT_RUN_SECTIONS` are not run whatever their marks.
"""

from __future__ import annotations

import contextlib
import difflib
import hashlib
import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import pytest

from .conftest import SHARED

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
RUN_LANGUAGES = {"bash", "console", "sh", "python"}
#: heading → why none of the section's blocks runs here (its owner marks them one by one)
MARK = re.compile(r"^<!-- (not run|needs|compare|s3): (.+?) -->$")
TIMING = re.compile(r"\d+(?:\.\d+)?\s?(?:ms|s|min|views/s)(?![\w/])")
ANSI = re.compile(r"\x1b\[[0-9;]*m")
ANY_LINES = {"…", "..."}


@dataclass
class Block:
    """One fenced block: where it is, its language, its text and its marks."""

    doc: Path
    line: int  # 1-based line of the opening fence
    language: str
    text: str
    marks: dict[str, str] = field(default_factory=dict)

    @property
    def where(self) -> str:
        return f"{self.doc.relative_to(ROOT)}:{self.line}"

    @property
    def runs(self) -> bool:
        return self.language in RUN_LANGUAGES and "not run" not in self.marks

    def commands(self) -> list[tuple[str, list[str]]]:
        """(command, shown output lines) in order; a bash block shows no output."""
        if self.language == "console":
            steps: list[tuple[str, list[str]]] = []
            for line in self.text.splitlines():
                if line.startswith("$ "):
                    steps.append((line[2:], []))
                else:
                    steps[-1][1].append(line)
            return steps
        lines = [line for line in self.text.replace("\\\n", " ").splitlines()
                 if line.strip() and not line.lstrip().startswith("#")]
        return [(line, []) for line in lines]


def blocks(doc: Path, text: str | None = None) -> list[Block]:
    """Every fenced block of ``doc`` (or of ``text``, read as ``doc``) with its marks."""
    lines = (doc.read_text() if text is None else text).splitlines()
    found, i = [], 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("```"):
            end = next(k for k in range(i + 1, len(lines)) if lines[k].startswith("```"))
            marks, k = {}, i - 1
            while k >= 0 and MARK.match(lines[k]):
                key, value = MARK.match(lines[k]).groups()
                marks[key] = value
                k -= 1
            found.append(Block(doc, i + 1, line[3:].strip(), "\n".join(lines[i + 1:end]) + "\n", marks))
            i = end
        i += 1
    return found


def normalised(text: str) -> list[str]:
    """Printed (or shown) lines as they are compared: no colour, progress bars or timings."""
    out = [TIMING.sub("<time>", ANSI.sub("", line)).rstrip() for line in text.splitlines() if "━" not in line]
    while out and not out[-1]:
        out.pop()
    return out


def mismatch(shown: list[str], printed: str, mode: str = "") -> str:
    """'' when ``printed`` is what ``shown`` shows (module doc: ``…``, timings), else a diff."""
    want, got = normalised("\n".join(shown)), normalised(printed)
    if mode.startswith("labels"):
        want, got = ([line.split(":", 1)[0] for line in lines] for lines in (want, got))
    pattern = "".join(r"(?:.*\n)*?" if line.strip() in ANY_LINES
                      else ".*".join(map(re.escape, line.split("…"))) + r"\n" for line in want)
    if re.fullmatch(pattern, "".join(line + "\n" for line in got)):
        return ""
    return "\n".join(difflib.unified_diff(want, got, "README shows", "printed", lineterm=""))


def fresh_checkout(tmp: Path) -> Path:
    """The tracked files and the built extension copied into ``tmp/sceneforge`` (``../shared``
    linked beside it where this checkout has it), and ``tmp/bin`` with ``sceneforge`` and
    ``python`` running this interpreter."""
    clone = tmp / "sceneforge"
    names = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, text=True,
                           check=True).stdout.split("\0")
    # and the in-place build of the ray-tracing extension, as `make install` leaves it in a checkout
    built = [str(p.relative_to(ROOT)) for p in (ROOT / "sceneforge" / "raytrace").glob("_embree*.so")]
    for name in filter(None, names + built):
        if (ROOT / name).is_file():
            (clone / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, clone / name)
    if SHARED.is_dir():
        (tmp / "shared").symlink_to(SHARED)
    (tmp / "bin").mkdir()
    for name, args in (("sceneforge", "-m sceneforge "), ("python", "")):
        (tmp / "bin" / name).write_text(f'#!/bin/sh\nexec "{sys.executable}" {args}"$@"\n')
        (tmp / "bin" / name).chmod(0o755)
    return clone


def shell(command: str, cwd: Path, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, **(env or {}), "PATH": f"{cwd.parent / 'bin'}{os.pathsep}{os.environ['PATH']}",
           "COLUMNS": "100", "NO_COLOR": "1"}
    return subprocess.run(["bash", "-c", command], cwd=cwd, env=env, stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True, timeout=900)


def python_block(block: Block) -> str:
    """The block's code, then an assertion per ``expr  # (shape) dtype`` comment line."""
    checks = []
    for line in block.text.splitlines():
        m = re.match(r"^([\w.\[\]]+)\s+#\s*\(([\d, ]+)\)\s*(\w*)", line)
        if m:
            expr, shape, dtype = m.groups()
            shape = tuple(int(d) for d in shape.replace(" ", "").split(",") if d)
            checks.append(f"assert tuple(__import__('numpy').shape({expr})) == {shape!r}, {expr!r}")
            if dtype in {"float32", "float64", "uint8", "int32", "int64", "bool"}:
                checks.append(f"assert str({expr}.dtype) == {dtype!r}, ({expr!r}, {expr}.dtype)")
    return block.text + "\n".join(checks) + "\n"


def run_block(block: Block, cwd: Path) -> list[str]:
    """Run one block in ``cwd``: the problems found (failed commands, outputs that differ)."""
    if "s3" in block.marks:
        with local_bucket(block.marks["s3"]) as env:
            return _run_block(block, cwd, env)
    return _run_block(block, cwd)


@contextlib.contextmanager
def local_bucket(bucket: str) -> Iterator[dict[str, str]]:
    """The environment of a client of a local S3 API holding the empty bucket ``bucket``."""
    s3fs = pytest.importorskip("s3fs", reason="the s3 extra (s3fs) is not installed")
    pytest.importorskip("moto.server", reason="the test extra (moto[server]) is not installed")
    from sceneforge.testing.s3 import local_s3

    with local_s3() as server:
        env = server.env
        s3fs.S3FileSystem(endpoint_url=server.endpoint, key=env["AWS_ACCESS_KEY_ID"],
                          secret=env["AWS_SECRET_ACCESS_KEY"], skip_instance_cache=True).mkdir(bucket)
        yield env


def _run_block(block: Block, cwd: Path, env: dict[str, str] | None = None) -> list[str]:
    if block.language == "python":
        done = shell(f"python - <<'README_PYTHON'\n{python_block(block)}README_PYTHON", cwd, env)
        return [f"{block.where}: the python block failed:\n{done.stdout}"] if done.returncode else []
    problems = []
    for command, shown in block.commands():
        done = shell(command, cwd, env)
        if done.returncode:
            problems.append(f"{block.where}: `{command}` exited {done.returncode}:\n{done.stdout}")
        elif block.language == "console" and (diff := mismatch(shown, done.stdout, block.marks.get("compare", ""))):
            problems.append(f"{block.where}: `{command}` printed other than the README shows:\n{diff}")
    return problems


def digests(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in root.rglob("*") if p.is_file() and "__pycache__" not in p.parts}


def test_every_block_is_run_or_marked_with_a_reason():
    for doc in DOCS:
        for block in blocks(doc):
            for key, value in block.marks.items():
                assert value.strip(), f"{block.where}: `{key}:` needs a reason or a path"
            if block.language == "console":
                assert block.text.startswith("$ "), f"{block.where}: a console block starts with `$ command`"
            if "compare" in block.marks:
                assert block.marks["compare"].startswith("labels"), f"{block.where}: unknown compare mode"


def test_marks_decide_what_runs():
    text = ("# x\n<!-- not run: needs a GPU -->\n```bash\nsceneforge train a\n```\n"
            "<!-- needs: nowhere/x -->\n<!-- compare: labels (machine) -->\n```console\n$ sceneforge doctor\n```\n"
            "## Input formats\n```bash\nsceneforge render c\n```\n"
            "<!-- s3: a-bucket -->\n```bash\nsceneforge validate s3://a-bucket/x.zarr\n```\n")
    found = blocks(ROOT / "README.md", text)
    assert [b.runs for b in found] == [False, True, True, True]  # "needs" is decided where the walkthrough runs
    assert found[0].marks == {"not run": "needs a GPU"}
    assert found[1].marks == {"needs": "nowhere/x", "compare": "labels (machine)"}
    assert found[3].marks == {"s3": "a-bucket"}


def test_shown_output_allows_elisions_and_timings_only():
    shown = ["a.zarr: 12 views in 43.3 s; rendering 0.5 views/s", "house …/x.json", "…", "done"]
    assert mismatch(shown, "bar ━━━ 1/2\na.zarr: 12 views in 9.5 s; rendering 2.3 views/s\nhouse /a/x.json\n"
                    "one\ntwo\ndone\n") == ""
    assert mismatch(shown, "a.zarr: 11 views in 9.5 s; rendering 2.3 views/s\nhouse /x.json\ndone\n")
    assert mismatch(["PASS  torch: 2.13.0"], "PASS  torch: 2.14.0\n", "labels (versions)") == ""
    assert mismatch(["PASS  torch: 2.13.0"], "WARN  torch: 2.14.0\n", "labels (versions)")


def test_tour_commands_run_below():
    readme = blocks(ROOT / "README.md")
    tour = next(b for b in readme if "the tour" in b.marks.get("not run", ""))
    ran = {command for b in readme if b.runs for command, _ in b.commands()}
    for command, _ in tour.commands():
        command = command.split("  #", 1)[0].strip()
        assert command in ran or command.startswith("source "), f"the tour's `{command}` runs in no block"


def test_an_edited_output_fails(tmp_path):
    """The toy-houses block passes as the README shows it and fails with one count edited."""
    block = next(b for b in blocks(ROOT / "README.md") if b.text.startswith("$ sceneforge toy-houses"))
    cwd = fresh_checkout(tmp_path)
    assert run_block(block, cwd) == []
    edited = Block(block.doc, block.line, block.language, re.sub(r"instances (\d+)", "instances 99", block.text, count=1))
    shutil.rmtree(cwd / "demo")
    problems = run_block(edited, cwd)
    assert len(problems) == 1 and "-toy_7_000  rooms 4  instances 99" in problems[0], problems


FIGURE = re.compile(r"!\[[^\]]*\]\(([^)\s]+\.png)\)")


def figures_below_blocks() -> list[tuple[Block, Path, str]]:
    """(console block, figure, file the block prints) for each figure linked right below a
    console block (before any other block or heading) whose shown output names a file of the
    figure's name: the figure is what that block's command draws."""
    found = []
    for doc in DOCS:
        lines = doc.read_text().splitlines()
        for block in blocks(doc):
            if block.language != "console":
                continue
            after = block.line + len(block.text.splitlines()) + 1  # 0-based: the line after the closing fence
            for line in lines[after:]:
                if line.startswith(("```", "#")):
                    break
                for target in FIGURE.findall(line):
                    name = re.escape(Path(target).name)
                    printed = re.findall(rf"(?<![\w/.…])((?:[\w.-]+/)*{name})\b", block.text)
                    if printed:
                        found.append((block, doc.parent / target, printed[-1]))
    return found


def different_pixels(a: Path, b: Path) -> float:
    """The share of pixels of two same-sized PNGs that differ by more than 32 levels in a
    channel (antialiasing and font rendering may differ by machine; boxes and points do not)."""
    Image = pytest.importorskip("PIL.Image")
    import numpy as np

    pa, pb = (np.asarray(Image.open(p).convert("RGB"), dtype=np.int16) for p in (a, b))
    assert pa.shape == pb.shape, f"{a.name} is {pa.shape[1]}×{pa.shape[0]}, {b} is {pb.shape[1]}×{pb.shape[0]}"
    return float((np.abs(pa - pb).max(axis=2) > 32).mean())


def test_figures_are_what_the_blocks_above_them_draw(tmp_path):
    """A figure right below a console block that prints a file of its name (the overhead camera's
    boxes, a house preview) is that file: the block run again on a fresh checkout prints what it
    shows and draws the figure."""
    pytest.importorskip("matplotlib")
    pairs = figures_below_blocks()
    assert {figure.name for _, figure, _ in pairs} >= {"overhead_camera.png", "toy_0_000.png"}, pairs
    cwd = fresh_checkout(tmp_path)
    for block, figure, printed in pairs:
        assert run_block(block, cwd) == []
        share = different_pixels(figure, cwd / printed)
        assert share < 0.005, f"{block.where}: {figure.relative_to(ROOT)} is not what the block draws " \
                              f"({printed}): {share:.1%} of the pixels differ"


def test_named_benchmarks_and_scripts_exist():
    """Every ``python benchmarks/X.py --opt`` (or scripts/) a page names exists and takes
    those options: a figure names the command that printed it."""
    named = 0
    for doc in DOCS:
        text = re.sub(r"\s*\n\s*", " ", doc.read_text())
        for m in re.finditer(r"`(?:[A-Z_]+=\S+ )*python ((?:benchmarks|scripts)/[\w.]+\.py)([^`]*)`", text):
            script, args = ROOT / m.group(1), m.group(2)
            assert script.is_file(), f"{doc.name}: {m.group(1)} does not exist"
            source = script.read_text()
            for option in re.findall(r"(--[\w-]+)", args):
                assert f'"{option}"' in source, f"{doc.name}: {m.group(1)} takes no {option}"
            named += 1
    assert named >= 8


def test_links_point_at_files():
    for doc in DOCS:
        for target in re.findall(r"\]\(([^)#\s]+)\)", doc.read_text()):
            if not re.match(r"\w+://", target):
                assert (doc.parent / target).exists(), f"{doc.name}: link to missing {target}"


@pytest.mark.slow
def test_readme_walkthrough(tmp_path):
    """Every runnable block, in order, as a new user would run them on a fresh checkout
    (those that need ``../shared`` only where it is); then no tracked file has changed and
    every output is under ``demo/``."""
    cwd = fresh_checkout(tmp_path)
    before = digests(cwd)
    runnable = [block for doc in DOCS for block in blocks(doc) if block.runs]
    problems, absent = [], []  # absent: the `needs:` paths of the blocks not run
    for block in runnable:
        if "needs" in block.marks and not (cwd / block.marks["needs"]).exists():
            absent.append(block.marks["needs"])
            continue
        problems += run_block(block, cwd)
    after = digests(cwd)
    changed = sorted(k for k in before if before[k] != after.get(k))
    outside = sorted(k for k in set(after) - set(before) if not k.startswith("demo/"))
    assert not problems, "\n\n".join(problems)
    assert changed == [] and outside == [], f"tracked files changed: {changed}; outputs outside demo/: {outside}"
    # only ../shared may be missing, and only from a checkout without it (a user's clone):
    # where it is, as in CI, every block runs
    assert not absent or (not SHARED.is_dir() and all(p.startswith("../shared/") for p in absent)), absent
    assert len(runnable) >= 10  # the blocks are found
