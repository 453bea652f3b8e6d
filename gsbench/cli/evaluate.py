"""``gsbench eval``: evaluate a mesh file against a scene's ground truth."""

from __future__ import annotations

from pathlib import Path

from gsbench.atomic import check_writable
from gsbench.cli.arguments import GT_HELP
from gsbench.errors import ConfigError, DataError


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("eval", help="evaluate a mesh against a scene's ground truth")
    parser.add_argument("--mesh", required=True)
    parser.add_argument("--scene", required=True)
    parser.add_argument("--evaluator", action="append",
                        help="evaluator name (repeatable; default: the dataset's, those the scene can feed)")
    parser.add_argument("--frame", choices=("normalised", "dataset"), default="normalised",
                        help="frame of the mesh: normalised (what gsbench methods write) or dataset (DTU mm world, TnT COLMAP)")
    parser.add_argument("--tnt-frame", choices=("colmap", "extent"), default="colmap",
                        help="a TnT scene's training frame, the run's data.tnt_frame (what --frame normalised means): "
                             "colmap (the papers', default) or extent (the runs recorded before the key)")
    parser.add_argument("--downscale", type=float, default=1.0,
                        help="load the scene's images downscaled (the run's data.downscale): sets the pixel "
                             "footprint surface_offset reports in")
    parser.add_argument("--max-size", type=int, nargs=2, metavar=("LONG", "SHORT"), default=None,
                        help="fit the images in this many pixels (the run's data.max_size; the cpu preset's is "
                             "240 150): the resolution silhouette compares masks at")
    parser.add_argument("--gt", default=None, help=GT_HELP)
    parser.add_argument("--dtu-culling", choices=("2dgs", "gof", "none"), default="2dgs",
                        help="mask culling before the DTU protocol (dtu_chamfer, normal_similarity): 2DGS's "
                             "disk(24) at 1600 px (default), GOF's disk(6) at the masks' resolution, or none")
    parser.add_argument("--points", action="store_true",
                        help="the file is a point cloud: score its points as they are (dtu_chamfer's mode pcd; "
                             "only dtu_chamfer takes one)")
    parser.add_argument("--out", default=None, help="write the results JSON here")
    parser.set_defaults(func=run)


def run(args) -> int:
    from gsbench.config.run_config import dataset_of
    from gsbench.data.loader import load_scene
    from gsbench.data.synthetic.make import ensure_scene
    from gsbench.evaluators.api import check_evaluation_memory, evaluate_mesh_file, format_table, mesh_counts
    from gsbench.evaluators.resolve import plan_evaluation, run_options
    from gsbench.runs.records import write_json_atomic
    from gsbench.training.progress import stage

    if not Path(args.mesh).is_file():
        raise DataError(f"{args.mesh}: mesh file not found; fix: --mesh names a .ply (a run folder's mesh.ply)")
    if args.out:  # before the evaluation, not after it
        if Path(args.out).is_dir():
            raise ConfigError(f"--out {args.out}: is a folder, and the results are one JSON file; fix: name a file, "
                              f"e.g. --out {Path(args.out) / 'eval.json'}")
        check_writable(Path(args.out).parent, "--out")
    size = {"downscale": args.downscale, "max_size": args.max_size or (), "gt_root": args.gt,
            "tnt_frame": args.tnt_frame}
    ensure_scene(args.scene)
    header = load_scene(args.scene, load_images=False, **size)
    plan = plan_evaluation(header, dataset_of(args.scene), args.evaluator or (), held_out=0)
    if plan.mesh:  # before the images are read
        check_evaluation_memory(args.mesh, plan.mesh, mesh_counts(args.mesh))
    scene = load_scene(args.scene, **size)
    culling = run_options(args.dtu_culling, plan.mesh)
    if args.points and set(plan.mesh) != {"dtu_chamfer"}:
        raise ConfigError(f"--points: only dtu_chamfer scores a point cloud, this evaluation has "
                          f"{', '.join(plan.mesh) or 'no mesh evaluator'}; fix: add --evaluator dtu_chamfer")
    options = {name: {"frame": args.frame, **culling.get(name, {}), **({"mode": "pcd"} if args.points else {})}
               for name in plan.mesh}
    results = evaluate_mesh_file(Path(args.mesh), scene, plan.mesh, options, progress=stage) if plan.mesh else \
        {"mesh": args.mesh, "scene": scene.name, "results": {}}
    results["skipped"] = {n: r for n, r in plan.skipped.items() if n != "image"}
    print(format_table(results))
    if args.out:
        write_json_atomic(Path(args.out), results)
        print(f"results written to {args.out}")
    return 0
