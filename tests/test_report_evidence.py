"""What the report says about its evidence: boards that mix code versions, ok records with a non-finite
metric, and run folders that never wrote a record."""

from __future__ import annotations

import json
import math

from gsbench.report.build import write_report
from tests.test_report import _copy_runs

OTHER = "fedcba9876543210fedcba9876543210fedcba98"


def _edit(path, **fields):
    data = json.loads(path.read_text())
    for key, value in fields.items():
        if isinstance(value, dict) and isinstance(data.get(key), dict):
            data[key].update(value)
        else:
            data[key] = value
    path.write_text(json.dumps(data))
    return data


def test_a_board_of_records_from_two_code_versions_is_flagged_with_its_rows(tmp_path):
    runs = _copy_runs(tmp_path)
    write_report(runs, tmp_path / "one", plots=False)
    assert "Code versions differ" not in (tmp_path / "one" / "leaderboard.md").read_text()
    (record,) = sorted(runs.glob("dtu/scan24/gof/*/record.json"))[:1]
    _edit(record, environment={"git_commit": OTHER, "git_dirty": True})
    write_report(runs, tmp_path / "two", plots=False)
    md = (tmp_path / "two" / "leaderboard.md").read_text()
    dtu_board = md.split("### DTU protocol")[1].split("\n### ")[0]
    assert "**Code versions differ** between this board's runs (0123456789ab: " in dtu_board
    assert f"{OTHER[:12]}+dirty: gof)" in dtu_board
    assert "Code versions differ" not in md.split("### Tanks and Temples protocol")[1].split("\n### ")[0]


def test_an_ok_record_with_a_nan_metric_is_warned_about(tmp_path):
    runs = _copy_runs(tmp_path)
    record = sorted(runs.glob("dtu/scan24/gof/*/record.json"))[0]
    data = _edit(record, metrics={"chamfer": math.nan})
    assert data["status"] == "ok"
    warnings = []
    write_report(runs, tmp_path / "out", plots=False, warn=warnings.append)
    assert any("status ok, but chamfer not finite (NaN or infinite)" in w for w in warnings), warnings


def test_a_run_folder_without_a_record_is_listed_as_unfinished(tmp_path):
    runs = _copy_runs(tmp_path)
    killed = runs / "dtu" / "scan24" / "3dgs" / "0123456789ab"
    killed.mkdir(parents=True)
    (killed / "config.yaml").write_text("method: {name: 3dgs}\n")
    (killed / "checkpoint.pt").write_bytes(b"")
    warnings = []
    write_report(runs, tmp_path / "out", plots=False, warn=warnings.append)
    assert any(w.startswith("dtu/scan24/3dgs/0123456789ab: a run folder without a record") for w in warnings)
    md = (tmp_path / "out" / "leaderboard.md").read_text()
    assert "| dtu/scan24/3dgs/0123456789ab | no record: killed before it finished?" in md


def test_a_finished_runs_second_stage_folder_is_not_an_unfinished_run(tmp_path):
    """SuGaR's refinement trains in ``refine/`` of its run folder, with its own config and checkpoints: once the
    run has its record, that folder is part of it, not a run killed before it finished."""
    runs = _copy_runs(tmp_path)
    finished = sorted(runs.glob("dtu/scan24/gof/*/record.json"))[0].parent
    stage = finished / "refine"
    stage.mkdir()
    (stage / "config.yaml").write_text("method: {name: sugar}\n")
    (stage / "checkpoint-final.pt").write_bytes(b"")
    warnings = []
    write_report(runs, tmp_path / "out", plots=False, warn=warnings.append)
    assert not any("refine: a run folder without a record" in w for w in warnings), warnings
