"""Pareto fronts of cost (time, memory, Gaussians) against error.

A point is on the front when no other point is at least as good in both cost and error and strictly
better in one. Cost is always minimised; the error is minimised, or maximised for a score such as F1.
Equal points are all on the front. `cost_points` applies this to the rows of a board (their final results),
`step_points` to every step of a board's curves of error against training time (docs/report.md §10.4).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from gsbench.report.aggregate import Board
from gsbench.report.anytime import CurvePoint


def pareto_front(points: list[tuple[float, float]], higher_is_better: bool = False) -> list[int]:
    """Indices (ascending) of the non-dominated ``(cost, value)`` points."""
    sign = -1.0 if higher_is_better else 1.0
    keyed = [(cost, sign * value) for cost, value in points]

    def dominates(a, b) -> bool:
        return a[0] <= b[0] and a[1] <= b[1] and (a[0] < b[0] or a[1] < b[1])

    return [i for i, p in enumerate(keyed) if not any(dominates(q, p) for q in keyed)]


COSTS = {  # Row.speed key -> (short name, axis label)
    "train": ("train", "training time (s)"),
    "total": ("total", "total time (s)"),
    "train_rss": ("memory", "peak RSS in training (MiB)"),
    "gaussians": ("Gaussians", "Gaussians"),
}


@dataclass(frozen=True)
class Point:
    """One row of a board against one cost: its mean cost, its mean metric over scenes, whether it
    covers every scene (only such rows compete for the front), and whether it is on the front; the 95%
    half-widths of both (`value_interval`, the cost's t-interval over its runs), None where a scene or the
    cost has a single run."""

    row: str
    cost: float
    value: float
    complete: bool
    front: bool
    cost_ci: float | None = None
    value_ci: float | None = None


def value_interval(board: Board, row) -> float | None:
    """Half-width of the 95% interval of a row's mean over its S scenes, from the scenes' t-intervals as
    independent: sqrt(Σ h_s²) / S; None unless every scene of the row has one."""
    stats = [row.cells[s].stat for s in board.scenes if row.cells.get(s) is not None and row.cells[s].stat]
    if not stats or any(s.ci is None for s in stats):
        return None
    return math.sqrt(sum(s.ci ** 2 for s in stats)) / len(stats)


def cost_points(board: Board, cost: str) -> list[Point]:
    """The rows of ``board`` that have both a mean ``cost`` (a `COSTS` key) and a mean metric."""
    raw = []
    for row in board.rows:
        value, complete = board.mean(row)
        spent = row.speed.get(cost)
        if value is not None and spent is not None:
            raw.append((row.name, spent.mean, value, complete, spent.ci, value_interval(board, row)))
    competing = [i for i, p in enumerate(raw) if p[3]]
    front = {competing[j] for j in pareto_front([raw[i][1:3] for i in competing], board.spec.higher_is_better)}
    return [Point(name, spent, value, complete, i in front, cost_ci, value_ci)
            for i, (name, spent, value, complete, cost_ci, value_ci) in enumerate(raw)]


@dataclass(frozen=True)
class StepPoint:
    """A step of a curve (`gsbench.report.anytime.CurvePoint`: its schedule length, step, mean time and value,
    whether wall-timed) and whether it is on the front of all the curves' steps."""

    curve: str
    point: CurvePoint
    front: bool


def step_points(series: dict[str, list[CurvePoint]], higher_is_better: bool) -> list[StepPoint]:
    """Every step of every curve of ``series`` (curve label -> its points), in that order, with the front over
    all of them (time against value)."""
    steps = [(label, point) for label, points in series.items() for point in points]
    front = set(pareto_front([(point.time, point.value) for _, point in steps], higher_is_better))
    return [StepPoint(label, point, i in front) for i, (label, point) in enumerate(steps)]
