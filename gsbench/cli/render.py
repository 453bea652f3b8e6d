"""``gsbench render``: the report's picture of one finished run, as a PNG."""

from __future__ import annotations

from pathlib import Path

from gsbench.atomic import atomic_path, check_writable
from gsbench.cli.arguments import RUN_DIR_HELP


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("render", help="a finished run's mesh shaded from two fixed views beside the ground "
                                   "truth (or the photos with their masks) and coloured by its distance to it: the "
                                   "report's picture")
    parser.add_argument("run_dir", metavar="RUN_DIR", help=RUN_DIR_HELP)
    parser.add_argument("--out", default=None, help="PNG file to write (default: RUN_DIR/surface.png)")
    parser.set_defaults(func=run)


def run(args) -> int:
    from gsbench.report.surfaces import surface_picture

    out = Path(args.out) if args.out else Path(args.run_dir) / "surface.png"
    check_writable(out.parent, "--out")
    picture = surface_picture(Path(args.run_dir))
    with atomic_path(out, keep_suffix=True) as tmp:
        tmp.write_bytes(picture.png)
    print(f"{out}: {picture.width}x{picture.height} PNG, {len(picture.png) // 1024} KiB (the report's picture of this run)")
    return 0
