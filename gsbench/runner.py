"""One run as cached stages: load → train → extract → evaluate → record (DESIGN.md §1, frameworks §3.4–3.5).

Folder: ``<out>/<dataset>/<scene>/<method>/<run_id>/`` holding ``config.yaml`` (the resolved config),
``checkpoint.pt`` / ``checkpoint-final.pt`` and ``metrics.jsonl`` (`gsbench.train`), ``mesh.ply``,
``eval.json``, ``stages.json`` (seconds and peak RSS of each stage when it was computed) and
``record.json`` (`gsbench.records.RunRecord`).

A stage is skipped when its output exists (final checkpoint, ``mesh.ply``, ``eval.json``), so running
the same config again resumes it; an interrupted training resumes from ``checkpoint.pt``. The scene is
always loaded; the trained model is loaded from the final checkpoint only when a later stage needs it.
Timings in the record are the stored ones of the invocation that computed each stage (``train``
counts optimisation steps only, over all resumes; ``extract`` and ``evaluate`` likewise exclude the
rest); ``total`` is their sum and ``wall_this_invocation`` the wall time of this call. Peak RSS is the
process high-water mark at the end of each stage (``ru_maxrss`` never decreases, so a stage's value
includes the earlier ones in that process).

Evaluation: the evaluators named in ``eval.evaluators``, else `default_evaluators` of the scene;
``dtu_chamfer`` gets ``cull = eval.dtu_culling``. With ``data.holdout_every > 0`` the held-out views
(``i % holdout_every == 0``, not trained on) are rendered and scored by the ``image`` evaluator
(inside the masks when ``data.use_masks``). A failure anywhere writes the record with status
``failed`` and the traceback tail, then re-raises.
"""

from __future__ import annotations

import json
import time
import traceback
from datetime import datetime, timezone
from pathlib import Path

import torch
import yaml

from gsbench.config import RunConfig, dataset_of, resolve
from gsbench.records import RunRecord, capture_environment, peak_rss_bytes, sha256_file, write_json_atomic
from gsbench.registry import METHODS
from gsbench.train import (FINAL_CHECKPOINT, Trainer, load_checkpoint, scaled_losses, schedule_scale, set_threads,
                           split_views)

MESH = "mesh.ply"
EVAL = "eval.json"
STAGES = "stages.json"
RECORD = "record.json"
ERROR_TAIL_LINES = 30


def resolve_run(method: str, scene: str, *, preset: str = "cpu", user_files=(), overrides=(),
                seed: int | None = None) -> RunConfig:
    """`gsbench.config.resolve` with the method plugin's ``Config`` (its paper defaults)."""
    cls = METHODS.get(method)
    return resolve(method, scene, preset=preset, user_files=user_files, overrides=overrides,
                   method_config_cls=cls.Config, seed=seed)


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


def _evaluate(method, scene, cfg: RunConfig, mesh_path: Path) -> dict:
    from gsbench.evaluators.api import default_evaluators, evaluate_mesh_file, get_evaluator  # noqa: PLC0415

    names = [n for n in (cfg.eval.evaluators or default_evaluators(scene)) if n != "image"]
    options = {"dtu_chamfer": {"cull": cfg.eval.dtu_culling}} if "dtu_chamfer" in names else {}
    report = evaluate_mesh_file(mesh_path, scene, names, options)
    held_out = split_views(len(scene.cameras), cfg.data.holdout_every)[1]
    if held_out:
        with torch.no_grad():
            renders = [method.render(scene.cameras[i], {"rgb"}).rgb.clamp(0, 1).numpy() for i in held_out]
        use_masks = bool(cfg.data.use_masks and scene.masks is not None)
        report["results"]["image"] = get_evaluator("image").evaluate(renders, scene, indices=tuple(held_out),
                                                                     use_masks=use_masks)
    return report


def run(cfg: RunConfig, *, echo=print) -> RunRecord:
    """Run (or resume) every stage of ``cfg``, write and return its record, print the metrics table."""
    from gsbench.evaluators.api import format_table  # noqa: PLC0415

    threads = set_threads(cfg.threads)
    folder = run_dir(cfg)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "config.yaml").write_text(yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    record = RunRecord(run_id=cfg.run_id, method=cfg.method["name"], scene=cfg.scene, dataset=dataset_of(cfg.scene),
                       seed=cfg.seed, config=cfg.to_dict(),
                       losses={"schedule": scaled_losses(cfg.losses, schedule_scale(cfg.train.iterations))},
                       environment=capture_environment(threads))
    stages = _Stages(folder / STAGES)
    start = time.perf_counter()
    try:
        report = _run_stages(cfg, folder, stages, record)
        record.status = "ok"
    except BaseException:
        record.status = "failed"
        record.error_tail = "".join(traceback.format_exc().splitlines(keepends=True)[-ERROR_TAIL_LINES:])
        raise
    finally:
        keys = ("load", "train", "extract", "evaluate")
        record.timings = {k: stages.data[k]["seconds"] for k in keys if k in stages.data}
        record.timings["total"] = sum(record.timings.values())
        record.timings["wall_this_invocation"] = time.perf_counter() - start
        phases = stages.data.get("train", {}).get("phases", {})
        record.timings.update({f"train.{name}": seconds for name, seconds in phases.items()})
        record.peak_rss_bytes = {k: stages.data[k]["peak_rss_bytes"] for k in keys if k in stages.data}
        record.environment["time_end_utc"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        record.write(folder / RECORD)
    echo(format_table(report))
    echo(f"record written to {folder / RECORD}")
    return record


def _run_stages(cfg: RunConfig, folder: Path, stages: _Stages, record: RunRecord) -> dict:
    """The stages proper; fills ``record`` and returns the evaluation report."""
    from gsbench.data.loader import load_scene  # noqa: PLC0415

    t0 = time.perf_counter()
    scene = load_scene(cfg.scene, downscale=cfg.data.downscale)
    stages.done("load", time.perf_counter() - t0)

    method = METHODS.get(cfg.method["name"])()
    method.setup(scene, cfg)
    record.losses["params"] = method.term_params()
    final, mesh_path, eval_path = folder / FINAL_CHECKPOINT, folder / MESH, folder / EVAL
    if not final.is_file():
        result = Trainer(method, scene, cfg, folder).fit()
        stages.done("train", result.seconds, it_per_s=result.it_per_s, num_gaussians=result.num_gaussians,
                    steps=result.steps, phases=result.phases)
    elif not (mesh_path.is_file() and eval_path.is_file()):
        method.load_state_dict(load_checkpoint(final)["method"])

    if not mesh_path.is_file():
        t0 = time.perf_counter()
        size = method.extract_mesh(scene, cfg, mesh_path)
        stages.done("extract", time.perf_counter() - t0, **size)

    if not eval_path.is_file():
        t0 = time.perf_counter()
        write_json_atomic(eval_path, _evaluate(method, scene, cfg, mesh_path))
        stages.done("evaluate", time.perf_counter() - t0)
    report = json.loads(eval_path.read_text())

    train, extract = stages.data["train"], stages.data["extract"]
    record.metrics = _flatten_metrics(report)
    record.eval_protocol = {n: r["protocol"] for n, r in report["results"].items()}
    record.it_per_s, record.num_gaussians = train["it_per_s"], train["num_gaussians"]
    record.mesh = {"path": str(mesh_path), "sha256": sha256_file(mesh_path), "checkpoint": str(final),
                   "vertices": extract["vertices"], "faces": extract["faces"]}
    return report
