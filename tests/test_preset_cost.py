"""`tools/preset_cost.py`: a run's cost scaled from an anchor run by the bench steps' ratio, and a suite's makespan by
longest-first list scheduling, checked against hand-computed values."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

TOOL = Path(__file__).resolve().parents[1] / "tools" / "preset_cost.py"


def _bench(steps: dict) -> dict:
    return {"environment": {"cpu": "test cpu", "git_commit": "0123456789"},
            "result": {"threads": 1, "results": [{"method": m, "step_ms": s} for m, s in steps.items()]}}


def test_runs_scale_with_the_step_ratio_and_the_suite_is_list_scheduled(tmp_path):
    """Anchor 3dgs: 3 600 CPU-s of training, 360 s after it. A method with twice the step trains 7 200 s (times the
    code factor 0.5: 3 600). One scene, one seed, one 1-core machine: the runs back to back; two cores: the longer."""
    bench, anchor = tmp_path / "bench.json", tmp_path / "record.json"
    bench.write_text(json.dumps(_bench({"3dgs": 500.0, "pgsr": 1000.0})))
    anchor.write_text(json.dumps({"method": "3dgs", "run_id": "abc", "timings": {
        "train_cpu": 3600.0, "train": 9000.0, "extract": 300.0, "evaluate": 50.0, "load": 10.0}}))
    out = subprocess.run([sys.executable, str(TOOL), "--bench", str(bench), "--anchor", str(anchor),
                          "--anchor-code-factor", "0.5", "--scenes", "1", "--seeds", "1", "--machines", "1", "2",
                          "--cores", "1"], capture_output=True, text=True, check=True).stdout
    assert "| 3dgs | 500 | 0.5 | 0.6 |" in out      # 1 800 s train, 2 160 s total
    assert "| pgsr | 1000 | 1.0 | 1.1 |" in out     # 3 600 s train, 3 960 s total
    assert "| 1 | 2 | 1.7 | 1.1 |" in out           # 6 120 s on one slot; the longer run, 3 960 s, on two


def test_an_anchor_method_missing_from_the_bench_is_a_one_line_error(tmp_path):
    bench, anchor = tmp_path / "bench.json", tmp_path / "record.json"
    bench.write_text(json.dumps(_bench({"pgsr": 1000.0})))
    anchor.write_text(json.dumps({"method": "3dgs", "run_id": "abc", "timings": {"train_cpu": 1.0}}))
    done = subprocess.run([sys.executable, str(TOOL), "--bench", str(bench), "--anchor", str(anchor)],
                          capture_output=True, text=True)
    assert done.returncode != 0 and "3dgs-800x600-300k" in done.stderr


def test_the_cluster_table_counts_runs_core_and_node_hours_and_list_schedules_on_nodes(tmp_path):
    """Anchor 3dgs at 800x600-300k: 3 600 CPU-s of training, 400 s after it. DTU (2 scenes) at that size: 3dgs
    4 000 s a run, pgsr (twice the step) 7 600; TnT (1 scene) at 800x600-1m, pixels 1.5: 3dgs 1.2 · 3 600 · 1.5 +
    400 = 6 880, pgsr 2.4 · 3 600 · 1.5 + 400 = 13 360. One seed, nodes of 2 cores."""
    bench, anchor = tmp_path / "bench.json", tmp_path / "record.json"
    results = [{"workload": w, "method": w.split("-")[0], "step_ms": s} for w, s in
               {"3dgs-800x600-300k": 500.0, "pgsr-800x600-300k": 1000.0, "3dgs-800x600-1m": 600.0,
                "pgsr-800x600-1m": 1200.0, "3dgs-spot": 10.0}.items()]
    bench.write_text(json.dumps({"environment": {"cpu": "c", "git_commit": "0" * 10},
                                 "result": {"threads": 1, "results": results}}))
    anchor.write_text(json.dumps({"method": "3dgs", "run_id": "abc", "timings": {
        "train_cpu": 3600.0, "extract": 300.0, "evaluate": 90.0, "load": 10.0}}))
    command = [sys.executable, str(TOOL), "--bench", str(bench), "--anchor", str(anchor), "--suite", "dtu", "2",
               "800x600-300k", "--suite", "tnt", "1", "800x600-1m", "1.5", "--seeds", "1", "--cores", "2",
               "--nodes", "1", "2"]
    out = subprocess.run(command, capture_output=True, text=True, check=True).stdout
    # dtu: runs 4000, 4000, 7600, 7600 = 23 200 s = 6.44 core-h, 3.22 node-h; longest 2.11 h; 1 node (2 slots):
    # 7600+4000 each = 3.22 h; 2 nodes: the longest, 2.11 h
    assert "| dtu (2 scenes × 2 methods × 1 seeds) | 4 | 6 | 3 | 2.1 | 3.2 | 2.1 |" in out
    # all: + 6 880 and 13 360 = 43 440 s = 12.07 core-h, 6.03 node-h, longest 3.71 h; 1 node: LPT of
    # 13360, 7600, 7600, 6880, 4000, 4000 on 2 slots: 13360+6880=20240 | 7600+7600+4000+4000=23200 → 6.44 h
    assert "| all | 6 | 12 | 6 | 3.7 | 6.4 | 3.7 |" in out
    skipped = subprocess.run([*command, "--skip", "pgsr"], capture_output=True, text=True, check=True).stdout
    assert "| all | 3 | 4 | 2 | 1.9 | 2.2 | 1.9 |" in skipped  # 4000+4000+6880 = 14 880 s
