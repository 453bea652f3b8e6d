"""A run's folder and the files in it, named once.

`gsbench run` writes ``<out>/<dataset>/<scene>/<method>/<run_id>/``: ``config.yaml`` (the resolved
configuration), ``checkpoint.pt`` (the latest resumable state, removed when training ends),
``checkpoint-final.pt``, ``metrics.jsonl`` (the training log), ``mesh.ply``, ``eval.json``, ``stages.json``
(per stage: seconds and peak memory), ``switches.json`` (the result-changing ``GSBENCH_*`` switches its
outputs were made with, `gsbench.runs.records.check_folder_switches`), ``record.json`` (the run record, written
last) and ``.lock`` (one process at a time). Training, the runner, sweeps, diagnostics and the report all reach
these files through `RunFolder`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class RunFolder:
    """The files of the run folder ``path`` (module docstring)."""

    path: Path

    CONFIG = "config.yaml"
    CHECKPOINT = "checkpoint.pt"
    FINAL_CHECKPOINT = "checkpoint-final.pt"
    METRICS = "metrics.jsonl"
    MESH = "mesh.ply"
    EVAL = "eval.json"
    STAGES = "stages.json"
    RECORD = "record.json"
    SWITCHES = "switches.json"
    LOCK = ".lock"

    def __post_init__(self):
        object.__setattr__(self, "path", Path(self.path))

    @property
    def config(self) -> Path:
        return self.path / self.CONFIG

    @property
    def checkpoint(self) -> Path:
        return self.path / self.CHECKPOINT

    @property
    def final_checkpoint(self) -> Path:
        return self.path / self.FINAL_CHECKPOINT

    @property
    def metrics(self) -> Path:
        return self.path / self.METRICS

    @property
    def mesh(self) -> Path:
        return self.path / self.MESH

    @property
    def eval(self) -> Path:
        return self.path / self.EVAL

    @property
    def stages(self) -> Path:
        return self.path / self.STAGES

    @property
    def record(self) -> Path:
        return self.path / self.RECORD

    @property
    def switches(self) -> Path:
        return self.path / self.SWITCHES

    @property
    def lock(self) -> Path:
        return self.path / self.LOCK
