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
