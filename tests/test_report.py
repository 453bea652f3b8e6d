"""`gsbench report`: leaderboard tables (golden files), the HTML page (linking its pictures, or embedding them),
a board's records file as input, Pareto fronts, variant labels and robustness to incomplete records.

Fixtures: ``tests/fixtures/report/runs/`` is a hand-made runs folder (DTU-like scan24/scan37 and
TnT-like spot-tnt/bunny-tnt; 3dgs, 2dgs, gof, ibgs; two seeds for some; one failed run; missing
combinations; mixed thread counts) with two sweep manifests in ``runs/sweeps/`` (an IBGS K grid with
a missing run, and named loss variants). The expected ``leaderboard.md`` and ``leaderboard.csv`` are
in ``tests/fixtures/report/golden/``. After an intended change of the output, regenerate them with

    GSBENCH_UPDATE_GOLDEN=1 python -m pytest -q tests/test_report.py

and review the diff of the golden files.
"""

from __future__ import annotations

import base64
import gzip
import json
import os
import shutil
import sys
from html.parser import HTMLParser
from pathlib import Path

import pytest

from gsbench.cli import main
from gsbench.config.files import reported_numbers
from gsbench.errors import GsbenchError
from gsbench.registry import METHODS
from gsbench.report.aggregate import natural_key
from gsbench.report.build import FILE_STEM_MAX, _file_stem, write_report
from gsbench.report.collect import label_variants, load_runs
from gsbench.report.pareto import pareto_front
from gsbench.report.records_file import RECORDS_FILE, BoardRecords, read_board, write_board

FIXTURES = Path(__file__).parent / "fixtures" / "report"
RUNS = FIXTURES / "runs"
GOLDEN = FIXTURES / "golden"


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    write_report(RUNS, out, generated="2026-01-01T00:00:00+00:00")
    return out


@pytest.mark.parametrize("name", ["leaderboard.md", "leaderboard.csv"])
def test_golden_tables(report, name):
    produced = (report / name).read_text()
    if os.environ.get("GSBENCH_UPDATE_GOLDEN"):
        GOLDEN.mkdir(parents=True, exist_ok=True)
        (GOLDEN / name).write_text(produced)
    assert produced == (GOLDEN / name).read_text(), f"{name} differs from the golden file (see the module docstring)"


class _Page(HTMLParser):
    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.tags: list[tuple[str, dict]] = []
        self.text: list[str] = []
        self.scripts = 0

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))
        self.scripts += tag == "script"

    def handle_data(self, data):
        self.text.append(data)


def _parsed(page: str) -> _Page:
    parser = _Page()
    parser.feed(page)
    parser.close()
    return parser


def test_html_links_its_pictures_is_sortable_and_lists_every_run(report):
    page = (report / "index.html").read_text()
    assert "http://" not in page and "https://" not in page
    parser = _parsed(page)
    text = " ".join(parser.text)
    run_ids = [json.loads(p.read_text())["run_id"] for p in RUNS.rglob("record.json")]
    assert len(run_ids) == 17
    assert all(run_id in text for run_id in run_ids)
    for tag, attrs in parser.tags:
        for name in ("src", "href"):
            value = attrs.get(name) or ""
            assert not value.startswith(("http://", "https://", "//")), (tag, name, value)
        if tag == "a":
            assert attrs["href"].startswith("#")
        assert not (tag in ("script", "link") and ("src" in attrs or "href" in attrs)), "no external script/style"
    pngs = sorted(p.name for p in (report / "plots").glob("*.png"))
    assert pngs == ["curves-dtu.png", "curves-tnt.png", "speed-dtu.png", "speed-tnt.png", "sweep-ibgs-k-dtu.png",
                    "sweep-ibgs-losses-dtu.png"]
    assert sorted(attrs["src"] for tag, attrs in parser.tags if tag == "img") == [f"plots/{n}" for n in pngs]
    assert "base64" not in page  # each picture is stored once, beside the page
    assert all((report / "plots" / n).read_bytes().startswith(b"\x89PNG") for n in pngs)
    tables = [attrs for tag, attrs in parser.tags if tag == "table"]
    assert tables and all("sortable" in a.get("class", "").split() for a in tables)
    assert parser.scripts == 1 and "table.sortable" in page
    assert "2026-01-01T00:00:00+00:00" in text
    assert "not comparable" in text.lower()


def test_self_contained_page_embeds_the_same_pictures(report, tmp_path):
    out = tmp_path / "shared"
    write_report(RUNS, out, self_contained=True, generated="2026-01-01T00:00:00+00:00")
    images = [attrs["src"] for tag, attrs in _parsed((out / "index.html").read_text()).tags if tag == "img"]
    embedded = sorted(base64.b64decode(src.removeprefix("data:image/png;base64,")) for src in images)
    assert len(images) == 6 and all(src.startswith("data:image/png;base64,") for src in images)
    assert embedded == sorted(p.read_bytes() for p in (report / "plots").glob("*.png"))
    assert (out / "leaderboard.md").read_text() == (report / "leaderboard.md").read_text()


def _board_of(runs: Path) -> BoardRecords:
    """The records and manifests of a runs folder, as `tools/commit_records.py` files them."""
    return BoardRecords(records={p.relative_to(runs).as_posix(): json.loads(p.read_text())
                                 for p in runs.rglob("record.json")},
                        manifests={p.relative_to(runs).as_posix(): json.loads(p.read_text())
                                   for p in runs.glob("sweeps/*.json")})


def test_a_board_file_keeps_every_record_exactly_and_gives_the_same_report(report, tmp_path):
    board = _board_of(RUNS)
    write_board(tmp_path / "board" / RECORDS_FILE, board)
    first = (tmp_path / "board" / RECORDS_FILE).read_bytes()
    write_board(tmp_path / "board" / RECORDS_FILE, _board_of(RUNS))
    assert (tmp_path / "board" / RECORDS_FILE).read_bytes() == first  # no time stamp: same records, same bytes
    back = read_board(tmp_path / "board" / RECORDS_FILE)
    assert back.records == board.records and back.manifests == board.manifests and not back.warnings
    assert [list(r) for r in back.records.values()] == [list(r) for r in board.records.values()]  # key order too
    for source in (tmp_path / "board" / RECORDS_FILE, tmp_path / "board"):  # the file, or the board's folder
        out = tmp_path / "out"
        write_report(source, out, plots=False)
        assert _tables((out / "leaderboard.md").read_text()) == _tables((report / "leaderboard.md").read_text())
        assert (out / "leaderboard.csv").read_text() == (report / "leaderboard.csv").read_text()


def _tables(markdown: str) -> list[str]:
    """The Markdown without its picture lines (a report with plots=False has none)."""
    return [line for line in markdown.splitlines() if line and not line.startswith("![")]


def test_a_damaged_line_of_a_board_file_is_a_warning_naming_it(tmp_path):
    file = tmp_path / RECORDS_FILE
    write_board(file, _board_of(RUNS))
    lines = gzip.decompress(file.read_bytes()).decode().splitlines()
    file.write_bytes(gzip.compress("\n".join(lines[:3] + ["{not json", '{"path": "x"}'] + lines[3:]).encode()))
    out = tmp_path / "out"
    write_report(file, out, plots=False)
    md = (out / "leaderboard.md").read_text()
    assert f"{file}:4: unreadable line skipped" in md and f"{file}:5: unreadable line skipped" in md
    file.write_bytes(b"\x1f\x8b not gzip")
    with pytest.raises(GsbenchError, match=f"{file}: cannot read the board's records"):
        write_report(file, out)


def test_pareto_front_minimises_cost_and_error_or_maximises_score():
    points = [(1.0, 0.9), (2.0, 0.5), (3.0, 0.6), (2.0, 0.5), (0.5, 1.5)]
    assert pareto_front(points) == [0, 1, 3, 4]  # (3, 0.6) is dominated; equal points both stay
    assert pareto_front(points, higher_is_better=True) == [4]  # cheapest and highest
    assert pareto_front([(1.0, 0.9), (2.0, 0.5), (3.0, 0.95), (0.5, 0.2)], higher_is_better=True) == [0, 2, 3]
    assert pareto_front([]) == []


def test_variant_labels_name_only_the_keys_that_differ():
    runs = label_variants(load_runs(RUNS)[0])
    rows = {r.row for r in runs if r.dataset == "dtu" and r.method == "ibgs"}
    assert rows == {f"ibgs [losses.eigvec.weight={w}, method.knn_k={k}]" for w, k in
                    (("0.0", 5), ("0.01", 3), ("0.01", 5), ("0.01", 8))}
    assert {r.row for r in runs if r.method == "2dgs"} == {"2dgs"}  # seeds and scenes are not variants


def test_rows_sort_numbers_by_value():
    names = ["ibgs [method.knn_k=10]", "ibgs [method.knn_k=2]", "3dgs", "ibgs [w=0.1]", "ibgs [w=0.01]"]
    assert sorted(names, key=natural_key) == ["3dgs", "ibgs [method.knn_k=2]", "ibgs [method.knn_k=10]",
                                              "ibgs [w=0.01]", "ibgs [w=0.1]"]


def _copy_runs(tmp_path) -> Path:
    runs = tmp_path / "runs"
    shutil.copytree(RUNS, runs)
    return runs


def test_incomplete_records_become_statuses_and_warnings_not_crashes(tmp_path):
    runs = _copy_runs(tmp_path)
    some = sorted(runs.glob("tnt/spot-tnt/3dgs/*/record.json"))[0]
    data = json.loads(some.read_text())
    data.update(status="running", metrics={}, timings={}, environment={})
    some.write_text(json.dumps(data))
    no_metric = sorted(runs.glob("tnt/spot-tnt/2dgs/*/record.json"))[0]
    data = json.loads(no_metric.read_text())
    data["metrics"] = {"precision": 0.5}
    no_metric.write_text(json.dumps(data))
    broken = runs / "dtu" / "scan24" / "gof" / "broken" / "record.json"
    broken.parent.mkdir(parents=True)
    broken.write_text("{not json")
    duplicate = runs / "copy" / "record.json"
    duplicate.parent.mkdir()
    shutil.copy(some, duplicate)
    (runs / "sweeps" / "bad.json").write_text('{"name": "bad"}')
    out = tmp_path / "out"
    write_report(runs, out, plots=False)
    md = (out / "leaderboard.md").read_text()
    assert "| 3dgs | 0.250 | 1 running | 0.250 (1/2 scenes) |" in md
    assert "| 2dgs | – | 1 no metric |" in md
    assert "dtu/scan24/gof/broken/record.json: unreadable record skipped" in md
    assert "found 2 times" in md and "sweeps/bad.json: unreadable sweep manifest skipped" in md
    assert not (out / "plots").exists()
    assert "<img" not in (out / "index.html").read_text()


def test_memory_is_the_training_high_water_mark_not_the_evaluators(tmp_path):
    runs = _copy_runs(tmp_path)
    some = sorted(runs.glob("tnt/spot-tnt/3dgs/*/record.json"))[0]
    data = json.loads(some.read_text())
    data["peak_rss_bytes"] = {"load": 2**28, "train": 3 * 2**28, "extract": 2**31, "evaluate": 2**32}
    some.write_text(json.dumps(data))
    (run,) = [r for r in load_runs(runs)[0] if r.run_id == data["run_id"]]
    assert run.train_peak_rss_bytes == 3 * 2**28
    del data["peak_rss_bytes"]["train"]  # a run that failed before training ended has no training peak
    some.write_text(json.dumps(data))
    (run,) = [r for r in load_runs(runs)[0] if r.run_id == data["run_id"]]
    assert run.train_peak_rss_bytes is None


def test_times_from_several_cpu_models_are_flagged_where_they_are_compared(tmp_path):
    """Sessions may run on different CPUs: a cost table whose runs mix CPU models says so, with the count on
    each, and the runs table names every run's CPU; a table from one CPU model has no such note."""
    runs = _copy_runs(tmp_path)
    some = sorted(runs.glob("tnt/spot-tnt/3dgs/*/record.json"))[0]
    data = json.loads(some.read_text())
    data["environment"]["cpu"] = "Other CPU"
    some.write_text(json.dumps(data))
    out = tmp_path / "report"
    write_report(runs, out, generated="2026-01-01T00:00:00+00:00")
    md = (out / "leaderboard.md").read_text()
    tnt_costs = md.split("### tnt: cost against")[1].split("\n#")[0]
    dtu_costs = md.split("### dtu: cost against")[1].split("\n#")[0]
    assert "CPU models differ between runs (Fixture CPU @ 2.00GHz: " in tnt_costs and "Other CPU: 1 run)" in tnt_costs
    assert "CPU models differ" not in dtu_costs
    assert "<td>Other CPU</td>" in (out / "index.html").read_text()


def test_plots_of_an_earlier_report_are_removed(tmp_path):
    """out/plots is the report's own: a figure an earlier report drew there and this one does not is removed,
    the others are (re)written; files that are not PNGs stay."""
    out = tmp_path / "out"
    (out / "plots").mkdir(parents=True)
    (out / "plots" / "sweep-gone-dtu.png").write_bytes(b"old")
    (out / "plots" / "notes.txt").write_text("mine")
    written = write_report(RUNS, out, generated="2026-01-01T00:00:00+00:00")
    pngs = sorted(p.name for p in (out / "plots").glob("*.png"))
    assert pngs and "sweep-gone-dtu.png" not in pngs
    assert pngs == sorted(p.name for p in written if p.suffix == ".png")
    assert (out / "plots" / "notes.txt").read_text() == "mine"
    write_report(RUNS, out, plots=False)
    assert not list((out / "plots").glob("*.png"))


def test_no_records_is_a_clear_error(tmp_path):
    with pytest.raises(GsbenchError, match=f"no run records .* under '{tmp_path}'"):
        write_report(tmp_path, tmp_path / "out")
    with pytest.raises(GsbenchError, match="does not exist"):
        write_report(tmp_path / "nowhere", tmp_path / "out")


def test_missing_matplotlib_names_the_fix(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)
    monkeypatch.setitem(sys.modules, "matplotlib.backends.backend_agg", None)
    with pytest.raises(GsbenchError, match=r"pip install matplotlib.*--no-plots"):
        write_report(RUNS, tmp_path / "out")


def test_cli_report(tmp_path, capsys):
    assert main(["report", str(RUNS), "--out", str(tmp_path / "r"), "--no-plots"]) == 0
    assert "leaderboard.md, leaderboard.csv, index.html" in capsys.readouterr().out
    write_board(tmp_path / "board" / RECORDS_FILE, _board_of(RUNS))
    assert main(["report", str(tmp_path / "board" / RECORDS_FILE), "--out", str(tmp_path / "board"),
                 "--self-contained"]) == 0
    assert "and 6 plots in plots/" in capsys.readouterr().out
    assert "data:image/png;base64," in (tmp_path / "board" / "index.html").read_text()
    assert main(["report", str(tmp_path / "empty-or-missing"), "--out", str(tmp_path / "r2")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_reported_numbers_are_well_formed():
    """Every built-in method that declares reported numbers names the metric of the protocol its paper used (DTU:
    the official script's Chamfer; TnT: F1 on vertices + face centroids, the 2DGS / GOF scripts) and a source."""
    declared = 0
    for name in METHODS.names():
        for dataset, entry in reported_numbers(name).items():
            declared += 1
            assert entry["metric"] == {"dtu": "chamfer", "tnt": "f1_centroids"}[dataset], name
            assert isinstance(entry["mean"], float) and entry["source"], name
            assert all(isinstance(v, float) for v in entry.get("scenes", {}).values()), name
    assert declared >= 6


def test_plot_file_names_stay_short_and_distinct():
    """A row label with many differing keys (SuGaR across code versions) made a surface plot's file name longer
    than file systems allow; stems are cut with a hash of the whole."""
    base = "surface-tnt-spot-sugar " + " ".join(f"method.key_{i}=unset" for i in range(20))
    a, b = _file_stem(base + " method.refinement=short"), _file_stem(base + " method.refinement=none")
    assert len(a) <= FILE_STEM_MAX and len(b) <= FILE_STEM_MAX and a != b
    assert _file_stem("surface-dtu-bunny 2dgs") == "surface-dtu-bunny-2dgs"


def test_keys_a_preset_sets_are_named_by_the_preset_alone(tmp_path):
    """Runs of one method at two presets differ in the keys the preset sets (iterations, image size): the rows
    are `[preset=cpu]` and `[preset=bench]`. A key that also varies within one preset stays in the label, so
    runs of different configs never share a row."""
    runs = _copy_runs(tmp_path)
    records = sorted(runs.glob("dtu/*/2dgs/*/record.json"))
    for i, path in enumerate(records):
        data = json.loads(path.read_text())
        bench = i % 2 == 1
        data["config"].update({"preset": "bench" if bench else "cpu", "train.iterations": 6000 if bench else 3000})
        if bench and i == 1:
            data["config"]["method.knn_k"] = 7  # an override within the bench preset
        path.write_text(json.dumps(data))
    rows = {r.row for r in label_variants(load_runs(runs)[0]) if (r.dataset, r.method) == ("dtu", "2dgs")}
    assert rows == {"2dgs [method.knn_k=unset, preset=cpu]", "2dgs [method.knn_k=unset, preset=bench]",
                    "2dgs [method.knn_k=7, preset=bench]"}
