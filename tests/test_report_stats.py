"""Rankings with confidence: the t-interval of a cell, the paired tests, shared ranks, the papers' orderings
tested (`gsbench.report.stats`, `gsbench.report.claims`) on constructed records; and suites of scenes in
sweeps (`gsbench.config.suites`)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from gsbench.config import files
from gsbench.config.suites import load_suite, suite_names
from gsbench.data.synthetic.builtin import BUILTIN_SCENES
from gsbench.errors import ConfigError
from gsbench.report.aggregate import leaderboard
from gsbench.report.build import write_report
from gsbench.report.claims import RELATIONS, evaluate_claims, load_claims, load_findings, verdict
from gsbench.report.collect import label_variants, load_manifests, load_runs
from gsbench.report.metrics import PAPERS_METRIC, metric_specs, reported
from gsbench.report.stats import (
    MIN_WILCOXON,
    comparisons,
    paired_test,
    pairs_to_decide,
    sign_test_p,
    significance_ranks,
    t_half_width,
)
from gsbench.runs.sweep import expand, load_sweep, with_suite
from sweep_files import sweep_file

SCENES = ("scan1", "scan2", "scan3")
SEEDS = (0, 1, 2)


def write_record(runs: Path, method: str, scene: str, seed: int, metrics: dict, dataset: str = "dtu",
                 config: dict | None = None) -> str:
    """An ok record as the runner writes it (the fields the report reads); returns its run id."""
    config = config or {}
    run_id = hashlib.sha1(json.dumps([method, scene, seed, config], sort_keys=True).encode()).hexdigest()[:12]
    record = {"run_id": run_id, "method": method, "scene": f"/data/{scene}", "dataset": dataset, "seed": seed,
              "status": "ok", "error_tail": "",
              "config": {"method": {"name": method, **config}, "train": {"iterations": 3000}, "threads": 1,
                         "preset": "cpu", "out": "runs"},
              "metrics": metrics, "timings": {"train": 10.0, "total": 12.0}, "num_gaussians": 1000,
              "eval_protocol": {}, "environment": {"threads": 1}}
    path = runs / dataset / scene / method / run_id / "record.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(record))
    return run_id


def board_of(runs_dir: Path, dataset: str = "dtu", metric: str = "chamfer"):
    runs = label_variants(load_runs(runs_dir)[0])
    return leaderboard(runs, dataset, metric_specs()[metric], {})


# ---------------------------------------------------------------- intervals


def test_t_interval_covers_the_mean_95_percent_of_the_time():
    rng = np.random.default_rng(20)
    for n in (3, 5):
        hits = 0
        for _ in range(2000):
            values = rng.normal(1.5, 0.2, n)
            hits += abs(values.mean() - 1.5) <= t_half_width(values)
        assert 0.93 <= hits / 2000 <= 0.97, (n, hits / 2000)


def test_t_interval_formula_and_one_value_has_none():
    assert t_half_width([1.0]) is None
    # n = 2: t(0.975, 1) = 12.706, s = 0.02828 -> h = 12.706 * 0.02828 / sqrt(2) = 0.2541
    assert t_half_width([0.62, 0.66]) == pytest.approx(0.2541, abs=1e-4)
    assert t_half_width([1.0, 2.0, 3.0]) == pytest.approx(2.4841, abs=1e-4)


def test_cells_show_mean_and_interval(tmp_path):
    runs = tmp_path / "runs"
    for seed, value in zip(SEEDS, (0.60, 0.62, 0.64)):
        write_record(runs, "2dgs", "scan1", seed, {"chamfer": value})
    write_record(runs, "3dgs", "scan1", 0, {"chamfer": 0.9})
    write_report(runs, tmp_path / "out", plots=False)
    md = (tmp_path / "out" / "leaderboard.md").read_text()
    assert "| 2dgs | **0.620 ± 0.050** |" in md  # t(0.975, 2) = 4.303, s = 0.02 -> 0.0497
    assert "| 3dgs | 0.900 |" in md  # one run: no interval
    csv = (tmp_path / "out" / "leaderboard.csv").read_text().splitlines()
    header = csv[0].split(",")
    row = dict(zip(header, next(line for line in csv if line.startswith("dtu,chamfer,mm,0,2dgs,,scan1")).split(",")))
    assert float(row["ci95_low"]) == pytest.approx(0.5703, abs=1e-4) and row["rank"] == "1"


# ---------------------------------------------------------------- paired tests


def test_sign_test_and_wilcoxon_p_values():
    assert sign_test_p(0, 0) == 1.0 and sign_test_p(3, 0) == pytest.approx(0.25) and sign_test_p(1, 1) == 1.0
    all_better = paired_test([-0.1, -0.2, -0.3, -0.15, -0.25, -0.05], higher_is_better=False)
    assert (all_better.test, all_better.wins, all_better.losses) == ("wilcoxon", 6, 0)
    assert all_better.p == pytest.approx(2 / 2**6) and all_better.a_better  # exact: both tails of W+ = 0
    zeros = paired_test([0.0] * 9, higher_is_better=False)
    assert zeros.test == "sign" and zeros.p == 1.0 and not zeros.significant
    tiny = paired_test([-0.1] * (MIN_WILCOXON - 1), higher_is_better=False)
    assert tiny.test == "sign" and tiny.p == pytest.approx(2 / 2**5) and not tiny.significant
    flipped = paired_test([0.1, 0.2, 0.3, 0.15, 0.25, 0.05], higher_is_better=True)
    assert flipped.a_better and flipped.swapped().b_better and flipped.swapped().mean_diff == pytest.approx(-0.175)
    assert paired_test([], higher_is_better=True).p is None


def test_a_known_difference_is_significant(tmp_path):
    runs = tmp_path / "runs"
    rng = np.random.default_rng(1)
    for scene, base in zip(SCENES, (0.6, 0.9, 1.2)):
        for seed in SEEDS:
            noise = rng.normal(0, 0.01)
            write_record(runs, "gof", scene, seed, {"chamfer": base + noise})
            write_record(runs, "2dgs", scene, seed, {"chamfer": base + noise + 0.1 + rng.normal(0, 0.01)})
    board = board_of(runs)
    tests = comparisons(board)
    gof_vs_2dgs = tests[("gof", "2dgs")]
    assert gof_vs_2dgs.n == 9 and gof_vs_2dgs.wins == 9 and gof_vs_2dgs.test == "wilcoxon"
    assert gof_vs_2dgs.p == pytest.approx(2 / 2**9) and gof_vs_2dgs.a_better
    assert tests[("2dgs", "gof")].b_better
    assert significance_ranks(board, tests) == {"gof": 1, "2dgs": 2}
    outcomes = {o.claim.text: o for o in evaluate_claims(label_variants(load_runs(runs)[0]), [], metric_specs())}
    assert outcomes["gof better than 2dgs"].verdict == "agrees"
    assert outcomes["radegs better than gof"].verdict == "not measured"
    assert "no runs of radegs" in outcomes["radegs better than gof"].why

    write_report(runs, tmp_path / "out", plots=False)
    md = (tmp_path / "out" / "leaderboard.md").read_text()
    ranks = md[md.index("### Ranks: DTU"):md.index("### Paired comparisons: DTU")]
    assert "| gof | **1** | **1** | **1** | **1.00** | **1** |" in ranks and "| 2dgs | 2 | 2 | 2 | 2.00 | 2 |" in ranks
    matrix = md[md.index("### Paired comparisons: DTU"):md.index("## The papers' orderings")]
    assert "| gof | **-0.102, 9/9 better, p=0.004 \\*** | – |" in matrix
    assert "| 2dgs | – | +0.102, 0/9 better, p=0.004 \\* |" in matrix
    claims = md[md.index("## The papers' orderings"):md.index("## Speed")]
    assert "| gof better than 2dgs | 0.74 vs 0.80 |" in claims and "| 0.004 (wilcoxon) | **agrees** | – |" in claims
    assert "| radegs better than gof |" in claims  # a group with a side on the board shows every claim of it
    left_out = next(line for line in claims.splitlines() if line.startswith("Left out, no run of any"))
    assert "GGGS > PGSR, RaDe-GS (DTU Chamfer, mm)" in left_out and "### GGGS > PGSR" not in claims
    assert "DTU Chamfer (mm) 3DGS > SuGaR" not in left_out
    assert 'id="paired-dtu"' in (tmp_path / "out" / "index.html").read_text()


def test_a_contradicted_claim_shows_its_measured_cause_or_unexplained(tmp_path):
    runs = tmp_path / "runs"
    for scene, base in zip(SCENES, (0.6, 0.9, 1.2)):
        for seed in SEEDS:
            write_record(runs, "sugar", scene, seed, {"chamfer": base + 0.01 * seed})
            write_record(runs, "2dgs", scene, seed, {"chamfer": base + 0.2 + 0.01 * seed})
    found = label_variants(load_runs(runs)[0])
    unexplained = {(o.claim.dataset, o.claim.text): o for o in evaluate_claims(found, [], metric_specs(), findings={})}
    assert unexplained["dtu", "2dgs better than sugar"].verdict == "disagrees"
    assert unexplained["dtu", "2dgs better than sugar"].cause == "unexplained"
    assert unexplained["dtu", "sugar better than 3dgs"].cause == ""  # not measured: no cause to give
    cause = {("dtu", "2dgs better than sugar"): "framing (docs/measurements.md)"}
    explained = {(o.claim.dataset, o.claim.text): o for o in evaluate_claims(found, [], metric_specs(), findings=cause)}
    assert explained["dtu", "2dgs better than sugar"].cause == "framing (docs/measurements.md)"
    assert load_findings() is not None  # the shipped file names only claims that exist
    bad = tmp_path / "findings.yaml"
    bad.write_text("causes:\n  dtu:\n    2dgs beats sugar: framing\n")
    with pytest.raises(ConfigError, match="2dgs beats sugar"):
        load_findings(bad)


def test_equal_distributions_are_not_separable_and_share_a_rank(tmp_path):
    runs = tmp_path / "runs"
    rng = np.random.default_rng(7)
    for scene in SCENES:
        for seed in SEEDS:
            write_record(runs, "radegs", scene, seed, {"chamfer": 0.7 + rng.normal(0, 0.05)})
            write_record(runs, "ibgs", scene, seed, {"chamfer": 0.7 + rng.normal(0, 0.05)})
            write_record(runs, "3dgs", scene, seed, {"chamfer": 0.7})
            write_record(runs, "2dgs", scene, seed, {"chamfer": 0.7})
    board = board_of(runs)
    tests = comparisons(board)
    assert tests[("ibgs", "radegs")].n == 9 and tests[("ibgs", "radegs")].p >= 0.05
    assert tests[("3dgs", "2dgs")].test == "sign" and tests[("3dgs", "2dgs")].p == 1.0  # every difference 0
    assert set(significance_ranks(board, tests).values()) == {1}
    outcomes = {o.claim.text: o for o in evaluate_claims(label_variants(load_runs(runs)[0]), [], metric_specs())}
    assert outcomes["ibgs at least as good as radegs"].verdict == "agrees (not separable)"
    write_report(runs, tmp_path / "out", plots=False)
    claims = (tmp_path / "out" / "leaderboard.md").read_text().split("## The papers' orderings")[1]
    line = next(x for x in claims.splitlines() if x.startswith("| ibgs at least as good as radegs |"))
    assert line.endswith(f"| {pairs_to_decide(tests[('ibgs', 'radegs')])} (have 9) | – |")


def test_equal_distributions_reject_at_about_the_nominal_rate():
    rng = np.random.default_rng(3)
    rejected = sum(paired_test(rng.normal(0, 1, 12) - rng.normal(0, 1, 12), False).significant for _ in range(400))
    assert 0.01 <= rejected / 400 <= 0.09  # a test that never rejects fails too


def test_pairs_to_decide_reaches_the_stated_power():
    rng = np.random.default_rng(4)
    z = rng.normal(0, 1, 50)
    measured = paired_test(-0.1 + 0.2 * (z - z.mean()) / z.std(ddof=1), higher_is_better=False)  # d̄ = -0.1, s_d = 0.2
    n = pairs_to_decide(measured)
    assert n == 33  # ((1.960 + 0.842) * 0.2 / 0.1)² = 31.40, / (3/π) = 32.9
    power = {size: sum(paired_test(rng.normal(-0.1, 0.2, size), False).a_better for _ in range(500)) / 500
             for size in (n, n // 3)}
    assert 0.72 <= power[n] <= 0.88 and power[n // 3] < 0.5, power


def test_pairs_to_decide_needs_a_difference_and_a_spread():
    assert pairs_to_decide(paired_test([-0.1], False)) is None  # one pair: no spread
    assert pairs_to_decide(paired_test([-0.1, 0.1], False)) is None  # no mean difference
    assert pairs_to_decide(paired_test([-0.1, -0.1], False)) == MIN_WILCOXON  # no spread: the tests' floor
    assert pairs_to_decide(paired_test([-0.1, -0.3, 0.1], False)) > pairs_to_decide(paired_test([-0.2, -0.3, -0.1], False))


def test_verdicts():
    assert verdict(">", None) == "not measured"
    better = paired_test([0.1] * 6, higher_is_better=True)
    assert verdict(">", better) == "agrees" and verdict(">", better.swapped()) == "disagrees"
    assert verdict("≈", better) == "disagrees" and verdict("≥", better.swapped()) == "disagrees"
    unclear = paired_test([0.1, -0.1, 0.2], higher_is_better=True)
    assert verdict(">", unclear) == "not separable" and verdict("≈", unclear) == "agrees (not separable)"
    assert verdict("≥", unclear) == "agrees (not separable)"


def test_ablation_cells_differing_from_the_baseline_are_marked(tmp_path):
    runs = tmp_path / "runs"
    entries = []
    for label, shift, config in (("ibgs", 0.0, {}), ("ibgs_without_Ld_Ln", 0.3, {"x": 1}), ("same", 0.0, {"x": 2})):
        for scene in SCENES[:2]:
            for seed in SEEDS:
                value = 0.7 + 0.01 * seed + shift + (0.001 * seed if label == "ibgs_without_Ld_Ln" else 0.0)
                run_id = write_record(runs, "ibgs", scene, seed, {"chamfer": value}, config=config)
                entries.append({"run_id": run_id, "label": label, "method": "ibgs", "scene": f"/data/{scene}",
                                "seed": seed, "status": "ok"})
    (runs / "sweeps").mkdir()
    (runs / "sweeps" / "ibgs_losses.json").write_text(json.dumps({"name": "ibgs_losses", "runs": entries}))
    write_report(runs, tmp_path / "out", plots=False)
    md = (tmp_path / "out" / "leaderboard.md").read_text()
    table = md[md.index("### sweep ibgs_losses"):md.index("## Failed")]
    assert "| ibgs_without_Ld_Ln | ibgs | 1.011 ± 0.027 | 1.011 ± 0.027 | 1.011 | +0.301 \\* | 0.031 (6) \\* |" in table
    assert "| same | ibgs | **0.710 ± 0.025** | **0.710 ± 0.025** | **0.710** | +0.000 | 1.000 (6) |" in table
    runs_list = label_variants(load_runs(runs)[0])
    outcomes = {o.claim.text: o for o in evaluate_claims(runs_list, load_manifests(runs)[0], metric_specs())}
    assert outcomes["ibgs better than ibgs_without_Ld_Ln"].verdict == "agrees"
    assert outcomes["ibgs better than ibgs_without_Ld_Ln"].test.n == 6
    assert outcomes["ibgs better than ibgs_Ls_and_eigval"].verdict == "not measured"


# ---------------------------------------------------------------- the claims as data


def test_claims_use_the_papers_metric_and_name_their_source():
    for claim in load_claims():
        # a claim about one kind of scene (``factor``) is in the metric its paper used there: RT2DGS reports PSNR only;
        # a claim about rendering is in PSNR (SuGaR's refined model, on a capture without ground-truth geometry)
        rendering = claim.factor == "transparent" or claim.sweep == "sugar_claims_scan65"
        assert claim.metric == ("psnr" if rendering else PAPERS_METRIC[claim.dataset]), claim
        assert claim.relation in RELATIONS and claim.source and " vs " in claim.paper, claim
        if claim.sweep:  # the labels are rows of the shipped sweep that repeats the ablation
            sweep = load_sweep(sweep_file(claim.sweep))
            if not str(sweep["base"].get("scene", "synthetic/")).startswith("synthetic/"):  # a capture the user copies
                sweep["base"]["scene"] = "synthetic/dtu-rig-bunny"  # in: its rows' labels do not depend on the scene
            labels = {r.label for r in expand(sweep)}
            assert {claim.better, claim.worse} <= labels, claim


def test_claims_between_methods_quote_the_methods_reported_means():
    """A claim's paper numbers are the two methods' reported means (one source, so they cannot drift apart); a claim
    about one kind of scene (``factor``) quotes its paper's own table, not a dataset's means."""
    for claim in (c for c in load_claims() if not c.sweep and not c.factor):
        sides = [reported(name, claim.dataset, []) for name in (claim.better, claim.worse)]
        assert [float(x) for x in claim.paper.split(" vs ")] == [side.mean for side in sides], claim


def _configs(tmp_path, monkeypatch, claims: str, order: str = "") -> Path:
    """A configs folder with methods a and b (DTU Chamfer means 0.5 and 0.75) and one group, as the shipped one."""
    (tmp_path / "methods").mkdir(parents=True)
    for name, mean in (("a", 0.5), ("b", 0.75)):
        (tmp_path / "methods" / f"{name}.yaml").write_text(
            f"plugin: x:Y\nreported: {{dtu: {{metric: chamfer, mean: {mean}, source: 'paper {name}'}}}}\n")
    (tmp_path / "methods" / "a.yaml").write_text((tmp_path / "methods" / "a.yaml").read_text() + claims)
    (tmp_path / "claim_groups.yaml").write_text(f"groups:\n  g: {{heading: 'A > B', dataset: dtu, metric: chamfer{order}}}\n")
    monkeypatch.setattr(files, "CONFIG_ROOT", tmp_path)
    return tmp_path


def test_claims_are_read_from_the_method_files(tmp_path, monkeypatch):
    """A side's number is its reported mean unless the entry's paper: gives it; a malformed entry is a ConfigError
    naming the file, the entry and the fix."""
    _configs(tmp_path, monkeypatch, "claims:\n  - {group: g, claim: [a > b, b ≈ x], source: [s1, s2], paper: {x: 1.0},"
                                    " digits: 3}\n", ", order: [b ≈ x, a > b]")
    assert [(c.text, c.paper, c.source, c.group) for c in load_claims()] == [
        ("b as good as x", "0.750 vs 1.000", "s1; s2", "A > B"), ("a better than b", "0.500 vs 0.750", "s1; s2", "A > B")]
    _configs(tmp_path / "withheld", monkeypatch, "claims:\n  - {group: g, claim: a > b, source: s, paper: {b: null}}\n", "")
    assert [c.paper for c in load_claims()] == ["0.50 vs –"]  # null: the paper has no number for this row of b
    for case, (claims, order, message) in enumerate((
            ("{group: h, claim: a > b, source: s}", "", "a.yaml: claims.0.: unknown group 'h'"),
            ("{group: g, claim: a > y, source: s}", "", "no paper number for 'y'.*give it under paper:"),
            ("{group: g, claim: a >> b, source: s}", "", "claim 'a >> b' must read 'better RELATION worse'"),
            ("{group: g, claim: a > b}", "", "a.yaml: claims.0.: a claims entry is a mapping with group, claim and source"),
            ("{group: g, claim: a > b, source: s}", ", order: [b > a]", "order must list each of the group's claims once"))):
        _configs(tmp_path / f"case{case}", monkeypatch, f"claims:\n  - {claims}\n", order)
        with pytest.raises(ConfigError, match=message):
            load_claims()


# ---------------------------------------------------------------- suites


def test_suites_list_the_protocols_scenes():
    assert suite_names() == ["dtu-framed", "dtu-like", "dtu-rig", "glass", "tnt-like", "tnt-rig"]
    for name, fmt in (("dtu-framed", "dtu"), ("dtu-like", "dtu"), ("dtu-rig", "dtu"), ("glass", "dtu"), ("tnt-like", "tnt"),
                      ("tnt-rig", "tnt")):
        suite = load_suite(name)
        assert suite.seeds == (0, 1, 2)
        assert all(BUILTIN_SCENES[s].format == fmt for s in suite.scenes)
    assert "synthetic/spot" in load_suite("dtu-like").scenes and "synthetic/spot-tnt" in load_suite("tnt-like").scenes


def _sweep(tmp_path, text) -> Path:
    path = tmp_path / "sweep.yaml"
    path.write_text(text)
    return path


def test_suites_expand_in_sweeps(tmp_path):
    suite = load_suite("dtu-like")
    runs = expand(load_sweep(_sweep(tmp_path, "base: {method: 3dgs, preset: quick}\nsuite: dtu-like\n")))
    assert [(r.config.scene, r.config.seed) for r in runs] == [(s, k) for s in suite.scenes for k in suite.seeds]
    own_seeds = expand(load_sweep(_sweep(tmp_path, "base: {method: 3dgs, preset: quick}\nsuite: tnt-like\nseeds: [4]\n")))
    assert [(r.config.scene, r.config.seed) for r in own_seeds] == [(s, 4) for s in load_suite("tnt-like").scenes]
    # --suite replaces a file's scenes; --seeds its seeds
    sweep = load_sweep(_sweep(tmp_path, "base: {method: 3dgs, preset: quick}\nscenes: [synthetic/spot]\n"))
    replaced = expand(with_suite(sweep, "suite:tnt-like", [1]))
    assert {r.config.scene for r in replaced} == set(load_suite("tnt-like").scenes)
    assert {r.config.seed for r in replaced} == {1}


def test_unknown_suite_is_an_error_listing_the_suites(tmp_path):
    with pytest.raises(ConfigError, match="unknown suite 'dtu-lik'.*did you mean 'dtu-like'.*dtu-framed, dtu-like, dtu-rig, glass, tnt-like, tnt-rig"):
        load_sweep(_sweep(tmp_path, "base: {method: 3dgs}\nsuite: dtu-lik\n"))
    with pytest.raises(ConfigError, match="unknown suite 'nope'; available suites: dtu-framed, dtu-like, dtu-rig, glass, tnt-like, tnt-rig"):
        with_suite({"base": {"method": "3dgs"}}, "nope")
    with pytest.raises(ConfigError, match="'suite'.*or 'scenes', not both"):
        load_sweep(_sweep(tmp_path, "base: {method: 3dgs}\nsuite: dtu-like\nscenes: [synthetic/spot]\n"))


def test_a_suite_as_one_scene_points_to_the_sweep(capsys):
    from gsbench.cli import main

    assert main(["config", "--method", "3dgs", "--scene", "suite:dtu-like"]) == 2
    assert "gsbench sweep FILE --suite dtu-like" in capsys.readouterr().err
    assert main(["run", "--method", "3dgs", "--scene", "suite:nope"]) == 2
    assert "available suites: dtu-framed, dtu-like, dtu-rig, glass, tnt-like, tnt-rig" in capsys.readouterr().err


def test_cpu_time_is_shown_only_when_every_run_of_the_row_recorded_it(tmp_path):
    """A row whose runs partly predate `timings.train_cpu` shows no CPU mean: it would be over fewer runs than the wall
    time beside it."""
    runs = tmp_path / "runs"
    for seed in (0, 1):
        write_record(runs, "3dgs", "scan24", seed, {"chamfer": 1.0})
        write_record(runs, "2dgs", "scan24", seed, {"chamfer": 0.9})
    for path in runs.rglob("record.json"):
        record = json.loads(path.read_text())
        if record["method"] == "2dgs" or record["seed"] == 0:
            record["timings"]["train_cpu"] = 8.0 + record["seed"]
            path.write_text(json.dumps(record))
    speed = {row.name: row.speed for row in board_of(runs).rows}
    assert speed["2dgs"]["train_cpu"].mean == 8.5 and speed["2dgs"]["train_cpu"].n == 2
    assert speed["3dgs"]["train_cpu"] is None and speed["3dgs"]["train"].n == 2
