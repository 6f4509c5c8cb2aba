"""The documentation stands alone: every section the code cites exists, and nothing points outside
the repository or at paths of the machine that wrote it."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCOPE = ("README.md", "DEVELOPERS.md", "CHANGELOG.md", "docs", "sage_core", "sage_cli", "benchmarks", "examples")
SUFFIXES = {".py", ".md", ".cpp", ".yaml", ".csv", ".json", ".txt", ".toml"}


def _files() -> list[Path]:
    out: list[Path] = []
    for name in SCOPE:
        p = REPO / name
        out += [p] if p.is_file() else [f for f in p.rglob("*") if f.is_file() and f.suffix in SUFFIXES]
    return out


def _sections(doc: Path) -> set[str]:
    """Section numbers of a page: the leading ``N`` / ``N.M`` of its headings."""
    return {m.group(1) for m in re.finditer(r"^#{2,4} (\d+(?:\.\d+)?)[. ]", doc.read_text(encoding="utf-8"), re.M)}


def test_every_cited_section_exists():
    cite = re.compile(r"docs/(\w+)\.md §(\d+(?:\.\d+)?)(?:[–-](\d+(?:\.\d+)?))?")
    seen = 0
    for f in _files():
        for m in cite.finditer(f.read_text(encoding="utf-8", errors="replace")):
            doc = REPO / "docs" / f"{m.group(1)}.md"
            assert doc.is_file(), f"{f.relative_to(REPO)} cites missing {doc.name}"
            for sec in filter(None, (m.group(2), m.group(3))):
                assert sec in _sections(doc), f"{f.relative_to(REPO)} cites {doc.name} §{sec}, which has no such section"
            seen += 1
    assert seen > 40  # the code does cite the pages


def test_nothing_points_outside_the_repository_or_at_this_machine():
    outside = re.compile(r"\.\./shared|shared/(docs|paper)|SAGE\.md")
    machine = re.compile(r"(?<![\w.~/-])/(work|home|root|tmp|mnt)/\w")
    for f in _files():
        text = f.read_text(encoding="utf-8", errors="replace")
        assert not outside.search(text), f"{f.relative_to(REPO)} points outside the repository"
        if f.suffix in (".md", ".json"):
            assert not machine.search(text), f"{f.relative_to(REPO)} names a path of this machine"
