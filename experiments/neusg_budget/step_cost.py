"""The cost of one NeuSG training step with each SDF encoding (experiments/neusg_budget/README.md): the real step of
`gsbench.bench.train` (cpu preset, ``synthetic/spot``, from the step after the cross terms start, every hash level
active by then), the dense grid of the starved row against the hash grid of the fair row (configs/sweeps/
neusg_budget.yaml gives the rows; the overrides below are its fair row's field).

    python experiments/neusg_budget/step_cost.py [--steps 10] [--warmup 3] [--json out.json]

One thread. Prints, per encoding, the mean and median step (wall ms), its CPU time (this process's, per timed step:
what the records' ``train_cpu`` sums, and what a shared machine inflates least) and the phases that change with the
field: the loss terms' forward (the NeuS render is in ``fwd.neus_rgb``), the backward and the optimizer (Adam over
the tables).
"""

from __future__ import annotations

import argparse
import json
import os
import time

from gsbench.bench.train import Workload, bench_workload
from gsbench.training.trainer import Trainer

HASH_FIELD = ("method.encoding=hash", "method.grid_levels=16", "method.grid_min_res=16", "method.grid_max_res=2048",
              "method.hash_table_log2=19")
WORKLOADS = {"dense": Workload("neusg"), "hash": Workload("neusg", HASH_FIELD)}
SHOWN = ("fwd.neus_rgb", "fwd.eikonal", "fwd.sdf_points", "fwd.sdf_align", "backward_rest", "optimizer")


class StepCpuClock:
    """Wraps `Trainer.train_step` while in use: the process CPU seconds of each call, in order."""

    def __init__(self):
        self.seconds: list[float] = []
        self._step = Trainer.train_step

    def __enter__(self):
        def timed(trainer, step):
            start = time.process_time()
            try:
                return self._step(trainer, step)
            finally:
                self.seconds.append(time.process_time() - start)
        Trainer.train_step = timed
        return self

    def __exit__(self, *exc):
        Trainer.train_step = self._step


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--json", help="also write the results here")
    args = parser.parse_args()
    scenes, results = {}, {}
    for name, workload in WORKLOADS.items():
        with StepCpuClock() as clock:
            result = bench_workload(f"neusg-{name}", workload, steps=args.steps, warmup=args.warmup, probe_steps=0,
                                    threads=1, scenes=scenes)
        result["step_cpu_ms"] = 1e3 * sum(clock.seconds[-args.steps:]) / args.steps
        results[name] = result
        phases = "  ".join(f"{k} {result['phases_ms'][k]:.0f}" for k in SHOWN if k in result["phases_ms"])
        print(f"{name:5s}: {result['step_ms']:.0f} ms a step (median {result['step_ms_median']:.0f}), "
              f"{result['step_cpu_ms']:.0f} ms of CPU, from step {result['first_timed_step']}, {result['steps']} steps; "
              f"{phases}", flush=True)
    print(f"hash / dense: {results['hash']['step_ms'] / results['dense']['step_ms']:.2f}x wall, "
          f"{results['hash']['step_cpu_ms'] / results['dense']['step_cpu_ms']:.2f}x CPU; load "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=1)


if __name__ == "__main__":
    main()
