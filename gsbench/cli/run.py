"""``gsbench run``: train a method on a scene, extract its mesh, evaluate it and write the record."""

from __future__ import annotations

import argparse

from gsbench.cli.arguments import GT_HELP, THREADS_HELP, threads_count


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("run", help="train a method on a scene, extract its mesh, evaluate it, write the record")
    parser.add_argument("--method", required=True, help="e.g. 2dgs (see `gsbench list`)")
    parser.add_argument("--scene", required=True, help="built-in name (synthetic/spot) or a scene folder "
                                                       "(a suite of scenes runs as a sweep: gsbench sweep FILE --suite NAME)")
    parser.add_argument("--preset", default="cpu", help="budget: quick, cpu (default), bench or paper")
    parser.add_argument("--config", action="append", help="user YAML file (repeatable)")
    parser.add_argument("--set", action="append", metavar="KEY=VALUE", help="override, e.g. train.iterations=500")
    parser.add_argument("--out", default=None, help="runs folder (default: the config's out, runs/)")
    parser.add_argument("--seed", type=int, default=None)
    parser.add_argument("--gt", default=None, help=GT_HELP)
    # SUPPRESS: absent here, the global `gsbench --threads` value stays in args
    parser.add_argument("--threads", type=threads_count, default=argparse.SUPPRESS, help=THREADS_HELP)
    parser.set_defaults(func=run)


def run(args) -> int:
    from gsbench.runs import runner

    cfg = runner.resolve_run(args.method, args.scene, preset=args.preset, user_files=args.config or (),
                             overrides=args.set or (), seed=args.seed, gt=args.gt)
    if args.out is not None:
        cfg.out = args.out
    if args.threads is not None:
        cfg.threads = args.threads
    runner.run(cfg)
    return 0
