"""GGGS (methods/gggs.py, methods/gggs_terms.py): a quick run to ok with its geometric terms on, exact resume,
the initial scale clamp, the depth–normal term's validity and the solid planes the multi-view terms warp."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from gsbench.cli import main
from gsbench.data.loader import load_scene
from gsbench.geometry.depth import pixel_rays
from gsbench.methods.gggs import solid_planes
from gsbench.methods.gggs_terms import depth_validity, gggs_normal_term
from gsbench.raster.types import RenderOutput
from gsbench.registry import METHODS
from gsbench.run_folder import RunFolder
from gsbench.runs.runner import resolve_run
from gsbench.training.trainer import Trainer, load_checkpoint
from tests.method_setup import interrupt_at
from tests.raster_scenes import make_camera

EARLY = ["losses.gggs_normal.start=0", "losses.gggs_geo.start=0", "losses.gggs_ncc.start=0"]


def test_quick_run_to_ok(tiny_spot, tmp_path, restore_threads):
    """200 steps with the three geometric terms from step 0: ok, a finite Chamfer, every term scheduled, the
    solid depth meshed."""
    assert main(["run", "--method", "gggs", "--scene", str(tiny_spot), "--preset", "quick", "--out", str(tmp_path),
                 "--set", "train.iterations=200", *[x for o in EARLY for x in ("--set", o)]]) == 0
    record = json.loads(next(tmp_path.rglob("record.json")).read_text())
    assert record["status"] == "ok" and math.isfinite(record["metrics"]["chamfer"])
    assert set(record["losses"]["schedule"]) >= {"l1_exposure", "dssim", "gggs_normal", "gggs_geo", "gggs_ncc"}
    assert record["config"]["mesh"]["depth"] == "solid" and record["mesh"]["faces"] > 0


def _trainer(tiny_spot, run_dir):
    cfg = resolve_run("gggs", str(tiny_spot), preset="quick",
                      overrides=["data.downscale=1", "train.iterations=12", "train.checkpoint_every=6", "threads=1",
                                 *EARLY])
    scene = load_scene(cfg.scene, downscale=cfg.data.downscale)
    method = METHODS.get("gggs")()
    method.setup(scene, cfg)
    return Trainer(method, scene, cfg, run_dir), scene


def test_resume_is_bit_identical(tiny_spot, tmp_path, monkeypatch, restore_threads):
    """12 steps straight vs 6 + crash + resume + 6, the multi-view terms active from step 0: the Gaussians and
    the per-image exposure equal, and the ``multiview`` seconds include the steps before the resume."""
    straight, _ = _trainer(tiny_spot, tmp_path / "a")
    straight.fit()
    interrupted, _ = _trainer(tiny_spot, tmp_path / "b")
    interrupt_at(interrupted, 7, monkeypatch)
    with pytest.raises(KeyboardInterrupt):
        interrupted.fit()
    monkeypatch.undo()
    saved = load_checkpoint(tmp_path / "b" / RunFolder.CHECKPOINT)["method"]["multiview_seconds"]
    resumed, _ = _trainer(tiny_spot, tmp_path / "b")
    result = resumed.fit()
    assert result.resumed_from == 6
    for name, param in straight.method.gaussians.params.items():
        assert torch.equal(param, resumed.method.gaussians.params[name]), name
    assert torch.equal(straight.method.exposure, resumed.method.exposure)
    # the neighbour work's seconds carry over the resume, as the step phases do
    assert 0 < saved < result.phases["multiview"]


def test_initial_scales_are_clamped_by_the_nearest_camera(tiny_spot, tmp_path):
    """Every initial scale is at most 0.05 × the distance from its centre to the nearest training camera."""
    trainer, scene = _trainer(tiny_spot, tmp_path)
    g = trainer.method.gaussians
    centres = torch.as_tensor(np.stack([scene.cameras[i].center for i in scene.train_views]), dtype=torch.float64)
    nearest = torch.cdist(g.params["means"].detach().double(), centres).min(1).values
    assert bool((g.scales.detach().double().max(-1).values <= 0.05 * nearest * (1 + 1e-5)).all())


def test_depth_normal_term_counts_valid_pixels_only():
    """A fronto-parallel plane at depth 2 with the matching normal scores 0 where valid; a hole (depth 0) makes
    its pixel and its four neighbours invalid (0, not 1); a wrong normal scores 1 per valid pixel."""
    cam = make_camera(8, 6)
    depth = torch.full((6, 8), 2.0)
    depth[3, 4] = 0.0
    valid = depth_validity(depth)
    assert not bool(valid[3, 4] | valid[2, 4] | valid[4, 4] | valid[3, 3] | valid[3, 5]) and bool(valid[2, 2])
    alpha = torch.ones(6, 8)
    facing = torch.tensor([0.0, 0.0, -1.0]).expand(6, 8, 3)
    batch = type("B", (), {"camera": cam})()
    render = RenderOutput(solid_depth=depth, alpha=alpha, normal=facing.clone())
    assert float(gggs_normal_term(render, batch, {})) < 1e-6
    render.normal = torch.tensor([1.0, 0.0, 0.0]).expand(6, 8, 3).clone()
    assert abs(float(gggs_normal_term(render, batch, {})) - float(valid.sum()) / 48) < 1e-6


def test_solid_planes_pass_through_the_depth_points():
    """The plane (d, n̂) of each pixel holds its point D·r: n̂·(D r) = −d; a pixel without depth has d = 0."""
    cam = make_camera(8, 6)
    depth = 1.0 + torch.rand(6, 8, generator=torch.Generator().manual_seed(0))
    depth[0, 0] = 0.0
    normal = torch.nn.functional.normalize(torch.randn(6, 8, 3, generator=torch.Generator().manual_seed(1)), dim=-1)
    d, n = solid_planes(RenderOutput(solid_depth=depth, normal=2.0 * normal), cam)
    points = depth[..., None] * pixel_rays(cam, depth.dtype)
    assert torch.allclose((n * points).sum(-1), -d, atol=1e-6) and float(d[0, 0]) == 0.0
