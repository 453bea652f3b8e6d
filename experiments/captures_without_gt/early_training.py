"""The start of training of finished runs: Gaussians at step 0 and at a given step, it/s up to it, and
the final numbers, one row per run folder.

    python experiments/captures_without_gt/early_training.py RUN_DIR [RUN_DIR ...] [--step 500]

Step 0 is the record's ``inputs.initial_gaussians``; N at ``--step`` and the rate come from
``metrics.jsonl`` (one line every ``train.log_every`` steps with the it/s of that window):
it/s over steps 1..S = S / Σ_windows (window steps / window it/s). ``--step`` must be a multiple of
``train.log_every``. The final columns are the record's: Chamfer (mm, DTU protocol) or F1, train
seconds and Gaussians.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def early_row(run: Path, step: int) -> dict:
    """One run's row (module docstring)."""
    record = json.loads((run / "record.json").read_text())
    lines = [json.loads(ln) for ln in (run / "metrics.jsonl").read_text().splitlines() if ln.strip()]
    window = [ln for ln in lines if ln["step"] <= step]
    if not window or window[-1]["step"] != step:
        raise SystemExit(f"{run}: metrics.jsonl has no line at step {step}; choose a multiple of train.log_every")
    seconds, previous = 0.0, 0
    for ln in window:
        seconds += (ln["step"] - previous) / ln["it_per_s"]
        previous = ln["step"]
    metrics = record.get("metrics", {})
    return {"run": f"{record['method']} {record['run_id']}",
            "init": record["config"]["method"].get("random_init_region", ""),
            "gaussians_step0": record.get("inputs", {}).get("initial_gaussians"),
            f"gaussians_step{step}": window[-1]["num_gaussians"], f"it_per_s_1_{step}": step / seconds,
            "chamfer_mm": metrics.get("chamfer"), "f1": metrics.get("f1"),
            "train_s": record.get("timings", {}).get("train"), "gaussians_final": record.get("num_gaussians")}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--step", type=int, default=500)
    args = parser.parse_args(argv)
    rows = [early_row(run, args.step) for run in args.runs]
    keys = list(rows[0])
    print(" | ".join(keys))
    for row in rows:
        print(" | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in row.values()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
