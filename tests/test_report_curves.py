"""Error against time in the report (docs/report.md §10): the runs' points, joining rows that differ only in the
schedule's length, the best curve at each time budget, the accuracy to reach and the Pareto front over every step.

Fixture: ``tests/fixtures/report/anytime/`` is a runs folder on two scenes (scan1, scan2) of the DTU protocol, with
points at 10%, 25%, 50% and 100% of each run's steps; the CPU-seconds and Chamfers are below, where the expected
results are computed by hand from them:

- 3dgs, cpu preset (3000 steps), seeds 0 and 1: seed 0 at 40, 100, 200, 400 s, seed 1 at 50, 110, 210, 420 s;
  scan1 seed 0: 2.0, 1.5, 1.2, 1.0; seed 1: 2.2, 1.6, 1.3, 1.1; scan2 seed 0: 3.0, 2.0, 1.6, 1.4; seed 1:
  2.8, 2.1, 1.7, 1.5.
- radegs, cpu preset, seeds 0 and 1: seed 0 at 90, 240, 480, 960 s, seed 1 at 100, 250, 500, 1000 s; scan1 seed 0:
  2.5, 1.4, 0.9, 0.7; seed 1: 2.4, 1.3, 0.8, 0.6; scan2 seed 0: 3.5, 1.9, 1.2, 1.0; seed 1: 3.3 (failed: no
  value), 1.8, 1.1, 0.9.
- radegs, preset "long" (12000 steps; otherwise the cpu configuration, so it joins the cpu rows), seed 0 at 360,
  970, 1920, 3840 s; scan1: 1.2, 0.8, 0.5, 0.4; scan2: 1.6, 1.0, 0.7, 0.6.
- radegs, bench preset (6000 steps at another resolution and budget: a curve of its own), seed 0 at 200, 500,
  1100, 2000 s; scan1: 1.8, 1.0, 0.6, 0.45; scan2: 2.4, 1.4, 0.9, 0.65.
- 2dgs: records from before points (their final result only, wall seconds of training 250 and 270 s for seeds 0
  and 1); scan1: 1.05, 0.95; scan2: 1.35, 1.25.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from gsbench.report.aggregate import leaderboard
from gsbench.report.anytime import (
    accuracy_to_reach,
    board_series,
    budget_results,
    first_reached,
    scene_series,
    standing,
)
from gsbench.report.build import write_report
from gsbench.report.collect import RunPoint, label_variants, load_runs, merge_resized_scenes
from gsbench.report.joins import curves, joins
from gsbench.report.metrics import MetricSpec
from gsbench.report.pareto import step_points
from gsbench.report.plots import LEGEND_CHARS, legend_labels

FIXTURE = Path(__file__).parent / "fixtures" / "report" / "anytime"
CHAMFER = MetricSpec("chamfer", False, "mm")
JOINED = "radegs [preset=cpu] + [preset=long]"
BENCH = "radegs [preset=bench]"


@pytest.fixture(scope="module")
def board():
    runs, warnings = load_runs(FIXTURE)
    assert not warnings
    return leaderboard(label_variants(merge_resized_scenes(runs)), "dtu", CHAMFER, {})


def test_a_record_without_points_is_its_final_point(board):
    (run,) = [r for r in board.rows[0].runs if (r.method, r.scene, r.seed) == ("2dgs", "scan2", 1)]
    assert run.points == (RunPoint(step=3000, ok=True, seconds=270.0, cpu_seconds=None, metrics={"chamfer": 1.25}),)


def test_a_second_stage_without_cpu_seconds_is_timed_by_wall_seconds(tmp_path):
    """SuGaR's refinement: its wall seconds join the training's; its record has no CPU seconds of it, so the final
    point has none (not the first stage's alone)."""
    record = {"run_id": "s1", "method": "sugar", "dataset": "dtu", "scene": "scan1", "seed": 0, "status": "ok",
              "config": {"train": {"iterations": 3000}}, "metrics": {"chamfer": 1.0},
              "timings": {"train": 100.0, "train_cpu": 95.0, "refine": 40.0}}
    (tmp_path / "s1").mkdir()
    (tmp_path / "s1" / "record.json").write_text(json.dumps(record))
    (run,), _ = load_runs(tmp_path)
    assert (run.points[0].seconds, run.points[0].cpu_seconds) == (140.0, None)


def test_recorded_points_keep_failed_ones_and_malformed_ones_warn(tmp_path, board):
    (run,) = [r for row in board.rows for r in row.runs
              if (r.method, r.scene, r.seed, r.iterations) == ("radegs", "scan2", 1, 3000)]
    assert [(p.step, p.ok, p.cpu_seconds, p.metrics) for p in run.points] == [
        (300, False, 100.0, {}), (750, True, 250.0, {"chamfer": 1.8}), (1500, True, 500.0, {"chamfer": 1.1}),
        (3000, True, 1000.0, {"chamfer": 0.9})]
    data = json.loads(sorted(FIXTURE.glob("dtu/scan1/3dgs/*/record.json"))[0].read_text())
    data["points"] = [{"step": "late"}]
    (tmp_path / "r").mkdir()
    (tmp_path / "r" / "record.json").write_text(json.dumps(data))
    (run,), warnings = load_runs(tmp_path)
    assert [(p.step, p.cpu_seconds, p.metrics) for p in run.points] == [(3000, data["timings"]["train_cpu"],
                                                                         data["metrics"])]
    assert warnings == ["r/record.json: 'points' is not a list of points (each an object with an integer 'step' and "
                        "a 'status'): only its final result is drawn; fix: re-run it, or remove 'points' from the "
                        "record"]


def test_rows_of_two_presets_join_only_when_they_differ_in_the_schedule_alone(board):
    made = curves(board)
    assert [c.label for c in made] == ["2dgs", "3dgs", BENCH, JOINED]
    found = {(j.a, j.b): (j.joined, j.keys) for j in joins(board, made)}
    assert found == {(BENCH, "radegs [preset=cpu]"): (False, ["data.max_size", "train.max_gaussians"]),
                     (BENCH, "radegs [preset=long]"): (False, ["data.max_size", "train.max_gaussians"]),
                     ("radegs [preset=cpu]", "radegs [preset=long]"): (True, [])}


def _record(root: Path, name: str, seed: int, **config) -> None:
    """An ok record of radegs on scan1 whose config is the cpu preset's, changed by ``config``."""
    base = {"preset": "cpu", "seed": seed, "scene": "synthetic/scan1", "threads": 1, "data": {"max_size": [240, 150]},
            "method": {"name": "radegs", "lr": 0.1},
            "train": {"iterations": 3000, "checkpoint_every": 500, "max_gaussians": 100000}}
    for key, value in config.items():  # section__field, or a top-level key
        section, _, field = key.rpartition("__")
        (base[section] if section else base)[field] = value
    record = {"run_id": f"{name}{seed}", "method": "radegs", "dataset": "dtu", "scene": "synthetic/scan1",
              "seed": seed, "status": "ok", "config": base, "metrics": {"chamfer": 1.0},
              "timings": {"train": 100.0, "train_cpu": 100.0}}
    (root / f"{name}{seed}").mkdir()
    (root / f"{name}{seed}" / "record.json").write_text(json.dumps(record))


@pytest.mark.parametrize("change, joined", [
    ({"train__iterations": 9000}, True),  # the schedule's length alone
    ({"train__iterations": 9000, "train__checkpoint_every": 1500, "preset": "long"}, True),  # and what runs it
    ({"data__max_size": [480, 300]}, False),  # the resolution
    ({"train__iterations": 9000, "train__max_gaussians": 200000}, False),  # the Gaussian budget too
    ({"method__lr": 0.2}, False),  # a method's setting
])
def test_two_runs_join_when_they_differ_only_in_iterations(tmp_path, change, joined):
    for seed in (0, 1):
        _record(tmp_path, "a", seed)
        _record(tmp_path, "b", seed, **change)
    board = leaderboard(label_variants(load_runs(tmp_path)[0]), "dtu", CHAMFER, {})
    assert len(board.rows) == 2
    assert len(curves(board)) == (1 if joined else 2)
    (pair,) = joins(board, curves(board))
    assert pair.joined == joined and (pair.keys == []) == joined


def test_the_band_is_the_range_over_seeds(board):
    (joined,) = [c for c in curves(board) if c.label == JOINED]
    points = {(p.iterations, p.step): p for p in scene_series(joined, "scan2", "chamfer")}
    at = points[(3000, 1500)]  # seeds 0 and 1: 480 and 500 s, 1.2 and 1.1
    assert (at.time, at.value, at.low, at.high, at.seeds) == (490.0, pytest.approx(1.15), 1.1, 1.2, 2)
    at = points[(3000, 300)]  # seed 1's point failed: seed 0's alone
    assert (at.time, at.value, at.low, at.high, at.seeds) == (90.0, 3.5, 3.5, 3.5, 1)
    at = board_series(board, curves(board))[None][JOINED][0]  # the mean panel: step 300 on both scenes
    assert (at.step, at.time, at.seeds) == (300, pytest.approx((95 + 90) / 2), 1)  # seed 0 alone is on both
    assert (at.value, at.low, at.high) == (pytest.approx((2.45 + 3.5) / 2), 3.0, 3.0)


def test_the_budget_table_ranks_as_a_hand_computation(board):
    """The value at B on a pair is that of the latest point at or before B; the curve's value the mean over its
    pairs, where it has one on each; the best against the runner-up over the pairs both have."""
    results = {r.budget: r for r in budget_results(board, curves(board))}
    assert sorted(results) == [60.0, 300.0, 900.0, 3600.0]

    def ranked(budget):
        return [(s.curve.label, round(s.mean, 9), len(s.reached)) for s in results[budget].ranked]

    # 1 min: only 3dgs has a point on every pair (40 and 50 s): (2.0 + 2.2 + 3.0 + 2.8) / 4
    assert ranked(60.0) == [("3dgs", 2.5, 4)]
    assert results[60.0].test is None
    # 5 min: 2dgs's final results (250, 270 s): (1.05 + 0.95 + 1.35 + 1.25) / 4; 3dgs at 200, 210 s:
    # (1.2 + 1.3 + 1.6 + 1.7) / 4; radegs at 240, 250 s (the long run's first point is at 360 s):
    # (1.4 + 1.3 + 1.9 + 1.8) / 4; the bench run at 200 s on seed 0 alone: (1.8 + 2.4) / 2
    assert ranked(300.0) == [("2dgs", 1.15, 4), ("3dgs", 1.45, 4), (JOINED, 1.6, 4), (BENCH, 2.1, 2)]
    test = results[300.0].test  # 2dgs − 3dgs: -0.15, -0.35, -0.25, -0.45: better on 4 of 4, sign test 2 / 2^4
    assert (test.n, round(test.mean_diff, 9), test.wins, test.test, test.p) == (4, -0.3, 4, "sign", 0.125)
    # 15 min: radegs seed 0 at 480 s (cpu; the long run's 360 s point is earlier), seed 1 at 500 s:
    # (0.9 + 0.8 + 1.2 + 1.1) / 4; bench at 500 s: (1.0 + 1.4) / 2; 2dgs and 3dgs at their end
    assert ranked(900.0) == [(JOINED, 1.0, 4), ("2dgs", 1.15, 4), (BENCH, 1.2, 2), ("3dgs", 1.25, 4)]
    test = results[900.0].test  # radegs − 2dgs: -0.15 on each of the 4 pairs
    assert (test.n, round(test.mean_diff, 9), test.wins, test.p) == (4, -0.15, 4, 0.125)
    # 60 min: radegs seed 0 at 1920 s (the long run; its 3840 s end is later), seed 1 at its end (1000 s):
    # (0.5 + 0.6 + 0.7 + 0.9) / 4; bench at its end (2000 s): (0.45 + 0.65) / 2
    assert ranked(3600.0) == [(BENCH, 0.55, 2), (JOINED, 0.675, 4), ("2dgs", 1.15, 4), ("3dgs", 1.25, 4)]
    test = results[3600.0].test  # bench − radegs on seed 0's pairs: 0.45 − 0.5, 0.65 − 0.7
    assert (test.n, round(test.mean_diff, 9), test.wins, test.p) == (2, -0.05, 2, 0.5)
    assert [(s.curve.label, sum(p is not None for p in s.reached.values())) for s in results[60.0].others] == [
        ("2dgs", 0), (BENCH, 0), (JOINED, 0)]


def test_the_accuracy_to_reach_and_when_each_curve_first_reaches_it(board):
    made = {c.label: c for c in curves(board)}
    # final means: 2dgs 1.15, 3dgs (1.0 + 1.1 + 1.4 + 1.5) / 4 = 1.25, bench 0.55, radegs (0.4 + 0.6 + 0.6 + 0.9) / 4
    target = accuracy_to_reach(board, list(made.values()))
    assert target == pytest.approx((0.625 + 1.15) / 2)
    reached = {label: first_reached(board, curve, target) for label, curve in made.items()}
    assert reached["2dgs"] is None and reached["3dgs"] is None
    # radegs: at 960 s (0.7 + 0.8 + 1.0 + 1.1) / 4 = 0.9; at 970 s the long run's point stands for seed 0,
    # (0.8 + 0.8 + 1.0 + 1.1) / 4 = 0.925; at 1000 s seed 1's end: (0.8 + 0.6 + 1.0 + 0.9) / 4 = 0.825
    assert (reached[JOINED].budget, reached[JOINED].mean) == (1000.0, pytest.approx(0.825))
    # the latest point stands, not the best: at 970 s seed 0's is the long run's (0.8, 1.0), not the cpu run's
    # better end at 960 s (0.7, 1.0); seed 1's at 500 s (0.8, 1.1)
    assert standing(board, made[JOINED], 970.0).mean == pytest.approx((0.8 + 0.8 + 1.0 + 1.1) / 4)
    assert (reached[BENCH].budget, reached[BENCH].mean) == (1100.0, pytest.approx(0.75))  # (0.6 + 0.9) / 2


def test_the_pareto_front_is_over_every_step(board):
    """The mean panel's steps: (mean over scenes of the mean over seeds of time, of the Chamfer)."""
    steps = step_points(board_series(board, curves(board))[None], higher_is_better=False)
    front = [(s.curve, s.point.iterations, s.point.step, round(s.point.time, 6), round(s.point.value, 6))
             for s in sorted(steps, key=lambda s: s.point.time) if s.front]
    assert front == [
        ("3dgs", 3000, 300, 45.0, 2.5),         # the cheapest
        ("3dgs", 3000, 750, 105.0, 1.8),        # radegs's 300 (92.5 s, 2.975) is dominated by 3dgs's 300
        ("3dgs", 3000, 1500, 205.0, 1.45),      # bench's 600 (200 s, 2.1) by 3dgs's 750
        ("2dgs", 3000, 3000, 260.0, 1.15),      # radegs's 750 (245 s, 1.6) by 3dgs's 1500
        (JOINED, 3000, 1500, 490.0, 1.0),       # the long run's 1200 (360 s, 1.4) and 3dgs's end (410 s, 1.25)
        (JOINED, 12000, 3000, 970.0, 0.9),      # bench's 1500 (500 s, 1.2) is dominated
        (JOINED, 3000, 3000, 980.0, 0.8),
        (BENCH, 6000, 3000, 1100.0, 0.75),
        (JOINED, 12000, 6000, 1920.0, 0.6),
        (BENCH, 6000, 6000, 2000.0, 0.55),
        (JOINED, 12000, 12000, 3840.0, 0.5),
    ]
    assert len(steps) == 4 + 1 + 4 + 4 + 4  # 3dgs, 2dgs, bench, radegs's two schedules


def test_a_scene_rendered_at_another_size_is_shown_on_its_scene(tmp_path):
    def record(run_id: str, scene: str, width: int) -> None:
        data = {"run_id": run_id, "method": "radegs", "dataset": "dtu", "scene": scene, "seed": 0, "status": "ok",
                "config": {"preset": "paper" if width == 1600 else "cpu"}, "metrics": {"chamfer": 1.0},
                "inputs": {"source_resolution": [width, width * 3 // 4]}}
        (tmp_path / run_id).mkdir()
        (tmp_path / run_id / "record.json").write_text(json.dumps(data))

    record("a", "synthetic/dtu-bunny", 400)
    record("b", "dtu-bunny-1600", 1600)  # dtu-bunny at 1600 x 1200
    record("c", "dtu-face-800", 1600)  # the suffix is not its width
    record("d", "dtu-spot-1600", 1600)  # no runs on dtu-spot
    runs = {r.run_id: (r.scene, r.scene_folder) for r in merge_resized_scenes(load_runs(tmp_path)[0])}
    assert runs == {"a": ("dtu-bunny", ""), "b": ("dtu-bunny", "dtu-bunny-1600"), "c": ("dtu-face-800", ""),
                    "d": ("dtu-spot-1600", "")}


def test_the_report_draws_the_curves_and_lists_the_tables(tmp_path):
    out = tmp_path / "report"
    write_report(FIXTURE, out, generated="2026-01-01T00:00:00+00:00")
    md = (out / "leaderboard.md").read_text()
    section = md.split("## Error against time")[1].split("\n## ")[0]
    assert "![dtu: Chamfer, official script (mm) against training CPU seconds](plots/curves-dtu.png)" in section
    assert "| 5 min | 2dgs | **1.150† (4 pairs)** | 3dgs | 1.450 (4 pairs) | -0.300 | 4/4 pairs | 0.125 (sign) |" \
           " 4 of 4 curves |" in section
    assert "| radegs [preset=cpu] | radegs [preset=long] | 3000 / 12000 | **one curve** |" in section
    assert f"| {JOINED} | 0/4 pairs reached | 1.600 (4 pairs) | 1.000 (4 pairs) | 0.675 (4 pairs) | 0.625 (4 pairs) " \
           "| 1000 s |" in section
    picture = (out / "plots" / "curves-dtu.png").read_bytes()
    assert picture.startswith(b"\x89PNG") and len(picture) < 150 * 1024  # docs/results/README.md's budget


def test_the_curves_legend_keeps_rows_apart_that_differ_only_in_the_middle_of_their_names():
    """The gggs_claims board's rows: an elided name (start … end) made three of the four read alike."""
    rows = ["gggs [losses.gggs_geo.weight=0.0, losses.gggs_ncc.weight=0.0, losses.gggs_normal.weight=0.05, "
            "mesh.depth=solid, method.surface_depth=solid]",
            "gggs [losses.gggs_geo.weight=0.02, losses.gggs_ncc.weight=0.6, losses.gggs_normal.weight=0.0, "
            "mesh.depth=solid, method.surface_depth=solid]",
            "gggs [losses.gggs_geo.weight=0.02, losses.gggs_ncc.weight=0.6, losses.gggs_normal.weight=0.05, "
            "mesh.depth=solid, method.surface_depth=solid]"]
    texts, columns = legend_labels(rows)
    assert columns == 1 and len(set(texts)) == 3
    assert [text.replace("\n", " ") for text in texts] == rows  # whole, wrapped at spaces
    assert all(len(line) <= LEGEND_CHARS for text in texts for line in text.splitlines())
    assert legend_labels(["3dgs", "radegs [preset=long]"]) == (["3dgs", "radegs [preset=long]"], 2)
