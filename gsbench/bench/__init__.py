"""`gsbench bench`: fixed-workload benchmarks of the training step (by phase), the rasterizer, the
evaluators and IBGS's overhead.

Performance claims in this project come from this command, written down with the workload, the
thread count and the machine (the result JSON carries `records.capture_environment`).
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from gsbench.bench import ibgs, raster, train
from gsbench.bench.eval import run_eval_benchmark, run_tnt_benchmark
from gsbench.errors import ConfigError
from gsbench.runs.records import capture_environment, write_json_atomic


def run_benchmark(args) -> int:
    """Run the benchmark named by ``args.target``, print a table, optionally write JSON."""
    threads = args.threads or torch.get_num_threads()
    if args.run and (args.target != "train" or args.workloads):
        raise ConfigError("--run times a run's own training steps: use it with `bench train` and without --workloads; "
                          "fix: drop --workloads (or --run)")
    if args.target == "raster":
        result = raster.run_raster_benchmark(kernels=args.kernels, workloads=args.workloads, repeats=args.repeats,
                                             threads=threads)
        print(raster.format_table(result))
    elif args.target == "train" and args.run:
        result = {"threads": threads, "steps": args.steps, "warmup": args.warmup, "results": [
            train.bench_run_folder(args.run, steps=args.steps, warmup=args.warmup, threads=threads)]}
        print(train.format_table(result))
    elif args.target == "train":
        result = train.run_train_benchmark(args.workloads, steps=args.steps, warmup=args.warmup, threads=threads)
        print(train.format_table(result))
    elif args.target == "ibgs":
        result = ibgs.run_ibgs_benchmark(sizes=args.sizes or ibgs.DEFAULT_SIZES, repeats=args.repeats)
        print(ibgs.format_table(result))
    else:
        result = {"dtu": run_eval_benchmark(n_vertices=args.vertices, n_gt=args.gt_points),
                  "tnt": run_tnt_benchmark(n_vertices=args.vertices, n_gt=args.gt_points)}
        print(json.dumps(result, indent=2, default=str))
    result = {"benchmark": args.target, "result": result, "environment": capture_environment(threads)}
    if args.json:
        write_json_atomic(Path(args.json), result)
        print(f"benchmark written to {args.json}")
    return 0
