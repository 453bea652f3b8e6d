"""``gsbench sweep``: expand a sweep file into runs and run them on an executor, skipping finished ones."""

from __future__ import annotations

import argparse

from gsbench.atomic import check_writable
from gsbench.cli.arguments import threads_count


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("sweep", help="expand a sweep file (configs/sweeps/) and run its runs, skipping finished ones")
    parser.add_argument("config", help="sweep YAML file")
    parser.add_argument("--dry-run", action="store_true", help="validate and print the runs and their ids only")
    parser.add_argument("--other-code", choices=("refuse", "rerun", "keep"), default="refuse",
                        help="finished records made by another code version (commit): refuse to mix them (default), "
                             "run them again, or keep them (the report flags boards that mix versions)")
    parser.add_argument("--suite", default=None, metavar="NAME",
                        help="run over this suite's scenes (configs/suites/, see `gsbench list`) instead of the "
                             "file's; seeds: the file's, else the suite's")
    parser.add_argument("--seeds", type=int, nargs="+", default=None, metavar="SEED",
                        help="seeds of every run, replacing the file's and the suite's")
    parser.add_argument("--set", action="append", metavar="KEY=VALUE",
                        help="override for every run, e.g. train.iterations=1000")
    parser.add_argument("--out", default=None, help="runs folder (default: each run's config out, runs/)")
    parser.add_argument("--threads", type=threads_count, default=argparse.SUPPRESS,
                        help="OpenMP / torch threads per run (default: the sweep file's executor.threads, "
                             "else the cores divided among the workers)")
    parser.add_argument("--executor", choices=("local", "ray"), default=None,
                        help="local processes or Ray (pip install \"gsbench[ray]\"); "
                             "default: the sweep file's executor.kind, else local")
    parser.add_argument("--workers", type=int, default=None,
                        help="runs at a time: local processes, or a local Ray cluster of workers × threads CPUs "
                             "(default: the sweep file's executor.workers, else 1)")
    parser.add_argument("--address", default=None,
                        help="the Ray cluster to connect to, e.g. auto (default: start a local one)")
    parser.set_defaults(func=run)


def run(args) -> int:
    from gsbench.runs.executors import make_executor, threads_per_run
    from gsbench.runs.sweep import check_run_count, expand, format_runs, load_sweep, run_sweep, with_suite

    sweep = with_suite(load_sweep(args.config), args.suite, args.seeds)
    print(f"# sweep {sweep['name']}: {check_run_count(sweep)} runs", flush=True)  # before expanding, which takes a while
    runs = expand(sweep, overrides=args.set or ())
    if args.dry_run:
        print(format_runs(runs))
        return 0
    for folder in sorted({args.out or r.config.out for r in runs}):
        check_writable(folder, "--out (or out: in the sweep's base)")
    settings = sweep.get("executor", {})
    workers = args.workers or settings.get("workers", 1)
    threads = threads_per_run(args.threads or settings.get("threads") or max(r.config.threads for r in runs), workers)
    with make_executor(args.executor or settings.get("kind", "local"), workers=workers, threads=threads,
                       address=args.address or settings.get("address"),
                       scene_paths=settings.get("scene_paths", "ship")) as executor:
        summary = run_sweep(runs, executor, name=sweep["name"], description=sweep.get("description", ""),
                            file=args.config, out=args.out, threads=threads, other_code=args.other_code)
    return summary.exit_status
