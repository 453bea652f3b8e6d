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
threads, OS, host, UTC start/end, and ``switches``: the value of every result-changing ``GSBENCH_*`` switch,
defaults included, `gsbench.switches`; records made before it was tracked lack it and ran at the defaults).
A method with a second stage (SuGaR's refinement) adds ``refine`` and ``refine_cpu`` to the timings.

``points`` (anytime evaluation, docs/training.md §9): one row per point in step order, the last the run's
final result (`final_point`), each with the keys of `POINT_KEYS`: ``step``, ``fraction`` (step /
train.iterations), ``final``, ``status`` (ok or failed), ``error`` (one line, null when ok), ``train_seconds``
and ``train_cpu_seconds`` (training so far, every training stage up to the point, evaluation excluded; CPU
null where unknown), ``num_gaussians``, ``metrics`` (the names of ``metrics``; {} when failed),
``extract_seconds``, ``evaluate_seconds``. A record written before points existed has none:
`record_points` reads it as its final point alone.

A run folder keeps the switches its outputs were made with in ``switches.json``; a run resumed under other
values is refused (`check_folder_switches`), so a record never mixes them.
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

import gsbench
from gsbench.atomic import atomic_path
from gsbench.errors import ConfigError
from gsbench.run_folder import RunFolder
from gsbench.switches import SWITCHES, result_switches

SCHEMA_VERSION = 1
POINT_KEYS = ("step", "fraction", "final", "status", "error", "train_seconds", "train_cpu_seconds", "num_gaussians",
              "metrics", "extract_seconds", "evaluate_seconds")
STATUSES = ("ok", "failed", "interrupted", "running")  # running: a record in memory until the run ends
TRACKED_PACKAGES = ("torch", "numpy", "scipy", "open3d", "pymeshlab", "trimesh", "scikit-image", "pycolmap")


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
