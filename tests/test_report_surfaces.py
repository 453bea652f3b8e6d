"""Pictures of surfaces (`gsbench.report.surfaces`): the report's Surfaces section and ``gsbench render`` draw
the same picture of a run; every picture is a valid PNG of the size the page states, the page shows each, and
a report rebuilt from the records alone (no meshes) keeps the pictures that show its runs."""

from __future__ import annotations

import io
import json
import re
import shutil

import pytest
from PIL import Image

from gsbench.cli import main
from gsbench.report import png
from gsbench.report.build import write_report
from gsbench.report.records_file import RECORDS_FILE, BoardRecords, write_board
from gsbench.runs.runner import resolve_run, run, run_dir
from tests.method_setup import QUICK


@pytest.fixture(scope="module")
def runs(tiny_spot, tmp_path_factory):
    """Two finished quick runs on tiny_spot (with its ground truth) and one on its photos alone (no ground truth)."""
    out = tmp_path_factory.mktemp("surfaces") / "runs"
    capture = out.parent / "scan1001"
    for part in ("image", "mask"):
        shutil.copytree(tiny_spot / part, capture / part)
    shutil.copy(tiny_spot / "cameras.npz", capture / "cameras.npz")
    folders = {}
    for method, scene in (("3dgs", tiny_spot), ("2dgs", tiny_spot), ("3dgs", capture)):
        no_gt = ["eval.evaluators=[mesh_stats]"] if scene == capture else []  # nothing to score it against
        cfg = resolve_run(method, str(scene), preset="quick", overrides=[*QUICK, *no_gt])
        cfg.out = str(out)
        assert run(cfg, echo=lambda *a: None).status == "ok"
        folders[(method, scene.name)] = run_dir(cfg)
    return out, folders


def _size(png: bytes) -> tuple[int, int]:
    with Image.open(io.BytesIO(png)) as image:
        image.verify()
    with Image.open(io.BytesIO(png)) as image:
        assert image.format == "PNG"
        return image.size


def test_every_surface_picture_is_a_valid_image_of_the_stated_size_and_on_the_page(runs, tmp_path):
    out, _ = runs
    report = tmp_path / "report"
    write_report(out, report, generated="2026-01-01T00:00:00+00:00")
    md = (report / "leaderboard.md").read_text()
    page = (report / "index.html").read_text()
    pictures = sorted((report / "plots").glob("surface-*.png"))
    assert len(pictures) == 3  # 3dgs and 2dgs with ground truth, 3dgs on the capture without
    assert "## Surfaces" in md
    for path in pictures:
        stated = re.search(rf"!\[[^\]]*, (\d+)x(\d+) px\]\(plots/{re.escape(path.name)}\)", md)
        assert stated, f"{path.name} is not referenced with its size"
        assert _size(path.read_bytes()) == (int(stated.group(1)), int(stated.group(2)))
        assert f'src="plots/{path.name}"' in page  # linked: each picture stored once
        assert path.stat().st_size < 200 * 1024  # palette, 75% scale


def test_render_draws_the_reports_picture_of_one_run(runs, tmp_path, capsys):
    _, folders = runs
    folder = folders[("3dgs", "scan1001")]
    assert main(["render", str(folder), "--out", str(tmp_path / "capture.png")]) == 0
    width, height = _size((tmp_path / "capture.png").read_bytes())
    assert f"{width}x{height} PNG" in capsys.readouterr().out
    assert main(["render", str(folder.parent)]) == 2  # not a run folder: one line, no traceback
    assert "config.yaml not found: the pictures show a finished run" in capsys.readouterr().err


def test_a_board_rebuilt_from_its_records_keeps_the_pictures_of_its_runs(runs, tmp_path):
    """The meshes are not committed: rebuilt from the board's records file, the report keeps each picture that
    says (its PNG text) it shows one of the row's ok runs, and the Markdown is unchanged; a picture of another
    run is dropped."""
    out, folders = runs
    board = tmp_path / "board"
    write_report(out, board, generated="2026-01-01T00:00:00+00:00")
    drawn = {p.name: p.read_bytes() for p in (board / "plots").glob("surface-*.png")}
    shown = {png.text(data)["run_id"] for data in drawn.values()}
    assert shown == {folder.name for folder in folders.values()}
    records = {p.relative_to(out).as_posix(): json.loads(p.read_text()) for p in out.rglob("record.json")}
    write_board(board / RECORDS_FILE, BoardRecords(records=records))
    before = (board / "leaderboard.md").read_text()
    write_report(board / RECORDS_FILE, board, generated="2026-01-01T00:00:00+00:00")
    assert (board / "leaderboard.md").read_text() == before
    assert {p.name: p.read_bytes() for p in (board / "plots").glob("surface-*.png")} == drawn
    elsewhere = tmp_path / "elsewhere"  # pictures found beside the records file, written to another folder
    write_report(board / RECORDS_FILE, elsewhere, generated="2026-01-01T00:00:00+00:00")
    assert (elsewhere / "leaderboard.md").read_text() == before
    name, data = sorted(drawn.items())[0]
    (board / "plots" / name).write_bytes(png.with_text(png.compact(data), {"run_id": "someoneelse", "seed": 0}))
    write_report(board / RECORDS_FILE, board, generated="2026-01-01T00:00:00+00:00")
    assert not (board / "plots" / name).exists() and f"plots/{name}" not in (board / "leaderboard.md").read_text()
