"""The pages point where they say: every relative link of README.md and docs/*.md reaches a
file (and its heading, where the link names one), and every section a comment or page
cites by name ("docs/quality.md, "Segment timing"") is still in that file. Measurements
move between the README and docs/ as the pages grow; a stale pointer fails here, not on a
reader."""

from __future__ import annotations

import re
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"\]\(([^)\s]+)\)")
CITATION = re.compile(r"\b(README|docs/[\w-]+\.md),\s*\"([^\"]+)\"")


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def prose(text: str) -> str:
    """The text outside fenced code blocks."""
    return re.sub(r"^```.*?^```", "", text, flags=re.M | re.S)


@cache
def headings(page: Path) -> list[str]:
    """The page's headings, read once per page however many links point into it."""
    return [line.lstrip("#").strip() for line in prose(page.read_text()).splitlines()
            if re.match(r"#{1,6} ", line)]


def section_names(page: Path) -> list[str]:
    """What a citation may name: the page's headings and its bold paragraph leads."""
    text = prose(page.read_text())
    bold = re.findall(r"^\*\*(.+?)\*\*", text, flags=re.M)
    return [" ".join(name.split()).lower() for name in headings(page) + bold]


def joined(text: str) -> str:
    """The text with its line breaks and comment markers gone: a citation may wrap."""
    return re.sub(r"\n\s*#*\s*", " ", text)


def test_slug_follows_github():
    assert slug("More motions cut from the corpus' own: worse") == "more-motions-cut-from-the-corpus-own-worse"
    assert slug("Before the converged tokenizer (3,000 steps)") == "before-the-converged-tokenizer-3000-steps"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_reach_a_file_and_heading(page):
    broken = []
    for target in LINK.findall(prose(page.read_text())):
        if re.match(r"[a-z]+:", target):  # http(s), mailto: not checked offline
            continue
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            broken.append(f"{target}: no file {path}")
        elif anchor and file.suffix == ".md" and anchor not in {slug(h) for h in headings(file)}:
            broken.append(f"{target}: no heading #{anchor} in {file.relative_to(ROOT)}")
    assert not broken, f"{page.name}: " + "; ".join(broken)


def cited_files() -> list[Path]:
    files = PAGES + sorted((ROOT / "configs").rglob("*.yaml"))
    for folder in ("segmo", "tools", "tests"):
        files += sorted((ROOT / folder).rglob("*.py"))
    return [f for f in files if f.name != Path(__file__).name]


def test_cited_sections_exist():
    missing = []
    for file in cited_files():
        for name, section in CITATION.findall(joined(file.read_text())):
            page = ROOT / ("README.md" if name == "README" else name)
            wanted = " ".join(section.rstrip("….").split()).lower()
            if not page.exists():
                missing.append(f"{file.relative_to(ROOT)}: {name} does not exist")
            elif not any(s.startswith(wanted) for s in section_names(page)):
                missing.append(f"{file.relative_to(ROOT)}: {name} has no section {section!r}")
    assert not missing, "\n".join(missing)


def test_citations_are_found():
    """The check above reads real citations (a regex that matched nothing would pass)."""
    text = (ROOT / "configs" / "mask" / "synthetic.yaml").read_text()
    assert len(CITATION.findall(joined(text))) >= 5
