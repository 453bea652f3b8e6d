"""The ``gsbench`` command line: argparse sub-commands, each importing its heavy modules lazily.

Errors derived from `GsbenchError` print as one line (what was found, what was expected, the fix)
and exit with status 2; ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from gsbench.atomic import atomic_path, check_writable
from gsbench.errors import ConfigError, DataError, GsbenchError, Interrupted
from gsbench.resources import set_threads


def threads_count(text: str) -> int:
    """``--threads``: an integer >= 0 (0: every core), else argparse's usage error."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0 (0: every core), got {text!r}")
    return value


def cmd_list(args) -> int:
    from gsbench.config.suites import load_suite, suite_names
    from gsbench.data.synthetic.builtin import BUILTIN_SCENES
    from gsbench.registry import EVALUATORS, METHODS

    print("methods:    " + (", ".join(METHODS.names()) or "(none registered yet)"))
    print("evaluators: " + ", ".join(EVALUATORS.names()))
    print("scenes (format, the object's mean share of each image, description):")
    for scene in BUILTIN_SCENES.values():
        print(f"  {scene.name:<24} {scene.format:<4} {scene.share:>5.1%}  {scene.description}")
    print("suites (gsbench sweep FILE --suite NAME):")
    for name in suite_names():
        suite = load_suite(name)
        print(f"  {name:<24} {len(suite.scenes)} scenes × seeds {', '.join(map(str, suite.seeds))}: "
              f"{', '.join(suite.scenes)}")
    return 0


def cmd_scene_make(args) -> int:
    from gsbench.data.loader import check_scene
    from gsbench.data.synthetic.make import make_mesh_scene, make_scene

    common = {"out": args.out, "res": args.res, "seed": args.seed, "supersample": args.supersample}
    if args.mesh:
        if args.name:
            raise ConfigError(f"scene make: give a built-in name or --mesh, not both (got {args.name!r} and --mesh {args.mesh})")
        path = make_mesh_scene(args.mesh, fmt=args.format or "dtu-colmap", framing=args.framing or "dtu", up=args.up,
                               yaw=args.yaw, albedo=args.albedo, largest_part=args.largest_part, smooth=args.smooth, **common)
    elif args.name:
        path = make_scene(args.name, fmt=args.format, framing=args.framing, **common)
    else:
        raise ConfigError("scene make: give a built-in name (gsbench list) or --mesh FILE")
    print(f"scene written to {path}")
    print(json.dumps(check_scene(path), indent=2, default=str))
    return 0


def cmd_scene_check(args) -> int:
    from gsbench.data.loader import check_scene

    report = check_scene(Path(args.dir), gt_root=args.gt)
    print(json.dumps(report, indent=2, default=str))
    return 0 if report["ok"] else 1


def cmd_scene_floor(args) -> int:
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


def cmd_config(args) -> int:
    import yaml

    from gsbench.config.checks import check_run_config
    from gsbench.config.run_config import resolve
    from gsbench.registry import METHODS

    method_cls = METHODS.get(args.method)
    cfg = resolve(
        args.method,
        args.scene,
        preset=args.preset,
        user_files=args.config or (),
        overrides=args.set or (),
        method_config_cls=getattr(method_cls, "Config", None),
        seed=args.seed,
        gt=args.gt,
    )
    check_run_config(cfg)
    print(f"# run id {cfg.run_id}")
    print(yaml.safe_dump(cfg.to_dict(), sort_keys=False), end="")
    return 0


def cmd_run(args) -> int:
    from gsbench.runs.runner import resolve_run, run

    cfg = resolve_run(args.method, args.scene, preset=args.preset, user_files=args.config or (),
                      overrides=args.set or (), seed=args.seed, gt=args.gt)
    if args.out is not None:
        cfg.out = args.out
    if args.threads is not None:
        cfg.threads = args.threads
    run(cfg)
    return 0


def cmd_sweep(args) -> int:
    from gsbench.runs.executors import make_executor, threads_per_run
    from gsbench.runs.sweep import expand, format_runs, load_sweep, run_sweep, with_suite

    sweep = with_suite(load_sweep(args.config), args.suite, args.seeds)
    runs = expand(sweep, overrides=args.set or ())
    print(f"# sweep {sweep['name']}: {len(runs)} runs")
    if args.dry_run:
        print(format_runs(runs))
        return 0
    for folder in sorted({args.out or r.config.out for r in runs}):
        check_writable(folder, "--out (or out: in the sweep's base)")
    settings = sweep.get("executor", {})
    workers = args.workers or settings.get("workers", 1)
    threads = threads_per_run(args.threads or settings.get("threads") or max(r.config.threads for r in runs), workers)
    with make_executor(args.executor or settings.get("kind", "local"), workers=workers, threads=threads,
                       address=args.address or settings.get("address")) as executor:
        summary = run_sweep(runs, executor, name=sweep["name"], description=sweep.get("description", ""),
                            file=args.config, out=args.out, threads=threads, other_code=args.other_code)
    if summary.interrupted:
        return 130
    return 1 if summary.counts["failed"] else 0


def cmd_eval(args) -> int:
    from gsbench.config.run_config import dataset_of
    from gsbench.data.loader import load_scene
    from gsbench.data.synthetic.make import ensure_scene
    from gsbench.evaluators.api import evaluate_mesh_file, format_table
    from gsbench.evaluators.resolve import plan_evaluation, run_options
    from gsbench.runs.records import write_json_atomic

    if not Path(args.mesh).is_file():
        raise DataError(f"{args.mesh}: mesh file not found; fix: --mesh names a .ply (a run folder's mesh.ply)")
    size = {"downscale": args.downscale, "max_size": args.max_size or (), "gt_root": args.gt}
    ensure_scene(args.scene)
    header = load_scene(args.scene, load_images=False, **size)
    if args.out:
        check_writable(Path(args.out).parent, "--out")  # before the evaluation, not after it
    plan = plan_evaluation(header, dataset_of(args.scene), args.evaluator or (), held_out=0)
    scene = load_scene(args.scene, **size)
    culling = run_options(args.dtu_culling, plan.mesh)
    if args.points and set(plan.mesh) != {"dtu_chamfer"}:
        raise ConfigError(f"--points: only dtu_chamfer scores a point cloud, this evaluation has "
                          f"{', '.join(plan.mesh) or 'no mesh evaluator'}; fix: add --evaluator dtu_chamfer")
    options = {name: {"frame": args.frame, **culling.get(name, {}), **({"mode": "pcd"} if args.points else {})}
               for name in plan.mesh}
    results = evaluate_mesh_file(Path(args.mesh), scene, plan.mesh, options) if plan.mesh else \
        {"mesh": args.mesh, "scene": scene.name, "results": {}}
    results["skipped"] = {n: r for n, r in plan.skipped.items() if n != "image"}
    print(format_table(results))
    if args.out:
        write_json_atomic(Path(args.out), results)
        print(f"results written to {args.out}")
    return 0


def cmd_bench(args) -> int:
    from gsbench.bench import run_benchmark

    return run_benchmark(args)


def cmd_depth(args) -> int:
    from gsbench.diagnostics.depth_check import check_run_depth, format_rows

    rows = check_run_depth(Path(args.run_dir), args.views)
    print(f"{args.run_dir}: the depth the TSDF fuses against the scene's exact depth on the object mask "
          "(e = (d − d*) / d*; e > 0: behind the surface)")
    print(format_rows(rows))
    return 0


def cmd_gaussians(args) -> int:
    from gsbench.diagnostics.gaussian_placement import format_placement, run_placement

    regions, within = run_placement(Path(args.run_dir), args.within)
    print(f"{args.run_dir}: the Gaussian centres against the scene's exact surfaces (within {within:.4g} dataset "
          "units of the object; of the environment; farther than that from every surface)")
    print(format_placement(regions))
    return 0


def cmd_render(args) -> int:
    from gsbench.report.surfaces import surface_picture

    out = Path(args.out) if args.out else Path(args.run_dir) / "surface.png"
    check_writable(out.parent, "--out")
    picture = surface_picture(Path(args.run_dir))
    with atomic_path(out, keep_suffix=True) as tmp:
        tmp.write_bytes(picture.png)
    print(f"{out}: {picture.width}x{picture.height} PNG, {len(picture.png) // 1024} KiB (the report's picture of this run)")
    return 0


def cmd_report(args) -> int:
    from gsbench.report.build import write_report

    check_writable(args.out, "--out")
    written = write_report(Path(args.runs_dir), Path(args.out), plots=not args.no_plots,
                           warn=lambda message: print(f"gsbench: warning: {message}", file=sys.stderr))
    plots = sum(1 for p in written if p.suffix == ".png")
    print(f"report written to {args.out}: " + ", ".join(p.name for p in written if p.suffix != ".png")
          + (f" and {plots} plot{'s' if plots > 1 else ''} in plots/" if plots else ""))
    return 0


GT_HELP = ("folder holding the ground truth when it is not beside the scene: DTU's Points/ and ObsMask/ "
           "(the official SampleSet), or a TnT scene's .ply, .json, _trans.txt and _COLMAP_SfM.log")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gsbench", description="Benchmark surface-reconstruction Gaussian splatting.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    parser.add_argument("--threads", type=threads_count, default=None, help="OpenMP / torch threads (0 = all)")
    sub = parser.add_subparsers(dest="command", required=True)

    sub.add_parser("list", help="methods, evaluators and built-in scenes").set_defaults(func=cmd_list)

    scene = sub.add_parser("scene", help="make or check scene folders").add_subparsers(dest="scene_command", required=True)
    make = scene.add_parser("make", help="generate a built-in synthetic scene, or a scene of any mesh file")
    make.add_argument("name", nargs="?", help="e.g. synthetic/spot (see `gsbench list`); or give --mesh")
    make.add_argument("--mesh", metavar="FILE", help="a mesh file (obj, ply, glb, gltf, off, stl): the object on the table "
                                                     "in a room (DTU layouts) or on the ground (tnt), exact ground truth")
    make.add_argument("--framing", default=None,
                      help="dtu (the object fills 34%% of each image, as on DTU), small (12.6%%, the first synthetic "
                           "scenes) or a share in (0, 1); default: dtu for --mesh, the scene's own for built-ins")
    make.add_argument("--up", default="y", choices=("x", "y", "z", "-x", "-y", "-z"), help="--mesh: the file's up axis")
    make.add_argument("--yaw", type=float, default=0.0, help="--mesh: turn the object about up by this many degrees "
                                                             "(the DTU cameras look from +y)")
    make.add_argument("--albedo", default="auto", help="--mesh: auto (the file's texture or colours, else procedural), "
                                                       "file, or a named albedo: procedural, uniform, painted, wood, "
                                                       "glaze, fine, stone")
    make.add_argument("--largest-part", action="store_true", help="--mesh: keep only the largest connected part")
    make.add_argument("--smooth", type=int, default=0, metavar="N",
                      help="--mesh: N iterations of Taubin smoothing (takes a scan's fine relief off, keeps its shape)")
    make.add_argument("--format", choices=("dtu", "dtu-colmap", "tnt"), default=None,
                      help="layout (default: the scene's own; dtu-colmap for --mesh)")
    make.add_argument("--out", default=None, help="folder (default: the cache, $GSBENCH_DATA)")
    make.add_argument("--res", type=int, nargs=2, metavar=("W", "H"), default=None, help="image size")
    make.add_argument("--seed", type=int, default=0)
    make.add_argument("--supersample", type=int, default=None,
                      help="rays per pixel side of the images (2: area-sampled; 1: the pixel centre only)")
    make.set_defaults(func=cmd_scene_make)
    check = scene.add_parser("check", help="validate a scene folder and print what was found (reads no pixels)")
    check.add_argument("dir")
    check.add_argument("--gt", default=None, help=GT_HELP)
    check.set_defaults(func=cmd_scene_check)
    floor = scene.add_parser("floor", help="the meshing floor: TSDF of a synthetic scene's exact depth, evaluated")
    floor.add_argument("name", help="a built-in scene, e.g. synthetic/dtu-spot")
    floor.add_argument("--preset", default="cpu", help="resolution and mesh settings as a run with this preset")
    floor.add_argument("--set", action="append", metavar="KEY=VALUE", help="override, e.g. mesh.voxel_size=0.002")
    floor.add_argument("--out", default="runs/floor", help="folder for floor.ply and floor.json")
    floor.set_defaults(func=cmd_scene_floor)

    config = sub.add_parser("config", help="print the resolved config of a run")
    config.add_argument("--method", required=True)
    config.add_argument("--scene", default="synthetic/spot")
    config.add_argument("--preset", default="cpu")
    config.add_argument("--config", action="append", help="user YAML file (repeatable)")
    config.add_argument("--set", action="append", metavar="KEY=VALUE", help="override, e.g. train.iterations=500")
    config.add_argument("--seed", type=int, default=None)
    config.add_argument("--gt", default=None, help=GT_HELP)
    config.set_defaults(func=cmd_config)

    run = sub.add_parser("run", help="train a method on a scene, extract its mesh, evaluate it, write the record")
    run.add_argument("--method", required=True, help="e.g. 2dgs (see `gsbench list`)")
    run.add_argument("--scene", required=True, help="built-in name (synthetic/spot) or a scene folder "
                                                    "(a suite of scenes runs as a sweep: gsbench sweep FILE --suite NAME)")
    run.add_argument("--preset", default="cpu", help="budget: quick, cpu (default), bench or paper")
    run.add_argument("--config", action="append", help="user YAML file (repeatable)")
    run.add_argument("--set", action="append", metavar="KEY=VALUE", help="override, e.g. train.iterations=500")
    run.add_argument("--out", default=None, help="runs folder (default: the config's out, runs/)")
    run.add_argument("--seed", type=int, default=None)
    run.add_argument("--gt", default=None, help=GT_HELP)
    run.add_argument("--threads", type=threads_count, default=argparse.SUPPRESS, help="OpenMP / torch threads (0 = all)")
    run.set_defaults(func=cmd_run)

    sweep = sub.add_parser("sweep", help="expand a sweep file (configs/sweeps/) and run its runs, skipping finished ones")
    sweep.add_argument("config", help="sweep YAML file")
    sweep.add_argument("--dry-run", action="store_true", help="validate and print the runs and their ids only")
    sweep.add_argument("--other-code", choices=("refuse", "rerun", "keep"), default="refuse",
                       help="finished records made by another code version (commit): refuse to mix them (default), "
                            "run them again, or keep them (the report flags boards that mix versions)")
    sweep.add_argument("--suite", default=None, metavar="NAME",
                       help="run over this suite's scenes (configs/suites/, see `gsbench list`) instead of the "
                            "file's; seeds: the file's, else the suite's")
    sweep.add_argument("--seeds", type=int, nargs="+", default=None, metavar="SEED",
                       help="seeds of every run, replacing the file's and the suite's")
    sweep.add_argument("--set", action="append", metavar="KEY=VALUE", help="override for every run, e.g. train.iterations=1000")
    sweep.add_argument("--out", default=None, help="runs folder (default: each run's config out, runs/)")
    sweep.add_argument("--threads", type=threads_count, default=argparse.SUPPRESS,
                       help="OpenMP / torch threads per run (default: the sweep file's executor.threads, "
                            "else the cores divided among the workers)")
    sweep.add_argument("--executor", choices=("local", "ray"), default=None,
                       help="local processes or Ray (pip install \"gsbench[ray]\"); "
                            "default: the sweep file's executor.kind, else local")
    sweep.add_argument("--workers", type=int, default=None,
                       help="runs at a time: local processes, or a local Ray cluster of workers × threads CPUs "
                            "(default: the sweep file's executor.workers, else 1)")
    sweep.add_argument("--address", default=None,
                       help="the Ray cluster to connect to, e.g. auto (default: start a local one)")
    sweep.set_defaults(func=cmd_sweep)

    evaluate = sub.add_parser("eval", help="evaluate a mesh against a scene's ground truth")
    evaluate.add_argument("--mesh", required=True)
    evaluate.add_argument("--scene", required=True)
    evaluate.add_argument("--evaluator", action="append",
                          help="evaluator name (repeatable; default: the dataset's, those the scene can feed)")
    evaluate.add_argument("--frame", choices=("normalised", "dataset"), default="normalised",
                          help="frame of the mesh: normalised (what gsbench methods write) or dataset (DTU mm world, TnT COLMAP)")
    evaluate.add_argument("--downscale", type=float, default=1.0,
                          help="load the scene's images downscaled (the run's data.downscale): sets the pixel "
                               "footprint surface_offset reports in")
    evaluate.add_argument("--max-size", type=int, nargs=2, metavar=("LONG", "SHORT"), default=None,
                          help="fit the images in this many pixels (the run's data.max_size; the cpu preset's is "
                               "240 150): the resolution silhouette compares masks at")
    evaluate.add_argument("--gt", default=None, help=GT_HELP)
    evaluate.add_argument("--dtu-culling", choices=("2dgs", "gof", "none"), default="2dgs",
                          help="mask culling before the DTU protocol (dtu_chamfer, normal_similarity): 2DGS's "
                               "disk(24) at 1600 px (default), GOF's disk(6) at the masks' resolution, or none")
    evaluate.add_argument("--points", action="store_true",
                          help="the file is a point cloud: score its points as they are (dtu_chamfer's mode pcd; "
                               "only dtu_chamfer takes one)")
    evaluate.add_argument("--out", default=None, help="write the results JSON here")
    evaluate.set_defaults(func=cmd_eval)

    bench = sub.add_parser("bench", help="fixed-workload benchmarks")
    bench.add_argument("target", choices=("train", "raster", "eval", "ibgs"))
    bench.add_argument("--kernels", nargs="+", default=None)
    bench.add_argument("--workloads", nargs="+", default=None,
                       help="e.g. 50k-400x300 200k-800x600 (raster); 3dgs 2dgs gof radegs ibgs sugar 3dgs-random-100k (train)")
    bench.add_argument("--run", default=None, metavar="RUN_DIR",
                       help="time a run's own steps from its checkpoint instead of a workload (train)")
    bench.add_argument("--steps", type=int, default=30, help="timed training steps per workload (train)")
    bench.add_argument("--warmup", type=int, default=10, help="untimed training steps before them (train)")
    bench.add_argument("--repeats", type=int, default=5)
    bench.add_argument("--sizes", type=int, nargs="+", default=None, help="Gaussian counts (ibgs; default 10000 100000)")
    bench.add_argument("--vertices", type=int, default=1_000_000, help="mesh size (eval)")
    bench.add_argument("--gt-points", type=int, default=2_000_000, help="GT size (eval)")
    bench.add_argument("--json", default=None, help="also write the result as JSON")
    bench.set_defaults(func=cmd_bench)

    depth = sub.add_parser("depth", help="a finished run's depth against its synthetic scene's exact depth, per view")
    depth.add_argument("run_dir", metavar="RUN_DIR", help="the run's folder (<out>/<dataset>/<scene>/<method>/<run_id>)")
    depth.add_argument("--views", type=int, nargs="+", default=[0, 10, 20, 30, 40], help="view indices (default: 0 10 20 30 40)")
    depth.set_defaults(func=cmd_depth)

    gaussians = sub.add_parser("gaussians", help="where a finished run's Gaussians are: on the object, on the "
                               "environment or in free space (synthetic scenes)")
    gaussians.add_argument("run_dir", metavar="RUN_DIR", help="the run's folder (<out>/<dataset>/<scene>/<method>/<run_id>)")
    gaussians.add_argument("--within", type=float, default=None,
                           help="distance to a surface that counts as on it, dataset units (default: 1.5%% of the "
                                "object's bounding-box diagonal)")
    gaussians.set_defaults(func=cmd_gaussians)

    render = sub.add_parser("render", help="a finished run's mesh shaded from two fixed views beside the ground truth "
                            "(or the photos with their masks) and coloured by its distance to it: the report's picture")
    render.add_argument("run_dir", metavar="RUN_DIR", help="the run's folder (<out>/<dataset>/<scene>/<method>/<run_id>)")
    render.add_argument("--out", default=None, help="PNG file to write (default: RUN_DIR/surface.png)")
    render.set_defaults(func=cmd_render)

    report = sub.add_parser("report", help="leaderboard tables, speed-vs-error plots and sweep ablations from run records")
    report.add_argument("runs_dir", metavar="RUNS_DIR", help="runs folder (searched recursively for record.json)")
    report.add_argument("--out", default="report", help="output folder (default: report/)")
    report.add_argument("--no-plots", action="store_true", help="skip the matplotlib plots (no PNGs, no figures)")
    report.set_defaults(func=cmd_report)
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


if __name__ == "__main__":
    sys.exit(main())
