"""A run's folder and the files in it, named once.

`gsbench run` writes ``<out>/<dataset>/<scene>/<method>/<run_id>/``: ``config.yaml`` (the resolved
configuration), ``checkpoint.pt`` (the latest resumable state, removed when training ends),
``checkpoint-final.pt``, ``metrics.jsonl`` (the training log), ``mesh.ply``, ``eval.json``, ``stages.json``
(per stage: seconds and peak memory), ``points/`` (anytime evaluation, docs/training.md §9: per point step
``<step>/mesh.ply``, ``<step>/eval.json`` and ``<step>.json``, its row of the record's ``points``, written
last), ``switches.json`` (the result-changing ``GSBENCH_*`` switches its
outputs were made with, `gsbench.runs.records.check_folder_switches`), ``record.json`` (the run record, written
last), ``.lock`` (one process at a time) and, for a method with a second stage, ``refine/`` (that stage's
checkpoints and training log). Training, the runner, sweeps, diagnostics and the report all reach
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
    POINTS = "points"
    LOCK = ".lock"
    REFINE = "refine"

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

    @property
    def refine(self) -> "RunFolder":
        """The folder of a second stage's training (its own checkpoints and log, so it resumes like the first)."""
        return RunFolder(self.path / self.REFINE)

    def written(self, point_steps=()) -> list[Path]:
        """Every file a run writes here (the module docstring's), with the points' at the steps ``point_steps`` and a
        second stage's."""
        points = [path for step in point_steps for path in (self.point_mesh(step), self.point_eval(step),
                                                             self.point_row(step))]
        return [self.config, self.checkpoint, self.final_checkpoint, self.metrics, self.mesh, self.eval, self.stages,
                self.switches, self.record, self.lock, *points, self.refine.checkpoint, self.refine.final_checkpoint,
                self.refine.metrics]

    def point_mesh(self, step: int) -> Path:
        """The mesh extracted at the point of training step ``step``."""
        return self.path / self.POINTS / str(int(step)) / self.MESH

    def point_eval(self, step: int) -> Path:
        """The evaluation report of that mesh (as ``eval.json`` is of the final one)."""
        return self.path / self.POINTS / str(int(step)) / self.EVAL

    def point_row(self, step: int) -> Path:
        """The point's row of the record's ``points``, written when the point is done (ok or failed)."""
        return self.path / self.POINTS / f"{int(step)}.json"
