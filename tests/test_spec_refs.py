"""The specification ships with the project: every citation of it points into docs/spec.md, at a
section that page has.

Code, help texts, schemas, tests and docs cite the page as ``docs/spec.md §N`` or ``§N.M``; a
bare ``§N`` is a section of it too, and ``paper §N`` a section of the paper. The page once lived
outside the repository, cited by an upper-case name; no file may cite that any more.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SPEC = ROOT / "docs" / "spec.md"
#: the files scanned: tracked or new (not ignored) files of these kinds
SUFFIXES = {".py", ".md", ".json", ".toml", ".sh", ".cpp", ".cfg", ".ini", ".txt", ".yml", ".yaml"}
NAMES = {"Makefile"}
#: a citation of a page that lived outside the repository: the upper-case word alone, as in
#: "SPEC §4" or "SPEC.md" (environment variables such as FSSPEC_S3_KEY are one longer word),
#: or a numbered principle of the team's style guide ("STYLE 14")
OUTSIDE = re.compile(r"\bSPEC\b|\bSTYLE\s+\d+")
#: a citation of a section or subsection; ``paper §N`` cites the paper instead
SECTION = re.compile(r"(?<!paper )§\s?(\d+(?:\.\d+)?)")
#: the headings of docs/spec.md: ``## N. Title`` and ``### N.M Title``
HEADING = re.compile(r"^(##|###) (\d+)\.(\d*) ", re.MULTILINE)
#: the top-level sections, numbered as code and tests cite them
TITLES = ("Conventions", "Input: houses", "Cameras", "Frontal multi-layer depth", "Ground-truth mesh per view",
          "Overhead (virtual) camera", "Overhead ground truth", "RGB", "The store", "Models", "Evaluation")


def spec_sections(text: str) -> list[str]:
    """The section numbers of the page's headings, in order: ``"4"``, ``"4.1"``, ..."""
    return [f"{major}.{minor}" if level == "###" else major for level, major, minor in HEADING.findall(text)]


def problems(text: str, where: str, sections: set[str]) -> list[str]:
    """``where:line: ...`` for every outside citation and every citation of a missing section."""
    found = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        if OUTSIDE.search(line):
            found.append(f"{where}:{lineno}: cites a page outside the repository (the spec: cite docs/spec.md "
                         f"§N): {line.strip()}")
        for number in SECTION.findall(line):
            if number not in sections:
                found.append(f"{where}:{lineno}: §{number} is no section of docs/spec.md: {line.strip()}")
    return found


def scanned_files() -> list[Path]:
    try:
        listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                                capture_output=True, text=True, check=True).stdout.split("\0")
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    paths = (ROOT / name for name in sorted(set(filter(None, listed))))
    return [p for p in paths if (p.suffix in SUFFIXES or p.name in NAMES) and p.is_file()
            and p != Path(__file__).resolve()]


def test_the_spec_has_the_eleven_sections_in_order_with_numbered_subsections():
    text = SPEC.read_text()
    tops = re.findall(r"^## (\d+)\. (.+)$", text, re.MULTILINE)
    assert [(int(n), title) for n, title in tops] == list(enumerate(TITLES, start=1))
    last = {}
    for section in spec_sections(text):
        major, _, minor = section.partition(".")
        if minor:
            assert int(minor) == last.get(major, 0) + 1, f"§{section} does not follow §{major}.{last.get(major, 0)}"
            last[major] = int(minor)


def test_every_citation_is_of_a_section_of_docs_spec():
    sections = set(spec_sections(SPEC.read_text()))
    found = []
    for path in scanned_files():
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        found += problems(text, str(path.relative_to(ROOT)), sections)
    assert not found, f"{len(found)} citations to fix:\n" + "\n".join(found)


def test_the_check_finds_outside_and_dangling_citations():
    sections = {"4", "4.1", "5"}
    text = ("a (SP" "EC §4)\nb (SP" "EC 5)\nsee SP" "EC.md\nFSSPEC_S3_KEY=x SPEC_S3_ENDPOINT=y\n"
            "docs/spec.md §4.1, §5\ndocs/spec.md §4.2\nthe table of paper §12\n§ 9\nrun tests (ST" "YLE 15)\n"
            "STYLE.md's anchors\n")
    assert [p.split(":")[1] for p in problems(text, "f", sections)] == ["1", "2", "3", "6", "8", "9"]
    assert "§4.2 is no section" in problems(text, "f", sections)[3]
