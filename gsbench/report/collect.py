"""Read what a report is built from, a runs folder or a board's records file (`gsbench.report.records_file`):
run records and sweep manifests, as plain immutable values.

In a runs folder, records are found anywhere below it (``**/record.json``), so one report can cover several
``--out`` folders. A record that cannot be read, or lacks the identity fields, becomes a warning, never a crash.
The same run id found twice is kept once, preferring an ``ok`` record, then the newest, then the first path.

A run's `RunPoint`s are its evaluations along training (the record's ``points``, docs/report.md §10); a record
without them (written before they existed) has one, its final result, built from its metrics and timings.

A scene folder named ``<scene>-<W>`` whose images are W pixels wide (the record's ``inputs.source_resolution``),
beside runs of the same dataset on ``<scene>``, is that scene rendered at another image size (``gsbench scene make
NAME --res W H`` draws the same cameras and ground truth at that size; the papers' preset ran on such a folder,
docs/results/README.md): `merge_resized_scenes` shows its runs as runs on ``<scene>``, beside the other presets'.

Rows of a leaderboard are configurations, not just methods: `label_variants` names each run by the config keys
whose values differ between runs of the same method on the same scene (e.g. ``method.knn_k=5``); keys that
follow from the preset are named by ``preset=...`` alone.

Sweep manifests (``sweeps/<name>.json``, written by ``gsbench sweep``; `gsbench.runs.sweep.Manifest`) give the
row labels of ablations; a run's status comes from its record (an entry without one is missing).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from gsbench.config.run_config import completed_config
from gsbench.errors import GsbenchError
from gsbench.report.records_file import board_file, read_board
from gsbench.run_folder import RunFolder
from gsbench.runs.records import final_point, flatten

RECORD_NAME = RunFolder.RECORD
# Identity and execution keys: they never distinguish two configurations of one method (the evaluation points
# do not change what a run trains, its final result included: issue 63's test of the runner).
NOT_A_VARIANT = ("seed", "scene", "out", "threads", "eval.points")
PRESET_KEY = "preset"
REQUIRED = ("run_id", "method", "dataset", "scene")


@dataclass(frozen=True)
class RunPoint:
    """One evaluation of a run along its training (an entry of the record's ``points``): the step, the seconds
    of training so far (``seconds`` wall, ``cpu_seconds`` the process's CPU, None where unknown; evaluation
    excluded) and the finite metrics; ``ok``: it was evaluated (a failed point has no metrics)."""

    step: int
    ok: bool
    seconds: float | None
    cpu_seconds: float | None
    metrics: dict


@dataclass(frozen=True)
class Run:
    """One run record, flattened to what the report reads. ``scene`` is the display name (the last
    path part of the record's scene, as in the runs folder); ``variant`` is set by `label_variants`."""

    run_id: str
    dataset: str
    scene: str
    method: str
    seed: int | None
    status: str
    path: str
    metrics: dict
    timings: dict
    it_per_s: float | None
    num_gaussians: int | None
    train_peak_rss_bytes: int | None  # process high-water mark through training (`_run`)
    threads: int | None
    iterations: int | None
    eval_protocol: dict
    environment: dict
    error_tail: str
    config: dict
    variant: str = ""
    skipped: dict = field(default_factory=dict)  # evaluator -> why it could not score the scene (record ``skipped``)
    densify_budget: dict = field(default_factory=dict)  # record ``densify_budget`` (gsbench.report.budget)
    points: tuple[RunPoint, ...] = ()  # in step order, the last the final result (module docstring)
    source_width: int | None = None  # the scene's image width on disk (record ``inputs.source_resolution``)
    scene_folder: str = ""  # the folder's name when `merge_resized_scenes` shows the run on another scene

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def row(self) -> str:
        """The leaderboard row name: the method, plus its variant when it has one."""
        return f"{self.method} [{self.variant}]" if self.variant else self.method


@dataclass(frozen=True)
class ManifestRun:
    run_id: str
    label: str
    method: str
    scene: str


@dataclass(frozen=True)
class Manifest:
    """A sweep manifest; ``path`` is relative to the runs folder."""

    name: str
    description: str
    file: str
    path: str
    runs: tuple[ManifestRun, ...]


@dataclass(frozen=True)
class Source:
    """What a report reads, as (path, JSON) pairs with the warnings of what could not be read. ``runs_dir`` is
    the runs folder (its run folders hold meshes and unfinished runs), None for a records file, whose folder
    (a board's, holding its earlier pictures) is ``board_dir``."""

    name: str
    records: list[tuple[str, object]]
    manifests: list[tuple[str, object]]
    record_warnings: list[str]
    manifest_warnings: list[str]
    runs_dir: Path | None = None
    board_dir: Path | None = None


def _read_json(folder: Path, pattern: str, what: str) -> tuple[list[tuple[str, object]], list[str]]:
    found, warnings = [], []
    for rel in sorted(path.relative_to(folder).as_posix() for path in folder.rglob(pattern)):
        path = folder / rel
        try:
            found.append((rel, json.loads(path.read_text())))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            warnings.append(f"{rel}: unreadable {what} skipped ({type(exc).__name__}: {exc})")
    return found, warnings


def read_source(path) -> Source:
    """The records and manifests of a runs folder or of a board's records file (or a folder holding one); a
    GsbenchError when ``path`` does not exist."""
    path = Path(path)
    if not path.exists():
        raise GsbenchError(f"runs folder '{path}' does not exist (expected the --out folder of gsbench run/sweep, or "
                           "a board's records.jsonl.gz)")
    file = board_file(path)
    if file is not None:
        board = read_board(file)
        return Source(str(file), sorted(board.records.items()), sorted(board.manifests.items()), board.warnings, [],
                      board_dir=file.parent)
    records, record_warnings = _read_json(path, RECORD_NAME, "record")
    manifests, manifest_warnings = _read_json(path, "sweeps/*.json", "sweep manifest")
    return Source(str(path), records, manifests, record_warnings, manifest_warnings, runs_dir=path)


def _number(value):
    return value if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def _finite_metrics(metrics) -> dict:
    """The finite numbers of a ``metrics`` mapping, as floats: a non-finite metric is no measurement."""
    return {k: float(v) for k, v in (metrics or {}).items() if _number(v) is not None and math.isfinite(v)}


def _recorded_points(points) -> tuple[RunPoint, ...] | None:
    """The record's ``points`` as `RunPoint`s; None when they are malformed (not a list of objects, each with
    an integer ``step`` and a ``status``)."""
    if not isinstance(points, list):
        return None
    read = []
    for point in points:
        if not (isinstance(point, dict) and isinstance(point.get("step"), int) and "status" in point):
            return None
        metrics = point.get("metrics")
        read.append(RunPoint(step=point["step"], ok=point["status"] == "ok",
                             seconds=_number(point.get("train_seconds")),
                             cpu_seconds=_number(point.get("train_cpu_seconds")),
                             metrics=_finite_metrics(metrics) if isinstance(metrics, dict) else {}))
    return tuple(read)


def _final_point(data: dict, ok: bool, iterations) -> RunPoint:
    """A record without ``points``: its final result as its one point (`gsbench.runs.records.final_point`: the
    refinement's seconds added to training's); a run that did not end ok: a failed point at its last step."""
    if ok and iterations:
        return _recorded_points([final_point(data)])[0]
    return RunPoint(step=int(iterations or 0), ok=False, seconds=None, cpu_seconds=None, metrics={})


def _run(data: dict, rel: str) -> tuple[Run, list[str]]:
    """The `Run` of a record, and the warnings about it (malformed ``points``)."""
    config = data.get("config") if isinstance(data.get("config"), dict) else {}
    environment = data.get("environment") if isinstance(data.get("environment"), dict) else {}
    # the record's high-water mark at the end of training: extraction and evaluation, the same for every
    # method and dominated by the evaluator's ground truth, are left out of the method's memory
    train_rss = _number((data.get("peak_rss_bytes") or {}).get("train"))
    threads = environment.get("threads") if _number(environment.get("threads")) else _number(config.get("threads"))
    train = config.get("train") if isinstance(config.get("train"), dict) else {}
    iterations = _number(train.get("iterations"))
    # a non-finite metric is no measurement: the run then counts as "no metric"
    metrics = _finite_metrics(data.get("metrics"))
    timings = {k: float(v) for k, v in (data.get("timings") or {}).items() if _number(v) is not None}
    # evaluators the plan left out (records from before the field have none)
    skipped = data.get("skipped") if isinstance(data.get("skipped"), dict) else {}
    # how the Gaussian budget bound training (records from before the field have none)
    budget = data.get("densify_budget") if isinstance(data.get("densify_budget"), dict) else {}
    status = str(data.get("status") or "unknown")
    size = (data.get("inputs") or {}).get("source_resolution") if isinstance(data.get("inputs"), dict) else None
    source_width = size[0] if isinstance(size, list) and size and isinstance(size[0], int) else None
    points = _recorded_points(data.get("points", []))
    warnings = []
    if points is None:
        warnings.append(f"{rel}: 'points' is not a list of points (each an object with an integer 'step' and a "
                        "'status'): only its final result is drawn; fix: re-run it, or remove 'points' from the record")
    if not points:  # a record from before points (or a run that failed before its first one)
        points = (_final_point(data, status == "ok", iterations),)
    run = Run(
        run_id=str(data["run_id"]), dataset=str(data["dataset"]), scene=Path(str(data["scene"]).rstrip("/")).name,
        method=str(data["method"]), seed=_number(data.get("seed")), status=status,
        path=rel, metrics=metrics, timings=timings, it_per_s=_number(data.get("it_per_s")),
        num_gaussians=_number(data.get("num_gaussians")), train_peak_rss_bytes=train_rss,
        threads=threads, iterations=iterations,
        eval_protocol=data.get("eval_protocol") if isinstance(data.get("eval_protocol"), dict) else {},
        environment=environment, error_tail=str(data.get("error_tail") or ""), config=flatten(completed_config(config)),
        skipped={str(k): " ".join(str(v).split()) for k, v in skipped.items()}, densify_budget=budget,
        points=points, source_width=source_width,
    )
    return run, warnings


def _keep_first(copies: list[Run]) -> list[Run]:
    """Duplicates of one run id ordered by preference: ok first, then the newest end time, then path."""
    ordered = sorted(copies, key=lambda r: r.path)
    ordered.sort(key=lambda r: str(r.environment.get("time_end_utc") or r.environment.get("time_utc") or ""),
                 reverse=True)
    ordered.sort(key=lambda r: not r.ok)
    return ordered


def unfinished_folders(source: Source) -> list[str]:
    """Run folders of a runs folder (relative paths) that hold a run's config or checkpoint but no record: runs
    killed before they wrote one (`gsbench run` with the same settings resumes them). A folder inside a run
    folder that has its record (a second stage's, SuGaR's ``refine/``) belongs to that finished run."""
    runs_dir = source.runs_dir
    if runs_dir is None:
        return []
    folders = {p.parent for name in (RunFolder.CONFIG, RunFolder.CHECKPOINT, RunFolder.FINAL_CHECKPOINT)
               for p in runs_dir.rglob(name)}

    def finished_parent(folder: Path) -> bool:
        return any(RunFolder(parent).record.is_file() for parent in folder.parents if parent != runs_dir
                   and runs_dir in parent.parents)

    return sorted(f.relative_to(runs_dir).as_posix() for f in folders
                  if not RunFolder(f).record.is_file() and not finished_parent(f))


def load_runs(source) -> tuple[list[Run], list[str]]:
    """Every readable record of ``source`` (a `Source`, or a path for `read_source`), one per run id, sorted; and
    the warnings. A source without a readable record is a GsbenchError naming it (and each damaged record)."""
    source = source if isinstance(source, Source) else read_source(source)
    found: dict[str, list[Run]] = {}
    warnings = list(source.record_warnings)
    for rel, data in source.records:
        missing = [k for k in REQUIRED if not isinstance(data, dict) or data.get(k) in (None, "")]
        if missing:
            warnings.append(f"{rel}: record without {', '.join(missing)} skipped")
            continue
        run, run_warnings = _run(data, rel)
        warnings += run_warnings
        non_finite = sorted(k for k, v in (data.get("metrics") or {}).items() if _number(v) is not None
                            and not math.isfinite(v))
        if run.ok and non_finite:
            warnings.append(f"{rel}: status ok, but {', '.join(non_finite)} not finite (NaN or infinite): shown as "
                            "missing; fix: look at that run's evaluation (eval.json) and re-run it")
        found.setdefault(run.run_id, []).append(run)
    if not found and warnings:
        raise GsbenchError(f"no readable run record in '{source.name}': {len(warnings)} damaged: {'; '.join(warnings)} "
                           "(fix: re-run those runs; gsbench run resumes from their checkpoints)")
    if not found:
        raise GsbenchError(
            f"no run records ({RECORD_NAME}) under '{source.name}'; expected "
            f"<dataset>/<scene>/<method>/<run_id>/{RECORD_NAME} (fix: pass the --out folder of gsbench run/sweep, or "
            "a board's records.jsonl.gz)"
        )
    runs = []
    for run_id, copies in found.items():
        copies = _keep_first(copies)
        runs.append(copies[0])
        if len(copies) > 1:
            others = ", ".join(c.path for c in copies[1:])
            warnings.append(f"run {run_id} found {len(copies)} times; using {copies[0].path}, ignoring {others}")
    runs.sort(key=lambda r: (r.dataset, r.method, r.scene, r.seed if r.seed is not None else -1, r.run_id))
    return runs, warnings


def merge_resized_scenes(runs: list[Run]) -> list[Run]:
    """The runs, those on a folder ``<scene>-<W>`` (W their images' width) of a dataset with runs on ``<scene>``
    shown on ``<scene>``, the folder's name kept in ``scene_folder`` (module docstring)."""
    scenes = {(run.dataset, run.scene) for run in runs}
    merged = []
    for run in runs:
        base, _, width = run.scene.rpartition("-")
        if base and run.source_width is not None and width == str(run.source_width) and (run.dataset, base) in scenes:
            run = dataclasses.replace(run, scene=base, scene_folder=run.scene)
        merged.append(run)
    return merged


def show_value(value) -> str:
    """A config value as row labels show it: ``unset`` for None, a string as is, else JSON."""
    if value is None:
        return "unset"
    return value if isinstance(value, str) else json.dumps(value, sort_keys=True)


def label_variants(runs: list[Run]) -> list[Run]:
    """The runs with ``variant`` set to ``key=value, ...`` over the config keys that take more than one
    value among the runs of one (dataset, method, scene); empty when a method ran one config only. When the
    preset is among them, a key with one value per preset (what the preset sets: image size, iterations,
    budget) is left to ``preset=...``; runs of different configs still never share a label."""
    values: dict[tuple, dict[str, set]] = {}
    presence: dict[tuple, dict[str, int]] = {}
    sizes: dict[tuple, int] = {}
    for run in runs:
        group = (run.dataset, run.method, run.scene)
        sizes[group] = sizes.get(group, 0) + 1
        seen, present = values.setdefault(group, {}), presence.setdefault(group, {})
        for key, value in run.config.items():
            seen.setdefault(key, set()).add(show_value(value))
            present[key] = present.get(key, 0) + 1
    varying: dict[tuple, set] = {}
    for group, seen in values.items():
        keys = varying.setdefault(group[:2], set())
        for key, options in seen.items():
            # a key that some runs of the group lack also varies
            if key not in NOT_A_VARIANT and (len(options) > 1 or presence[group][key] < sizes[group]):
                keys.add(key)
    for (dataset, method), keys in varying.items():
        if PRESET_KEY in keys:
            ours = [r for r in runs if (r.dataset, r.method) == (dataset, method)]
            keys -= {k for k in keys - {PRESET_KEY} if _follows_preset(ours, k)}
    labelled = []
    for run in runs:
        keys = sorted(varying[(run.dataset, run.method)])
        variant = ", ".join(f"{k}={show_value(run.config.get(k))}" for k in keys)
        labelled.append(dataclasses.replace(run, variant=variant))
    return labelled


def _follows_preset(runs: list[Run], key: str) -> bool:
    """Whether ``key`` takes one value among the runs of each preset: then ``preset=...`` names it."""
    by_preset: dict[str, set] = {}
    for run in runs:
        by_preset.setdefault(show_value(run.config.get(PRESET_KEY)), set()).add(show_value(run.config.get(key)))
    return all(len(values) == 1 for values in by_preset.values())


def load_manifests(source) -> tuple[list[Manifest], list[str]]:
    """Every sweep manifest of ``source`` (a `Source` or a path), sorted by path; and warnings."""
    source = source if isinstance(source, Source) else read_source(source)
    manifests, warnings = [], list(source.manifest_warnings)
    for rel, data in source.manifests:
        try:
            entries = tuple(
                ManifestRun(run_id=str(r["run_id"]), label=str(r.get("label") or "base"),
                            method=str(r.get("method", "")), scene=Path(str(r.get("scene", "")).rstrip("/")).name)
                for r in data["runs"]
            )
        except (KeyError, TypeError, AttributeError) as exc:
            warnings.append(f"{rel}: unreadable sweep manifest skipped ({type(exc).__name__}: {exc})")
            continue
        manifests.append(Manifest(name=str(data.get("name") or Path(rel).stem),
                                  description=str(data.get("description") or ""), file=str(data.get("file") or ""),
                                  path=rel, runs=entries))
    return manifests, warnings
