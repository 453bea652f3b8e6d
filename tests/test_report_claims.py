"""A paper's claim about its own parts, tested between two rows of the sweep that repeats its ablation
(`gsbench.report.claims`, `gsbench.report.stats.mean_interval`, `gsbench.report.views.method_claims_tables`): on
constructed records whose effects, intervals, p-values and verdicts are computed by hand below."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import pytest

from gsbench.config import files
from gsbench.report.build import write_report
from gsbench.report.claims import NO_NUMBER, evaluate_claims, load_claims
from gsbench.report.collect import label_variants, load_manifests, load_runs
from gsbench.report.metrics import metric_specs
from gsbench.report.stats import mean_interval, paired_test

SCENES = ("dtu-rig-bunny", "dtu-rig-face")
SEEDS = (0, 1, 2)
# gggs − other per (scene, seed), Chamfer mm (lower is better), in the order SCENES × SEEDS
MEDIAN = (-0.02, -0.04, -0.06, -0.08, -0.10, -0.12)  # gggs better on all six
MULTIVIEW = (0.05, 0.06, 0.07, 0.08, 0.09, 0.10)  # gggs worse on all six
DEPTH_NORMAL = (-0.03, 0.01, -0.02, 0.04, -0.01, 0.02)  # mixed


def write_sweep(runs: Path, name: str, rows: dict[str, tuple]) -> None:
    """Records of method gggs on SCENES × SEEDS, one row per label with Chamfer 0.5 + 0.01·seed + 0.1·scene index
    for ``gggs`` and that minus the row's differences for the others, and the sweep's manifest."""
    entries = []
    for label, differences in rows.items():
        for i, (scene, seed) in enumerate((s, d) for s in SCENES for d in SEEDS):
            base = 0.5 + 0.01 * seed + 0.1 * SCENES.index(scene)
            value = base - (differences[i] if differences else 0.0)
            run_id = hashlib.sha1(json.dumps([label, scene, seed]).encode()).hexdigest()[:12]
            record = {"run_id": run_id, "method": "gggs", "scene": f"/data/{scene}", "dataset": "dtu", "seed": seed,
                      "status": "ok", "error_tail": "", "metrics": {"chamfer": value}, "num_gaussians": 1000,
                      "config": {"method": {"name": "gggs", "row": label}, "train": {"iterations": 3000},
                                 "threads": 1, "preset": "cpu", "out": "runs"},
                      "timings": {"train": 10.0, "total": 12.0}, "eval_protocol": {}, "environment": {"threads": 1}}
            path = runs / "dtu" / scene / "gggs" / run_id / "record.json"
            path.parent.mkdir(parents=True)
            path.write_text(json.dumps(record))
            entries.append({"run_id": run_id, "label": label, "method": "gggs", "scene": f"/data/{scene}",
                            "seed": seed, "status": "ok"})
    (runs / "sweeps").mkdir(exist_ok=True)
    (runs / "sweeps" / f"{name}.json").write_text(json.dumps({"name": name, "runs": entries}))


@pytest.fixture(scope="module")
def gggs_claims(tmp_path_factory) -> Path:
    runs = tmp_path_factory.mktemp("claims") / "runs"
    write_sweep(runs, "gggs_claims", {"gggs": (), "gggs_median_depth": MEDIAN, "gggs_without_multiview": MULTIVIEW,
                                      "gggs_without_depth_normal": DEPTH_NORMAL})
    return runs


def test_the_interval_of_a_mean_difference_by_hand():
    """d = −0.02 … −0.12: d̄ = −0.07, s_d = 0.02 · sd(1..6) = 0.02 · 1.870829 = 0.0374166,
    t(0.975, 5) = 2.570582, h = 2.570582 · 0.0374166 / √6 = 0.0392669; one pair has no interval."""
    low, high = mean_interval(paired_test(MEDIAN, higher_is_better=False))
    assert low == pytest.approx(-0.07 - 0.0392669, abs=1e-6) and high == pytest.approx(-0.07 + 0.0392669, abs=1e-6)
    assert mean_interval(paired_test([-0.1], higher_is_better=False)) is None
    assert mean_interval(paired_test([-0.1, -0.1], higher_is_better=False)) == pytest.approx((-0.1, -0.1))


def test_a_claim_between_two_rows_of_a_sweep_is_measured_as_by_hand(gggs_claims):
    """The shipped claims of GGGS's ablation against the sweep's rows. gggs against the median depth: better on all
    six pairs, Wilcoxon W+ = 0 of six, two-sided exact p = 2/2⁶ = 0.03125: agrees. Without the multi-view terms
    better on all six: disagrees, Δ = +0.075, interval 0.075 ± 2.570582 · 0.0187083/√6. Without the depth–normal
    term: ranks of |d| 5, 1.5, 3.5, 6, 1.5, 3.5, W+ = 11 against W− = 10: p ≈ 1, not separable; d̄ = 0.01/6,
    s_d = √((0.0035 − 6 d̄²)/5) = 0.0263944, the interval d̄ ± 0.0276993 = [−0.0260, +0.0294] spans 0."""
    runs = label_variants(load_runs(gggs_claims)[0])
    outcomes = {o.claim.text: o for o in evaluate_claims(runs, load_manifests(gggs_claims)[0], metric_specs(),
                                                         findings={}) if o.claim.sweep == "gggs_claims"}
    median = outcomes["gggs better than gggs_median_depth"]
    assert (median.verdict, median.test.n, median.test.wins, median.test.test) == ("agrees", 6, 6, "wilcoxon")
    assert median.test.p == pytest.approx(2 / 2 ** 6) and median.test.mean_diff == pytest.approx(-0.07)
    assert median.claim.method == "gggs" and median.claim.paper == f"0.47 vs {NO_NUMBER}"
    multiview = outcomes["gggs better than gggs_without_multiview"]
    assert (multiview.verdict, multiview.test.wins, multiview.cause) == ("disagrees", 0, "unexplained")
    half = 2.570582 * 0.0187083 / math.sqrt(6)
    assert mean_interval(multiview.test) == pytest.approx((0.075 - half, 0.075 + half), abs=1e-6)
    depth_normal = outcomes["gggs better than gggs_without_depth_normal"]
    assert depth_normal.verdict == "not separable" and depth_normal.test.p > 0.9
    assert depth_normal.test.mean_diff == pytest.approx(0.01 / 6)
    assert mean_interval(depth_normal.test) == pytest.approx((0.01 / 6 - 0.0276993, 0.01 / 6 + 0.0276993), abs=1e-6)


def test_the_report_gives_one_table_of_a_methods_own_claims(gggs_claims, tmp_path):
    """`gsbench report` on the sweep: GGGS's table of its own claims, each with Δ, its 95% interval, the pairs and
    the verdict, as computed by hand above; the group's table gains the interval too; no table for a method none
    of whose ablations ran."""
    write_report(gggs_claims, tmp_path / "out", plots=False)
    md = (tmp_path / "out" / "leaderboard.md").read_text()
    own = md[md.index("### gggs: the paper's claims about its own parts"):]
    own = own[:own.index("\n### ", 1)]
    metric = "sweep gggs_claims, dtu chamfer"
    assert (f"| gggs better than gggs_median_depth | {metric} | 0.47 vs – | -0.070 | [-0.109, -0.031] | 6 | "
            "**agrees** |") in own
    assert f"| gggs better than gggs_without_multiview | {metric} | 0.47 vs – | +0.075 | [+0.055, +0.095] | 6 | " \
           "disagrees |" in own
    assert f"| gggs better than gggs_without_depth_normal | {metric} | 0.47 vs – | +0.002 | [-0.026, +0.029] | 6 | " \
           "not separable |" in own
    assert "### ibgs: the paper's claims about its own parts" not in md
    group = md[md.index("### GGGS: its stochastic-solid depth"):]
    assert ("| sweep gggs_claims: gggs vs gggs_median_depth | -0.070 | [-0.109, -0.031] | 6/6 pairs | "
            "0.031 (wilcoxon) |") in group


def test_an_ablation_row_without_a_paper_number_is_quoted_as_a_dash(tmp_path, monkeypatch):
    """A side of a sweep claim with neither a paper: number nor a reported mean is quoted "–" (a claim between
    methods still needs both: tests/test_report_stats.py); the claim keeps the method whose file declares it."""
    (tmp_path / "methods").mkdir()
    (tmp_path / "methods" / "a.yaml").write_text(
        "plugin: x:Y\nreported: {dtu: {metric: chamfer, mean: 0.5, source: 'paper a'}}\n"
        "claims:\n  - {group: g, claim: [a > a_without_x, a_k=5 > a_k=1], source: s, paper: {a_k=5: 0.6}}\n")
    (tmp_path / "claim_groups.yaml").write_text("groups:\n  g: {heading: 'A', dataset: dtu, metric: chamfer, "
                                                "sweep: a_ablation}\n")
    monkeypatch.setattr(files, "CONFIG_ROOT", tmp_path)
    assert [(c.text, c.paper, c.method, c.sweep) for c in load_claims()] == [
        ("a better than a_without_x", "0.50 vs –", "a", "a_ablation"),
        ("a_k=5 better than a_k=1", "0.60 vs –", "a", "a_ablation")]
