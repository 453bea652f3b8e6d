"""``gsbench bench``: fixed-workload timings of training, the rasteriser, the evaluation and IBGS."""

from __future__ import annotations


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("bench", help="fixed-workload benchmarks")
    parser.add_argument("target", choices=("train", "raster", "eval", "ibgs"))
    parser.add_argument("--kernels", nargs="+", default=None)
    parser.add_argument("--workloads", nargs="+", default=None,
                        help="e.g. 50k-400x300 200k-800x600 (raster); 3dgs 2dgs gof radegs ibgs sugar 3dgs-random-100k (train)")
    parser.add_argument("--run", default=None, metavar="RUN_DIR",
                        help="time a run's own steps from its checkpoint instead of a workload (train)")
    parser.add_argument("--steps", type=int, default=30, help="timed training steps per workload (train)")
    parser.add_argument("--warmup", type=int, default=10, help="untimed training steps before them (train)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--sizes", type=int, nargs="+", default=None, help="Gaussian counts (ibgs; default 10000 100000)")
    parser.add_argument("--vertices", type=int, default=1_000_000, help="mesh size (eval)")
    parser.add_argument("--gt-points", type=int, default=2_000_000, help="GT size (eval)")
    parser.add_argument("--json", default=None, help="also write the result as JSON")
    parser.set_defaults(func=run)


def run(args) -> int:
    from gsbench.bench import run_benchmark

    return run_benchmark(args)
