"""Every link between the README and the pages of ``docs/`` points at a file and a heading
that exist, so that figures moved between RESULTS.md and NOTES.md leave no dead link."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"\]\(([^)\s#]*)(?:#([^)\s]+))?\)")


def _anchor(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces as dashes."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    found, fenced = set(), False
    for line in page.read_text().splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and line.startswith("#"):
            found.add(_anchor(line.lstrip("#")))
    return found


def test_anchor_follows_githubs_rule() -> None:
    assert _anchor(" DORP's rows: 1-3 objects (2026-12-07)") == "dorps-rows-1-3-objects-2026-12-07"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_links_of_the_page_resolve(page: Path) -> None:
    broken = []
    for match in LINK.finditer(page.read_text()):
        target, anchor = match.groups()
        if "://" in target or target.startswith("mailto:"):
            continue
        path = (page.parent / target).resolve() if target else page
        line = page.read_text()[: match.start()].count("\n") + 1
        if not path.exists():
            broken.append(f"line {line}: {target} does not exist")
        elif anchor and path.suffix == ".md" and anchor not in _anchors(path):
            broken.append(f"line {line}: no heading {anchor!r} in {path.name}")
    assert not broken, f"{page.name}: " + "; ".join(broken)
