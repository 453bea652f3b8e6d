"""`tools/commit_records.py`: finished runs' records merged into a board's records file with the machine's paths made
relative; a run that is only interrupted (it resumes) is left out, a failed one is kept; the sweeps' manifests go
with them; `--extract` writes them back into a runs folder."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from gsbench.report.records_file import RECORDS_FILE, BoardRecords, read_board, write_board

TOOL = Path(__file__).resolve().parents[1] / "tools" / "commit_records.py"


def _record(folder: Path, status: str, runs: Path, cache: Path, **extra) -> dict:
    folder.mkdir(parents=True, exist_ok=True)
    record = {"run_id": folder.name, "status": status, "scene": str(cache / "synthetic" / "spot"),
              "config": {"out": str(runs)}, "mesh": {"path": str(folder / "mesh.ply")}, **extra}
    (folder / "record.json").write_text(json.dumps(record))
    return record


def _commit(runs: Path, board: Path, cache: Path, *options: str) -> str:
    return subprocess.run([sys.executable, str(TOOL), *options, str(runs), str(board)], capture_output=True, text=True,
                          env={**os.environ, "GSBENCH_DATA": str(cache)}, check=True).stdout


def test_finished_records_are_merged_with_relative_paths_and_interrupted_ones_left_out(tmp_path):
    runs, cache, board = tmp_path / "runs", tmp_path / "cache", tmp_path / "board"
    _record(runs / "dtu" / "spot" / "3dgs" / "aaa", "ok", runs, cache)
    _record(runs / "dtu" / "spot" / "2dgs" / "bbb", "failed", runs, cache,
            error_tail='  File "/home/me/wt3/gsbench/mesh/tsdf.py", line 9, in fuse\n'
                       '  File "/usr/lib/python3/site-packages/torch/nn.py", line 2, in f\n')
    _record(runs / "dtu" / "spot" / "gof" / "ccc", "interrupted", runs, cache)
    manifest = {"name": "abl", "runs": [{"run_id": "aaa", "label": "base", "dir": "dtu/spot/3dgs/aaa"}]}
    (runs / "sweeps").mkdir()
    (runs / "sweeps" / "abl.json").write_text(json.dumps(manifest))
    assert "2 records and 1 sweep manifests merged" in _commit(runs, board, cache)
    committed = read_board(board / RECORDS_FILE)
    assert sorted(committed.records) == ["dtu/spot/2dgs/bbb/record.json", "dtu/spot/3dgs/aaa/record.json"]
    assert committed.manifests == {"sweeps/abl.json": manifest}
    copied = committed.records["dtu/spot/3dgs/aaa/record.json"]
    assert copied["config"]["out"] == "." and copied["mesh"]["path"] == "dtu/spot/3dgs/aaa/mesh.ply"
    assert copied["scene"] == "$GSBENCH_DATA/synthetic/spot"
    assert committed.records["dtu/spot/2dgs/bbb/record.json"]["error_tail"] == (
        '  File "gsbench/mesh/tsdf.py", line 9, in fuse\n  File "site-packages/torch/nn.py", line 2, in f\n')


def test_a_newer_record_replaces_the_one_of_its_run_id_and_the_others_stay(tmp_path):
    runs, cache, board = tmp_path / "runs", tmp_path / "cache", tmp_path / "board" / RECORDS_FILE
    kept = {"run_id": "old", "status": "ok", "metrics": {"chamfer": 1.0}}
    write_board(board, BoardRecords(records={"dtu/spot/3dgs/old/record.json": kept,
                                             "elsewhere/aaa/record.json": {"run_id": "aaa", "status": "failed"}}))
    _record(runs / "dtu" / "spot" / "3dgs" / "aaa", "ok", runs, cache)
    _commit(runs, board, cache)
    records = read_board(board).records
    assert records["dtu/spot/3dgs/old/record.json"] == kept  # exactly as committed
    assert sorted(records) == ["dtu/spot/3dgs/aaa/record.json", "dtu/spot/3dgs/old/record.json"]
    assert records["dtu/spot/3dgs/aaa/record.json"]["status"] == "ok"


def test_a_committed_manifest_keeps_the_runs_a_later_invocation_lacks(tmp_path):
    """A sweep run a seed at a time: the committed manifest of seed 0 gains seed 1's entries, and an entry in both
    takes the newer status."""
    runs, cache, board = tmp_path / "runs", tmp_path / "cache", tmp_path / "board"
    seed0 = [{"run_id": "a0", "seed": 0, "status": "ok"}, {"run_id": "b0", "seed": 0, "status": "pending"}]
    write_board(board / RECORDS_FILE, BoardRecords(manifests={"sweeps/abl.json": {"name": "abl", "runs": seed0}}))
    (runs / "sweeps").mkdir(parents=True)
    seed1 = [{"run_id": "b0", "seed": 0, "status": "skipped"}, {"run_id": "a1", "seed": 1, "status": "ok"}]
    (runs / "sweeps" / "abl.json").write_text(json.dumps({"name": "abl", "description": "now", "runs": seed1}))
    _commit(runs, board, cache)
    merged = read_board(board / RECORDS_FILE).manifests["sweeps/abl.json"]
    assert merged["description"] == "now"
    assert [(e["run_id"], e["status"]) for e in merged["runs"]] == [("a0", "ok"), ("b0", "skipped"), ("a1", "ok")]


def test_extract_writes_the_board_back_without_overwriting(tmp_path):
    runs, cache, board = tmp_path / "runs", tmp_path / "cache", tmp_path / "board"
    first = _record(runs / "dtu" / "spot" / "3dgs" / "aaa", "ok", runs, cache)
    _record(runs / "dtu" / "spot" / "2dgs" / "bbb", "ok", runs, cache)
    _commit(runs, board, cache)
    out = tmp_path / "again"
    (out / "dtu" / "spot" / "2dgs" / "bbb").mkdir(parents=True)
    (out / "dtu" / "spot" / "2dgs" / "bbb" / "record.json").write_text("mine")
    assert "1 files written" in _commit(board, out, cache, "--extract")
    assert (out / "dtu" / "spot" / "2dgs" / "bbb" / "record.json").read_text() == "mine"
    extracted = json.loads((out / "dtu" / "spot" / "3dgs" / "aaa" / "record.json").read_text())
    assert extracted == read_board(board / RECORDS_FILE).records["dtu/spot/3dgs/aaa/record.json"]
    assert extracted["run_id"] == first["run_id"] and extracted["config"]["out"] == "."
