"""A method set up on a scene with the quick preset and a few hundred random Gaussians (method tests)."""

import math

import pytest

from gsbench.data.loader import load_scene
from gsbench.registry import METHODS
from gsbench.runs.runner import resolve_run, run
from gsbench.training.trainer import Trainer

TINY = ["data.downscale=1", "method.random_init_points=400", "train.checkpoint_every=0"]


def setup_method(name, scene_dir, *overrides):
    """(method after `setup`, scene, resolved config) for ``name`` on ``scene_dir`` with TINY + ``overrides``."""
    cfg = resolve_run(name, str(scene_dir), preset="quick", overrides=[*TINY, *overrides])
    scene = load_scene(cfg.scene, downscale=cfg.data.downscale)
    m = METHODS.get(name)()
    m.setup(scene, cfg)
    return m, scene, cfg


def straight_and_resumed(method, scene_dir, tmp_path, monkeypatch, *overrides, crash_after: int):
    """Two Trainers of ``method``: one trained straight through, one that crashes after step ``crash_after``
    and is resumed from its checkpoint by a fresh Trainer (``overrides`` set the schedule)."""
    def trainer(folder):
        m, scene, cfg = setup_method(method, scene_dir, *overrides)
        return Trainer(m, scene, cfg, folder)

    straight = trainer(tmp_path / "a")
    straight.fit()
    interrupted = trainer(tmp_path / "b")
    original = interrupted.train_step
    monkeypatch.setattr(interrupted, "train_step", lambda step: original(step) if step <= crash_after else 1 / 0)
    with pytest.raises(ZeroDivisionError):
        interrupted.fit()
    resumed = trainer(tmp_path / "b")
    resumed.fit()
    return straight, resumed


# A TSDF voxel of about one pixel at 64x48; one evaluator keeps the run short.
QUICK = ["data.downscale=1", "method.random_init_points=2000", "train.iterations=60", "train.checkpoint_every=0",
         "train.log_every=10", "mesh.voxel_size=0.02", "mesh.sdf_trunc=0.08", "eval.evaluators=[dtu_chamfer]",
         "threads=1"]


def quick_run(name, scene_dir, tmp_path, *overrides):
    """The record of a quick end-to-end run (train, mesh, dtu_chamfer), checked ok, finite and meshed."""
    cfg = resolve_run(name, str(scene_dir), preset="quick", overrides=[*QUICK, *overrides])
    cfg.out = str(tmp_path / "runs")
    record = run(cfg, echo=lambda *a: None)
    assert record.status == "ok" and record.method == name and record.num_gaussians > 0
    assert all(math.isfinite(record.metrics[k]) for k in ("chamfer", "accuracy", "completeness"))
    assert record.mesh["faces"] > 0
    return record


def interrupt_at(trainer, step: int, monkeypatch) -> None:
    """Make ``trainer.fit()`` stop with a KeyboardInterrupt (Ctrl-C) at training step ``step``."""
    original = trainer.train_step

    def train_step(t):
        if t == step:
            raise KeyboardInterrupt
        return original(t)

    monkeypatch.setattr(trainer, "train_step", train_step)
