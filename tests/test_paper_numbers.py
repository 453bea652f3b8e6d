"""A method is stated once: its paper's numbers stand in its file (``configs/methods/<method>.yaml``: ``reported:``,
and the ``paper:`` of the claims entries quoting other tables), once; the report's claims read them from there, so
a number typed again in the Python source or in another method's file fails here. Likewise the papers' methods
(``paper_benchmark:``) are not listed again in the report or the benchmarks."""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

from gsbench.bench.train import PAPER_METHODS
from gsbench.config import files
from gsbench.config.files import CLAIMS_KEY, config_root, declared_plugins, load_yaml, method_declaration, reported_numbers
from gsbench.errors import ConfigError
from gsbench.report.claims import GROUPS_FILE, quoted_numbers

REPO = Path(__file__).resolve().parent.parent
SOURCE = [p for folder in ("gsbench", "methods", "evaluators") for p in sorted((REPO / folder).rglob("*.py"))]
READERS = sorted((REPO / "gsbench" / "report").glob("*.py")) + sorted((REPO / "gsbench" / "bench").glob("*.py"))
CLAIMS_MODULE = REPO / "gsbench" / "report" / "claims.py"
QUOTED = re.compile(r"(\d+\.\d+) vs (\d+\.\d+)")  # a claim's numbers as the report quotes them
NAMED = re.compile(r"([A-Za-z0-9][A-Za-z0-9-]*)\)?[ :=(]{1,3}(\d+\.\d+)")  # "PGSR 0.53", "3DGS: 1.96"
METHODS = {re.sub(r"[^a-z0-9]", "", name) for name in declared_plugins("methods")}


def paper_numbers() -> list[tuple[str, str, float, str, str]]:
    """(file, metric, value, source, side) of every number the method files declare: ``reported:`` (side: the
    method, or a scene of its) and the claims entries' ``paper:`` (side: the row or method quoted)."""
    groups = load_yaml(config_root() / GROUPS_FILE)["groups"]
    found = []
    for method in declared_plugins("methods"):
        file = f"configs/methods/{method}.yaml"
        for entry in reported_numbers(method).values():
            found.append((file, entry["metric"], float(entry["mean"]), entry["source"], method))
            found += [(file, entry["metric"], float(v), entry["source"], scene) for scene, v in
                      (entry.get("scenes") or {}).items()]
        for entry in method_declaration(method, CLAIMS_KEY) or []:
            source = entry["source"] if isinstance(entry["source"], str) else "; ".join(entry["source"])
            metric = groups[entry["group"]]["metric"]
            found += [(file, metric, v, source, side) for side, v in quoted_numbers(entry).items() if v is not None]
    return found


def significant_digits(value: float) -> int:
    return len(repr(value).replace(".", "").replace("-", "").strip("0"))


def test_a_claim_reads_the_reported_number_it_quotes():
    """A claims entry gives under ``paper:`` only what no ``reported:`` holds: a side whose method reports that
    very number is read from there, not typed again."""
    groups = load_yaml(config_root() / GROUPS_FILE)["groups"]
    typed_again = []
    for method in declared_plugins("methods"):
        for i, entry in enumerate(method_declaration(method, CLAIMS_KEY) or []):
            group = groups[entry["group"]]
            for label, value in quoted_numbers(entry).items():
                reported = reported_numbers(label).get(group["dataset"]) or {}
                if value is not None and reported.get("metric") == group["metric"] and reported.get("mean") == value:
                    typed_again.append(f"configs/methods/{method}.yaml claims[{i}].paper.{label} = {value}")
    assert not typed_again, f"numbers the sides' reported: already hold (drop them from paper:): {typed_again}"


def test_no_paper_number_stands_in_two_files():
    numbers = paper_numbers()
    assert len(numbers) > 100 and {n[1] for n in numbers} == {"chamfer", "f1_centroids", "psnr"}
    files: dict[tuple, set] = {}
    for file, metric, value, source, _ in numbers:
        files.setdefault((metric, value, source), set()).add(file)
    twice = {key: sorted(where) for key, where in files.items() if len(where) > 1}
    assert not twice, f"the same paper number in two files: {twice}"


def _prose(path: Path):
    """(line, text) of every string literal and comment of a Python file, or every comment of a YAML file."""
    if path.suffix == ".yaml":
        for line, text in enumerate(path.read_text().splitlines(), 1):
            if "#" in text:
                yield line, text[text.index("#"):]
        return
    for token in tokenize.generate_tokens(io.StringIO(path.read_text()).readline):
        if token.type in (tokenize.STRING, tokenize.COMMENT):
            yield token.start[0], token.string


def _key(name: str) -> str:
    return re.sub(r"[^a-z0-9]", "", name.lower())  # RaDe-GS -> radegs


def test_no_paper_number_is_written_out_again():
    """Not in the prose of the Python source (strings, comments) or of the method files (comments): a claim's
    numbers as the report quotes them ("0.47 vs 0.53"), or a method's number after its name ("PGSR 0.53"). Not
    as a float literal: any paper number in the claims module, one of three significant digits or more (0.674,
    32.57) in the report and the benchmarks (two-digit ones there are colours and fractions)."""
    numbers = paper_numbers()
    values = {value for _, _, value, _, _ in numbers}
    by_side: dict[str, set] = {}
    for _, _, value, _, side in numbers:
        by_side.setdefault(_key(side), set()).add(value)
    found = []
    for path in SOURCE + sorted((config_root() / "methods").glob("*.yaml")):
        for line, text in _prose(path):
            where = f"{path.relative_to(REPO)}:{line}"
            found += [f"{where}: '{m.group(0)}'" for m in QUOTED.finditer(text)
                      if float(m.group(1)) in values and float(m.group(2)) in values]
            found += [f"{where}: '{m.group(0)}'" for m in NAMED.finditer(text)
                      if float(m.group(2)) in by_side.get(_key(m.group(1)), ()) and _key(m.group(1)) in METHODS]
    for path in READERS:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, float) and node.value in values:
                if path == CLAIMS_MODULE or significant_digits(node.value) >= 3:
                    found.append(f"{path.relative_to(REPO)}:{node.lineno}: {node.value}")
    assert not found, f"paper numbers written again (they stand in configs/methods/<method>.yaml): {found}"


def test_the_papers_methods_are_listed_only_in_their_files():
    """The papers' methods come from ``paper_benchmark:`` in their files, in its order; no list of three or more
    method names in the report or the benchmarks states them again."""
    assert PAPER_METHODS == ("3dgs", "sugar", "2dgs", "gof", "radegs", "ibgs", "pgsr", "gggs", "neusg", "rt2dgs")
    methods = set(declared_plugins("methods"))
    found = []
    for path in READERS:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.Tuple, ast.List, ast.Set)) and len(node.elts) >= 3 and all(
                    isinstance(e, ast.Constant) and e.value in methods for e in node.elts):
                found.append(f"{path.relative_to(REPO)}:{node.lineno}")
    assert not found, f"lists of methods typed in the source (paper_benchmark: in their files): {found}"


def test_a_place_among_the_papers_methods_is_taken_once(tmp_path, monkeypatch):
    (tmp_path / "methods").mkdir()
    for name, place in (("a", 2), ("b", 1), ("c", None)):
        (tmp_path / "methods" / f"{name}.yaml").write_text("plugin: x:Y\n" + (f"paper_benchmark: {place}\n" if place else ""))
    monkeypatch.setattr(files, "CONFIG_ROOT", tmp_path)
    assert files.paper_methods() == ("b", "a")
    (tmp_path / "methods" / "c.yaml").write_text("plugin: x:Y\npaper_benchmark: 2\n")
    with pytest.raises(ConfigError, match="configs/methods/c.yaml: paper_benchmark must be a place"):
        files.paper_methods()
