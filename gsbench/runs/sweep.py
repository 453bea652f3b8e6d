"""Sweep files: a grid of runs over one pipeline (docs/design.md §10.1), expanded and validated.

A sweep file (``configs/sweeps/*.yaml``)::

    name: ibgs_k                     # optional; default: the file name
    description: ...                 # optional, free text
    base: {method: ibgs, scene: synthetic/spot, preset: cpu, train.iterations: 1000}
    variants:                        # optional named rows (ablations); each may set method/preset too
      full: {}
      no_sadc: {method.sadc: false}
    grid: {method.knn_k: [2, 3, 4]}  # optional, cartesian product
    zip: {a.b: [1, 2], c.d: [3, 4]}  # optional, lists of one length, taken together
    scenes: [synthetic/spot]         # optional; default: base.scene
    suite: dtu-like                  # optional, instead of scenes: configs/suites/dtu-like.yaml
    seeds: [0]                       # optional; default: the suite's seeds, else [base seed or 0]
    executor: {kind: local, workers: 1, threads: 2, address: null}  # optional defaults of the CLI options
    # and, for the ray executor, scene_paths: ship (default) or shared (gsbench.runs.scene_shipping)

Every key other than ``method``, ``scene``, ``preset`` and ``seed`` is a config path (dotted, or
nested mappings that are flattened to dotted paths) applied as a ``--set`` override after the
method/dataset/preset layers. The runs are variants × grid × zip × scenes × seeds, in that order.
A ``suite`` (`gsbench.config.suites`) gives the scenes and, unless the sweep has ``seeds``, the seeds; it
excludes ``scenes``. `with_suite` applies the command line's ``--suite`` / ``--seeds`` to a loaded sweep.
`expand` resolves every run (`gsbench.runs.runner.resolve_run`: unknown keys and bad types fail with the
run's label) and checks its loss-term names against the registry, so a sweep fails before it
starts; a sweep of more than `MAX_SWEEP_RUNS` runs (`count_runs`, from the lengths of its lists) fails before
that. Each run's id is its resolved config's (`gsbench.config.run_config.run_id`), so re-running a sweep
finds the finished runs.

Running (`run_sweep`): every unfinished run is one task (`run_one`) on an executor
(`gsbench.runs.executors`: local processes or Ray); a manifest (`Manifest`, written under a file lock, so sweeps
of one name running at once keep each other's entries) records the sweep's runs and their statuses for the
report, and a summary (`SweepSummary`) says how it ended. Ctrl-C, SIGTERM and SIGHUP stop the sweep's runs (each
keeps its last checkpoint) and end it with a line naming them.
"""

from __future__ import annotations

import fcntl
import itertools
import json
import math
import os
import signal
import threading
import time
import traceback
from concurrent.futures import FIRST_COMPLETED, CancelledError, wait
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from gsbench.config.checks import check_run_config
from gsbench.config.files import load_yaml
from gsbench.config.run_config import RunConfig, parse_override
from gsbench.config.suites import SUITE_PREFIX, load_suite
from gsbench.errors import ConfigError, Interrupted
from gsbench.run_folder import RunFolder
from gsbench.runs.records import RunRecord, code_version, git_state, write_json_atomic
from gsbench.runs.run_lock import run_lock
from gsbench.runs.runner import ERROR_TAIL_LINES, resolve_run, run, run_dir

SWEEP_KEYS = ("name", "description", "base", "variants", "grid", "zip", "scenes", "suite", "seeds", "executor")
IDENTITY_KEYS = ("method", "scene", "preset", "seed")
EXECUTOR_KEYS = ("kind", "workers", "threads", "address", "scene_paths")
# The sweep waits for runs in slices of this many seconds: a SIGINT the kernel delivers to another
# thread (torch's, tqdm's) only sets CPython's flag, and an untimed wait would never look at it.
SIGNAL_POLL_SECONDS = 0.5
# Signals that stop a sweep as Ctrl-C does (`stop_signals_raised`): a batch scheduler's time limit, a closed terminal.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)
# The most runs a sweep may have (`count_runs`): expanding resolves every run, about 15 ms each, and a larger grid
# would not finish on one machine anyway.
MAX_SWEEP_RUNS = 10_000


@dataclass
class SweepRun:
    """One expanded run: its row ``label`` (variant and grid/zip values), the resolved ``config``."""

    label: str
    config: RunConfig

    @property
    def run_id(self) -> str:
        return self.config.run_id


def flatten(mapping: dict, prefix: str = "") -> dict:
    """Nested mappings -> {dotted.path: leaf}; ``method: <name>`` stays one key."""
    flat = {}
    for key, value in mapping.items():
        path = f"{prefix}{key}"
        if isinstance(value, dict) and value and path != "method":
            flat.update(flatten(value, f"{path}."))
        else:
            flat[path] = value
    return flat


def load_sweep(path) -> dict:
    """The sweep file as a checked mapping (unknown top-level keys and malformed sections fail)."""
    path = Path(path)
    data = load_yaml(path)
    unknown = set(data) - set(SWEEP_KEYS)
    if unknown:
        raise ConfigError(f"{path}: unknown sweep keys {sorted(unknown)}; valid: {', '.join(SWEEP_KEYS)}")
    for key in ("base", "variants", "grid", "zip", "executor"):
        if not isinstance(data.get(key, {}), dict):
            raise ConfigError(f"{path}: '{key}' must be a mapping")
    unknown = set(data.get("executor", {})) - set(EXECUTOR_KEYS)
    if unknown:
        raise ConfigError(f"{path}: unknown executor keys {sorted(unknown)}; valid: {', '.join(EXECUTOR_KEYS)}")
    for key in ("grid", "zip"):
        for name, values in data.get(key, {}).items():
            if not isinstance(values, list) or not values:
                raise ConfigError(f"{path}: {key}.{name} must be a non-empty list of values")
    lengths = {len(v) for v in data.get("zip", {}).values()}
    if len(lengths) > 1:
        raise ConfigError(f"{path}: every zip list must have the same length, got {sorted(lengths)}")
    for key in ("scenes", "seeds"):
        if key in data and (not isinstance(data[key], list) or not data[key]):
            raise ConfigError(f"{path}: '{key}' must be a non-empty list")
    if "suite" in data:
        if "scenes" in data:
            raise ConfigError(f"{path}: give 'suite' (its scenes and seeds) or 'scenes', not both")
        if not isinstance(data["suite"], str):
            raise ConfigError(f"{path}: 'suite' must be the name of one suite (configs/suites/<name>.yaml)")
        try:
            load_suite(data["suite"])
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from exc
    data.setdefault("name", path.stem)
    return data


def with_suite(sweep: dict, suite: str | None = None, seeds=None) -> dict:
    """``sweep`` with its scenes replaced by ``suite``'s (``--suite``; seeds from the suite unless the sweep
    has its own) and its seeds by ``seeds`` (``--seeds``); unchanged when both are None."""
    sweep = dict(sweep)
    if suite is not None:
        load_suite(suite)  # unknown names fail here, with the list of suites
        sweep.pop("scenes", None)
        sweep["suite"] = str(suite).removeprefix(SUITE_PREFIX)
    if seeds:
        sweep["seeds"] = [int(s) for s in seeds]
    return sweep


def scenes_and_seeds(sweep: dict) -> tuple[list | None, list | None]:
    """(scenes, seeds) of a sweep: its own, or its suite's (the sweep's ``seeds`` win); None: not given."""
    scenes, seeds = sweep.get("scenes"), sweep.get("seeds")
    if sweep.get("suite"):
        suite = load_suite(sweep["suite"])
        scenes, seeds = list(suite.scenes), seeds or list(suite.seeds)
    return scenes, seeds


def _rows(section: dict) -> list[dict]:
    """grid -> the cartesian product of its lists as dicts; zip -> its lists taken together."""
    keys = list(section)
    return [dict(zip(keys, values)) for values in itertools.product(*(section[k] for k in keys))]


def _label(variant: str | None, values: dict) -> str:
    parts = ([variant] if variant else []) + [f"{k}={v}" for k, v in values.items()]
    return " ".join(parts) or "base"


def count_runs(sweep: dict) -> int:
    """How many runs ``sweep`` expands to (variants × grid × zip × scenes × seeds), from the lengths of its lists,
    without resolving any."""
    scenes, seeds = scenes_and_seeds(sweep)
    zipped = sweep.get("zip", {})
    return (max(1, len(sweep.get("variants", {}))) * math.prod(len(v) for v in sweep.get("grid", {}).values())
            * (len(next(iter(zipped.values()))) if zipped else 1) * len(scenes or [None]) * len(seeds or [None]))


def check_run_count(sweep: dict) -> int:
    """`count_runs`, or a ConfigError when it is above `MAX_SWEEP_RUNS`, naming the fix."""
    count = count_runs(sweep)
    if count > MAX_SWEEP_RUNS:
        raise ConfigError(f"sweep {sweep.get('name', '')}: {count:,} runs, more than the {MAX_SWEEP_RUNS:,} a sweep may "
                          "have (variants × grid × zip × scenes × seeds); fix: split the grid into several sweep files "
                          "(give them one name: their runs share one manifest), or run a part at a time with --seeds "
                          "or --suite")
    return count


def expand(sweep: dict, overrides=()) -> list[SweepRun]:
    """Resolve every run of ``sweep`` (module docstring); ``overrides`` (``a.b=c`` texts, e.g. a
    smaller budget) apply to every run after the sweep's own settings. Every run is checked
    (`gsbench.config.checks.check_run_config`), so a bad grid value fails here, before any run starts (also with
    ``--dry-run``); errors name the run's label. A sweep of more than `MAX_SWEEP_RUNS` fails first
    (`check_run_count`)."""
    check_run_count(sweep)
    extra = {}
    for text in overrides:
        extra.update(flatten(parse_override(text)))

    base = flatten(sweep.get("base", {}))
    variants = {str(k): flatten(v or {}) for k, v in sweep.get("variants", {}).items()} or {None: {}}
    grid = _rows(sweep.get("grid", {}))
    zipped = sweep.get("zip", {})
    zip_rows = [dict(zip(zipped, values)) for values in zip(*zipped.values())] if zipped else [{}]
    scenes, seeds = scenes_and_seeds(sweep)
    runs = []
    for (variant, changes), point, paired in itertools.product(variants.items(), grid, zip_rows):
        settings = {**base, **changes, **point, **paired, **extra}
        label = _label(variant, {**point, **paired})
        for scene in scenes or [settings.get("scene")]:
            for seed in seeds or [settings.get("seed", 0)]:
                runs.append(SweepRun(label, _resolve(settings, scene, seed, label)))
    return runs


def _resolve(settings: dict, scene, seed, label: str) -> RunConfig:
    method = settings.get("method")
    if not method or not scene:
        raise ConfigError(f"sweep run '{label}': needs a method and a scene (in base, variants, grid or scenes)")
    overrides = [f"{k}={json.dumps(v)}" for k, v in settings.items() if k not in IDENTITY_KEYS]
    try:
        cfg = resolve_run(str(method), str(scene), preset=str(settings.get("preset", "cpu")),
                          overrides=overrides, seed=int(seed))
        check_run_config(cfg)
    except ConfigError as exc:
        raise ConfigError(f"sweep run '{label}' ({method} on {scene}): {exc}") from exc
    return cfg


def format_runs(runs: list[SweepRun]) -> str:
    """A plain-text table of the runs: id, method, scene, seed, label."""
    rows = [("run id", "method", "scene", "seed", "label")]
    rows += [(r.run_id, r.config.method["name"], r.config.scene, str(r.config.seed), r.label) for r in runs]
    widths = [max(len(row[i]) for row in rows) for i in range(4)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(row[:4], widths)) + "  " + row[4] for row in rows]
    lines.insert(1, "  ".join("-" * w for w in widths) + "  " + "-" * 5)
    return "\n".join(lines)


@dataclass
class RunOutcome:
    """What a task sends back to the sweep: small and picklable, whatever the executor."""

    run_id: str
    status: str  # ok | failed
    seconds: float
    error_tail: str = ""


def _quiet(*_args) -> None:
    """The runner's per-run printing, dropped: the sweep reports progress."""


def run_one(cfg: RunConfig) -> RunOutcome:
    """The task every executor runs: ``cfg`` in this process with its own thread count (``cfg.threads``).
    A failing run returns status failed with its traceback tail (the runner has written the failed
    record), so it never takes the sweep down."""
    start = time.perf_counter()
    try:
        run(cfg, echo=_quiet)
    except Exception:  # noqa: BLE001  (recorded by the runner; the sweep goes on)
        tail = "".join(traceback.format_exc().splitlines(keepends=True)[-ERROR_TAIL_LINES:])
        return RunOutcome(cfg.run_id, "failed", time.perf_counter() - start, tail)
    return RunOutcome(cfg.run_id, "ok", time.perf_counter() - start)


OTHER_CODE = ("refuse", "rerun", "keep")  # what a sweep does with finished records made by other code


def is_finished(cfg: RunConfig) -> bool:
    """The run's record exists with status ok."""
    path = RunFolder(run_dir(cfg)).record
    return path.is_file() and RunRecord.read(path).status == "ok"


def record_code(cfg: RunConfig) -> str | None:
    """The code version (`gsbench.runs.records.code_version`) the run's record was made by."""
    return code_version(RunRecord.read(RunFolder(run_dir(cfg)).record).environment or {})


def current_code() -> str | None:
    """The version of the code running now, as `record_code` reads it; None outside a git checkout."""
    return code_version(git_state())


def settle_other_code(runs: list[SweepRun], finished: set, policy: str, echo) -> set:
    """The finished runs to skip, given ``policy`` for those whose record another code version made
    (`OTHER_CODE`): ``refuse`` (a ConfigError listing them, before any run starts), ``rerun`` (their folders'
    outputs are removed and they run again), ``keep`` (skipped, and said). Records of unknown code count as
    other code; so does everything when the running code's own version is unknown."""
    if policy not in OTHER_CODE:
        raise ConfigError(f"--other-code must be one of {', '.join(OTHER_CODE)}, got {policy!r}")
    now = current_code()
    codes = {r.run_id: record_code(r.config) for r in runs if r.run_id in finished}
    other = {r.run_id: r for r in runs if r.run_id in codes and (now is None or codes[r.run_id] != now)}
    if not other:
        return finished
    versions = sorted({str(codes[run_id]) for run_id in other})
    what = (f"{len(other)} of the sweep's {len(finished)} finished runs were made by other code ({', '.join(versions)}; "
            f"now {now or 'unknown'})")
    if policy == "refuse":
        raise ConfigError(f"{what}; fix: --other-code rerun (run them again with this code) or --other-code keep "
                          "(keep their numbers; the report flags boards that mix versions)")
    if policy == "keep":
        echo(f"{what}: kept (--other-code keep)")
        return finished
    echo(f"{what}: running them again (--other-code rerun)")
    for sweep_run in other.values():
        files = RunFolder(run_dir(sweep_run.config))
        for path in (files.record, files.eval, files.mesh, files.stages, files.final_checkpoint, files.checkpoint,
                     files.metrics):
            path.unlink(missing_ok=True)
    return finished - set(other)


def read_manifest_runs(path: Path) -> list[dict]:
    """The ``runs`` entries of the manifest at ``path`` (none when there is no file)."""
    if not path.is_file():
        return []
    try:
        return list(json.loads(path.read_text())["runs"])
    except (ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f"{path}: unreadable sweep manifest ({type(exc).__name__}: {exc}); fix: move it aside "
                          "(the sweep writes a new one; its records are untouched)") from exc


def merge_manifest_runs(earlier: list[dict], now: list[dict]) -> list[dict]:
    """An earlier manifest's entries for runs that ``now`` lacks (another ``--seeds`` or ``--suite``, so a sweep
    run a seed at a time lists every seed), in their order, then ``now``'s."""
    ids = {entry["run_id"] for entry in now}
    return [entry for entry in earlier if entry.get("run_id") not in ids] + list(now)


@contextmanager
def manifest_lock(path: Path):
    """An exclusive lock on ``.<name>.lock`` beside the manifest at ``path`` (``fcntl.flock``, blocking) for the
    block: each read-modify-write of a manifest holds it, so sweeps of one name writing into one ``--out`` at once
    (started together, or one per ``--seeds``) lose none of each other's entries. The system releases it when the
    holder exits, however it exits."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path.with_name(f".{path.name}.lock"), os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the flock


class Manifest:
    """``<out>/sweeps/<name>.json``, what the report builds ablation tables from::

        {"name", "description", "file", "runs": [{"run_id", "label", "method", "scene", "seed", "dir", "status"}]}

    ``dir`` is the run folder relative to ``<out>``; ``status`` is pending, skipped (finished by an
    earlier invocation), ok, failed or cancelled (interrupted, or never started). Written when the sweep starts, an
    earlier invocation's entries for runs this one does not have kept before this one's (`merge_manifest_runs`);
    then each change puts this sweep's entries in place among those the file holds then. Every write reads the file
    and replaces it atomically under `manifest_lock`, so other sweeps of the name writing at the same time keep
    their entries."""

    def __init__(self, path: Path, *, name: str, description: str, file: str, runs: list[SweepRun], out: Path,
                 finished: set):
        self.path = path
        self.header = {"name": name, "description": description, "file": file}
        entries = [{"run_id": r.run_id, "label": r.label, "method": r.config.method["name"], "scene": r.config.scene,
                    "seed": r.config.seed, "dir": str(run_dir(r.config).relative_to(out)),
                    "status": "skipped" if r.run_id in finished else "pending"} for r in runs]
        self._by_id = {entry["run_id"]: entry for entry in entries}
        self._update(lambda earlier: merge_manifest_runs(earlier, entries))

    def set(self, run_id: str, status: str) -> None:
        self._by_id[run_id]["status"] = status
        self._update(self._with_mine)

    def _with_mine(self, runs: list[dict]) -> list[dict]:
        """``runs`` (the file's) with this sweep's entries in their places, and at the end those it lacks."""
        present = {entry.get("run_id") for entry in runs}
        return [self._by_id.get(entry.get("run_id"), entry) for entry in runs] + \
            [entry for run_id, entry in self._by_id.items() if run_id not in present]

    def _update(self, change) -> None:
        """Under the lock: the file's entries, ``change``d, written back with this sweep's header."""
        with manifest_lock(self.path):
            write_json_atomic(self.path, {**self.header, "runs": change(read_manifest_runs(self.path))})


@dataclass
class SweepSummary:
    """How a sweep ended: counts (ok, skipped, failed, cancelled), wall time, the failed runs, and the signal that
    stopped it (``SIGINT``: Ctrl-C, ``SIGTERM``, ``SIGHUP``; "" when it ran to the end)."""

    name: str
    counts: dict
    seconds: float
    failures: list  # (SweepRun, RunOutcome)
    stopped_by: str = ""

    @property
    def interrupted(self) -> bool:
        return bool(self.stopped_by)

    @property
    def exit_status(self) -> int:
        """128 + the stopping signal's number (130 for Ctrl-C, 143 for SIGTERM, 129 for SIGHUP), as a shell gives
        a process that signal ends; else 1 when a run failed, 0 when none did."""
        if self.stopped_by:
            return 128 + signal.Signals[self.stopped_by].value
        return 1 if self.counts["failed"] else 0

    def format(self, tail_lines: int = 5) -> str:
        c = self.counts
        lines = [f"sweep {self.name}{' interrupted' if self.interrupted else ''}: {c['ok']} ok, {c['skipped']} skipped "
                 f"(finished earlier), {c['failed']} failed, {c['cancelled']} cancelled in {self.seconds:.1f} s"]
        for sweep_run, outcome in self.failures:
            lines.append(f"failed: {outcome.run_id} ({sweep_run.label}), {sweep_run.config.method['name']} "
                         f"on {sweep_run.config.scene}:")
            lines += ["    " + line for line in outcome.error_tail.strip().splitlines()[-tail_lines:]]
        return "\n".join(lines)


def _unique(runs: list[SweepRun]) -> list[SweepRun]:
    """Runs with the same resolved config share a folder: each id runs once (its first row)."""
    first: dict = {}
    for sweep_run in runs:
        first.setdefault(sweep_run.run_id, sweep_run)
    return list(first.values())


def _outcome(future, sweep_run: SweepRun) -> RunOutcome:
    """The task's outcome; an executor error (a worker that died, a Ray error) is a failed run, a run stopped by a
    signal to its worker alone (`Interrupted`: its record says interrupted, it resumes) a cancelled one."""
    try:
        return future.result()
    except Interrupted as exc:
        return RunOutcome(sweep_run.run_id, "cancelled", 0.0, f"stopped by {exc}")
    except Exception as exc:  # noqa: BLE001
        return RunOutcome(sweep_run.run_id, "failed", 0.0, f"{type(exc).__name__}: {exc}")


def eta_seconds(run_seconds: list[float], left: int, slots: int) -> float | None:
    """The time the ``left`` runs still take on ``slots`` slots, from the finished runs' own measured times:
    mean(run_seconds) · ⌈left / slots⌉ (None before a run has finished)."""
    if not run_seconds:
        return None
    return sum(run_seconds) / len(run_seconds) * math.ceil(left / max(1, slots))


class _Tally:
    """A running sweep's counts, failures and unfinished runs, mirrored to the manifest, ``echo`` and one progress
    bar: runs done, running (at most the executor's ``slots``) and failed, and the `eta_seconds` of the rest."""

    def __init__(self, todo: list[SweepRun], skipped: int, manifest: Manifest, name: str, echo, slots: int = 1):
        self.counts = {"ok": 0, "skipped": skipped, "failed": 0, "cancelled": 0}
        self.failures: list = []
        self.unfinished = {sweep_run.run_id: sweep_run for sweep_run in todo}
        self.manifest, self.echo, self.slots = manifest, echo, slots
        self.run_seconds: list[float] = []
        self.bar = tqdm(total=len(todo), desc=f"sweep {name}", unit="run", disable=None)
        self._show()

    def _show(self) -> None:
        left = len(self.unfinished)
        eta = eta_seconds(self.run_seconds, left, self.slots)
        self.bar.set_postfix_str(f"running {min(left, self.slots)}, failed {self.counts['failed']}, ETA "
                                 f"{'?' if eta is None else tqdm.format_interval(eta)}")

    def finish(self, sweep_run: SweepRun, outcome: RunOutcome) -> None:
        del self.unfinished[sweep_run.run_id]
        self.counts[outcome.status] += 1
        if outcome.status == "failed":
            self.failures.append((sweep_run, outcome))
        elif outcome.status == "ok":
            self.run_seconds.append(outcome.seconds)
        self.manifest.set(sweep_run.run_id, outcome.status)
        self.bar.update()
        self._show()
        cfg = sweep_run.config
        self.echo(f"{outcome.status:<6} {cfg.method['name']} on {cfg.scene}, seed {cfg.seed} ({sweep_run.label}), "
                  f"run {cfg.run_id}, {outcome.seconds:.1f} s")

    def cancel_unfinished(self) -> None:
        for run_id in list(self.unfinished):
            del self.unfinished[run_id]
            self.counts["cancelled"] += 1
            self.manifest.set(run_id, "cancelled")


def _apply(runs: list[SweepRun], out: str | None, threads: int | None) -> list[SweepRun]:
    """Each resolved config once, with ``out`` (made absolute) and ``threads`` set when given."""
    runs = _unique(runs)
    for sweep_run in runs:
        cfg = sweep_run.config
        cfg.out = str(Path(out if out is not None else cfg.out).resolve())
        if threads is not None:
            cfg.threads = threads
    return runs


def run_sweep(runs: list[SweepRun], executor, *, name: str = "sweep", description: str = "", file: str = "",
              out: str | None = None, threads: int | None = None, other_code: str = "refuse",
              echo=tqdm.write) -> SweepSummary:
    """Run ``runs`` on ``executor`` (a `concurrent.futures.Executor`, see `gsbench.runs.executors`) and return
    the summary, also echoed.

    ``out`` and ``threads`` replace every run's own; ``out`` is made absolute (the Ray executor writes each run's
    outputs there as they come back from its node). Runs whose record has status ok are skipped, so re-running a
    sweep resumes it, when the records were made by this code; ``other_code`` says what happens to those made
    by another (`settle_other_code`). A failing run is recorded and the others go on. The manifest (`Manifest`) is
    written when the sweep starts and updated as runs finish. With an executor that runs elsewhere the sweep holds
    ``out``'s lock (`output_lock`), so a second such sweep into ``out`` is refused.

    Ctrl-C, SIGTERM or SIGHUP (`stop_signals_raised`): the runs not started are cancelled and the running ones
    are stopped at once (``executor.terminate_workers()``; an executor without it lets them finish). A stopped run
    keeps what it had written (finished stages, its last checkpoint), so re-running the sweep resumes it;
    finished records are untouched (written atomically). Both count as cancelled, one line says what was stopped
    (`_stopped_line`), and the summary has ``stopped_by`` set.
    """
    start = time.perf_counter()
    runs = _apply(runs, out, threads)
    root = Path(runs[0].config.out)
    with output_lock(executor, root):
        tally, stopped_by = _sweep(runs, executor, root, name, description, file, other_code, echo)
    summary = SweepSummary(name, tally.counts, time.perf_counter() - start, tally.failures, stopped_by)
    echo(summary.format())
    return summary


@contextmanager
def output_lock(executor, root: Path):
    """``root``'s lock (`gsbench.runs.run_lock`) held for the block when ``executor`` runs elsewhere
    (``executor.runs_elsewhere``: the Ray executor), so a second sweep there is refused, `RunLockedError` naming
    the first; nothing for a local one, whose runs lock their own folders."""
    if not getattr(executor, "runs_elsewhere", False):
        yield
        return
    with run_lock(root):
        yield


def _sweep(runs: list[SweepRun], executor, root: Path, name: str, description: str, file: str, other_code: str,
           echo) -> tuple["_Tally", str]:
    """`run_sweep` once ``runs`` are settled: (its tally, the signal that stopped it or "")."""
    finished = {sweep_run.run_id for sweep_run in runs if is_finished(sweep_run.config)}
    finished = settle_other_code(runs, finished, other_code, echo)
    todo = [sweep_run for sweep_run in runs if sweep_run.run_id not in finished]
    manifest = Manifest(root / "sweeps" / f"{name}.json", name=name, description=description, file=str(file),
                        runs=runs, out=root, finished=finished)
    tally = _Tally(todo, len(finished), manifest, name, echo, getattr(executor, "slots", 1))
    futures: dict = {}
    stopped_by = ""
    with stop_signals_raised():
        try:
            for sweep_run in todo:
                futures[executor.submit(run_one, sweep_run.config)] = sweep_run
            pending = set(futures)
            while pending:  # a timed wait: a signal delivered to another thread still wakes this one
                done, pending = wait(pending, timeout=SIGNAL_POLL_SECONDS, return_when=FIRST_COMPLETED)
                for future in sorted(done, key=list(futures).index):
                    tally.finish(futures[future], _outcome(future, futures[future]))
        except (KeyboardInterrupt, Interrupted) as exc:
            stopped_by = "SIGINT" if isinstance(exc, KeyboardInterrupt) else str(exc)
            _stop(executor, futures)
            stopped = []
            for future, sweep_run in futures.items():
                if sweep_run.run_id not in tally.unfinished or future.cancelled():
                    continue
                if future.exception() is None:
                    tally.finish(sweep_run, future.result())  # finished while the sweep was stopping
                elif isinstance(future.exception(), Interrupted):
                    stopped.append(sweep_run)  # its worker recorded it interrupted at the signal
            echo(_stopped_line(name, stopped_by, stopped, len(tally.unfinished) - len(stopped)))
            tally.cancel_unfinished()
        finally:
            tally.bar.close()
    return tally, stopped_by


@contextmanager
def stop_signals_raised():
    """In the main thread, `STOP_SIGNALS` raise `Interrupted` (its text the signal's name) for the block, as Ctrl-C
    raises KeyboardInterrupt: the sweep stops its workers instead of leaving them running when it dies. Only the
    first does: one more while the sweep stops its workers (a scheduler's second notice) is ignored. A signal that
    was ignored when the block began (``nohup`` ignores SIGHUP) stays ignored."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received = []

    def _raise(signum, _frame):
        if not received:
            received.append(signum)
            raise Interrupted(signal.Signals(signum).name)

    previous = {signum: signal.signal(signum, _raise) for signum in STOP_SIGNALS
                if signal.getsignal(signum) is not signal.SIG_IGN}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, signal.SIG_DFL if handler is None else handler)  # None: set outside Python


def _stopped_line(name: str, stopped_by: str, stopped: list[SweepRun], not_started: int) -> str:
    """What a sweep stopped by ``stopped_by`` stopped: the runs that were running (each keeps its last checkpoint) and
    how many had not started; the same command resumes them all."""
    running = "; ".join(f"{r.config.method['name']} on {r.config.scene}, seed {r.config.seed}, run {r.run_id}"
                        for r in stopped)
    return (f"sweep {name} stopped by {stopped_by}: {len(stopped)} running run{'' if len(stopped) == 1 else 's'} "
            f"stopped{f' ({running})' if stopped else ''}, {not_started} not started; the same command resumes "
            "them (a stopped run from its last checkpoint)")


def _stop(executor, futures: dict) -> None:
    """Cancel what has not started, stop what runs (when the executor can), and block until every future
    is finished or cancelled (`concurrent.futures.wait` would hang on a future cancelled by a shutdown:
    it never reaches the "cancelled and notified" state that `wait` counts)."""
    terminate = getattr(executor, "terminate_workers", None)
    if terminate is not None:
        terminate()
    else:
        executor.shutdown(wait=True, cancel_futures=True)
    for future in futures:
        with suppress(CancelledError):
            future.exception()
