"""The committed boards (docs/results/): each within the budget docs/results/README.md states, made of its records file,
its leaderboard and its pictures (each linked from the leaderboard, none left over), and rebuilt by `gsbench report`
from its records file to the committed tables."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

from gsbench.report.build import write_report
from gsbench.report.records_file import RECORDS_FILE, read_board

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "docs" / "results"
BUDGET = re.compile(r"a board at most (\d+) MiB, a picture at most (\d+) KiB,\s+docs/results/ at most (\d+) MiB in all")
PICTURE = re.compile(r"^!\[.*\]\(plots/([^)]+)\)$", re.M)


def _budget() -> tuple[int, int, int]:
    """(board, picture, total) in bytes, from the README's budget line."""
    found = BUDGET.search((RESULTS / "README.md").read_text())
    assert found, "docs/results/README.md states no budget ('a board at most N MiB, a picture at most N KiB, ...')"
    board, picture, total = (int(n) for n in found.groups())
    return board * 2**20, picture * 2**10, total * 2**20


def _committed() -> list[Path]:
    """The tracked files under docs/results/ (what a clone holds; a rebuilt index.html is ignored)."""
    listed = subprocess.run(["git", "ls-files", "-z", "docs/results"], cwd=ROOT, capture_output=True, check=True)
    return [ROOT / name for name in listed.stdout.decode().split("\0") if name and (ROOT / name).is_file()]


def _boards() -> list[Path]:
    return sorted(path for path in RESULTS.iterdir() if path.is_dir())


def test_every_board_is_within_the_budget():
    board_budget, picture_budget, total_budget = _budget()
    files = _committed()
    sizes = {path: path.stat().st_size for path in files}
    assert sum(sizes.values()) <= total_budget, f"docs/results/ holds {sum(sizes.values()):,} bytes"
    for board in _boards():
        size = sum(n for path, n in sizes.items() if board in path.parents)
        assert size <= board_budget, f"{board.name}: {size:,} bytes, over the budget of {board_budget:,}"
    large = [f"{path.relative_to(RESULTS)}: {n:,} bytes" for path, n in sizes.items()
             if path.suffix == ".png" and n > picture_budget]
    assert not large, f"pictures over {picture_budget:,} bytes (gsbench.report.png.compact makes them small): {large}"
    assert not [path for path in files if path.name == "index.html"], "a page is rebuilt, not committed"


@pytest.mark.parametrize("board", _boards(), ids=lambda path: path.name)
def test_a_board_is_its_records_its_leaderboard_and_its_pictures(board):
    records = read_board(board / RECORDS_FILE)
    assert records.records and not records.warnings, records.warnings
    assert all(isinstance(r, dict) and r.get("run_id") for r in records.records.values())
    pictures = {path.name for path in (board / "plots").glob("*.png")}
    if not (board / "leaderboard.md").is_file():
        assert not pictures, f"{board.name}: pictures without a leaderboard"
        return
    linked = set(PICTURE.findall((board / "leaderboard.md").read_text()))
    assert linked == pictures, f"{board.name}: linked but missing {linked - pictures}, left over {pictures - linked}"


@pytest.mark.slow
@pytest.mark.parametrize("board", [b for b in _boards() if (b / "leaderboard.md").is_file()], ids=lambda path: path.name)
def test_a_board_rebuilt_from_its_records_gives_its_committed_tables(board, tmp_path):
    """The meshes are not committed: the rebuilt report keeps the committed surface pictures. After a change of the
    report's output, rebuild the boards (docs/results/README.md) and review their diff."""
    write_report(board / RECORDS_FILE, tmp_path, generated="2026-01-01T00:00:00+00:00")
    for name in ("leaderboard.md", "leaderboard.csv"):
        assert (tmp_path / name).read_text() == (board / name).read_text(), f"{board.name}/{name} is not rebuilt"
    kept = sorted(p.name for p in (tmp_path / "plots").glob("surface-*.png"))
    assert kept == sorted(p.name for p in (board / "plots").glob("surface-*.png"))
