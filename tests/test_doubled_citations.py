"""No citation names its document twice: a document's path, then its section numbers, never the path again
before the next section (a bulk replace once wrote the path twice in a row, and twice around one section).

Scanned: every tracked text source (*.py, *.yaml, *.md, *.cpp, ...), the committed reports included. The
section sign is written as an escape here: tests/test_doc_references.py reads a literal one as a citation.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SUFFIXES = ("*.py", "*.yaml", "*.yml", "*.md", "*.cpp", "*.h", "*.toml", "*.txt", "*.cfg")
SECTION_SIGN = "\u00a7"
DOC = r"(?:docs/[\w./-]+|CONTRIBUTING|README)\.md"
BETWEEN = r"[\s,;(and–#/*-]*"  # what may separate a path from its sections: punctuation, "and", comment marks
# a document path, its section numbers, then the same path again
DOUBLED = re.compile(rf"(?<![\w/])({DOC})((?:{BETWEEN}{SECTION_SIGN} ?\d+(?:\.\d+)*)*){BETWEEN}(?<![\w/])\1(?![\w/])")


def doubled_citations(text: str) -> list[str]:
    return [match.group(0) for match in DOUBLED.finditer(text)]


def test_the_pattern_finds_a_doubled_citation_and_passes_a_single_one():
    path, s = "docs/methods/sugar.md", SECTION_SIGN
    assert doubled_citations(f"(SuGaR, {path} {path} {s}5)") == [f"{path} {path}"]
    assert doubled_citations(f"log(x + 1e-10), {path} {s}3.2, {path} {s}3.2, {s}5") == [f"{path} {s}3.2, {path}"]
    assert doubled_citations(f"({path} {s}1,\n# {path} {s}8)") != []  # across a wrapped comment
    assert doubled_citations(f"({path} {s}3.2, {s}5) and docs/methods/gof.md {s}4") == []
    assert doubled_citations(f"{path}. What the authors confirmed: {path} {s}1.2") == []  # two sentences


def test_no_citation_names_its_document_twice():
    listed = subprocess.run(["git", "ls-files", *SUFFIXES], cwd=ROOT, capture_output=True, text=True,
                            check=True).stdout.split()
    found = []
    for name in listed:
        path = ROOT / name
        if not path.is_file():
            continue
        text = path.read_text(errors="replace")
        for match in DOUBLED.finditer(text):
            found.append(f"{name}:{text.count(chr(10), 0, match.start()) + 1}: {match.group(0)!r}")
    assert not found, "doubled citations (write the path once, then its sections):\n" + "\n".join(found)
