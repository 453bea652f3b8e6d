"""``gsbench gaussians``: where a finished run's Gaussians are (object, environment or free space)."""

from __future__ import annotations

from pathlib import Path

from gsbench.cli.arguments import RUN_DIR_HELP


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("gaussians", help="where a finished run's Gaussians are: on the object, on the "
                                   "environment or in free space (synthetic scenes)")
    parser.add_argument("run_dir", metavar="RUN_DIR", help=RUN_DIR_HELP)
    parser.add_argument("--within", type=float, default=None,
                        help="distance to a surface that counts as on it, dataset units (default: 1.5%% of the "
                             "object's bounding-box diagonal)")
    parser.set_defaults(func=run)


def run(args) -> int:
    from gsbench.diagnostics.gaussian_placement import format_placement, run_placement

    regions, within = run_placement(Path(args.run_dir), args.within)
    print(f"{args.run_dir}: the Gaussian centres against the scene's exact surfaces (within {within:.4g} dataset "
          "units of the object; of the environment; farther than that from every surface)")
    print(format_placement(regions))
    return 0
