"""Every relative link of README.md and docs/ resolves: the file (or directory) it names,
and for `#anchor` a heading of that file (GitHub's slugs) or an explicit HTML anchor. A
clone can follow them; links to web pages are not fetched."""

from __future__ import annotations

import os
import re
import unicodedata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").rglob("*.md")])

FENCE = re.compile(r"^(```|~~~).*?^\1[^\n]*$", re.MULTILINE | re.DOTALL)
CODE_SPAN = re.compile(r"(`+)(?:(?!\1).)+?\1", re.DOTALL)
INLINE = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
REFERENCE = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s.*)?$", re.MULTILINE)
HTML = re.compile(r"""<(?:a|img)\b[^>]*?\b(?:href|src)\s*=\s*["']([^"']+)["']""", re.IGNORECASE)
HTML_ANCHOR = re.compile(r"""<[a-z]+\b[^>]*?\b(?:id|name)\s*=\s*["']([^"']+)["']""", re.I)
HEADING = re.compile(r"^#{1,6}\s+(.*?)\s*#*\s*$", re.MULTILINE)
SCHEME = re.compile(r"^[a-z][a-z0-9+.-]*:", re.IGNORECASE)


def prose(text: str) -> str:
    """The text outside code blocks and code spans (where link syntax is not a link)."""
    return CODE_SPAN.sub("", FENCE.sub("", text))


def links(page: Path) -> list[str]:
    text = prose(page.read_text())
    found = INLINE.findall(text) + REFERENCE.findall(text) + HTML.findall(text)
    return [target for target in found if not SCHEME.match(target)]


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: its text (no markup) lower-cased, punctuation dropped
    but for '-' and '_', spaces to '-'."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link: its text
    text = re.sub(r"<[^>]+>", "", text).replace("`", "").lower()
    kept = "".join(c for c in text if c in " -_" or unicodedata.category(c)[0] in "LN")
    return kept.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = FENCE.sub("", page.read_text())
    seen: dict[str, int] = {}
    names = set(HTML_ANCHOR.findall(text))
    for heading in HEADING.findall(text):
        base = slug(heading)
        count = seen.get(base, 0)
        seen[base] = count + 1
        names.add(base if count == 0 else f"{base}-{count}")
    return names


def test_the_slugs_are_githubs():
    assert slug("Sim-to-real gap diagnosis (`egovib gap`, `egovib gap validate`)") == (
        "sim-to-real-gap-diagnosis-egovib-gap-egovib-gap-validate"
    )
    assert slug("Your robot in five commands") == "your-robot-in-five-commands"
    assert slug("PR2, 21 × 21: the [paper](x.md)") == "pr2-21--21-the-paper"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page):
    broken = []
    for target in links(page):
        path, _, anchor = target.partition("#")
        where = (page.parent / path).resolve() if path else page
        if not where.exists():
            broken.append(f"{target}: no {os.path.relpath(where, ROOT)}")
        elif anchor and where.suffix == ".md" and anchor not in anchors(where):
            broken.append(f"{target}: no heading #{anchor} in {where.relative_to(ROOT)}")
    assert not broken, f"{page.relative_to(ROOT)}: " + "; ".join(broken)


def test_the_pages_have_links_to_check():
    """The link syntax is found: README alone links to docs/ many times."""
    assert len([t for t in links(ROOT / "README.md") if t.startswith("docs/")]) >= 5


#: Paths of one machine: a clone has none of them (code blocks included).
MACHINE_PATH = re.compile(r"(?<![\w.~-])/(?:tmp|work|home|root|Users|check)/[\w.-]")


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_path_of_one_machine(page):
    text = page.read_text()
    found = [m.group(0) for m in MACHINE_PATH.finditer(text)]
    assert not found, f"{page.relative_to(ROOT)}: {found[:5]}"
