"""Run records: one JSON per run, written atomically, with the environment that produced it.

Schema (docs/design.md §8.2), version `SCHEMA_VERSION`:
identity (method, scene, dataset, seed, run_id, status — ok, failed, interrupted (Ctrl-C or SIGTERM,
resumable), … — and error_tail), resolved config and effective loss
terms, ``inputs`` (what was trained on: the resolution and the size on disk, the downscale factor, the
views trained and held out, masks, the initial Gaussian count), eval protocols, metrics, ``skipped``
evaluators with the reason each could not score the scene, timings per stage in seconds (``load``, ``train``, ``extract``,
``evaluate``, ``total``; training excludes the others; ``train.<phase>``: seconds of each part of
the training step, ``render``, ``loss``, ``backward``, ``densify``, ``optimizer``, ``checks``, and
of method-specific phases inside them, e.g. IBGS ``train.knn``; docs/training.md §5), iterations/s, Gaussian count,
``densify_budget`` (``max_gaussians``, ``first_cut_step``: the first step at which the budget left
densification candidates out, null if never, ``candidates_cut``; docs/training.md §6; empty in
records of runs trained before it was tracked), peak RSS per
stage, mesh path + sha256, environment (gsbench version, git commit/dirty, package versions, CPU,
threads, OS, host, UTC start (``time_utc``: the run's first invocation's, kept when it is resumed or run again)
and end (``time_end_utc``: when the record was written), and ``switches``: the value of every result-changing
``GSBENCH_*`` switch, defaults included, `gsbench.switches`; records made before it was tracked lack it and ran at
the defaults).
A method with a second stage (SuGaR's refinement) adds ``refine`` and ``refine_cpu`` to the timings.

``points`` (anytime evaluation, docs/training.md §9): one row per point in step order, the last the run's
final result (`final_point`), each with the keys of `POINT_KEYS`: ``step``, ``fraction`` (step /
train.iterations), ``final``, ``status`` (ok or failed), ``error`` (one line, null when ok), ``train_seconds``
and ``train_cpu_seconds`` (training so far, every training stage up to the point, evaluation excluded; CPU
null where unknown), ``num_gaussians``, ``metrics`` (the names of ``metrics``; {} when failed),
``extract_seconds``, ``evaluate_seconds``. A record written before points existed has none:
`record_points` reads it as its final point alone.

A run folder keeps the switches its outputs were made with in ``switches.json``; a run resumed under other
values is refused (`check_folder_switches`), so a record never mixes them. Its ``config.yaml`` and ``record.json``
must be those of the run its name is (`check_folder_identity`): an edited one is refused by every command that reads
the folder, so no output is made or read under settings other than its run id's.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import platform
import socket
import subprocess
from dataclasses import dataclass, field
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path

import yaml

import gsbench
from gsbench.atomic import atomic_path
from gsbench.config.run_config import EXECUTION_ONLY_KEYS, completed_config, run_id
from gsbench.errors import ConfigError, one_line
from gsbench.run_folder import RunFolder
from gsbench.switches import SWITCHES, result_switches

SCHEMA_VERSION = 1
POINT_KEYS = ("step", "fraction", "final", "status", "error", "train_seconds", "train_cpu_seconds", "num_gaussians",
              "metrics", "extract_seconds", "evaluate_seconds")
STATUSES = ("ok", "failed", "interrupted", "running")  # running: a record in memory until the run ends
TRACKED_PACKAGES = ("torch", "numpy", "scipy", "open3d", "pymeshlab", "trimesh", "scikit-image", "pycolmap")
SHOWN_DIFFERENCES = 3  # changed settings a message about an edited run folder names
_ABSENT = object()  # a setting one of two configurations lacks
_EDITED = "a run folder holds the files of one run, and editing them changes nothing that run made"
_REWRITE = "delete it (`gsbench run` of this run writes it again from the folder's outputs)"


@dataclass
class RunRecord:
    """Everything one run produced; `write` stores it as ``record.json`` in the run folder."""

    run_id: str
    method: str
    scene: str
    dataset: str
    seed: int
    status: str = "running"
    error_tail: str = ""
    config: dict = field(default_factory=dict)
    losses: dict = field(default_factory=dict)
    inputs: dict = field(default_factory=dict)
    eval_protocol: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)
    points: list = field(default_factory=list)
    skipped: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    it_per_s: float | None = None
    num_gaussians: int | None = None
    densify_budget: dict = field(default_factory=dict)
    peak_rss_bytes: dict = field(default_factory=dict)
    mesh: dict = field(default_factory=dict)
    environment: dict = field(default_factory=dict)
    schema_version: int = SCHEMA_VERSION

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def write(self, path: Path) -> None:
        if self.status not in STATUSES:
            raise ValueError(f"record status must be one of {STATUSES}, got '{self.status}'")
        write_json_atomic(Path(path), self.to_dict())

    @classmethod
    def read(cls, path: Path) -> "RunRecord":
        data = json.loads(Path(path).read_text())
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in names})


def final_point(record: dict) -> dict:
    """The final point of the record ``record`` (a dict, `RunRecord.to_dict` or a ``record.json``): its metrics and
    Gaussian count at step train.iterations; its training time ``timings.train`` plus ``timings.refine`` for a
    method with a second stage, its CPU time ``train_cpu`` plus ``refine_cpu`` likewise (null when one is unknown);
    its extraction and evaluation seconds those of the ``extract`` and ``evaluate`` stages."""
    timings = record.get("timings", {})
    cpu = timings.get("train_cpu")
    if "refine" in timings:
        cpu = None if cpu is None or timings.get("refine_cpu") is None else cpu + timings["refine_cpu"]
    return {"step": int(record["config"]["train"]["iterations"]), "fraction": 1.0, "final": True, "status": "ok",
            "error": None, "train_seconds": timings.get("train", 0.0) + timings.get("refine", 0.0),
            "train_cpu_seconds": cpu, "num_gaussians": record.get("num_gaussians"),
            "metrics": dict(record.get("metrics", {})), "extract_seconds": timings.get("extract", 0.0),
            "evaluate_seconds": timings.get("evaluate", 0.0)}


def record_points(record: dict) -> list[dict]:
    """The ``points`` of the record ``record`` (a dict); one written before points existed: its `final_point` when it
    finished (status ok), else none."""
    if record.get("points"):
        return list(record["points"])
    return [final_point(record)] if record.get("status") == "ok" else []


def write_json_atomic(path: Path, obj) -> None:
    """Write JSON to a temp file in the same folder, fsync, then `os.replace` (atomic on POSIX)."""
    with atomic_path(path) as tmp, open(tmp, "w") as fh:
        json.dump(obj, fh, indent=2, sort_keys=True, default=_json_default)
        fh.write("\n")
        fh.flush()
        os.fsync(fh.fileno())


def _json_default(obj):
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot store {type(obj).__name__} in a run record")


def sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(chunk), b""):
            digest.update(block)
    return digest.hexdigest()


def git_state() -> dict:
    root = Path(gsbench.__file__).resolve().parent.parent
    try:
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5)
        if commit.returncode != 0:
            return {"git_commit": None, "git_dirty": None}
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain"], capture_output=True, text=True, timeout=5)
        return {"git_commit": commit.stdout.strip(), "git_dirty": bool(dirty.stdout.strip())}
    except (OSError, subprocess.SubprocessError):
        return {"git_commit": None, "git_dirty": None}


def code_version(environment: dict) -> str | None:
    """The code a record's ``environment`` (or `git_state`) names: its commit, ``+dirty`` when the tree had
    uncommitted changes; None when unknown."""
    commit = environment.get("git_commit")
    return None if not commit else str(commit) + ("+dirty" if environment.get("git_dirty") else "")


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _package_versions() -> dict:
    versions = {}
    for name in TRACKED_PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def capture_environment(threads: int | None = None) -> dict:
    """What produced a number: versions, commit, CPU, thread count, OS, host, UTC time."""
    return {
        "gsbench": gsbench.__version__,
        **git_state(),
        "python": platform.python_version(),
        "packages": _package_versions(),
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "threads": threads,
        "os": f"{platform.system()} {platform.release()}",
        "hostname": socket.gethostname(),
        "time_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "switches": result_switches(),
    }


def check_folder_switches(files: RunFolder) -> None:
    """Refuse to add to the run folder ``files`` (existing, locked) when its outputs were made under other
    result-changing switches; else store this process's in its ``switches.json``. A folder with outputs but no
    such file predates it: its outputs were made at the defaults."""
    now = result_switches()
    made = {entry.name for entry in files.path.iterdir()} - {files.CONFIG, files.LOCK, files.SWITCHES}
    if made:
        stored = json.loads(files.switches.read_text()) if files.switches.is_file() else {}
        before = {s.name: stored.get(s.name, s.default) for s in SWITCHES if s.name in now}
        changed = [name for name in now if now[name] != before[name]]
        if changed:
            was = ", ".join(f"{name}={before[name]}" for name in changed)
            raise ConfigError(f"{files.path} was run with {was} and this process has "
                              f"{', '.join(f'{name}={now[name]}' for name in changed)}: resuming would mix them in one "
                              f"record; fix: set {was} again to resume it, or remove the folder (or choose another "
                              "--out) to run it afresh with these switches")
    if not made or not files.switches.is_file():
        write_json_atomic(files.switches, now)


def check_folder_identity(files: RunFolder, config: dict | None = None) -> None:
    """Refuse the run folder ``files`` unless its ``config.yaml`` and ``record.json`` (those it has) are those of the
    run its name is: the run id of each one's configuration (`gsbench.config.run_config.run_id`), and the record's
    ``run_id``, must be the folder's name. A changed setting is named against ``config`` (the resolved configuration
    of the run, given by `gsbench run`, whose run id names the folder), else against the other file."""
    name = files.path.name
    record = _read_folder_file(files.record, json.loads)
    stored = _read_folder_file(files.config, yaml.safe_load)
    if record is not None and not (isinstance(record.get("config"), dict) and isinstance(record.get("run_id"), str)):
        raise _unreadable(files.record, "no config or run_id")
    settings = {path: found for path, found in ((files.config, stored), (files.record, (record or {}).get("config")))
                if found is not None}
    runs = {path: run_id(found) for path, found in settings.items()}
    if record is not None and record["run_id"] != name and runs[files.record] == name:
        raise ConfigError(f"{files.record}: its run_id is {record['run_id']}, not {name}, the run whose folder this is "
                          f"and whose configuration the record holds; {_EDITED}; fix: {_REWRITE}")
    if len(runs) == 2 and name not in runs.values() and len(set(runs.values())) == 1:
        raise ConfigError(f"{files.path}: the folder is named {name}, and its {files.CONFIG} and {files.RECORD} are "
                          f"those of run {runs[files.config]}; a run folder is named by its run id; fix: rename it to "
                          f"{runs[files.config]}")
    wrong = [path for path, found in runs.items() if found != name]
    if wrong:
        other = files.record if wrong[0] == files.config else files.config
        reference, source = ((config, "this run's configuration") if config is not None else
                             (settings.get(other), other.name) if runs.get(other) == name else (None, ""))
        raise _not_this_run(wrong[0], name, settings[wrong[0]], reference, source, is_record=wrong[0] == files.record)


def _not_this_run(path: Path, name: str, settings: dict, reference: dict | None, source: str, *,
                  is_record: bool) -> ConfigError:
    """The error of ``path`` (``config.yaml`` or ``record.json``, holding ``settings``) in the folder of run ``name``:
    the settings it changed from ``reference`` (those of run ``name``, from ``source``; None when unknown)."""
    changed = [] if reference is None else _differences(settings, reference)
    shown = "; ".join(f"{key} is {_shown(mine)} there and {_shown(theirs)} in {source}"
                      for key, mine, theirs in changed[:SHOWN_DIFFERENCES])
    more = f" (and {len(changed) - SHOWN_DIFFERENCES} more)" if len(changed) > SHOWN_DIFFERENCES else ""
    if is_record:
        fix = _REWRITE
    else:
        edited = " ".join(f"--set {key}={_shown(mine)}" for key, mine, _ in changed if mine is not _ABSENT)
        fix = ("undo the edit, or delete the file (`gsbench run` of this run writes it again); to run with the edited "
               f"settings, make them a run of its own: gsbench run ... {edited or '--set KEY=VALUE'}")
    return ConfigError(f"{path}: not the {'record' if is_record else 'configuration'} of run {name}, whose folder this "
                       f"is: {shown + more if changed else f'its settings are those of run {run_id(settings)}'}; "
                       f"{_EDITED}; fix: {fix}")


def _read_folder_file(path: Path, parse) -> dict | None:
    """``path`` parsed (a mapping), None when there is none; a ConfigError naming it when it is unreadable."""
    if not path.is_file():
        return None
    try:
        found = parse(path.read_text())
    except (ValueError, yaml.YAMLError, UnicodeDecodeError) as exc:
        raise _unreadable(path, one_line(exc, 120)) from exc
    if not isinstance(found, dict):
        raise _unreadable(path, "not a mapping")
    return found


def _unreadable(path: Path, why: str) -> ConfigError:
    return ConfigError(f"{path}: unreadable ({why}): not a file gsbench wrote; fix: delete it (`gsbench run` of this "
                       "run writes it again)")


def _differences(mine: dict, theirs: dict) -> list[tuple[str, object, object]]:
    """(dotted key, value in ``mine``, value in ``theirs``) of every setting the two resolved configurations give
    different values (a field one predates at its default, `completed_config`; execution-only keys left out)."""
    flat_mine, flat_theirs = flatten(completed_config(mine)), flatten(completed_config(theirs))
    pairs = {key: (flat_mine.get(key, _ABSENT), flat_theirs.get(key, _ABSENT))
             for key in set(flat_mine) | set(flat_theirs) if key.split(".")[0] not in EXECUTION_ONLY_KEYS}
    return [(key, mine, theirs) for key, (mine, theirs) in sorted(pairs.items()) if mine != theirs]


def flatten(settings: dict, prefix: str = "") -> dict:
    """Nested mappings as dotted keys: ``{"data": {"max_size": [64, 48]}}`` -> ``{"data.max_size": [64, 48]}``."""
    flat = {}
    for key, value in settings.items():
        if isinstance(value, dict) and value:
            flat.update(flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _shown(value) -> str:
    """A setting's value as ``--set`` takes it (compact JSON, which is YAML; a string as it is)."""
    if value is _ABSENT:
        return "absent"
    return value if isinstance(value, str) else json.dumps(value, separators=(",", ":"))
