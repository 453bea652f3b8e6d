"""Anytime evaluation (``eval.points``, docs/training.md §9): the points leave training as it was, bit for bit (RNG
streams, model, time); a run stopped at a point resumes to the same record; a failing point is recorded and the run
goes on; the key's validation; the record's points of runs made before them."""

from __future__ import annotations

import hashlib
import json
import pickle
import random
import time
from pathlib import Path

import numpy as np
import pytest
import torch

import gsbench.runs.runner as runner
from gsbench.config.checks import check_run_config
from gsbench.config.run_config import point_steps, run_id
from gsbench.errors import ConfigError
from gsbench.mesh import MeshError
from gsbench.methods.base import Method
from gsbench.run_folder import RunFolder
from gsbench.runs.records import POINT_KEYS, final_point, record_points, sha256_file
from gsbench.runs.runner import resolve_run, run, run_dir
from gsbench.runs.sweep import expand, load_sweep
from gsbench.training.trainer import Trainer, load_checkpoint
from sweep_files import sweep_file

# 60 steps of the quick preset on the 64x48 Spot, densifying every 10 steps up to step 30 (no opacity reset, which
# would empty the model this early), a checkpoint every 15; the mesh's statistics and the held-out views' image
# metrics (render_image) keep the evaluation short.
SETTINGS = ["data.downscale=1", "method.random_init_points=2000", "train.iterations=60", "train.checkpoint_every=15",
            "train.log_every=10", "mesh.voxel_size=0.02", "mesh.sdf_trunc=0.08", "eval.evaluators=[mesh_stats,image]",
            "data.holdout_every=8", "method.refine_every=10", "method.reset_every=100000", "threads=1"]
POINTS = "eval.points=[0.1,0.25,0.5]"  # steps 6, 15 and 30 of 60
STEPS = [6, 15, 30, 60]
# (the DTU-rig board and the ablations that share its runs take two points, configs/sweeps/dtu_rig.yaml)
BOARDS = ("all_methods", "dtu_like", "tnt_like", "dtu_framed", "glass", "bench_dtu", "bench_tnt", "ibgs_k_tnt",
          "ibgs_losses_tnt")


def config(method, scene, out, *extra):
    cfg = resolve_run(method, str(scene), preset="quick", overrides=[*SETTINGS, *extra])
    cfg.out = str(out)
    return cfg


def quick(method, scene, out, *extra):
    return run(config(method, scene, out, *extra), echo=lambda *a: None)


def result(record) -> tuple:
    """What a run produced: its metrics, its Gaussian count, its mesh."""
    return record.metrics, record.num_gaussians, record.mesh["sha256"]


def folder_of(record) -> RunFolder:
    return RunFolder(Path(record.mesh["path"]).parent)


def point_meshes(record) -> dict:
    return {step: sha256_file(folder_of(record).point_mesh(step)) for step in STEPS[:-1]}


def rng_digest() -> str:
    """The python, numpy and torch RNG states, hashed."""
    return hashlib.sha256(pickle.dumps((random.getstate(), np.random.get_state(), torch.get_rng_state().numpy()))).hexdigest()


@pytest.fixture(scope="module")
def runs_3dgs(tiny_spot, tmp_path_factory):
    """(plain, with points) quick 3DGS records, each uninterrupted."""
    threads = torch.get_num_threads()
    out = tmp_path_factory.mktemp("runs")
    records = quick("3dgs", tiny_spot, out / "plain"), quick("3dgs", tiny_spot, out / "points", POINTS)
    torch.set_num_threads(threads)
    return records


def check_points(plain, pointed):
    """``pointed``'s final point is ``plain``'s result; its other points are the model's along the way."""
    assert result(pointed) == result(plain) and pointed.status == "ok"
    assert plain.points == [final_point(plain.to_dict())]
    assert [p["step"] for p in pointed.points] == STEPS and all(set(p) == set(POINT_KEYS) for p in pointed.points)
    assert [p["fraction"] for p in pointed.points] == [0.1, 0.25, 0.5, 1.0]
    assert [p["final"] for p in pointed.points] == [False, False, False, True]
    final = pointed.points[-1]
    assert final["metrics"] == plain.metrics and final["num_gaussians"] == plain.num_gaussians
    assert final["train_seconds"] == pointed.timings["train"] and final["train_cpu_seconds"] == pointed.timings["train_cpu"]
    trained = [p["train_seconds"] for p in pointed.points]
    assert trained == sorted(trained) and all(p["train_cpu_seconds"] > 0 for p in pointed.points)
    logged = {row["step"]: row["num_gaussians"] for row in map(json.loads, open(folder_of(pointed).metrics))}
    assert pointed.points[2]["num_gaussians"] == logged[30]
    assert pointed.points[0]["num_gaussians"] == pointed.inputs["initial_gaussians"]
    assert pointed.points[0]["num_gaussians"] < pointed.points[1]["num_gaussians"]  # densified in between
    assert all(folder_of(pointed).point_eval(step).is_file() for step in STEPS[:-1]) and len(set(point_meshes(pointed).values())) == 3
    for point in pointed.points[:-1]:
        assert point["status"] == "ok" and point["error"] is None and set(point["metrics"]) == set(plain.metrics)
        assert point["extract_seconds"] > 0 and point["evaluate_seconds"] > 0


def test_the_final_point_is_the_plain_runs_result_bit_for_bit(runs_3dgs):
    check_points(*runs_3dgs)


def test_the_final_point_of_a_method_with_a_3d_filter_is_its_plain_result(tiny_spot, tmp_path, restore_threads, capsys):
    """GOF: the Mip-Splatting 3D filter (recomputed at densification, part of the state) and the abs-gradient
    densification; a line when each point starts and ends."""
    check_points(quick("gof", tiny_spot, tmp_path / "plain"), quick("gof", tiny_spot, tmp_path / "points", POINTS))
    err = capsys.readouterr().err
    assert "point at step 15/60: extracting the mesh (tsdf) and evaluating" in err
    assert "point at step 15: components 1" in err and "(extract " in err


def test_a_point_that_draws_random_numbers_changes_the_model_and_takes_time_leaves_training_as_it_was(
        tiny_spot, tmp_path, monkeypatch, restore_threads):
    """Every RNG stream at the start of every step is as without points, and so is the result; the point runs
    without gradients and its time (1.5 s of CPU each) is not training's."""
    states = {"plain": [], "points": []}
    step = Trainer.train_step

    def logged_step(self, t):
        states[key].append(rng_digest())
        return step(self, t)

    def meddling(method, trained, *args):
        assert not torch.is_grad_enabled()
        random.random(), np.random.rand(), torch.rand(1)
        method.gaussians.params["means"].data.add_(0.1)
        method.sh_degree = 0
        method.optimizer.state.clear()
        start = time.process_time()
        while time.process_time() - start < 1.5:
            pass
        evaluate_point(method, trained, *args)

    monkeypatch.setattr(Trainer, "train_step", logged_step)
    key = "plain"
    plain = quick("3dgs", tiny_spot, tmp_path / "plain")
    evaluate_point = runner._evaluate_point
    monkeypatch.setattr(runner, "_evaluate_point", meddling)
    key = "points"
    pointed = quick("3dgs", tiny_spot, tmp_path / "points", POINTS)
    assert len(states["points"]) == 60 and states["points"] == states["plain"]
    assert result(pointed) == result(plain) and [p["status"] for p in pointed.points] == ["ok"] * 4
    assert pointed.timings["train_cpu"] < plain.timings["train_cpu"] + 2  # 3 x 1.5 s spent in the points
    assert pointed.timings["train"] < plain.timings["train"] + 2


def stop_during_point_30(monkeypatch):
    """Ctrl-C while the point at step 30 is evaluated (its mesh written, its row not)."""
    evaluate = runner._evaluate

    def interrupted(method, scene, cfg, mesh_path, plan):
        if mesh_path.parent.name == "30":
            raise KeyboardInterrupt
        return evaluate(method, scene, cfg, mesh_path, plan)

    monkeypatch.setattr(runner, "_evaluate", interrupted)


def stop_after_point_30(monkeypatch):
    """Ctrl-C just after the point at step 30 wrote its row, before the step's checkpoint."""
    stage = runner.stage

    def interrupted(message, *args):
        stage(message, *args)
        if message.startswith("point at step 30:"):
            raise KeyboardInterrupt

    monkeypatch.setattr(runner, "stage", interrupted)


@pytest.mark.parametrize("stop", [stop_during_point_30, stop_after_point_30])
def test_a_run_stopped_at_a_point_resumes_to_the_uninterrupted_record(stop, runs_3dgs, tiny_spot, tmp_path, monkeypatch,
                                                                    restore_threads):
    """It resumes from the checkpoint of step 15, trains to 30 again and takes the point there unless its row was
    written; the points before it are not taken again."""
    _, uninterrupted = runs_3dgs
    cfg = config("3dgs", tiny_spot, tmp_path, POINTS)
    files = RunFolder(run_dir(cfg))
    stop(monkeypatch)
    with pytest.raises(KeyboardInterrupt):
        run(cfg, echo=lambda *a: None)
    monkeypatch.undo()
    stopped = json.loads(files.record.read_text())
    assert stopped["status"] == "interrupted" and load_checkpoint(files.checkpoint)["step"] == 15
    assert [p["step"] for p in stopped["points"]] == ([6, 15] if stop is stop_during_point_30 else [6, 15, 30])
    taken = []
    evaluate_point = runner._evaluate_point
    monkeypatch.setattr(runner, "_evaluate_point", lambda method, trained, *a: (
        taken.append(trained.steps), evaluate_point(method, trained, *a)))
    resumed = run(cfg, echo=lambda *a: None)
    assert taken == ([30] if stop is stop_during_point_30 else [])
    assert result(resumed) == result(uninterrupted) and point_meshes(resumed) == point_meshes(uninterrupted)
    same = ("step", "status", "num_gaussians", "metrics")
    assert [{k: p[k] for k in same} for p in resumed.points] == [{k: p[k] for k in same} for p in uninterrupted.points]


def test_a_failing_point_is_recorded_with_its_reason_and_the_run_goes_on(runs_3dgs, tiny_spot, tmp_path, monkeypatch,
                                                                         restore_threads, capsys):
    plain, _ = runs_3dgs
    extract = Method.extract_mesh

    def empty_at_first_point(self, scene, cfg, out_path):
        if out_path.parent.name == "6":
            raise MeshError("TSDF fusion produced an empty mesh")
        return extract(self, scene, cfg, out_path)

    monkeypatch.setattr(Method, "extract_mesh", empty_at_first_point)
    record = quick("3dgs", tiny_spot, tmp_path, POINTS)
    failed = record.points[0]
    assert record.status == "ok" and result(record) == result(plain)
    assert failed["status"] == "failed" and failed["error"] == "MeshError: TSDF fusion produced an empty mesh"
    assert failed["metrics"] == {} and failed["evaluate_seconds"] == 0.0 and failed["step"] == 6
    assert [p["status"] for p in record.points[1:]] == ["ok"] * 3
    assert "point at step 6: failed: MeshError: TSDF fusion produced an empty mesh" in capsys.readouterr().err


def test_points_resolve_to_steps_before_the_end(tiny_spot):
    def steps(points, iterations=60):
        return point_steps(resolve_run("3dgs", str(tiny_spot), preset="quick",
                                       overrides=[f"eval.points={points}", f"train.iterations={iterations}"]))

    assert steps("[0.1, 0.25, 0.5]") == [6, 15, 30] and steps("[]") == []
    assert steps("[45, 0.1, 1]") == [1, 6, 45] and steps("[0.001]") == [1]
    assert steps("[0.1, 0.25, 0.5]", 3000) == [300, 750, 1500]


@pytest.mark.parametrize("points, message", [
    ("[1.0]", r"eval.points: 1.0 is a fraction of the run and must be in \(0, 1\).*write a step as an integer"),
    ("[1.5]", r"eval.points: 1.5 is a fraction of the run and must be in \(0, 1\)"),
    ("[-0.5]", r"must be in \(0, 1\)"),
    ("[0]", r"eval.points: step 0 must be >= 1"),
    ("[60]", r"eval.points: 60 is step 60, not before the end of the run \(train.iterations 60\), which is always a "
             r"point; fix: drop it"),
    ("[0.999]", r"0.999 is step 60, not before the end"),
    ("[100]", r"100 is step 100, not before the end"),
    ("[0.1, 6]", r"eval.points: 0.1 and 6 are both step 6 of 60; fix: drop one"),
    ("[half]", r"eval.points: 'half' is not a number; eval.points takes steps \(int >= 1\) or fractions"),
    ("[true]", r"eval.points: True is not a number"),
])
def test_bad_points_are_refused_before_the_run_naming_the_key_and_the_fix(points, message, tiny_spot):
    cfg = resolve_run("3dgs", str(tiny_spot), preset="quick", overrides=[f"eval.points={points}", "train.iterations=60"])
    with pytest.raises(ConfigError, match=message):
        check_run_config(cfg)


def test_points_must_be_a_list(tiny_spot):
    with pytest.raises(ConfigError, match="config key 'eval.points' must be list, found 0.5"):
        resolve_run("3dgs", str(tiny_spot), preset="quick", overrides=["eval.points=0.5"])


def test_no_points_keeps_the_run_id_of_records_made_before_points_and_points_make_another(tiny_spot):
    cfg = resolve_run("3dgs", str(tiny_spot), preset="quick")
    before = cfg.to_dict()
    del before["eval"]["points"]
    assert cfg.eval.points == [] and cfg.run_id == run_id(before)
    assert resolve_run("3dgs", str(tiny_spot), preset="quick", overrides=[POINTS]).run_id != cfg.run_id


def test_the_boards_evaluate_between_opacity_resets_at_15_25_and_50_percent_of_the_run():
    for board in BOARDS:
        assert load_sweep(sweep_file(board))["base"]["eval.points"] == [0.15, 0.25, 0.5], board
    runs = expand(load_sweep(sweep_file("all_methods")))
    assert runs and all(r.config.eval.points == [0.15, 0.25, 0.5] for r in runs)


def test_a_record_made_before_points_reads_as_its_final_point():
    """`record_points`: the run's result at step train.iterations; a second stage's time added to training's."""
    record = {"status": "ok", "config": {"train": {"iterations": 3000}}, "metrics": {"chamfer": 1.5}, "num_gaussians": 9,
              "timings": {"train": 100.0, "train_cpu": 90.0, "extract": 5.0, "evaluate": 7.0}}
    assert record_points(record) == [{"step": 3000, "fraction": 1.0, "final": True, "status": "ok", "error": None,
                                      "train_seconds": 100.0, "train_cpu_seconds": 90.0, "num_gaussians": 9,
                                      "metrics": {"chamfer": 1.5}, "extract_seconds": 5.0, "evaluate_seconds": 7.0}]
    refined = {**record, "timings": {**record["timings"], "refine": 20.0, "refine_cpu": 19.0}}
    assert record_points(refined)[0]["train_seconds"] == 120.0 and record_points(refined)[0]["train_cpu_seconds"] == 109.0
    refined["timings"].pop("refine_cpu")  # a record from before the refine stage's CPU time was kept
    assert record_points(refined)[0]["train_cpu_seconds"] is None
    assert record_points({**record, "status": "failed"}) == []
    assert record_points({**record, "points": [{"step": 1}]}) == [{"step": 1}]
