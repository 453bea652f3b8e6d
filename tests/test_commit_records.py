"""`tools/commit_records.py`: finished runs' records copied into a committed folder with the machine's paths made
relative; a run that is only interrupted (it resumes) is left out, a failed one is kept; the sweeps' manifests
go with them."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

TOOL = Path(__file__).resolve().parents[1] / "tools" / "commit_records.py"


def _record(folder: Path, status: str, runs: Path, cache: Path) -> None:
    folder.mkdir(parents=True)
    record = {"run_id": folder.name, "status": status, "scene": str(cache / "synthetic" / "spot"),
              "config": {"out": str(runs)}, "mesh": {"path": str(folder / "mesh.ply")}}
    (folder / "record.json").write_text(json.dumps(record))


def test_finished_records_are_copied_with_relative_paths_and_interrupted_ones_left_out(tmp_path):
    runs, cache, committed = tmp_path / "runs", tmp_path / "cache", tmp_path / "committed"
    _record(runs / "dtu" / "spot" / "3dgs" / "aaa", "ok", runs, cache)
    _record(runs / "dtu" / "spot" / "2dgs" / "bbb", "failed", runs, cache)
    failed = json.loads((runs / "dtu" / "spot" / "2dgs" / "bbb" / "record.json").read_text())
    failed["error_tail"] = ('  File "/home/me/wt3/gsbench/mesh/tsdf.py", line 9, in fuse\n'
                            '  File "/usr/lib/python3/site-packages/torch/nn.py", line 2, in f\n')
    (runs / "dtu" / "spot" / "2dgs" / "bbb" / "record.json").write_text(json.dumps(failed))
    _record(runs / "dtu" / "spot" / "gof" / "ccc", "interrupted", runs, cache)
    manifest = {"name": "abl", "runs": [{"run_id": "aaa", "label": "base", "dir": "dtu/spot/3dgs/aaa"}]}
    (runs / "sweeps").mkdir()
    (runs / "sweeps" / "abl.json").write_text(json.dumps(manifest))
    done = subprocess.run([sys.executable, str(TOOL), str(runs), str(committed)], capture_output=True, text=True,
                          env={**os.environ, "GSBENCH_DATA": str(cache)}, check=True)
    assert "2 records and 1 sweep manifests written" in done.stdout
    assert json.loads((committed / "sweeps" / "abl.json").read_text()) == manifest
    copied = json.loads((committed / "dtu" / "spot" / "3dgs" / "aaa" / "record.json").read_text())
    assert copied["config"]["out"] == "." and copied["mesh"]["path"] == "dtu/spot/3dgs/aaa/mesh.ply"
    assert copied["scene"] == "$GSBENCH_DATA/synthetic/spot"
    tail = json.loads((committed / "dtu" / "spot" / "2dgs" / "bbb" / "record.json").read_text())["error_tail"]
    assert tail == ('  File "gsbench/mesh/tsdf.py", line 9, in fuse\n'
                    '  File "site-packages/torch/nn.py", line 2, in f\n')
    assert not (committed / "dtu" / "spot" / "gof").exists()


def test_a_committed_manifest_keeps_the_runs_a_later_invocation_lacks(tmp_path):
    """A sweep run a seed at a time: the committed manifest of seed 0 gains seed 1's entries, and an entry in both
    takes the newer status."""
    runs, cache, committed = tmp_path / "runs", tmp_path / "cache", tmp_path / "committed"
    (committed / "sweeps").mkdir(parents=True)
    seed0 = [{"run_id": "a0", "seed": 0, "status": "ok"}, {"run_id": "b0", "seed": 0, "status": "pending"}]
    (committed / "sweeps" / "abl.json").write_text(json.dumps({"name": "abl", "runs": seed0}))
    (runs / "sweeps").mkdir(parents=True)
    seed1 = [{"run_id": "b0", "seed": 0, "status": "skipped"}, {"run_id": "a1", "seed": 1, "status": "ok"}]
    (runs / "sweeps" / "abl.json").write_text(json.dumps({"name": "abl", "description": "now", "runs": seed1}))
    subprocess.run([sys.executable, str(TOOL), str(runs), str(committed)], capture_output=True, text=True,
                   env={**os.environ, "GSBENCH_DATA": str(cache)}, check=True)
    merged = json.loads((committed / "sweeps" / "abl.json").read_text())
    assert merged["description"] == "now"
    assert [(e["run_id"], e["status"]) for e in merged["runs"]] == [("a0", "ok"), ("b0", "skipped"), ("a1", "ok")]
