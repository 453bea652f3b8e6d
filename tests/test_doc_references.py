"""Every document the code cites is in the repository, and every section it cites exists there.

Scanned: the tracked ``*.py``, ``*.yaml``, ``*.cpp`` and ``*.md`` files (not the committed reports in
docs/results/). A citation is a repository path ending in ``.md`` followed by section numbers
(``docs/methods/gof.md §3.6``, ``docs/design.md §8.2, §8.4``); each path must exist and each number
must be a heading (``## 3 …``, ``### 3.6 …``) of that document. A "§" that follows no document path,
and the names of the documents the project was started from, are not allowed: a newcomer with only
this repository could not follow them.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CITATION = re.compile(r"((?:docs/[\w./-]+|CONTRIBUTING|README)\.md)((?:[ ,;(and–-]*§ ?\d+(?:\.\d+)*)*)")
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


def test_every_cited_document_and_section_exists():
    problems, cache = [], {}
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
        for match in re.finditer("§", text):
            if match.start() not in covered and not rel.startswith("docs/") and rel != "CONTRIBUTING.md":
                line = text.count("\n", 0, match.start()) + 1
                problems.append(f"{rel}:{line}: a § that follows no document path")
        for match in OUTSIDE.finditer(text):
            line = text.count("\n", 0, match.start()) + 1
            problems.append(f"{rel}:{line}: cites {match.group(1)}, a document outside this repository")
    assert not problems, "\n".join(problems)
