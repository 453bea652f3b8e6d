"""What one factor of a scene costs each method: the report's tables of twin scenes.

A built-in scene may be the twin of another, made from it with one factor changed
(`gsbench.data.synthetic.builtin.BuiltinScene`: ``twin_of`` and ``factor``; each glass scene is its opaque
twin made transparent, ``dtu-bunny-far`` is ``dtu-bunny`` framed at 12.6% of the image). For each dataset
and factor with runs on both scenes of a pair, one table: a line per row (a method configuration, as on the
leaderboard) and pair, and a line per row over all the factor's pairs. A line's values are over its
(pair, seed) matches: the row's ok run on the changed scene against its ok run of the same seed on the twin
(several runs on one side: averaged). For each metric of `TWIN_METRICS` and the training wall time:

- the twin's and the changed scene's value: their means over the matches with that value;
- Δ = changed − twin, the mean of the matches' differences, and the paired test of those differences
  (`gsbench.report.stats.paired_test`), starred when p < 0.05.

A Δ in the metric's bad direction is what the factor costs the row; two rows' Δ compare what it costs them
(whether a method made for the factor, such as ray tracing for glass, recovers it).
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass
from pathlib import Path

from gsbench.data.synthetic.builtin import BUILTIN_SCENES
from gsbench.report.aggregate import natural_key
from gsbench.report.collect import Run
from gsbench.report.metrics import MetricSpec
from gsbench.report.stats import ALPHA, PairedTest, paired_test
from gsbench.report.tables import MISSING, Table, TCell, number, plain
from gsbench.report.views import TIMES_NOTE, p_text, slug, star

TWIN_METRICS = {"dtu": ("chamfer", "completeness", "psnr"), "tnt": ("f1", "recall", "psnr")}
ALL_PAIRS = "all"


@dataclass(frozen=True)
class TwinPair:
    """``changed`` is ``twin`` with ``factor`` changed (display names, the last part of the scene names)."""

    changed: str
    twin: str
    factor: str


def twin_pairs() -> list[TwinPair]:
    """Every pair of the built-in table, sorted by factor and changed scene."""
    pairs = [TwinPair(Path(name).name, Path(scene.twin_of).name, scene.factor)
             for name, scene in BUILTIN_SCENES.items() if scene.twin_of]
    return sorted(pairs, key=lambda p: (p.factor, natural_key(p.changed)))


def changed_scenes(factor: str) -> set[str]:
    """The display names of the scenes made from their twins with ``factor`` changed."""
    return {pair.changed for pair in twin_pairs() if pair.factor == factor}


def _matches(runs: list[Run], pairs: list[TwinPair], read) -> list[tuple[float, float]]:
    """[(twin, changed)] over the (pair, seed) matches of ``runs``: a pair's two scenes each with an ok run of that
    seed with a value (several runs on one side: averaged)."""
    by_key: dict[tuple, list[float]] = {}
    for run in runs:
        value = read(run) if run.ok else None
        if value is not None:
            by_key.setdefault((run.scene, run.seed), []).append(value)
    matches = []
    for pair in pairs:
        seeds = {seed for scene, seed in by_key if scene == pair.changed}
        seeds &= {seed for scene, seed in by_key if scene == pair.twin}
        for seed in sorted(seeds, key=lambda s: -1 if s is None else s):
            matches.append((statistics.fmean(by_key[(pair.twin, seed)]),
                            statistics.fmean(by_key[(pair.changed, seed)])))
    return matches


def _sides(matches: list[tuple[float, float]], digits: int) -> list[TCell]:
    """The twin's and the changed scene's mean over the matches."""
    if not matches:
        return [TCell(MISSING), TCell(MISSING)]
    twin, changed = (statistics.fmean(side) for side in zip(*matches))
    return [TCell(number(twin, digits), twin), TCell(number(changed, digits), changed)]


def _delta_cell(test: PairedTest, digits: int) -> TCell:
    if test.mean_diff is None:
        return TCell(MISSING)
    return TCell(f"{test.mean_diff:+.{digits}f}{star(test)} (p {p_text(test.p)}, {test.n})", test.mean_diff,
                 "bad" if test.b_better else "")


def twin_tables(runs: list[Run], specs: dict[str, MetricSpec]) -> list[Table]:
    """One table per dataset and factor that the runs cover (module docstring); none without twin runs."""
    tables = []
    for dataset, metrics in TWIN_METRICS.items():
        mine = [r for r in runs if r.dataset == dataset]
        scenes = {r.scene for r in mine}
        by_factor: dict[str, list[TwinPair]] = {}
        for pair in twin_pairs():
            if pair.changed in scenes and pair.twin in scenes:
                by_factor.setdefault(pair.factor, []).append(pair)
        for factor, pairs in by_factor.items():
            tables.append(_factor_table(dataset, factor, pairs, mine, [specs.get(m) or MetricSpec(m, False, "")
                                                                        for m in metrics]))
    return tables


def _factor_table(dataset: str, factor: str, pairs: list[TwinPair], runs: list[Run],
                  specs: list[MetricSpec]) -> Table:
    header = ["method", "scenes (changed / twin)"]
    for spec in specs:
        header += [f"{spec.label}: twin", f"{spec.label}: changed", f"Δ {spec.label}"]
    header += ["train (s): twin", "train (s): changed"]
    scenes = {scene for pair in pairs for scene in (pair.changed, pair.twin)}
    rows_of: dict[str, list[Run]] = {}
    for run in runs:
        if run.scene in scenes:
            rows_of.setdefault(run.row, []).append(run)
    lines = []
    for name in sorted(rows_of, key=natural_key):
        row_runs = rows_of[name]
        groups = [(f"{p.changed} / {p.twin}", [p]) for p in pairs]
        if len(pairs) > 1:
            groups.append((f"{ALL_PAIRS} ({len(pairs)} pairs)", pairs))
        for label, group in groups:
            cells, measured = [plain(name), plain(label)], False
            for spec in specs:
                matches = _matches(row_runs, group, lambda run, m=spec.name: run.metrics.get(m))
                measured |= bool(matches)
                digits = 2 if spec.name == "psnr" else 3
                test = paired_test([c - t for t, c in matches], bool(spec.higher_is_better))
                cells += [*_sides(matches, digits), _delta_cell(test, digits)]
            cells += _sides(_matches(row_runs, group, lambda run: run.timings.get("train")), 1)
            if measured:
                lines.append(cells)
    notes = [f"Each changed scene is made from its twin with one factor changed: {factor}. A line's values are "
             f"means over its (pair, seed) matches: a pair's two scenes each with an ok run of the row with that seed "
             f"and a value. Δ = changed − twin, with the paired test's p and the number of matches "
             f"(`gsbench.report.twins`); *: p < {ALPHA}; a Δ marked bad is significantly worse on the changed scene. "
             f"A line without any match is left out.", TIMES_NOTE]
    title = f"{dataset}: what '{factor}' costs each method"
    return Table(f"twins-{slug(dataset)}-{slug(factor)}", title, header, lines, notes)
