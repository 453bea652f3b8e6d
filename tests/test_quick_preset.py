"""The quick preset is the smoke run of every method: each one trains, meshes and evaluates to ``ok`` with the
preset as it ships (its schedules scaled to its 600 steps), on the built-in synthetic/spot."""

from __future__ import annotations

import math

import pytest

from gsbench.registry import METHODS
from gsbench.runs.runner import resolve_run, run


@pytest.mark.slow
@pytest.mark.parametrize("method", METHODS.names())
def test_every_method_runs_the_quick_preset_to_ok(method, tmp_path):
    cfg = resolve_run(method, "synthetic/spot", preset="quick", overrides=["eval.evaluators=[dtu_chamfer]"])
    assert cfg.train.iterations == 600  # the preset's own length, not a test's
    cfg.out = str(tmp_path / "runs")
    record = run(cfg, echo=lambda *a: None)
    assert record.status == "ok" and record.num_gaussians > 0 and record.mesh["faces"] > 0
    assert math.isfinite(record.metrics["chamfer"])
