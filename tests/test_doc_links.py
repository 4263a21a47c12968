"""Every link from the README or docs/ to a section of another page (or of its own) names a
heading that page has: moving or renaming a section leaves no link pointing nowhere."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
LINK = re.compile(r"\]\(([^)#\s]*)#([^)\s]+)\)")


def anchor(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    out, fenced = set(), False
    for line in page.read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and line.startswith("#"):
            out.add(anchor(line.lstrip("#")))
    return out


def test_anchor_follows_githubs_rule():
    assert anchor(" Threads and device") == "threads-and-device"
    assert anchor("`prior=none` on SIFT + PnP's own SIFT and grey") == "priornone-on-sift--pnps-own-sift-and-grey"


def test_every_section_link_names_a_heading_of_its_page():
    known = {page.resolve(): anchors(page) for page in PAGES}
    broken = []
    for page in PAGES:
        for match in LINK.finditer(page.read_text(encoding="utf-8")):
            target = (page.parent / match.group(1)).resolve() if match.group(1) else page.resolve()
            if target in known and match.group(2) not in known[target]:
                broken.append(f"{page.relative_to(REPO)} -> {match.group(1) or page.name}#{match.group(2)}")
    assert not broken, broken
