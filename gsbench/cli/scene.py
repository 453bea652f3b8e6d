"""``gsbench scene make|check|floor``: generate a scene folder, validate one, or mesh a synthetic scene's
exact depth (the meshing floor)."""

from __future__ import annotations

import json
from pathlib import Path

from gsbench.cli.arguments import GT_HELP
from gsbench.errors import ConfigError


def add_parser(subparsers) -> None:
    scene = subparsers.add_parser("scene", help="make or check scene folders").add_subparsers(dest="scene_command",
                                                                                              required=True)
    make_parser = scene.add_parser("make", help="generate a built-in synthetic scene, or a scene of any mesh file")
    make_parser.add_argument("name", nargs="?", help="e.g. synthetic/spot (see `gsbench list`); or give --mesh")
    make_parser.add_argument("--mesh", metavar="FILE",
                             help="a mesh file (obj, ply, glb, gltf, off, stl): the object on the table "
                                  "in a room (DTU layouts) or on the ground (tnt), exact ground truth")
    make_parser.add_argument("--framing", default=None,
                             help="dtu (the object fills 34%% of each image, as on DTU), small (12.6%%, the first "
                                  "synthetic scenes) or a share in (0, 1); in DTU's rig it sets the object's size, in the "
                                  "synthetic rigs the camera distance; default: dtu for --mesh, the scene's own for built-ins")
    make_parser.add_argument("--rig", default=None, choices=("dtu", "barn", "cap", "ring", "band"),
                             help="--mesh: the cameras (default: the dataset's own: dtu = DTU's 49 cameras, the object "
                                  "sized by --framing; barn = Tanks-and-Temples Barn's lens and floor plan; cap, ring, band: "
                                  "synthetic rigs of the first scenes)")
    make_parser.add_argument("--up", default="y", choices=("x", "y", "z", "-x", "-y", "-z"),
                             help="--mesh: the file's up axis")
    make_parser.add_argument("--yaw", type=float, default=0.0,
                             help="--mesh: turn the object about up by this many degrees (the DTU cameras look from +y)")
    make_parser.add_argument("--albedo", default="auto",
                             help="--mesh: auto (the file's texture or colours, else procedural), file, or a named "
                                  "albedo: procedural, uniform, painted, wood, glaze, fine, stone")
    make_parser.add_argument("--largest-part", action="store_true", help="--mesh: keep only the largest connected part")
    make_parser.add_argument("--smooth", type=int, default=0, metavar="N",
                             help="--mesh: N iterations of Taubin smoothing (takes a scan's fine relief off, keeps its "
                                  "shape)")
    make_parser.add_argument("--format", choices=("dtu", "dtu-colmap", "tnt"), default=None,
                             help="layout (default: the scene's own; dtu-colmap for --mesh)")
    make_parser.add_argument("--out", default=None, help="folder (default: the cache, $GSBENCH_DATA)")
    make_parser.add_argument("--res", type=int, nargs=2, metavar=("W", "H"), default=None, help="image size")
    make_parser.add_argument("--seed", type=int, default=0)
    make_parser.add_argument("--supersample", type=int, default=None,
                             help="rays per pixel side of the images (2: area-sampled; 1: the pixel centre only)")
    make_parser.set_defaults(func=make)

    check_parser = scene.add_parser("check", help="validate a scene folder and print what was found (reads no pixels)")
    check_parser.add_argument("dir")
    check_parser.add_argument("--gt", default=None, help=GT_HELP)
    check_parser.set_defaults(func=check)

    floor_parser = scene.add_parser("floor",
                                    help="the meshing floor: TSDF of a synthetic scene's exact depth, evaluated")
    floor_parser.add_argument("name", help="a built-in scene, e.g. synthetic/dtu-spot")
    floor_parser.add_argument("--preset", default="cpu", help="resolution and mesh settings as a run with this preset")
    floor_parser.add_argument("--set", action="append", metavar="KEY=VALUE", help="override, e.g. mesh.voxel_size=0.002")
    floor_parser.add_argument("--out", default="runs/floor", help="folder for floor.ply and floor.json")
    floor_parser.set_defaults(func=floor)


def make(args) -> int:
    from gsbench.data.loader import check_scene
    from gsbench.data.synthetic.make import make_mesh_scene, make_scene

    common = {"out": args.out, "res": args.res, "seed": args.seed, "supersample": args.supersample}
    if args.mesh:
        if args.name:
            raise ConfigError(f"scene make: give a built-in name or --mesh, not both (got {args.name!r} and --mesh {args.mesh})")
        path = make_mesh_scene(args.mesh, fmt=args.format or "dtu-colmap", framing=args.framing or "dtu", up=args.up,
                               yaw=args.yaw, rig=args.rig, albedo=args.albedo, largest_part=args.largest_part, smooth=args.smooth, **common)
    elif args.name:
        path = make_scene(args.name, fmt=args.format, framing=args.framing, **common)
    else:
        raise ConfigError("scene make: give a built-in name (gsbench list) or --mesh FILE")
    print(f"scene written to {path}")
    print(json.dumps(check_scene(path), indent=2, default=str))
    return 0


def check(args) -> int:
    from gsbench.data.loader import check_scene

    report = check_scene(Path(args.dir), gt_root=args.gt)
    print(json.dumps(report, indent=2, default=str))
    return 0 if report["ok"] else 1


def floor(args) -> int:
    from gsbench.evaluators.api import format_table
    from gsbench.mesh.floor import floor_report
    from gsbench.runs.records import write_json_atomic

    out = Path(args.out)
    report = floor_report(args.name, preset=args.preset, overrides=args.set or (), out=out)
    res, mesh = report["config"]["resolution"], report["config"]["mesh"]
    print(f"TSDF of the exact depth of {args.name} at {res[0]}x{res[1]} (voxel_size {mesh['voxel_size']}, "
          f"sdf_trunc {mesh['sdf_trunc']}, masks {report['config']['use_masks']}):")
    print(format_table(report))
    write_json_atomic(out / "floor.json", report)
    print(f"mesh and results written to {out}")
    return 0
