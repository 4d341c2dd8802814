"""The README and docs/ hold together: every relative link names a file that exists, every
#anchor a heading of its page (GitHub's rules for heading anchors), and the README leads to
every page of docs/. No network: links with a scheme (https:, mailto:) are not followed."""

from __future__ import annotations

import re
import sys
import unicodedata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FENCE = re.compile(r"^\s*(```|~~~)")
INLINE_CODE = re.compile(r"(`+)(.+?)\1")
# [text](target) and ![alt](target); the text may hold one level of brackets or code
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(\s*<?([^)\s>]*)>?(?:\s+\"[^\"]*\")?\s*\)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
HTML_ANCHOR = re.compile(r"<a\s+(?:id|name)=\"([^\"]+)\"")
SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")


def pages() -> list[Path]:
    """README.md and every page of docs/."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def prose_lines(text: str) -> list[tuple[int, str]]:
    """(line number, line) outside fenced code blocks, inline code spans blanked out."""
    lines, fenced = [], False
    for number, line in enumerate(text.splitlines(), start=1):
        if FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            lines.append((number, INLINE_CODE.sub(lambda m: " " * len(m.group(0)), line)))
    return lines


def heading_text(markdown: str) -> str:
    """A heading as GitHub renders its text: code spans' content, links' text, no emphasis."""
    text = INLINE_CODE.sub(lambda m: m.group(2).strip(), markdown)
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", text)
    return re.sub(r"\*+", "", text)


def slug(text: str) -> str:
    """GitHub's anchor of a heading's text: lower case, every character that is not a letter,
    a digit, a mark, '_', '-' or a space dropped, each space a '-'."""
    kept = "".join(ch for ch in text.lower().strip()
                   if ch.isalnum() or ch in "_- " or unicodedata.category(ch).startswith("M"))
    return kept.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    """Every anchor a link may name on ``page``: its headings' slugs (the second of two equal
    ones gets '-1', the third '-2', …) and explicit <a id=…> anchors."""
    found: set[str] = set()
    seen: dict[str, int] = {}
    text = page.read_text(encoding="utf-8")
    fenced = False
    for line in text.splitlines():
        if FENCE.match(line):
            fenced = not fenced
            continue
        if fenced:
            continue
        found.update(HTML_ANCHOR.findall(line))
        match = HEADING.match(line)
        if match:
            base = slug(heading_text(match.group(2)))
            count = seen.get(base, 0)
            seen[base] = count + 1
            found.add(base if count == 0 else f"{base}-{count}")
    return found


def link_problems(page: Path) -> list[str]:
    """One line per link of ``page`` that does not resolve."""
    problems = []
    for number, line in prose_lines(page.read_text(encoding="utf-8")):
        for target in LINK.findall(line):
            if not target or SCHEME.match(target):
                continue
            path_part, _, fragment = target.partition("#")
            destination = (page.parent / path_part).resolve() if path_part else page
            where = f"{page.relative_to(ROOT)}:{number}: {target}"
            if not destination.exists():
                problems.append(f"{where}: no such file")
            elif fragment and destination.suffix == ".md" and fragment not in anchors(destination):
                problems.append(f"{where}: no heading with anchor #{fragment} in "
                                f"{destination.relative_to(ROOT)}")
    return problems


def test_every_relative_link_and_anchor_of_the_readme_and_docs_resolves() -> None:
    problems = [problem for page in pages() for problem in link_problems(page)]
    assert not problems, "broken links:\n" + "\n".join(problems)


def test_the_readme_leads_to_every_page_of_docs() -> None:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    linked = {target.partition("#")[0] for _, line in prose_lines(readme)
              for target in LINK.findall(line)}
    missing = [f"docs/{page.name}" for page in pages()[1:] if f"docs/{page.name}" not in linked]
    assert not missing, f"pages of docs/ the README does not link to: {missing}"


def test_the_readme_stays_a_guide() -> None:
    lines = (ROOT / "README.md").read_text(encoding="utf-8").count("\n")
    assert lines <= 350, f"README.md has {lines} lines; move the detail to a page of docs/"


def test_slugs_follow_githubs_rules() -> None:
    assert slug(heading_text("One command: --sitl")) == "one-command---sitl"
    assert slug(heading_text("The live 3D view (Foxglove, Lichtblick)")) == (
        "the-live-3d-view-foxglove-lichtblick")
    assert slug(heading_text("gramian.projector_consensus")) == "gramianprojector_consensus"
    assert slug(heading_text("Watching a swarm started elsewhere: `swarm-observe`")) == (
        "watching-a-swarm-started-elsewhere-swarm-observe")
    assert slug(heading_text("[Sweeps](docs/sweeps.md) and **more**")) == "sweeps-and-more"


def test_the_checker_finds_a_missing_file_a_missing_anchor_and_skips_code(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "a.md").write_text("# A page\n\n## Two words\n\n## Two words\n")
    page = tmp_path / "README.md"
    page.write_text(
        "[ok](docs/a.md#two-words) [ok too](docs/a.md#two-words-1) [self](#top)\n"
        "[gone](docs/b.md) [bad anchor](docs/a.md#three-words) [web](https://example.org/x)\n"
        "`[in code](nowhere.md)`\n"
        "```\n[in a block](nowhere.md)\n```\n"
        "# Top\n")
    assert link_problems(page) == [
        "README.md:2: docs/b.md: no such file",
        "README.md:2: docs/a.md#three-words: no heading with anchor #three-words in "
        "docs/a.md",
    ]
