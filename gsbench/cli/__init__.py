"""The ``gsbench`` command line: one module per sub-command, each with ``add_parser(subparsers)`` and the
function it runs, importing its heavy modules inside that function so that ``gsbench --help`` and
``gsbench list`` start without torch.

Errors derived from `GsbenchError` print as one line (what was found, what was expected, the fix)
and exit with status 2; ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import argparse
import sys

from gsbench.cli import bench, config, depth, evaluate, gaussians, listing, render, report, run, scene, sweep
from gsbench.cli.arguments import THREADS_HELP, threads_count
from gsbench.errors import GsbenchError, Interrupted
from gsbench.resources import set_threads

# in the order `gsbench --help` lists them
COMMANDS = (listing, scene, config, run, sweep, evaluate, bench, depth, gaussians, render, report)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gsbench", description="Benchmark surface-reconstruction Gaussian splatting.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    parser.add_argument("--threads", type=threads_count, default=None, help=THREADS_HELP)
    subparsers = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(subparsers)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.threads:  # before a stage loads torch, which reads OMP_NUM_THREADS then
        set_threads(args.threads)
    try:
        return args.func(args)
    except GsbenchError as exc:
        if args.debug:
            raise
        print(f"gsbench: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("gsbench: interrupted", file=sys.stderr)
        return 130
    except Interrupted:
        print("gsbench: interrupted (SIGTERM)", file=sys.stderr)
        return 143
