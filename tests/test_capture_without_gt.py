"""A capture without ground truth and without SfM points (a DTU scan in the IDR layout as downloaded,
before the evaluation data): it trains, meshes and is judged by what can be measured; an evaluator the
user names that cannot apply fails before any loading; ``--gt`` finds ground truth kept elsewhere."""

from __future__ import annotations

import json
import math
import shutil

import pytest

from gsbench.cli import main
from gsbench.data.loader import check_scene, has_ground_truth
from gsbench.runs import runner
from gsbench.runs.records import RunRecord
from gsbench.runs.runner import resolve_run, run_dir

QUICK = ["method.random_init_points=2000", "train.iterations=60", "train.checkpoint_every=30", "train.log_every=10",
         "mesh.voxel_size=0.02", "mesh.sdf_trunc=0.08"]
NO_GT_METRICS = ("psnr", "ssim", "mask_iou", "outside_hull_area_share", "components", "watertight", "area")


@pytest.fixture(scope="module")
def capture(tiny_spot, tmp_path_factory):
    """tiny_spot's photos, masks and cameras only, in a folder named like a DTU scan; its ground truth
    (Points/, ObsMask/) copied to a folder of its own, as the official SampleSet is."""
    base = tmp_path_factory.mktemp("capture")
    scan = base / "scan1001"
    scan.mkdir()
    for part in ("image", "mask"):
        shutil.copytree(tiny_spot / part, scan / part)
    shutil.copy(tiny_spot / "cameras.npz", scan / "cameras.npz")
    gt = base / "SampleSet"
    for part in ("Points", "ObsMask"):
        shutil.copytree(tiny_spot / part, gt / part)
    return scan, gt


def _run(scan, out, *extra, expect=0, gt=None):
    sets = [arg for s in (*QUICK, *extra) for arg in ("--set", s)]
    gt_args = ["--gt", str(gt)] if gt else []
    assert main(["run", "--method", "3dgs", "--scene", str(scan), "--preset", "quick", "--out", str(out),
                 "--threads", "2", *gt_args, *sets]) == expect
    cfg = resolve_run("3dgs", str(scan), preset="quick", overrides=[*QUICK, *extra], gt=gt)
    cfg.out = str(out)
    return run_dir(cfg)


def test_scene_check_is_ok_without_ground_truth_and_names_what_it_looked_for(capture):
    scan, gt = capture
    report = check_scene(scan)
    assert report["ok"] and report["errors"] == [] and report["images"] == 49 and report["masks"] == 49
    found = report["ground_truth"]
    assert not found["found"] and "stl1001_total.ply" in found["missing"] and "not found" in found["missing"]
    assert all("{" not in path for path in found["files"]) and not any(found["files"].values())
    with_gt = check_scene(scan, gt_root=gt)
    assert with_gt["ground_truth"]["found"] and all(with_gt["ground_truth"]["files"].values())


def test_capture_without_ground_truth_runs_to_ok_with_what_can_be_measured(capture, tmp_path, capsys):
    scan, _ = capture
    assert not has_ground_truth(scan)
    folder = _run(scan, tmp_path / "runs")
    record = RunRecord.read(folder / "record.json")
    assert record.status == "ok", record.error_tail
    assert record.config["data"]["holdout_every"] == 8  # auto: held out where there is no ground truth
    assert record.inputs["resolution"] == [64, 48] and record.inputs["views_held_out"] == 7
    assert record.inputs["views_trained"] == 42 and record.inputs["masks"] and record.inputs["sfm_points"] == 0
    assert 0 < record.inputs["initial_gaussians"] <= 2000
    for metric in NO_GT_METRICS:
        assert math.isfinite(record.metrics[metric]), metric
    assert record.metrics["mask_iou"] > 0.3 and record.metrics["psnr"] > 10
    assert set(record.skipped) == {"dtu_chamfer", "normal_similarity"}
    assert "stl1001_total.ply" in record.skipped["dtu_chamfer"] and "--gt" in record.skipped["dtu_chamfer"]
    assert "dtu_chamfer" not in record.metrics and record.timings["train"] > 0 and record.num_gaussians > 0
    err = capsys.readouterr().err
    assert "evaluator dtu_chamfer skipped" in err and "training 60 steps" in err and "evaluating" in err

    assert main(["report", str(tmp_path / "runs"), "--out", str(tmp_path / "report"), "--no-plots"]) == 0
    board = (tmp_path / "report" / "leaderboard.md").read_text()
    assert "without ground truth" in board and "mask_iou" in board.replace("mask IoU", "mask_iou")

    # --gt afterwards: the stored plan differs, so only the evaluation is recomputed
    mesh = folder / "mesh.ply"
    assert main(["eval", "--mesh", str(mesh), "--scene", str(scan), "--gt", str(capture[1]),
                 "--evaluator", "dtu_chamfer", "--out", str(tmp_path / "eval.json")]) == 0
    scored = json.loads((tmp_path / "eval.json").read_text())
    assert math.isfinite(scored["results"]["dtu_chamfer"]["metrics"]["chamfer"])


def test_naming_an_evaluator_the_scene_cannot_feed_fails_before_loading(capture, tmp_path, capsys, monkeypatch):
    scan, _ = capture
    header_only = runner.load_run_scene

    def cameras_only(cfg, *, load_images=True):
        assert not load_images, "the images were loaded before the evaluation was planned"
        return header_only(cfg, load_images=False)

    monkeypatch.setattr(runner, "load_run_scene", cameras_only)
    _run(scan, tmp_path / "runs", "eval.evaluators=[dtu_chamfer]", expect=2)
    err = capsys.readouterr().err
    assert "dtu_chamfer" in err and "stl1001_total.ply" in err and "--gt" in err
    assert not (tmp_path / "runs").exists()  # nothing trained, no failed record


def test_gt_elsewhere_is_found_and_keeps_every_view_for_training(capture):
    scan, gt = capture
    assert has_ground_truth(scan, gt)
    cfg = resolve_run("3dgs", str(scan), preset="quick", overrides=QUICK, gt=str(gt))
    assert cfg.data.holdout_every == 0 and cfg.gt == str(gt)
    assert cfg.run_id == resolve_run("3dgs", str(scan), preset="quick", overrides=[*QUICK, "data.holdout_every=0"]).run_id
    with pytest.raises(Exception, match="ground-truth folder not found"):
        resolve_run("3dgs", str(scan), preset="quick", overrides=QUICK, gt=str(gt / "nope"))
