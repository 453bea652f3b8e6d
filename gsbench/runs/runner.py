"""One run as cached stages: load → train → extract → evaluate → record (docs/design.md §1, §8).

Folder: ``<out>/<dataset>/<scene>/<method>/<run_id>/`` holding ``config.yaml`` (the resolved config),
``checkpoint.pt`` / ``checkpoint-final.pt`` and ``metrics.jsonl`` (`gsbench.training.trainer`), ``mesh.ply``,
``eval.json``, ``stages.json`` (seconds and peak RSS of each stage when it was computed), ``points/`` and
``record.json`` (`gsbench.runs.records.RunRecord`).

A stage is skipped when its output exists (final checkpoint, ``mesh.ply``, ``eval.json``), so running
the same config again resumes it, and says from where; an interrupted training resumes from ``checkpoint.pt``.
The record keeps the run's first start (``environment.time_utc``) over resumes and reruns. The scene is
always loaded; the trained model is loaded from the final checkpoint only when a later stage needs it.
Timings in the record are the stored ones of the invocation that computed each stage (``train``
counts optimisation steps only, over all resumes; ``extract`` and ``evaluate`` likewise exclude the
rest); ``total`` is their sum and ``wall_this_invocation`` the wall time of this call; ``train_cpu`` is
training's CPU time (`gsbench.training.trainer.TrainResult.cpu_seconds`). Peak RSS is the
process high-water mark at the end of each stage (``ru_maxrss`` never decreases, so a stage's value
includes the earlier ones in that process).

Evaluation is planned before anything is loaded (`gsbench.evaluators.resolve.plan_evaluation` on the
scene read without its images): ``eval.evaluators`` when named (each must apply, else an error before
loading), else the dataset's defaults, each skipped with its reason in the record (``skipped``) when
the scene lacks what it needs, so a capture without ground truth runs to ``ok``. ``dtu_chamfer`` gets
``cull = eval.dtu_culling`` (2dgs, gof or none; `gsbench.evaluators.culling`), as does ``normal_similarity``
on DTU scenes. The held-out views (``data.holdout_every``; by default every 8th view of
a scene without ground truth) are rendered and scored by the ``image`` evaluator (inside the masks
when ``data.use_masks``). ``eval.json`` is recomputed when the plan differs from the one it holds
(e.g. ``--gt`` given after a first run). A failure anywhere after the plan writes the record with
status ``failed`` and the traceback tail, then re-raises.

Anytime evaluation (``eval.points``, docs/training.md §9): at each point step of the main training stage the
Trainer hands the model to `_evaluate_point`, which extracts and evaluates it as the end does into
``points/<step>/`` and writes its row last (``points/<step>.json``), failed with its reason when extraction
or evaluation raises (a full disk stops the run instead); a point whose row exists is not taken again. The record's ``points`` are those rows
and the final point (`gsbench.runs.records.final_point`).

The method is set up, trained and meshed on the scene with its ground truth hidden
(`gsbench.data.method_scene.scene_for_method`: reading it raises `GroundTruthRead`); only evaluation reads it.

Progress: one line per stage on stderr (`gsbench.training.progress.stage`), and training's own progress lines
when stderr is not a terminal.
"""

from __future__ import annotations

import dataclasses
import json
import signal
import threading
import time
import traceback
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path

import torch
import yaml

from gsbench.atomic import DiskFullError, atomic_path, check_writable_files, disk_full_error
from gsbench.config.checks import check_run_config
from gsbench.config.run_config import RunConfig, dataset_of, point_steps, resolve
from gsbench.data.cache import scene_dir
from gsbench.data.loader import load_scene
from gsbench.data.method_scene import scene_for_method
from gsbench.data.synthetic.builtin import builtin_name
from gsbench.data.synthetic.make import ensure_scene
from gsbench.errors import Interrupted, one_line
from gsbench.evaluators.api import evaluate_mesh_file, format_table
from gsbench.evaluators.resolve import get_evaluator, plan_evaluation, run_options
from gsbench.registry import METHODS
from gsbench.resources import peak_rss_bytes, set_threads
from gsbench.run_folder import RunFolder
from gsbench.runs.records import (RunRecord, capture_environment, check_folder_identity, check_folder_switches,
                                  final_point, sha256_file, write_json_atomic)
from gsbench.runs.run_lock import run_lock
from gsbench.switches import departures
from gsbench.training.progress import stage
from gsbench.training.trainer import Trainer, TrainResult, load_checkpoint, scaled_losses, schedule_scale

ERROR_TAIL_LINES = 30
OUT_OPTION = "--out (or out: in a config file)"  # the setting that chooses where a run writes
POINT_METRICS_SHOWN = 3  # metrics in a point's progress line


def resolve_run(method: str, scene: str, *, preset: str = "cpu", user_files=(), overrides=(),
                seed: int | None = None, gt: str | None = None, recorded: dict | None = None) -> RunConfig:
    """`gsbench.config.run_config.resolve` with the method plugin's ``Config`` (its paper defaults)."""
    cls = METHODS.get(method)
    return resolve(method, scene, preset=preset, user_files=user_files, overrides=overrides,
                   method_config_cls=cls.Config, seed=seed, gt=gt, recorded=recorded)


def resolve_recorded(resolved: dict) -> RunConfig:
    """The `RunConfig` a finished run was run with, from the resolved config it wrote (``config.yaml``), the
    fields added after it at the values it ran with (`resolve`'s ``recorded``)."""
    return resolve_run(resolved["method"]["name"], resolved["scene"], preset=resolved["preset"], recorded=resolved)


def make_run_scene(cfg: RunConfig) -> None:
    """The step before loading: ``cfg``'s built-in scene made when its folder is missing or holds another version
    of it (`ensure_scene`, what ``gsbench scene make`` runs), with a progress line on its first use."""
    name = builtin_name(cfg.scene)
    if name is not None and not scene_dir(name).is_dir():
        stage(f"making {name} (first use; `gsbench scene make {name}` makes it ahead)")
    ensure_scene(cfg.scene)


def load_run_scene(cfg: RunConfig, *, load_images: bool = True):
    """The scene of ``cfg`` at its resolution (``data.downscale``, ``data.max_size``), in its training frame
    (``data.tnt_frame``), with its ``--gt``; a built-in scene must have been made (`make_run_scene`)."""
    return load_scene(cfg.scene, downscale=cfg.data.downscale, max_size=cfg.data.max_size,
                      load_images=load_images, gt_root=cfg.gt or None, holdout_every=cfg.data.holdout_every,
                      tnt_frame=cfg.data.tnt_frame)


def plan_run_evaluation(cfg: RunConfig, scene):
    """`plan_evaluation` of ``cfg``'s evaluators on ``scene`` (loaded with or without images)."""
    return plan_evaluation(scene, dataset_of(cfg.scene), cfg.eval.evaluators, len(scene.held_out_views))


def scene_inputs(scene, cfg: RunConfig) -> dict:
    """The record's ``inputs``: what the run trains on (`gsbench.runs.records` module docstring)."""
    cam = scene.cameras[0]
    return {"resolution": [cam.width, cam.height], "source_resolution": list(scene.source_size or ()),
            "downscale": scene.downscale, "views_trained": len(scene.train_views), "views_held_out": len(scene.held_out_views),
            "masks": scene.has_masks, "sfm_points": 0 if scene.points is None else int(len(scene.points)),
            "ground_truth": None if scene.gt is None else str(scene.gt.root)}


def run_dir(cfg: RunConfig) -> Path:
    """``<out>/<dataset>/<scene name>/<method>/<run_id>`` (the scene name is its last path part)."""
    scene_name = Path(str(cfg.scene).rstrip("/")).name
    return Path(cfg.out) / dataset_of(cfg.scene) / scene_name / cfg.method["name"] / cfg.run_id


class _Stages:
    """``stages.json``: per stage {seconds, peak_rss_bytes}, written when the stage completes."""

    def __init__(self, path: Path):
        self.path = path
        self.data = json.loads(path.read_text()) if path.is_file() else {}

    def done(self, name: str, seconds: float, **extra) -> None:
        self.data[name] = {"seconds": float(seconds), "peak_rss_bytes": peak_rss_bytes(), **extra}
        write_json_atomic(self.path, self.data)


def _flatten_metrics(report: dict) -> dict:
    """{metric: value} over evaluators; a name two evaluators share is prefixed with the evaluator."""
    flat: dict = {}
    for name, res in report["results"].items():
        for metric, value in res["metrics"].items():
            flat[f"{name}.{metric}" if metric in flat else metric] = value
    return flat


def _evaluate(method, scene, cfg: RunConfig, mesh_path: Path, plan) -> dict:
    options = run_options(cfg.eval.dtu_culling, plan.mesh, cfg.eval.dtu_sampled)
    report = evaluate_mesh_file(mesh_path, scene, plan.mesh, options, progress=stage) if plan.mesh else \
        {"mesh": str(mesh_path), "scene": scene.name, "results": {}}
    report["plan"], report["skipped"] = list(plan.names), plan.skipped
    held_out = scene.held_out_views
    if plan.image:
        with torch.no_grad():
            renders = [method.render_image(scene.cameras[i]).clamp(0, 1).numpy() for i in held_out]
        use_masks = bool(cfg.data.use_masks and scene.masks is not None)
        report["results"]["image"] = get_evaluator("image").evaluate(renders, scene, indices=tuple(held_out),
                                                                     use_masks=use_masks)
    return report


def run(cfg: RunConfig, *, echo=print) -> RunRecord:
    """Run (or resume) every stage of ``cfg``, write and return its record, print the metrics table.

    The configuration is checked (`gsbench.config.checks`), every file the run will write checked writable
    (`gsbench.atomic.check_writable_files`), a run folder that exists checked to be this run's
    (`gsbench.runs.records.check_folder_identity`), a missing built-in scene made (`make_run_scene`) and the
    evaluation planned before anything else is read or written; the run folder is locked while this process works
    in it (`gsbench.runs.run_lock`). Ctrl-C or SIGTERM records status ``interrupted`` (the run resumes from its
    last checkpoint), any other exception ``failed`` with its traceback tail; both re-raise, a full disk as a
    `gsbench.atomic.DiskFullError`."""
    check_run_config(cfg)
    folder = run_dir(cfg)
    check_writable_files(RunFolder(folder).written(point_steps(cfg)), OUT_OPTION)
    check_folder_identity(RunFolder(folder), cfg.to_dict())
    threads = set_threads(cfg.threads)
    for warning in departures():
        stage(f"warning: {warning}")
    make_run_scene(cfg)
    stage(f"{cfg.method['name']} on {cfg.scene}: reading the cameras and planning the evaluation")
    header = load_run_scene(cfg, load_images=False)
    if away := header.check_cameras_face_scene():
        stage(f"warning: {away}")
    plan = plan_run_evaluation(cfg, header)
    for name, reason in plan.skipped.items():
        stage(f"evaluator {name} skipped: {reason}")
    try:
        with run_lock(folder), interrupts_raised():
            return _run_locked(cfg, folder, header, plan, threads, echo)
    except OSError as exc:  # a write that is not atomic_path's (the training log, the lock file)
        full = disk_full_error(exc, exc.filename or folder)
        if full is None:
            raise
        raise full from exc


def _run_locked(cfg: RunConfig, folder: Path, header, plan, threads: int, echo) -> RunRecord:
    """`run` once it holds the folder's lock: the record, the stages, the status."""
    check_folder_switches(RunFolder(folder))
    with atomic_path(RunFolder(folder).config) as tmp:
        tmp.write_text(yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    record = RunRecord(run_id=cfg.run_id, method=cfg.method["name"], scene=cfg.scene, dataset=dataset_of(cfg.scene),
                       seed=cfg.seed, config=cfg.to_dict(),
                       losses={"schedule": scaled_losses(cfg.losses, schedule_scale(cfg.train.iterations))},
                       environment=capture_environment(threads), inputs=scene_inputs(header, cfg),
                       skipped=dict(plan.skipped))
    if RunFolder(folder).record.is_file():  # the run's start: that of its first invocation, kept by resumes and reruns
        first = RunRecord.read(RunFolder(folder).record).environment.get("time_utc")
        record.environment["time_utc"] = first or record.environment["time_utc"]
    stages = _Stages(RunFolder(folder).stages)
    start = time.perf_counter()
    try:
        report = _run_stages(cfg, folder, stages, record, plan)
        record.status = "ok"
    except (KeyboardInterrupt, Interrupted):
        record.status = "interrupted"
        raise
    except BaseException:
        record.status = "failed"
        record.error_tail = "".join(traceback.format_exc().splitlines(keepends=True)[-ERROR_TAIL_LINES:])
        raise
    finally:
        keys = ("load", "train", "refine", "extract", "evaluate")
        record.timings = {k: stages.data[k]["seconds"] for k in keys if k in stages.data}
        record.timings["total"] = sum(record.timings.values())
        record.timings["wall_this_invocation"] = time.perf_counter() - start
        phases = stages.data.get("train", {}).get("phases", {})
        for name in ("train", "refine"):
            if stages.data.get(name, {}).get("cpu_seconds") is not None:
                record.timings[f"{name}_cpu"] = stages.data[name]["cpu_seconds"]
        record.timings.update({f"train.{name}": seconds for name, seconds in phases.items()})
        record.peak_rss_bytes = {k: stages.data[k]["peak_rss_bytes"] for k in keys if k in stages.data}
        record.points = _record_points(cfg, RunFolder(folder), record)
        record.environment["time_end_utc"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        record.write(RunFolder(folder).record)
    echo(format_table(report))
    echo(f"record written to {RunFolder(folder).record}")
    return record


@contextmanager
def interrupts_raised():
    """Turn SIGTERM into `Interrupted` for the block (main thread only: elsewhere signals stay as they are)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def _raise(signum, _frame):
        raise Interrupted(f"signal {signum}")

    previous = signal.signal(signal.SIGTERM, _raise)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _stored_report(eval_path: Path, plan) -> dict | None:
    """``eval.json`` when it holds this plan's evaluators, else None (the stage is recomputed)."""
    if not eval_path.is_file():
        return None
    report = json.loads(eval_path.read_text())
    return report if report.get("plan") == list(plan.names) else None


def _second_stage(method, scene, cfg: RunConfig, second_cfg: RunConfig, sub: RunFolder, stages: _Stages, record: RunRecord):
    """The method's second model (SuGaR's refinement), trained from the first in ``sub`` (its own checkpoints,
    so it resumes like the first) or loaded when it finished; recorded as the ``refine`` stage."""
    stage("building the second stage from the trained model")
    t0, c0 = time.perf_counter(), time.process_time()
    second = method.second_stage(scene, cfg, second_cfg)
    built, built_cpu = time.perf_counter() - t0, time.process_time() - c0
    record.inputs["second_stage"] = second.describe()
    if not sub.final_checkpoint.is_file():
        stage(f"refining: {second_cfg.train.iterations} steps, {len(second.gaussians)} Gaussians")
        result = Trainer(second, scene, second_cfg, sub.path).fit()
        cpu = None if result.cpu_seconds is None else built_cpu + result.cpu_seconds
        stages.done("refine", built + result.seconds, cpu_seconds=cpu, build_seconds=built, it_per_s=result.it_per_s,
                    num_gaussians=result.num_gaussians, steps=result.steps)
    else:
        second.load_state_dict(load_checkpoint(sub.final_checkpoint)["method"])
    return second


def _evaluate_point(method, trained: TrainResult, scene, given, cfg: RunConfig, plan, files: RunFolder) -> None:
    """One point (docs/training.md §9): ``method`` after ``trained.steps`` steps meshed (from ``given``, the scene
    without its ground truth) and evaluated (on ``scene``) as at the end, into ``points/<step>/``; its row
    (`gsbench.runs.records.POINT_KEYS`) written last, failed with its one-line reason when the extractor or an
    evaluator raises. An interruption (Ctrl-C, SIGTERM) stops the run."""
    step, iterations = trained.steps, cfg.train.iterations
    stage(f"point at step {step}/{iterations}: extracting the mesh ({cfg.mesh.extractor}) and evaluating")
    row = {"step": step, "fraction": step / iterations, "final": False, "status": "ok", "error": None,
           "train_seconds": trained.seconds, "train_cpu_seconds": trained.cpu_seconds,
           "num_gaussians": trained.num_gaussians, "metrics": {}, "extract_seconds": 0.0, "evaluate_seconds": 0.0}
    mesh = files.point_mesh(step)
    mesh.parent.mkdir(parents=True, exist_ok=True)
    timed, t0 = "extract_seconds", time.perf_counter()
    try:
        method.extract_mesh(given, cfg, mesh)
        row[timed], timed, t0 = time.perf_counter() - t0, "evaluate_seconds", time.perf_counter()
        report = _evaluate(method, scene, cfg, mesh, plan)
        write_json_atomic(files.point_eval(step), report)
        row["metrics"] = _flatten_metrics(report)
        row[timed] = time.perf_counter() - t0
    except DiskFullError:  # the run stops (and a rerun takes the point), as it would at any other write
        raise
    except Exception as exc:  # noqa: BLE001  the point fails, the run goes on (Ctrl-C and Interrupted are not Exceptions)
        row[timed] = time.perf_counter() - t0
        row.update(status="failed", error=one_line(f"{type(exc).__name__}: {exc}"))
    write_json_atomic(files.point_row(step), row)
    shown = ", ".join(f"{name} {value:.4g}" if isinstance(value, float) else f"{name} {value}"
                      for name, value in list(row["metrics"].items())[:POINT_METRICS_SHOWN])
    stage(f"point at step {step}: {shown if row['status'] == 'ok' else 'failed: ' + row['error']} (extract "
          f"{row['extract_seconds']:.1f} s, evaluate {row['evaluate_seconds']:.1f} s)")


def _record_points(cfg: RunConfig, files: RunFolder, record: RunRecord) -> list[dict]:
    """The record's ``points``: the rows of the points taken, in step order, then the final point when the run is
    ``ok``. A finished run that lacks a point's row (removed after training) says so: only training again takes it."""
    rows = []
    for step in point_steps(cfg):
        if files.point_row(step).is_file():
            rows.append(json.loads(files.point_row(step).read_text()))
        elif record.status == "ok":
            stage(f"warning: {files.point_row(step)} is missing, so the record has no point at step {step}; remove "
                  f"{files.final_checkpoint.name} to train again and take it")
    return [*rows, final_point(record.to_dict())] if record.status == "ok" else rows


def _run_stages(cfg: RunConfig, folder: Path, stages: _Stages, record: RunRecord, plan) -> dict:
    """The stages proper; fills ``record`` and returns the evaluation report."""
    t0 = time.perf_counter()
    cam = record.inputs["resolution"]
    stage(f"loading {record.inputs['views_trained'] + record.inputs['views_held_out']} views at {cam[0]}x{cam[1]}")
    scene = load_run_scene(cfg)
    stages.done("load", time.perf_counter() - t0)

    given = scene_for_method(scene, cfg.method["name"])  # the method trains and meshes without the ground truth
    method = METHODS.get(cfg.method["name"])()
    method.setup(given, cfg)
    record.inputs["initial_gaussians"] = len(method.gaussians)
    record.losses["params"] = method.term_params()
    files = RunFolder(folder)
    final, mesh_path, eval_path = files.final_checkpoint, files.mesh, files.eval
    report = _stored_report(eval_path, plan)
    if not final.is_file():
        if not files.checkpoint.is_file():  # else the Trainer says the step it resumes from
            stage(f"training {cfg.train.iterations} steps from {len(method.gaussians)} Gaussians")
        pending = [step for step in point_steps(cfg) if not files.point_row(step).is_file()]
        result = Trainer(method, given, cfg, folder, points=pending,
                         on_point=lambda model, trained: _evaluate_point(model, trained, scene, given, cfg, plan, files)).fit()
        stages.done("train", result.seconds, cpu_seconds=result.cpu_seconds, it_per_s=result.it_per_s,
                    num_gaussians=result.num_gaussians,
                    steps=result.steps, phases=result.phases, budget=dataclasses.asdict(result.budget))
    elif not (mesh_path.is_file() and report is not None):
        stage(f"resuming after training (step {cfg.train.iterations} of {cfg.train.iterations}) from {final}")
        method.load_state_dict(load_checkpoint(final)["method"])
    else:
        stage(f"finished already: every stage's output is in {folder}; the record is written again from them")

    second_cfg = method.second_stage_config(cfg)
    if second_cfg is not None and not mesh_path.is_file():
        method = _second_stage(method, given, cfg, second_cfg, files.refine, stages, record)

    if not mesh_path.is_file():
        stage(f"extracting the mesh ({cfg.mesh.extractor})")
        t0 = time.perf_counter()
        size = method.extract_mesh(given, cfg, mesh_path)
        stages.done("extract", time.perf_counter() - t0, **size)
        report = None

    if report is None:
        stage(f"evaluating: {', '.join(plan.names) or 'nothing applies'}")
        t0 = time.perf_counter()
        report = _evaluate(method, scene, cfg, mesh_path, plan)
        write_json_atomic(eval_path, report)
        stages.done("evaluate", time.perf_counter() - t0)

    train, extract = stages.data["train"], stages.data["extract"]
    record.metrics = _flatten_metrics(report)
    record.eval_protocol = {n: r["protocol"] for n, r in report["results"].items()}
    record.it_per_s, record.num_gaussians = train["it_per_s"], train["num_gaussians"]
    record.densify_budget = train.get("budget", {})  # stages written before the budget was tracked: none
    described = {k: v for k, v in extract.items() if k not in ("seconds", "peak_rss_bytes")}  # what the extractor told
    record.mesh = {"path": str(mesh_path), "sha256": sha256_file(mesh_path), "checkpoint": str(final), **described}
    return report
