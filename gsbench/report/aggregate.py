"""Group runs into the rows and cells of the report and summarise them (mean, std and 95% interval
over seeds).

A `Board` is one table: rows (a configuration of a method, or a sweep label) × scenes of one dataset,
ranked by one metric. A `Cell` holds the runs of one row on one scene; its value is the mean over its
``ok`` runs that have the metric, with the sample standard deviation and the half-width of the 95%
Student t-interval of the mean (`gsbench.report.stats.t_half_width`) when there are several. The row
mean is the mean of its scene means (each scene weighs the same, as in the papers); it is ranked only
when the row has a value on every scene of the board. Missing runs are counted: for the leaderboard,
the (scene, seed) pairs a row lacks among its seeds; for a sweep, the manifest entries without a record.

A scene none of whose runs has the ranking metric, where a run's record says that metric's evaluator
was skipped (``skipped``: the scene cannot feed it, e.g. a capture without ground truth), is left off
the leaderboard (`unscored_scenes`, listed in ``Board.unscored``): its runs did not fail, they are
judged by the measures that need no ground truth (the report's own table for them).
"""

from __future__ import annotations

import re
import statistics
from dataclasses import dataclass, field

from gsbench.report.collect import Manifest, Run
from gsbench.report.metrics import DATASET_TITLES, MetricSpec, Reported
from gsbench.report.stats import t_half_width

STATUS_ORDER = ("ok", "no metric", "failed", "interrupted", "running", "missing")
SPEED = {  # key -> how to read it from a run
    "train": lambda r: r.timings.get("train"),
    "train_cpu": lambda r: r.timings.get("train_cpu"),
    "total": lambda r: r.timings.get("total"),
    "it_per_s": lambda r: r.it_per_s,
    "train_rss": lambda r: r.train_peak_rss_bytes,
    "gaussians": lambda r: r.num_gaussians,
}


@dataclass(frozen=True)
class Stat:
    n: int
    mean: float
    std: float | None  # sample standard deviation; None for a single value
    ci: float | None = None  # half-width of the 95% Student t-interval of the mean; None for a single value

    @property
    def interval(self) -> tuple[float, float] | None:
        return None if self.ci is None else (self.mean - self.ci, self.mean + self.ci)


def stat(values) -> Stat | None:
    values = [float(v) for v in values if v is not None]
    if not values:
        return None
    several = len(values) > 1
    return Stat(len(values), statistics.fmean(values), statistics.stdev(values) if several else None,
                t_half_width(values) if several else None)


@dataclass
class Cell:
    runs: list[Run]
    metric: str
    missing: int = 0

    @property
    def stat(self) -> Stat | None:
        return stat(r.metrics.get(self.metric) for r in self.runs if r.ok)

    @property
    def statuses(self) -> dict[str, int]:
        counts: dict[str, int] = {}
        for run in self.runs:
            status = "no metric" if run.ok and self.metric not in run.metrics else run.status
            counts[status] = counts.get(status, 0) + 1
        if self.missing:
            counts["missing"] = self.missing
        return _ordered(counts)


@dataclass
class Row:
    name: str
    methods: list[str]
    cells: dict[str, Cell]
    speed: dict[str, Stat | None] = field(default_factory=dict)

    @property
    def runs(self) -> list[Run]:
        return [r for cell in self.cells.values() for r in cell.runs]

    def scene_mean(self, scenes: list[str]) -> tuple[float | None, int]:
        """(mean of the scene means over the scenes that have one, how many scenes have one)."""
        means = [self.cells[s].stat.mean for s in scenes if s in self.cells and self.cells[s].stat]
        return (statistics.fmean(means) if means else None), len(means)

    @property
    def counts(self) -> dict[str, int]:
        """Runs per status (``no metric``: ok without the ranking metric) plus ``missing``, in `STATUS_ORDER`."""
        counts: dict[str, int] = {}
        for cell in self.cells.values():
            for status, n in cell.statuses.items():
                counts[status] = counts.get(status, 0) + n
        return _ordered(counts)

    @property
    def threads(self) -> list:
        return sorted({r.threads for r in self.runs if r.threads is not None})

    @property
    def iterations(self) -> list:
        return sorted({r.iterations for r in self.runs if r.iterations is not None})


@dataclass
class Board:
    """One ranked table. ``grid_key``/``grid_values``: a sweep over one numeric key (shown transposed)."""

    title: str
    dataset: str
    spec: MetricSpec
    scenes: list[str]
    rows: list[Row]
    reported: dict[str, Reported] = field(default_factory=dict)
    grid_key: str | None = None
    grid_values: list[float] = field(default_factory=list)
    unscored: list[str] = field(default_factory=list)  # scenes left off: the metric's evaluator was skipped

    def mean(self, row: Row) -> tuple[float | None, bool]:
        """(row mean over scenes, whether every scene has a value)."""
        value, n = row.scene_mean(self.scenes)
        return value, n == len(self.scenes)

    def best(self, column: str) -> set[str]:
        """Names of the rows with the best value in ``column`` (a scene, or ``mean`` over complete rows)."""
        values = {}
        for row in self.rows:
            if column == "mean":
                value, complete = self.mean(row)
                if complete:
                    values[row.name] = value
            elif column in row.cells and row.cells[column].stat:
                values[row.name] = row.cells[column].stat.mean
        if not values:
            return set()
        target = (max if self.spec.higher_is_better else min)(values.values())
        return {name for name, value in values.items() if value == target}


def _ordered(counts: dict[str, int]) -> dict[str, int]:
    rank = {s: i for i, s in enumerate(STATUS_ORDER)}
    return dict(sorted(counts.items(), key=lambda kv: (rank.get(kv[0], len(rank)), kv[0])))


def make_row(name: str, runs: list[Run], metric: str, missing: dict[str, int], methods=()) -> Row:
    """A row of ``runs`` (any scenes); ``missing``: scene -> runs expected there but not found;
    ``methods``: the methods of those missing runs (a row may have no run at all)."""
    cells: dict[str, Cell] = {}
    for run in runs:
        cells.setdefault(run.scene, Cell([], metric)).runs.append(run)
    for scene, n in missing.items():
        if n:
            cells.setdefault(scene, Cell([], metric)).missing = n
    return Row(name, sorted({r.method for r in runs} | set(methods)), dict(sorted(cells.items())), speed_stats(runs))


def speed_stats(runs: list[Run]) -> dict[str, Stat | None]:
    """Each `SPEED` figure over ``runs``' ok runs. The CPU time is left out (None) unless every ok run recorded it:
    a mean over part of a row's runs would sit beside a wall time over all of them."""
    ok = [r for r in runs if r.ok]
    speed = {key: stat(read(r) for r in ok) for key, read in SPEED.items()}
    if any(SPEED["train_cpu"](r) is None for r in ok):
        speed["train_cpu"] = None
    return speed


def natural_key(name: str) -> tuple:
    """Sort key reading the numbers in a row name as numbers: ``knn_k=2`` before ``knn_k=10``."""
    parts = re.split(r"(\d+(?:\.\d+)?)", name)
    return tuple(float(p) if i % 2 else p for i, p in enumerate(parts))


def unscored_scenes(runs: list[Run], spec: MetricSpec) -> list[str]:
    """Scenes where no run has ``spec``'s metric and some run records its evaluator as skipped (any
    evaluator when ``spec`` does not name one), sorted."""
    scenes: dict[str, list[Run]] = {}
    for run in runs:
        scenes.setdefault(run.scene, []).append(run)
    unscored = []
    for scene, group in scenes.items():
        if any(spec.name in r.metrics for r in group):
            continue
        if any((spec.evaluator in r.skipped) if spec.evaluator else bool(r.skipped) for r in group):
            unscored.append(scene)
    return sorted(unscored)


def leaderboard(runs: list[Run], dataset: str, spec: MetricSpec, reported: dict[str, Reported]) -> Board:
    """The method × scene board of ``dataset``: one row per configuration (`Run.row`), sorted by name
    (`natural_key`); scenes that cannot be scored by ``spec`` are left off (`unscored_scenes`)."""
    runs = [r for r in runs if r.dataset == dataset]
    unscored = unscored_scenes(runs, spec)
    runs = [r for r in runs if r.scene not in unscored]
    scenes = sorted({r.scene for r in runs})
    groups: dict[str, list[Run]] = {}
    for run in runs:
        groups.setdefault(run.row, []).append(run)
    rows = []
    for name in sorted(groups, key=natural_key):
        group = groups[name]
        seeds = {r.seed for r in group}
        missing = {s: len(seeds - {r.seed for r in group if r.scene == s}) for s in scenes}
        rows.append(make_row(name, group, spec.name, missing))
    title = f"{DATASET_TITLES.get(dataset, dataset)} ({dataset}): {spec.label}, {spec.direction}"
    return Board(title, dataset, spec, scenes, rows, reported, unscored=unscored)


def _grid(labels: list[str]) -> tuple[str | None, list[float]]:
    """(key, values) when every label is one ``key=<number>`` of the same key; else (None, [])."""
    parts = [label.split() for label in labels]
    if not parts or any(len(p) != 1 or "=" not in p[0] for p in parts):
        return None, []
    keys = {p[0].split("=", 1)[0] for p in parts}
    try:
        values = [float(p[0].split("=", 1)[1]) for p in parts]
    except ValueError:
        return None, []
    return (keys.pop(), values) if len(keys) == 1 else (None, [])


def ablations(manifest: Manifest, by_id: dict[str, Run], specs_by_dataset: dict[str, MetricSpec]) -> list[Board]:
    """One board per dataset of a sweep: rows are its labels in manifest order (grid sweeps over one
    numeric key: in value order), cells its runs; manifest entries without a record count as missing
    (their dataset is that of the records of the same scene, or the sweep's only dataset)."""
    scene_dataset = {r.scene: r.dataset for r in by_id.values()}
    found = {by_id[e.run_id].dataset for e in manifest.runs if e.run_id in by_id}
    only = next(iter(found)) if len(found) == 1 else ""

    def dataset_of(entry) -> str:
        return by_id[entry.run_id].dataset if entry.run_id in by_id else scene_dataset.get(entry.scene, only)

    boards = []
    for dataset in sorted({dataset_of(e) for e in manifest.runs} - {""}):
        spec = specs_by_dataset.get(dataset)
        entries = [e for e in manifest.runs if dataset_of(e) == dataset]
        if spec is None:
            continue
        labels = list(dict.fromkeys(e.label for e in entries))
        key, values = _grid(labels)
        if key is not None:
            values, labels = (list(t) for t in zip(*sorted(zip(values, labels))))
        rows = []
        for label in labels:
            mine = [e for e in entries if e.label == label]
            runs = [by_id[e.run_id] for e in mine if e.run_id in by_id]
            missing: dict[str, int] = {}
            for entry in mine:
                if entry.run_id not in by_id:
                    missing[entry.scene] = missing.get(entry.scene, 0) + 1
            rows.append(make_row(label, runs, spec.name, missing, {e.method for e in mine if e.method}))
        scenes = sorted({e.scene for e in entries} | {r.scene for row in rows for r in row.runs})
        title = f"sweep {manifest.name} ({dataset}): {spec.label}, {spec.direction}"
        boards.append(Board(title, dataset, spec, scenes, rows, {}, key, values))
    return boards
