"""The README and docs/ hold together: every relative link names a file that exists, every
#anchor a heading of its page (GitHub's rules for heading anchors), and the README leads to
every page of docs/. No network: links with a scheme (https:, mailto:) are not followed."""

from __future__ import annotations

import os
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


# A section named by its heading in a comment, docstring, help text or page: README "X",
# README, "X", README's "X", README section "X", docs/PAGE.md, "X", docs/PAGE.md "X" (or
# ../docs/PAGE.md from a directory beside docs/); the quotes "…", '…' or “…”; the heading may run
# onto the next line (behind a '#' in a comment).
SECTION_REFERENCE = re.compile(
    r"(?<![\w/.-])(?:\.\./)*(?P<page>README(?:\.md)?|docs/[\w-]+\.md)(?:'s)?(?=[,\s])"
    r",?[ \t]*(?:\n[ \t]*(?:#+[ \t]*)?)?(?:section[ \t]+)?"
    r"(?:\"(?P<double>[^\"\n]*(?:\n[^\"\n]*)?)\""
    r"|'(?P<single>(?:[^'\n]|'(?=[a-z]))*)'"
    r"|“(?P<curly>[^”]*)”)")
SOURCE_SUFFIXES = {".py", ".toml", ".md"}
# Not the project's text: environments, caches, build output, runs; and this file, whose
# checker test writes broken references on purpose.
PRUNED_DIRECTORIES = {"__pycache__", "node_modules"}
PRUNED_PATHS = {"runs", "out", "build", "benchmarks/results"}


def one_line(text: str) -> str:
    """``text`` on one line: the comment markers of a wrapped line dropped, white space single."""
    return " ".join(re.sub(r"\n[ \t]*#*", " ", text).split())


def section_key(text: str) -> str:
    """A heading or a quoted reference to it as compared: its rendered text on one line, trailing
    punctuation dropped, lower case."""
    return one_line(heading_text(text)).rstrip(".,;:!?").lower()


def section_keys(page: Path) -> set[str]:
    """The headings of ``page`` outside fenced code, as ``section_key`` compares them."""
    keys, fenced = set(), False
    for line in page.read_text(encoding="utf-8").splitlines():
        if FENCE.match(line):
            fenced = not fenced
            continue
        match = None if fenced else HEADING.match(line)
        if match:
            keys.add(section_key(match.group(2)))
    return keys


def project_files() -> list[Path]:
    """Every .py, .toml and .md file of the project but this one."""
    found = []
    for directory, subdirectories, names in os.walk(ROOT):
        subdirectories[:] = sorted(
            name for name in subdirectories
            if not name.startswith(".") and not name.endswith(".egg-info")
            and name not in PRUNED_DIRECTORIES
            and (Path(directory) / name).relative_to(ROOT).as_posix() not in PRUNED_PATHS)
        found.extend(Path(directory) / name for name in sorted(names)
                     if Path(name).suffix in SOURCE_SUFFIXES)
    return [path for path in found if path != ROOT / "tests" / "test_docs.py"]


def section_reference_problems(path: Path, keys: dict[str, set[str] | None]) -> list[str]:
    """One line per reference in ``path`` to a section its page does not have; ``keys`` caches
    each page's headings (None: no such page)."""
    text = path.read_text(encoding="utf-8", errors="replace")
    if "README" not in text and "docs/" not in text:
        return []
    problems = []
    for match in SECTION_REFERENCE.finditer(text):
        page = "README.md" if match["page"].startswith("README") else match["page"]
        if page not in keys:
            keys[page] = section_keys(ROOT / page) if (ROOT / page).is_file() else None
        section = next(group for group in match.group("double", "single", "curly")
                       if group is not None)
        where = f"{path.relative_to(ROOT)}:{text.count(chr(10), 0, match.start()) + 1}"
        if keys[page] is None:
            problems.append(f"{where}: {page} does not exist")
        elif section_key(section) not in keys[page]:
            problems.append(f"{where}: {page} has no heading {one_line(section)!r}")
    return problems


def test_every_section_named_in_the_project_is_a_heading_of_its_page() -> None:
    keys: dict[str, set[str] | None] = {}
    problems = [problem for path in project_files()
                for problem in section_reference_problems(path, keys)]
    assert not problems, ("sections named that their page does not have (the README's sections "
                          "moved to docs/: name the page and its heading):\n" + "\n".join(problems))


def test_the_section_checker_finds_a_missing_heading_and_a_missing_page(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    (tmp_path / "docs").mkdir()
    (tmp_path / "README.md").write_text("# Vigil\n\n## Try it\n\n```\n# In a block\n```\n")
    (tmp_path / "docs" / "sweeps.md").write_text(
        "# Sweeps\n\n## The gate in CI\n\n## An example: how fast may a target move?\n")
    source = tmp_path / "cli.py"
    source.write_text(
        '"""As the README\'s "Try it." says; README, "try it"; README section \'Try it\'."""\n'
        '# (docs/sweeps.md, "The gate in CI"; docs/sweeps.md "An example: how fast may a\n'
        '# target move?"; docs/sweeps.md,\n#   “Sweeps”); the README\'s picture, README.md.\n'
        'HELP = "the sweep file (README, \'Sweeps\'), docs/sweeps.md \'The gate\'"\n'
        '# README "In a block"; README\'s "Across\n# machines"; docs/gone.md, "Sweeps"\n'
        '[Sweeps](../docs/sweeps.md); ../docs/sweeps.md, "Gone"\n')
    assert section_reference_problems(source, {}) == [
        "cli.py:5: README.md has no heading 'Sweeps'",
        "cli.py:5: docs/sweeps.md has no heading 'The gate'",
        "cli.py:6: README.md has no heading 'In a block'",
        "cli.py:6: README.md has no heading 'Across machines'",
        "cli.py:7: docs/gone.md does not exist",
        "cli.py:8: docs/sweeps.md has no heading 'Gone'",
    ]
    for skipped in (".venv/lib/a.py", "runs/case2/notes.md", "tests/test_docs.py"):
        (tmp_path / skipped).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / skipped).write_text('README "Gone"\n')
    (tmp_path / "tests" / "runs").mkdir()
    (tmp_path / "tests" / "runs" / "test_a.py").write_text("")
    assert project_files() == [tmp_path / "README.md", source, tmp_path / "docs" / "sweeps.md",
                               tmp_path / "tests" / "runs" / "test_a.py"]
