"""``gsbench depth``: a finished run's depth against its synthetic scene's exact depth, per view."""

from __future__ import annotations

from pathlib import Path

from gsbench.cli.arguments import RUN_DIR_HELP


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("depth", help="a finished run's depth against its synthetic scene's exact depth, per view")
    parser.add_argument("run_dir", metavar="RUN_DIR", help=RUN_DIR_HELP)
    parser.add_argument("--views", type=int, nargs="+", default=[0, 10, 20, 30, 40],
                        help="view indices (default: 0 10 20 30 40)")
    parser.set_defaults(func=run)


def run(args) -> int:
    from gsbench.diagnostics.depth_check import check_run_depth, format_rows

    rows = check_run_depth(Path(args.run_dir), args.views)
    print(f"{args.run_dir}: the depth the TSDF fuses against the scene's exact depth on the object mask "
          "(e = (d − d*) / d*; e > 0: behind the surface)")
    print(format_rows(rows))
    return 0
