"""The report's twin-scene tables (`gsbench.report.twins`): the built-in table's twins, and what a factor costs
each row, measured on matched (pair, seed) runs."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from gsbench.data.synthetic.builtin import BUILTIN_SCENES
from gsbench.report.build import write_report
from gsbench.report.claims import evaluate_claims, load_claims
from gsbench.report.collect import Run, label_variants
from gsbench.report.metrics import metric_specs
from gsbench.report.twins import twin_pairs, twin_tables


def _run(method: str, scene: str, seed: int, chamfer: float | None, *, status: str = "ok", psnr: float = 30.0,
         train: float = 100.0) -> Run:
    metrics = {"psnr": psnr} if chamfer is None else {"chamfer": chamfer, "completeness": 2 * chamfer, "psnr": psnr}
    return Run(run_id=f"{method}-{scene}-{seed}", dataset="dtu", scene=scene, method=method, seed=seed, status=status,
               path=f"dtu/{scene}/{method}/{seed}/record.json", metrics=metrics, timings={"train": train},
               it_per_s=None, num_gaussians=None, train_peak_rss_bytes=None, threads=1, iterations=3000,
               eval_protocol={}, environment={}, error_tail="", config={})


def test_every_twin_is_a_built_in_scene_of_the_same_format_with_a_named_factor():
    twins = [(name, scene) for name, scene in BUILTIN_SCENES.items() if scene.twin_of]
    assert {Path(name).name for name, _ in twins} >= {"dtu-glass-orb", "dtu-glass-wine", "dtu-glass-bottle",
                                                       "dtu-bunny-far", "dtu-bunny-smooth"}
    for name, scene in twins:
        assert scene.twin_of in BUILTIN_SCENES and scene.twin_of != name
        assert BUILTIN_SCENES[scene.twin_of].format == scene.format
        assert scene.factor and not BUILTIN_SCENES[scene.twin_of].twin_of
    assert {p.twin for p in twin_pairs() if p.factor == "transparent"} == {
        "dtu-glass-orb-opaque", "dtu-glass-wine-opaque", "dtu-glass-bottle-opaque"}


def _lines(table) -> dict[tuple[str, str], list[str]]:
    return {(row[0].text, row[1].text): [cell.text for cell in row] for row in table.rows}


def test_the_cost_of_a_factor_is_the_paired_change_over_matched_seeds():
    # 2dgs loses 1.0 mm on every glass scene and seed; rt2dgs gains 0.1 on one pair, loses 0.1 on another
    runs = []
    for seed in range(3):
        for name, base in (("orb", 0.5), ("wine", 0.7)):
            runs += [_run("2dgs", f"dtu-glass-{name}-opaque", seed, base + 0.01 * seed),
                     _run("2dgs", f"dtu-glass-{name}", seed, base + 1.0 + 0.01 * seed, train=130.0)]
        runs += [_run("rt2dgs", "dtu-glass-orb-opaque", seed, 0.6), _run("rt2dgs", "dtu-glass-orb", seed, 0.5),
                 _run("rt2dgs", "dtu-glass-wine-opaque", seed, 0.6), _run("rt2dgs", "dtu-glass-wine", seed, 0.7)]
    runs += [_run("2dgs", "dtu-glass-orb", 3, 9.0),  # no twin run of seed 3: unmatched, left out of every value
             _run("2dgs", "dtu-glass-wine-opaque", 3, 9.0, status="failed"),
             _run("3dgs", "dtu-glass-bottle", 0, 1.0)]  # only the changed side: no line
    (table,) = twin_tables(runs, metric_specs())
    assert "transparent" in table.title
    lines = _lines(table)
    assert not any(name == "3dgs" for name, _ in lines)
    assert set(lines) == {(m, s) for m in ("2dgs", "rt2dgs")
                          for s in ("dtu-glass-orb / dtu-glass-orb-opaque", "dtu-glass-wine / dtu-glass-wine-opaque",
                                    "all (2 pairs)")}
    header = table.header
    chamfer = header.index("Chamfer, official script (mm): twin")
    every = lines[("2dgs", "all (2 pairs)")]
    assert every[chamfer:chamfer + 2] == ["0.610", "1.610"]
    assert every[chamfer + 2] == "+1.000 * (p 0.031, 6)"  # six matches all worse: Wilcoxon's smallest p
    assert every[header.index("train (s): changed")] == "130.0"
    assert lines[("rt2dgs", "dtu-glass-orb / dtu-glass-orb-opaque")][chamfer + 2] == "-0.100 (p 0.250, 3)"
    assert lines[("rt2dgs", "all (2 pairs)")][chamfer + 2].startswith("+0.000 ")
    completeness = header.index("Δ completeness (mm)")
    assert every[completeness] == "+2.000 * (p 0.031, 6)"
    significant = next(row for row in table.rows if row[0].text == "2dgs" and row[1].text.startswith("all"))
    assert significant[chamfer + 2].style == "bad"  # lower is better: the glass side is significantly worse


def test_rows_without_a_metric_on_both_sides_leave_it_empty():
    runs = [_run("2dgs", "dtu-glass-orb-opaque", 0, None, psnr=30.0), _run("2dgs", "dtu-glass-orb", 0, None, psnr=24.5)]
    (table,) = twin_tables(runs, metric_specs())
    (line,) = _lines(table).values()
    assert line[table.header.index("Δ Chamfer, official script (mm)")] == "–"
    assert line[table.header.index("Δ PSNR (dB)")] == "-5.50 (p 1.000, 1)"
    assert twin_tables([_run("2dgs", "dtu-spot", 0, 1.0)], metric_specs()) == []  # its twin never ran


@pytest.mark.parametrize("with_twins", [True, False])
def test_the_report_has_the_twin_section_only_when_twin_scenes_ran(tmp_path, with_twins):
    runs = tmp_path / "runs"
    scenes = ["dtu-bunny", "dtu-bunny-far"] if with_twins else ["dtu-bunny", "dtu-face"]
    for i, scene in enumerate(scenes):
        for seed in (0, 1):
            folder = runs / "dtu" / scene / "radegs" / f"{i}{seed}0000000000"
            folder.mkdir(parents=True)
            (folder / "record.json").write_text(json.dumps({
                "run_id": folder.name, "dataset": "dtu", "scene": f"synthetic/{scene}", "method": "radegs",
                "seed": seed, "status": "ok", "metrics": {"chamfer": 0.5 + i + seed / 10, "completeness": 0.6},
                "timings": {"train": 10.0}}))
    write_report(runs, tmp_path / "out", plots=False)
    md = (tmp_path / "out" / "leaderboard.md").read_text()
    assert ("## Twin scenes: what one factor costs" in md) == with_twins
    if with_twins:
        assert "| radegs | dtu-bunny-far / dtu-bunny | 0.550 | 1.550 | +1.000 (p 0.500, 2) |" in md


def test_a_claim_about_transparent_objects_pairs_only_the_glass_scenes():
    """RT2DGS's claim (PSNR above 2DGS on transparent objects) is tested on the glass scenes alone: here rt2dgs is
    better on every glass run and worse on every opaque twin, which would cancel if the twins were paired too."""
    runs = []
    for seed in range(3):
        for name in ("orb", "wine"):
            runs += [_run("2dgs", f"dtu-glass-{name}", seed, 1.0, psnr=25.0 + seed),
                     _run("rt2dgs", f"dtu-glass-{name}", seed, 1.0, psnr=26.0 + seed),
                     _run("2dgs", f"dtu-glass-{name}-opaque", seed, 1.0, psnr=30.0 + seed),
                     _run("rt2dgs", f"dtu-glass-{name}-opaque", seed, 1.0, psnr=29.0 + seed)]
    claims = [c for c in load_claims() if c.factor == "transparent" and not c.sweep]  # the methods' claims, not rt2dgs_light's
    assert {(c.better, c.worse, c.metric) for c in claims} == {("rt2dgs", "2dgs", "psnr"), ("rt2dgs", "3dgs", "psnr")}
    outcomes = {o.claim.worse: o for o in evaluate_claims(label_variants(runs), [], metric_specs(), claims, {})}
    assert outcomes["2dgs"].verdict == "agrees"
    assert outcomes["2dgs"].test.n == 6 and outcomes["2dgs"].test.mean_diff == pytest.approx(1.0)
    assert outcomes["3dgs"].verdict == "not measured"
    unrestricted = [replace(c, factor="") for c in claims[:1]]
    (everywhere,) = evaluate_claims(label_variants(runs), [], metric_specs(), unrestricted, {})
    assert everywhere.test.n == 12 and everywhere.verdict == "not separable"
