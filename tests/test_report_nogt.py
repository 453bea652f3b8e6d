"""`gsbench report` for captures without ground truth: their measures get their own section with the
skipped evaluators and why, and the leaderboards neither break nor mis-rank because of them."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from gsbench.report.build import write_report
from gsbench.report.collect import load_runs
from gsbench.report.metrics import metric_specs, primary_metric

RUNS = Path(__file__).parent / "fixtures" / "report" / "runs"
GOLDEN = Path(__file__).parent / "fixtures" / "report" / "golden"
NO_GT_VALUES = {"psnr": 27.3456, "ssim": 0.9123, "mask_iou": 0.8714, "outside_hull_area_share": 0.01234,
                "components": 3.0, "watertight": 0.0, "area": 45321.7, "vertices": 5000.0, "faces": 9996.0}
NO_GT_ROW = "| dtu | scan1001 | 2dgs | 0 | ok | 27.35 | 0.912 | 0.871 | 0.0123 | 3 | no | 45,322 | 12.5 | 12,345 |"
CHAMFER_REASON = ("no ground truth: Points/stl/stl1001_total.ply not found; fix: --gt PATH, the folder holding it "
                  "(DTU: Points/ and ObsMask/; TnT: the scene's .ply, .json, _trans.txt, _COLMAP_SfM.log)")


def _write(runs: Path, run_id: str, scene: str, metrics: dict, skipped: dict | None, method: str = "2dgs",
           seed: int = 0) -> None:
    record = {"run_id": run_id, "method": method, "scene": f"/data/captures/{scene}", "dataset": "dtu", "seed": seed,
              "status": "ok", "error_tail": "",
              "config": {"method": {"name": method, "depth_ratio": 1.0}, "train": {"iterations": 3000},
                         "threads": 1, "preset": "cpu", "mesh": {"extractor": "tsdf"}, "out": "runs",
                         "losses": {"depth_distortion": {"weight": 1000.0}, "normal_consistency": {"weight": 0.05}}},
              "metrics": metrics, "timings": {"train": 12.5, "total": 20.25}, "num_gaussians": 12345,
              "eval_protocol": {}, "environment": {"threads": 1}}
    if skipped is not None:  # records from before the field have none
        record["skipped"] = skipped
    path = runs / "dtu" / scene / method / run_id / "record.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(record))


def test_capture_without_gt_beside_the_fixture_runs(tmp_path):
    runs = tmp_path / "runs"
    shutil.copytree(RUNS, runs)
    _write(runs, "nogt0000001", "scan1001", NO_GT_VALUES,
           {"dtu_chamfer": CHAMFER_REASON, "normal_similarity": "no ground truth:\n  not found"})
    write_report(runs, tmp_path / "out", plots=False)
    md = (tmp_path / "out" / "leaderboard.md").read_text()

    # the DTU leaderboard is the fixture's, ranked as before: scan1001 is no column and no "no metric" cell
    golden = (GOLDEN / "leaderboard.md").read_text()
    board = golden[golden.index("### DTU protocol"):golden.index("- Chamfer, official script (mm), lower is better")]
    assert board in md
    assert "no metric" not in md and "(1/3 scenes)" not in md and "(2/3 scenes)" not in md
    assert "Not on this board: scan1001" in md

    section = md[md.index("## Captures without ground truth"):md.index("## Sweeps")]
    assert NO_GT_ROW in section
    header = ("| dataset | scene | method | seed | status | PSNR (dB) | SSIM | mask IoU | outside-hull area share | "
              "components | watertight | area (units^2) | train (s) | Gaussians |")
    assert header in section
    assert f"| dtu | scan1001 | dtu_chamfer | {CHAMFER_REASON} | 2dgs | 1 |" in section
    assert "| dtu | scan1001 | normal_similarity | no ground truth: not found | 2dgs | 1 |" in section
    # the capture is no failure: the failed table holds the fixture's one failed run only
    failed = md[md.index("## Failed and unfinished runs"):md.index("## Protocols")]
    assert "scan1001" not in failed and failed.count("| failed |") == 1
    html = (tmp_path / "out" / "index.html").read_text()
    assert "Captures without ground truth" in html and "45,322" in html


def test_fixture_runs_have_no_such_section():
    assert "without ground truth" not in (GOLDEN / "leaderboard.md").read_text()


def test_only_captures_without_gt_and_without_held_out_views(tmp_path):
    """Nothing can rank them (no PSNR: no view held out; mesh statistics never rank): no leaderboard, a
    warning, and the section with every value; a record without the ``skipped`` field reads as none."""
    runs = tmp_path / "runs"
    geometry_only = {k: v for k, v in NO_GT_VALUES.items() if k not in ("psnr", "ssim")}
    _write(runs, "nogt0000001", "scan1001", geometry_only,
           {"dtu_chamfer": CHAMFER_REASON, "image": "no view is held out (data.holdout_every is 0)"})
    _write(runs, "nogt0000002", "scan1001", geometry_only, None, method="3dgs")
    skipped = {r.method: r.skipped for r in load_runs(runs)[0]}
    assert skipped == {"3dgs": {}, "2dgs": {"dtu_chamfer": CHAMFER_REASON,
                                            "image": "no view is held out (data.holdout_every is 0)"}}
    write_report(runs, tmp_path / "out", plots=False)
    md = (tmp_path / "out" / "leaderboard.md").read_text()
    assert "### DTU protocol" not in md and "| area |" not in md
    assert "dataset 'dtu'" in md.split("## Warnings")[1]
    section = md[md.index("## Captures without ground truth"):]
    assert NO_GT_ROW.replace("27.35 | 0.912", "– | –") in section
    assert "| dtu | scan1001 | 3dgs | 0 | ok | – | – |" in section
    assert "| image | no view is held out (data.holdout_every is 0) | 2dgs | 1 |" in section
    assert "| failed |" not in md and "no metric" not in md
    assert (tmp_path / "out" / "leaderboard.csv").read_text().count("\n") == 1  # the header only


def test_held_out_psnr_ranks_captures_without_gt(tmp_path):
    runs = tmp_path / "runs"
    _write(runs, "nogt0000001", "scan1001", NO_GT_VALUES, {"dtu_chamfer": CHAMFER_REASON})
    _write(runs, "nogt0000002", "scan1001", dict(NO_GT_VALUES, psnr=25.0), {"dtu_chamfer": CHAMFER_REASON},
           method="3dgs")
    write_report(runs, tmp_path / "out", plots=False)
    md = (tmp_path / "out" / "leaderboard.md").read_text()
    assert "### DTU protocol (dtu): PSNR (dB), higher is better" in md
    assert "| 2dgs | **27.346** | **27.346** |" in md and "| 3dgs | 25.000 | 25.000 |" in md


def test_no_ground_truth_measures_never_rank():
    specs = metric_specs()
    assert primary_metric("custom", {"area", "components", "mask_iou", "outside_hull_area_share", "watertight",
                                     "vertices", "faces", "mask_iou_min"}, specs) is None
    assert primary_metric("custom", {"area", "mask_iou", "psnr"}, specs).name == "psnr"
    assert primary_metric("dtu", {"area", "mask_iou"}, specs).name == "chamfer"
    assert specs["mask_iou"].evaluator == "silhouette" and specs["area"].evaluator == "mesh_stats"
