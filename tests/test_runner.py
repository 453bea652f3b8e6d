"""The runner (gsbench.runs.runner, ``gsbench run``): quick end-to-end runs per method, cached stages, resume
after an interruption, failure records."""

from __future__ import annotations

import json
import math

import pytest
import trimesh

from gsbench.cli import main
from gsbench.run_folder import RunFolder
from gsbench.runs.records import RunRecord, sha256_file
from gsbench.runs.runner import resolve_run, run_dir
from gsbench.training.trainer import Trainer, load_checkpoint, save_atomic

# Idle OpenMP threads must sleep, not spin (see gsbench.training.trainer.set_threads); set at collection, before
# any test loads the rasterizer extension.
# A TSDF voxel of about one pixel at 64x48 (a finer grid meshes pixel noise and slows evaluation).
QUICK = ["data.downscale=1", "method.random_init_points=2000", "train.iterations=60", "train.checkpoint_every=30",
         "train.log_every=10", "mesh.voxel_size=0.02", "mesh.sdf_trunc=0.08"]


def gsbench_run(method, scene, out, *extra_sets, expect=0):
    sets = [arg for s in (*QUICK, *extra_sets) for arg in ("--set", s)]
    assert main(["run", "--method", method, "--scene", str(scene), "--preset", "quick", "--out", str(out),
                 "--threads", "2", *sets]) == expect
    cfg = resolve_run(method, str(scene), preset="quick", overrides=[*QUICK, *extra_sets])
    cfg.out = str(out)
    return run_dir(cfg)


@pytest.mark.parametrize("method", ["3dgs", "2dgs"])
def test_quick_run_trains_meshes_evaluates_and_records(method, tiny_spot, tmp_path, capsys):
    folder = gsbench_run(method, tiny_spot, tmp_path / "runs")
    assert folder.parent.parent.parent.name == "dtu" and folder.parent.name == method
    record = RunRecord.read(folder / "record.json")
    assert record.status == "ok" and record.method == method and record.run_id == folder.name
    for metric in ("chamfer", "accuracy", "completeness", "normal_consistency"):
        assert math.isfinite(record.metrics[metric]), metric
    assert set(record.timings) >= {"load", "train", "extract", "evaluate", "total", "train_cpu"}
    assert record.timings["train_cpu"] > 0  # the CPU time of the same steps (docs/design.md §8.1)
    assert set(record.peak_rss_bytes) == {"load", "train", "extract", "evaluate"}
    assert record.num_gaussians > 0 and record.it_per_s > 0
    assert record.densify_budget["max_gaussians"] == 20000 and set(record.densify_budget) == {
        "max_gaussians", "first_cut_step", "candidates_cut"}
    assert record.mesh["sha256"] == sha256_file(folder / "mesh.ply") and record.mesh["faces"] > 0
    assert set(record.eval_protocol) == {"dtu_chamfer", "normal_similarity", "silhouette", "mesh_stats"}
    assert record.skipped == {} and record.inputs["resolution"] == [64, 48] and record.inputs["views_held_out"] == 0
    assert {"render", "loss", "backward", "densify", "optimizer", "checks"} <= {
        k.split(".", 1)[1] for k in record.timings if k.startswith("train.")}
    assert record.losses["schedule"]["l1"] == {"weight": 0.8, "start": 0, "end": -1}
    assert record.config["train"]["iterations"] == 60 and record.environment["threads"] == 2
    logged = [json.loads(line) for line in (folder / RunFolder.METRICS).read_text().splitlines()]
    assert [row["step"] for row in logged] == [10, 20, 30, 40, 50, 60]
    assert {"l1", "dssim", "total", "num_gaussians", "it_per_s"} <= set(logged[-1])
    assert (folder / RunFolder.FINAL_CHECKPOINT).is_file() and not (folder / RunFolder.CHECKPOINT).exists()
    assert "chamfer" in capsys.readouterr().out
    if method == "2dgs":
        assert record.losses["schedule"]["normal_consistency"]["start"] == 14  # 7000 · 60/30000
        assert record.losses["params"] == {"normal_consistency": {"depth_ratio": 1.0}}


ONE_EVALUATOR = "eval.evaluators=[dtu_chamfer]"  # the stage tests need one metric, not every protocol


def test_second_run_skips_every_finished_stage(tiny_spot, tmp_path, monkeypatch):
    folder = gsbench_run("3dgs", tiny_spot, tmp_path / "runs", ONE_EVALUATOR)
    first = RunRecord.read(folder / "record.json")

    def must_not_run(*args, **kwargs):
        raise AssertionError("a finished stage ran again")

    monkeypatch.setattr(Trainer, "fit", must_not_run)
    monkeypatch.setattr("gsbench.methods.base.Method.extract_mesh", must_not_run)
    monkeypatch.setattr("gsbench.runs.runner._evaluate", must_not_run)
    gsbench_run("3dgs", tiny_spot, tmp_path / "runs", ONE_EVALUATOR)
    second = RunRecord.read(folder / "record.json")
    assert second.status == "ok" and second.metrics == first.metrics and second.mesh == first.mesh
    assert second.timings["train"] == first.timings["train"]


def test_eval_stage_reruns_from_the_final_checkpoint_when_its_output_is_missing(tiny_spot, tmp_path, monkeypatch):
    folder = gsbench_run("2dgs", tiny_spot, tmp_path / "runs", ONE_EVALUATOR)
    first = RunRecord.read(folder / "record.json")
    first_vertices = sorted(map(tuple, trimesh.load(folder / "mesh.ply", process=False).vertices.round(6)))
    (folder / "mesh.ply").unlink()
    (folder / "eval.json").unlink()
    monkeypatch.setattr(Trainer, "fit", lambda self: pytest.fail("training ran again"))
    gsbench_run("2dgs", tiny_spot, tmp_path / "runs", ONE_EVALUATOR)
    second = RunRecord.read(folder / "record.json")
    # The same trained model gives the same surface; open3d's parallel hash map orders the vertices
    # differently each time, so compare sorted vertices, not the file hash.
    assert second.mesh["faces"] == first.mesh["faces"]
    assert sorted(map(tuple, trimesh.load(folder / "mesh.ply", process=False).vertices.round(6))) == first_vertices
    # The evaluators sample the mesh in vertex order, so the scores move slightly with that order.
    assert second.metrics["chamfer"] == pytest.approx(first.metrics["chamfer"], rel=2e-2)


def interrupted_at_step_45(scene, out, monkeypatch):
    """A quick 3DGS run stopped by Ctrl-C at step 45 (its checkpoint is at 30); returns its resolved config."""
    step = Trainer.train_step

    def interrupt_at_45(self, t):
        if t == 45:
            raise KeyboardInterrupt
        return step(self, t)

    monkeypatch.setattr(Trainer, "train_step", interrupt_at_45)
    gsbench_run("3dgs", scene, out, ONE_EVALUATOR, expect=130)  # the CLI's Ctrl-C exit code
    monkeypatch.undo()
    cfg = resolve_run("3dgs", str(scene), preset="quick", overrides=[*QUICK, ONE_EVALUATOR])
    cfg.out = str(out)
    return cfg


def test_interrupted_training_resumes_from_its_checkpoint(tiny_spot, tmp_path, monkeypatch):
    cfg = interrupted_at_step_45(tiny_spot, tmp_path / "runs", monkeypatch)
    folder = run_dir(cfg)
    assert RunRecord.read(folder / "record.json").status == "interrupted"  # resumable, not a failure
    assert (folder / RunFolder.CHECKPOINT).is_file()
    gsbench_run("3dgs", tiny_spot, tmp_path / "runs", ONE_EVALUATOR)
    assert RunRecord.read(folder / "record.json").status == "ok"
    logged = [json.loads(line)["step"] for line in (folder / RunFolder.METRICS).read_text().splitlines()]
    assert logged == [10, 20, 30, 40, 50, 60]  # the line of step 40 (after the checkpoint at 30) is not repeated
    assert RunRecord.read(folder / "record.json").timings["train_cpu"] > 0  # carried over the resume


def test_resume_from_a_checkpoint_without_cpu_time_records_none(tiny_spot, tmp_path, monkeypatch):
    """A checkpoint written before `timings.train_cpu` existed: the steps before it have no CPU time, so the record
    gives none rather than the part after the resume as if it were the whole."""
    cfg = interrupted_at_step_45(tiny_spot, tmp_path / "runs", monkeypatch)
    checkpoint = run_dir(cfg) / RunFolder.CHECKPOINT
    state = load_checkpoint(checkpoint)
    del state["cpu_seconds"]
    save_atomic(state, checkpoint)
    gsbench_run("3dgs", tiny_spot, tmp_path / "runs", ONE_EVALUATOR)
    record = RunRecord.read(run_dir(cfg) / "record.json")
    assert record.status == "ok" and "train_cpu" not in record.timings and record.timings["train"] > 0


def test_failure_writes_a_failed_record_and_exits_non_zero(tiny_spot, tmp_path, capsys):
    folder = gsbench_run("3dgs", tiny_spot, tmp_path / "runs", "method.random_init_points=0", expect=2)
    record = RunRecord.read(folder / "record.json")
    assert record.status == "failed"
    assert "random_init_points must be > 0" in record.error_tail
    assert "load" in record.timings and "train" not in record.timings
    assert "random_init_points" in capsys.readouterr().err
