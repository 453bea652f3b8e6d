"""Sweep files: a grid of runs over one pipeline (DESIGN.md §3 "Executor"), expanded and validated.

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
    seeds: [0]                       # optional; default: [base seed or 0]

Every key other than ``method``, ``scene``, ``preset`` and ``seed`` is a config path (dotted, or
nested mappings that are flattened to dotted paths) applied as a ``--set`` override after the
method/dataset/preset layers. The runs are variants × grid × zip × scenes × seeds, in that order.
`expand` resolves every run (`gsbench.runner.resolve_run`: unknown keys and bad types fail with the
run's label) and checks its loss-term names against the registry, so a sweep fails before it
starts. Each run's id is its resolved config's (`gsbench.config.run_id`), so re-running a sweep
finds the finished runs.
"""

from __future__ import annotations

import itertools
import json
from dataclasses import dataclass
from pathlib import Path

from gsbench.config import RunConfig, load_yaml
from gsbench.errors import ConfigError

SWEEP_KEYS = ("name", "description", "base", "variants", "grid", "zip", "scenes", "seeds", "executor")
IDENTITY_KEYS = ("method", "scene", "preset", "seed")


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
    for key in ("base", "variants", "grid", "zip"):
        if not isinstance(data.get(key, {}), dict):
            raise ConfigError(f"{path}: '{key}' must be a mapping")
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
    data.setdefault("name", path.stem)
    return data


def _rows(section: dict) -> list[dict]:
    """grid -> the cartesian product of its lists as dicts; zip -> its lists taken together."""
    keys = list(section)
    return [dict(zip(keys, values)) for values in itertools.product(*(section[k] for k in keys))]


def _label(variant: str | None, values: dict) -> str:
    parts = ([variant] if variant else []) + [f"{k}={v}" for k, v in values.items()]
    return " ".join(parts) or "base"


def expand(sweep: dict, overrides=()) -> list[SweepRun]:
    """Resolve every run of ``sweep`` (module docstring); ``overrides`` (``a.b=c`` texts, e.g. a
    smaller budget) apply to every run after the sweep's own settings. Errors name the run's label."""
    from gsbench.config import parse_override  # noqa: PLC0415
    from gsbench.losses import get_term  # noqa: PLC0415
    from gsbench.runner import resolve_run  # noqa: PLC0415

    extra = {}
    for text in overrides:
        extra.update(flatten(parse_override(text)))

    base = flatten(sweep.get("base", {}))
    variants = {str(k): flatten(v or {}) for k, v in sweep.get("variants", {}).items()} or {None: {}}
    grid = _rows(sweep.get("grid", {}))
    zipped = sweep.get("zip", {})
    zip_rows = [dict(zip(zipped, values)) for values in zip(*zipped.values())] if zipped else [{}]
    runs = []
    for (variant, changes), point, paired in itertools.product(variants.items(), grid, zip_rows):
        settings = {**base, **changes, **point, **paired, **extra}
        label = _label(variant, {**point, **paired})
        for scene in sweep.get("scenes") or [settings.get("scene")]:
            for seed in sweep.get("seeds") or [settings.get("seed", 0)]:
                runs.append(SweepRun(label, _resolve(settings, scene, seed, label, resolve_run, get_term)))
    return runs


def _resolve(settings: dict, scene, seed, label: str, resolve_run, get_term) -> RunConfig:
    method = settings.get("method")
    if not method or not scene:
        raise ConfigError(f"sweep run '{label}': needs a method and a scene (in base, variants, grid or scenes)")
    overrides = [f"{k}={json.dumps(v)}" for k, v in settings.items() if k not in IDENTITY_KEYS]
    try:
        cfg = resolve_run(str(method), str(scene), preset=str(settings.get("preset", "cpu")),
                          overrides=overrides, seed=int(seed))
        for term in cfg.losses:
            get_term(term)
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


def run_sweep(runs: list[SweepRun], *, out: str | None = None, threads: int | None = None, echo=print) -> dict:
    """Run ``runs`` one after another in this process; finished runs (record status ok) are skipped and
    a failing run is recorded (``status: failed``) without stopping the others. Returns the counts."""
    from gsbench.records import RunRecord  # noqa: PLC0415
    from gsbench.runner import RECORD, run, run_dir  # noqa: PLC0415

    counts = {"ok": 0, "skipped": 0, "failed": 0}
    for i, sweep_run in enumerate(runs, 1):
        cfg = sweep_run.config
        if out is not None:
            cfg.out = out
        if threads is not None:
            cfg.threads = threads
        record_path = run_dir(cfg) / RECORD
        if record_path.is_file() and RunRecord.read(record_path).status == "ok":
            counts["skipped"] += 1
            continue
        echo(f"[{i}/{len(runs)}] {cfg.method['name']} on {cfg.scene} ({sweep_run.label}), run {cfg.run_id}")
        try:
            run(cfg, echo=echo)
            counts["ok"] += 1
        except Exception as exc:  # noqa: BLE001  (recorded by the runner; the sweep goes on)
            counts["failed"] += 1
            echo(f"run {cfg.run_id} failed: {type(exc).__name__}: {exc}")
    echo(f"sweep: {counts['ok']} ran, {counts['skipped']} already finished, {counts['failed']} failed")
    return counts
