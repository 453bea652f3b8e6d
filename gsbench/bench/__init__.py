"""`gsbench bench`: fixed-workload benchmarks of the training step (by phase), the rasterizer, the
evaluators and IBGS's overhead.

Performance claims in this project come from this command, written down with the workload, the
thread count and the machine (the result JSON carries `records.capture_environment`).
"""

from __future__ import annotations

import json
from pathlib import Path

from gsbench.records import capture_environment, write_json_atomic


def run_benchmark(args) -> int:
    """Run the benchmark named by ``args.target``, print a table, optionally write JSON."""
    import torch  # noqa: PLC0415

    threads = args.threads or torch.get_num_threads()
    if args.target == "raster":
        from gsbench.bench.raster import format_table, run_raster_benchmark  # noqa: PLC0415

        result = run_raster_benchmark(kernels=args.kernels, workloads=args.workloads, repeats=args.repeats, threads=threads)
        print(format_table(result))
    elif args.target == "train":
        from gsbench.bench.train import format_table, run_train_benchmark  # noqa: PLC0415

        result = run_train_benchmark(args.workloads, steps=args.steps, warmup=args.warmup, threads=threads)
        print(format_table(result))
    elif args.target == "ibgs":
        from gsbench.bench.ibgs import DEFAULT_SIZES, format_table, run_ibgs_benchmark  # noqa: PLC0415

        result = run_ibgs_benchmark(sizes=args.sizes or DEFAULT_SIZES, repeats=args.repeats)
        print(format_table(result))
    else:
        from gsbench.bench.eval import run_eval_benchmark, run_tnt_benchmark  # noqa: PLC0415

        result = {"dtu": run_eval_benchmark(n_vertices=args.vertices, n_gt=args.gt_points),
                  "tnt": run_tnt_benchmark(n_vertices=args.vertices, n_gt=args.gt_points)}
        print(json.dumps(result, indent=2, default=str))
    result = {"benchmark": args.target, "result": result, "environment": capture_environment(threads)}
    if args.json:
        write_json_atomic(Path(args.json), result)
        print(f"benchmark written to {args.json}")
    return 0
