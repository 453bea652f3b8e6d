"""Every document the code cites is in the repository, and every section it cites exists there.

Scanned: the tracked ``*.py``, ``*.yaml``, ``*.cpp`` and ``*.md`` files (not the committed reports in
docs/results/). A citation is a repository path ending in ``.md`` (under docs/ or experiments/, or the top-level
README and CONTRIBUTING) followed by section numbers (``docs/methods/gof.md §3.6``, ``docs/design.md §8.2,
§8.4``) or by a quoted heading (``experiments/inset/README.md, "The trained inset"``, or ``("…")``; the quote may
run over lines of a comment); each path must exist, each number must be a heading (``## 3 …``, ``### 3.6 …``) of
that document, and each quoted heading the start of one of its headings. A "§" that follows no document path,
and the names of the documents the project was started from, are not allowed: a newcomer with only this
repository could not follow them. The relative links of the Markdown documents must lead to a file or folder.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOCUMENT = r"(?:(?:docs|experiments)/[\w./-]+|CONTRIBUTING|README)\.md"
CITATION = re.compile(rf"({DOCUMENT})((?:[ ,;(and–-]*§ ?\d+(?:\.\d+)*)*)")
QUOTED_HEADING = re.compile(rf'({DOCUMENT}),? \(?"([^"]+)"')
LINE_BREAK = re.compile(r"\s*\n\s*(?:#|//|\*)?\s*")  # a quote that runs on in a comment or an indented line
TITLE = re.compile(r"^#{1,6} (.+)$", re.M)
LINK = re.compile(r"\]\(([^)\s#]+)(?:#[^)]*)?\)")
SECTION = re.compile(r"§ ?(\d+(?:\.\d+)*)")
HEADING = re.compile(r"^#{2,4} (\d+(?:\.\d+)*)[ .]", re.M)
OUTSIDE = re.compile(r"(?<![\w/])(DESIGN\.md|methods-3dgs-2dgs-sugar\.md|methods-gof-radegs-ibgs\.md|frameworks\.md"
                     r"|(?<!docs/)evaluation\.md|(?<!docs/)performance\.md|design card)")


def _sources() -> list[Path]:
    listed = subprocess.run(["git", "ls-files", "*.py", "*.yaml", "*.cpp", "*.md"], cwd=ROOT, capture_output=True,
                            text=True, check=True).stdout.split()
    own = Path(__file__).resolve().relative_to(ROOT).as_posix()  # its docstring and patterns name what it forbids
    return [ROOT / name for name in listed
            if not name.startswith("docs/results/") and name != own and (ROOT / name).is_file()]


def _headings(doc: Path, cache: dict) -> set[str]:
    if doc not in cache:
        cache[doc] = set(HEADING.findall(doc.read_text()))
    return cache[doc]


def _titles(doc: Path, cache: dict) -> list[str]:
    if doc not in cache:
        cache[doc] = TITLE.findall(doc.read_text())
    return cache[doc]


def test_every_cited_document_and_section_exists():
    problems, cache, titles = [], {}, {}
    for path in _sources():
        text = path.read_text(errors="replace")
        rel = path.relative_to(ROOT).as_posix()
        covered = set()
        for match in CITATION.finditer(text):
            doc = ROOT / match.group(1)
            line = text.count("\n", 0, match.start()) + 1
            if not doc.is_file():
                problems.append(f"{rel}:{line}: cites {match.group(1)}, which is not in the repository")
                continue
            for number in SECTION.findall(match.group(2)):
                if number not in _headings(doc, cache):
                    problems.append(f"{rel}:{line}: {match.group(1)} has no section {number}")
            covered.update(range(match.start(), match.end()))
        for match in QUOTED_HEADING.finditer(text):
            doc, heading = ROOT / match.group(1), LINE_BREAK.sub(" ", match.group(2))
            if doc.is_file() and not any(title.startswith(heading) for title in _titles(doc, titles)):
                line = text.count("\n", 0, match.start()) + 1
                problems.append(f'{rel}:{line}: {match.group(1)} has no heading "{heading}"')
        for match in re.finditer("§", text):
            if match.start() not in covered and not rel.startswith("docs/") and rel != "CONTRIBUTING.md":
                line = text.count("\n", 0, match.start()) + 1
                problems.append(f"{rel}:{line}: a § that follows no document path")
        for match in OUTSIDE.finditer(text):
            line = text.count("\n", 0, match.start()) + 1
            problems.append(f"{rel}:{line}: cites {match.group(1)}, a document outside this repository")
    assert not problems, "\n".join(problems)


def test_every_relative_link_of_a_document_resolves():
    problems = []
    for path in _sources():
        if path.suffix != ".md" or path.is_relative_to(ROOT / "tests"):
            continue
        text = path.read_text()
        for match in LINK.finditer(text):
            target = match.group(1)
            if re.match(r"[a-z]+:", target) or (path.parent / target).exists():
                continue
            line = text.count("\n", 0, match.start()) + 1
            problems.append(f"{path.relative_to(ROOT).as_posix()}:{line}: links to {target}, which is not there")
    assert not problems, "\n".join(problems)
