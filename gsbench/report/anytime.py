"""Error against training time (docs/report.md §10): a board's curves (`gsbench.report.joins`) as series of
points over seeds, and their values at time budgets.

**Time** of a point: its training CPU-seconds (``train_cpu_seconds``), else, where the record has none, its wall
seconds of training (``train_seconds``): such a point is *wall-timed*, and the plots and tables say so. Only the
ok points of ok runs that have the board's metric count.

**Series** (`scene_series`, `mean_series`). Per curve, scene and schedule length (``train.iterations``), the
points are matched by step across seeds: at each step the mean time and the mean value over the seeds that have
it, the band from their minimum to their maximum. Over the board's scenes, a step counts where every scene has
it: the means over scenes of those per-scene means, the band the minimum to maximum over the seeds present on
every scene of each seed's mean over scenes.

**Value at a budget B** (`value_at`) of a curve on a (scene, seed) pair: the value of the latest of its points
on that pair with time <= B (its joined rows' runs pooled; ties: the longer schedule, then the later step);
*not reached* when there is none. A curve's *pairs* are the pairs on which it has a point. It is *eligible* at B
when its pairs cover every scene of the board and it has a value at B on each of them; its value at B is then
the mean over its pairs (`Standing`). Eligible curves rank by that mean; the best is tested against the
runner-up with `gsbench.report.stats.paired_test` over the pairs both have (`budget_results`).

**Accuracy to reach** (`accuracy_to_reach`): the median of the curves' final values (their values at no limit,
over the curves eligible there). Half the curves reach it by their end, so the time at which each does
(`first_reached`: the earliest time of its points at which it is eligible and at least as good) separates fast
from slow on any board, whatever its scenes' scale; a fixed one (1 mm) would be reached by every curve of one
board and by none of another.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass

from gsbench.report.aggregate import Board
from gsbench.report.collect import Run
from gsbench.report.joins import Curve
from gsbench.report.stats import PairedTest, paired_test

BUDGETS = (60.0, 300.0, 900.0, 3600.0)  # CPU-seconds: 1, 5, 15 and 60 minutes of one core


@dataclass(frozen=True)
class Timed:
    """One ok point of one run with the board's metric."""

    scene: str
    seed: int
    iterations: int
    step: int
    time: float
    wall: bool  # timed by wall seconds: the record has no CPU seconds for it
    value: float


def timed_points(run: Run, metric: str) -> list[Timed]:
    """The ok points of ``run`` (none unless it is ok) that have ``metric`` and a time, in step order."""
    if not run.ok:
        return []
    seed = -1 if run.seed is None else run.seed
    timed = []
    for point in run.points:
        time = point.cpu_seconds if point.cpu_seconds is not None else point.seconds
        if point.ok and metric in point.metrics and time is not None:
            timed.append(Timed(run.scene, seed, run.iterations or 0, point.step, time, point.cpu_seconds is None,
                               point.metrics[metric]))
    return timed


@dataclass(frozen=True)
class CurvePoint:
    """A step of a series: mean time and value, the band ``low``–``high`` (min–max over ``seeds`` seeds; over the
    scenes, the seeds present on every scene, none: no band)."""

    iterations: int
    step: int
    time: float
    value: float
    low: float
    high: float
    seeds: int
    wall: bool  # some of its points are wall-timed


def _per_seed(curve: Curve, scene: str, metric: str) -> dict[tuple[int, int], dict[int, tuple[float, float, bool]]]:
    """(iterations, step) -> seed -> (time, value, wall) on ``scene``; several runs on one seed averaged."""
    found: dict[tuple[int, int], dict[int, list[Timed]]] = {}
    for run in curve.runs:
        if run.scene == scene:
            for point in timed_points(run, metric):
                found.setdefault((point.iterations, point.step), {}).setdefault(point.seed, []).append(point)
    return {key: {seed: (statistics.fmean(p.time for p in points), statistics.fmean(p.value for p in points),
                         any(p.wall for p in points)) for seed, points in by_seed.items()}
            for key, by_seed in sorted(found.items())}


def _point(key: tuple[int, int], times: list[float], values: list[float], band: list[float], seeds: int,
           wall: bool) -> CurvePoint:
    return CurvePoint(key[0], key[1], statistics.fmean(times), statistics.fmean(values), min(band), max(band),
                      seeds, wall)


def scene_series(curve: Curve, scene: str, metric: str) -> list[CurvePoint]:
    """The curve's points on ``scene``, in (iterations, step) order (module docstring)."""
    series = []
    for key, seeds in _per_seed(curve, scene, metric).items():
        values = [value for _, value, _ in seeds.values()]
        series.append(_point(key, [time for time, _, _ in seeds.values()], values, values, len(values),
                             any(wall for _, _, wall in seeds.values())))
    return series


def mean_series(curve: Curve, scenes: list[str], metric: str) -> list[CurvePoint]:
    """The curve's points over every one of ``scenes``, in (iterations, step) order (module docstring)."""
    per_scene = [_per_seed(curve, scene, metric) for scene in scenes]
    if not per_scene:
        return []
    series = []
    for key in sorted(set.intersection(*(set(cells) for cells in per_scene))):
        cells = [cells[key] for cells in per_scene]
        times = [statistics.fmean(t for t, _, _ in seeds.values()) for seeds in cells]
        values = [statistics.fmean(v for _, v, _ in seeds.values()) for seeds in cells]
        common = sorted(set.intersection(*(set(seeds) for seeds in cells)))
        band = [statistics.fmean(seeds[seed][1] for seeds in cells) for seed in common] or [statistics.fmean(values)]
        series.append(_point(key, times, values, band, len(common),
                             any(w for seeds in cells for _, _, w in seeds.values())))
    return series


def board_series(board: Board, made: list[Curve]) -> dict[str | None, dict[str, list[CurvePoint]]]:
    """Panel -> curve label -> series: a panel per scene of the board, and None for the mean over its scenes;
    curves without a point in a panel are left out of it."""
    metric = board.spec.name
    panels: dict[str | None, dict[str, list[CurvePoint]]] = {}
    for scene in [*board.scenes, None]:
        panel = {}
        for curve in made:
            series = mean_series(curve, board.scenes, metric) if scene is None else scene_series(curve, scene, metric)
            if series:
                panel[curve.label] = series
        panels[scene] = panel
    return panels


def pooled_points(board: Board, curve: Curve) -> dict[tuple[str, int], list[Timed]]:
    """(scene, seed) -> the curve's points there on the board's scenes, sorted by (time, iterations, step)."""
    pairs: dict[tuple[str, int], list[Timed]] = {}
    for run in curve.runs:
        if run.scene in board.scenes:
            for point in timed_points(run, board.spec.name):
                pairs.setdefault((point.scene, point.seed), []).append(point)
    return {pair: sorted(points, key=lambda p: (p.time, p.iterations, p.step))
            for pair, points in sorted(pairs.items())}


def value_at(points: list[Timed], budget: float) -> Timed | None:
    """The latest of ``points`` (sorted as `pooled_points` sorts them) with time <= ``budget``; None if none."""
    reached = [point for point in points if point.time <= budget]
    return reached[-1] if reached else None


@dataclass(frozen=True)
class Standing:
    """A curve at a budget: pair -> its point there (None: not reached); ``eligible`` (module docstring)."""

    curve: Curve
    budget: float
    reached: dict[tuple[str, int], Timed | None]
    eligible: bool

    @property
    def values(self) -> dict[tuple[str, int], float]:
        return {pair: point.value for pair, point in self.reached.items() if point is not None}

    @property
    def mean(self) -> float | None:
        """Mean over the curve's pairs when it is eligible, else None."""
        return statistics.fmean(self.values.values()) if self.eligible else None

    @property
    def wall(self) -> bool:
        """Some of the points it stands on are wall-timed."""
        return any(point.wall for point in self.reached.values() if point is not None)


def standing(board: Board, curve: Curve, budget: float, pooled: dict | None = None) -> Standing:
    """``curve`` at ``budget`` (``pooled``: its `pooled_points`, computed when None)."""
    pooled = pooled_points(board, curve) if pooled is None else pooled
    reached = {pair: value_at(points, budget) for pair, points in pooled.items()}
    covered = {scene for scene, _ in pooled} >= set(board.scenes)
    return Standing(curve, budget, reached, bool(pooled) and covered and all(p is not None for p in reached.values()))


def _key(board: Board, value: float) -> float:
    """Sort key putting the better value first."""
    return -value if board.spec.higher_is_better else value


@dataclass(frozen=True)
class BudgetResult:
    """A budget: the eligible curves best first, the others, and the best against the runner-up (None with
    fewer than two eligible)."""

    budget: float
    ranked: list[Standing]
    others: list[Standing]
    test: PairedTest | None


def budget_results(board: Board, made: list[Curve], budgets=BUDGETS) -> list[BudgetResult]:
    """Each of ``budgets`` on ``board`` (module docstring)."""
    pooled = {curve.label: pooled_points(board, curve) for curve in made}
    results = []
    for budget in budgets:
        at = [standing(board, curve, budget, pooled[curve.label]) for curve in made]
        ranked = sorted((s for s in at if s.eligible), key=lambda s: (_key(board, s.mean), s.curve.label))
        test = None
        if len(ranked) >= 2:
            best, runner_up = ranked[0].values, ranked[1].values
            shared = sorted(set(best) & set(runner_up))
            test = paired_test([best[pair] - runner_up[pair] for pair in shared], bool(board.spec.higher_is_better))
        results.append(BudgetResult(budget, ranked, [s for s in at if not s.eligible], test))
    return results


def accuracy_to_reach(board: Board, made: list[Curve]) -> float | None:
    """The median of the curves' final means, over the curves eligible at no limit; None when none is."""
    finals = [s.mean for s in (standing(board, curve, math.inf) for curve in made) if s.eligible]
    return statistics.median(finals) if finals else None


def first_reached(board: Board, curve: Curve, target: float) -> Standing | None:
    """The curve at the earliest time of its points at which it is eligible and its mean is at least as good as
    ``target``; None when it never is."""
    pooled = pooled_points(board, curve)
    for time in sorted({point.time for points in pooled.values() for point in points}):
        at = standing(board, curve, time, pooled)
        if at.eligible and _key(board, at.mean) <= _key(board, target):
            return at
    return None
