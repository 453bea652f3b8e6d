"""``gsbench report``: leaderboards, plots and ablations from a folder of run records."""

from __future__ import annotations

import sys
from pathlib import Path

from gsbench.atomic import check_writable


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("report", help="leaderboard tables, speed-vs-error plots and sweep ablations from run records")
    parser.add_argument("runs_dir", metavar="SOURCE", help="runs folder (searched recursively for record.json), or a "
                        "board's records.jsonl.gz or the folder holding it")
    parser.add_argument("--out", default="report", help="output folder (default: report/)")
    parser.add_argument("--no-plots", action="store_true", help="skip the matplotlib plots (no PNGs, no figures)")
    parser.add_argument("--self-contained", action="store_true",
                        help="embed the pictures in index.html (one file to share) instead of linking plots/")
    parser.set_defaults(func=run)


def run(args) -> int:
    from gsbench.report.build import write_report

    check_writable(args.out, "--out")
    written = write_report(Path(args.runs_dir), Path(args.out), plots=not args.no_plots,
                           self_contained=args.self_contained,
                           warn=lambda message: print(f"gsbench: warning: {message}", file=sys.stderr))
    plots = sum(1 for p in written if p.suffix == ".png")
    print(f"report written to {args.out}: " + ", ".join(p.name for p in written if p.suffix != ".png")
          + (f" and {plots} plot{'s' if plots > 1 else ''} in plots/" if plots else ""))
    return 0
