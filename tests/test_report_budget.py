"""The Gaussian budget in the report (gsbench.report.budget): cuts recorded by the trainer, the final-count
statement for records without them, and the speed table's column, on constructed records."""

from __future__ import annotations

import json
from pathlib import Path

from gsbench.report.budget import NEAR, budget_text, budget_use
from gsbench.report.build import write_report
from gsbench.report.collect import load_runs


def write_record(runs: Path, method: str, seed: int, *, budget: int = 0, final: int = 1000,
                 densify_budget: dict | None = None) -> None:
    """An ok record on scene scan1 with ``train.max_gaussians = budget`` (0: none), a final Gaussian count
    and, unless None, the trainer's ``densify_budget``."""
    run_id = f"{method}{seed}{budget}{final}"
    record = {"run_id": run_id, "method": method, "scene": "/data/scan1", "dataset": "dtu", "seed": seed,
              "status": "ok", "config": {"method": {"name": method}, "train": {"iterations": 3000,
                                                                            "max_gaussians": budget}},
              "metrics": {"chamfer": 1.0}, "timings": {"train": 10.0, "total": 12.0}, "num_gaussians": final,
              "environment": {"threads": 1}}
    if densify_budget is not None:
        record["densify_budget"] = densify_budget
    path = runs / "dtu" / "scan1" / method / run_id / "record.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(record))


def cut(step):
    return {"max_gaussians": 100, "first_cut_step": step, "candidates_cut": 0 if step is None else 7}


def test_recorded_cuts_give_the_count_and_the_median_first_step(tmp_path):
    for seed, step in enumerate((200, 700, 300, None)):
        write_record(tmp_path, "ibgs", seed, budget=100, final=100, densify_budget=cut(step))
    runs = load_runs(tmp_path)[0]
    assert [budget_use(r).first_cut_step for r in sorted(runs, key=lambda r: r.seed)] == [200, 700, 300, None]
    assert budget_text(runs) == "3/4 cut at 100, from step 300"


def test_records_without_cuts_state_only_how_many_ended_at_the_budget(tmp_path):
    write_record(tmp_path, "sugar", 0, budget=1000, final=int(NEAR * 1000))
    write_record(tmp_path, "sugar", 1, budget=1000, final=80)  # pruned after densifying: not "cut" either way
    write_record(tmp_path, "sugar", 2, budget=1000, final=80, densify_budget=cut(900))
    runs = load_runs(tmp_path)[0]
    uses = {r.seed: budget_use(r) for r in runs}
    assert uses[0].reached and not uses[0].recorded and not uses[1].reached and uses[2].reached
    assert budget_text(runs) == "1/1 cut at 1,000, from step 900; 1/2 ended ≥ 95% of 1,000 (cuts not recorded)"


def test_runs_without_a_budget_have_no_budget_cell(tmp_path):
    write_record(tmp_path, "3dgs", 0, budget=0, final=5000, densify_budget=cut(None))
    runs = load_runs(tmp_path)[0]
    assert budget_use(runs[0]).budget is None and budget_text(runs) == "–"


def test_the_speed_table_shows_the_budget_of_each_row(tmp_path):
    runs = tmp_path / "runs"
    write_record(runs, "ibgs", 0, budget=100, final=100, densify_budget=cut(200))
    write_record(runs, "radegs", 0, budget=100, final=60, densify_budget=cut(None))
    write_report(runs, tmp_path / "rep", generated="2026-01-01T00:00:00+00:00")
    text = (tmp_path / "rep" / "leaderboard.md").read_text()
    assert "| Gaussian budget |" in text
    assert "| 1/1 cut at 100, from step 200 |" in text and "| 0/1 cut at 100 |" in text
