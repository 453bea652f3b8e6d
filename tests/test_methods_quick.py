"""The 3DGS and 2DGS plugins: paper defaults, declared info, setup, and quick runs on the hard scenes."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
import trimesh

from gsbench.data.loader import load_scene
from gsbench.data.synthetic.make import make_scene
from gsbench.registry import METHODS
from gsbench.runs.runner import resolve_run
from gsbench.training.strategies.default import DefaultStrategy
from gsbench.training.trainer import Trainer

# Idle OpenMP threads must sleep, not spin (see gsbench.training.trainer.set_threads); set at collection.


def test_registered_methods_declare_kernel_primitive_mesh_depth_and_terms():
    gs3d, gs2d = METHODS.get("3dgs"), METHODS.get("2dgs")
    assert (gs3d.info().kernel, gs3d.info().primitive) == ("ewa", "3d")
    assert (gs2d.info().kernel, gs2d.info().primitive) == ("surfel", "2d")
    expected = {"3dgs": ("expected", {"l1", "dssim"}),
                "2dgs": ("median", {"l1", "dssim", "depth_distortion", "normal_consistency"})}
    for name, (depth, terms) in expected.items():
        cfg = resolve_run(name, "synthetic/spot", preset="paper")  # the method's yaml declares both
        assert cfg.mesh.depth == depth and set(cfg.losses) == terms


def test_defaults_are_the_papers():
    p3, p2 = METHODS.get("3dgs").Config(), METHODS.get("2dgs").Config()
    assert (p3.position_lr_init, p3.position_lr_final, p3.feature_lr, p3.opacity_lr, p3.scaling_lr,
            p3.rotation_lr) == (0.00016, 0.0000016, 0.0025, 0.05, 0.005, 0.001)
    assert (p3.grad_threshold, p3.refine_start, p3.refine_stop, p3.refine_every,
            p3.reset_every, p3.prune_opacity, p3.init_opacity) == (0.0002, 500, 15000, 100, 3000, 0.005, 0.1)
    assert p2.prune_opacity == 0.05 and p2.depth_ratio == 1.0
    losses = resolve_run("2dgs", "synthetic/spot", preset="paper").losses
    assert losses["normal_consistency"] == {"weight": 0.05, "start": 7000, "end": -1}
    assert losses["depth_distortion"] == {"weight": 1000.0, "start": 3000, "end": -1}
    assert losses["l1"]["weight"] == 0.8 and losses["dssim"]["weight"] == 0.2


@pytest.mark.parametrize("method", ["3dgs", "2dgs"])
def test_setup_builds_named_adam_groups_with_scaled_position_lr(method, tiny_spot):
    cfg = resolve_run(method, str(tiny_spot), preset="quick", overrides=["method.random_init_points=300"])
    scene = load_scene(cfg.scene, downscale=1)
    m = METHODS.get(method)()
    m.setup(scene, cfg)
    assert len(m.gaussians) == 300 and m.gaussians.dims == (2 if method == "2dgs" else 3)
    centres = np.stack([c.center for c in scene.cameras])
    assert m.extent == pytest.approx(1.1 * np.linalg.norm(centres - centres.mean(0), axis=1).max())
    lrs = {g["name"]: g["lr"] for g in m.optimizer.param_groups}
    assert lrs["means"] == pytest.approx(0.00016 * m.extent) and lrs["sh_rest"] == pytest.approx(0.0025 / 20)
    assert m.optimizer.defaults["eps"] == 1e-15
    m.update_schedules(300, 300 / 30000)  # the end of a 300-step run: lr at its final value, SH at max
    assert {g["name"]: g["lr"] for g in m.optimizer.param_groups}["means"] == pytest.approx(0.0000016 * m.extent)
    assert m.sh_degree == cfg.raster.sh_degree
    strategy = m.strategy()
    assert isinstance(strategy, DefaultStrategy) and strategy.scene_extent == m.extent
    assert strategy.prune_opacity == (0.05 if method == "2dgs" else 0.005)
    assert strategy.max_gaussians == cfg.train.max_gaussians


def test_sfm_points_initialise_and_are_capped_by_the_budget(tiny_spot):
    cfg = resolve_run("3dgs", str(tiny_spot), preset="quick", overrides=["train.max_gaussians=50"])
    scene = load_scene(cfg.scene, downscale=1)
    scene = dataclasses.replace(scene, points=np.random.default_rng(0).uniform(-0.5, 0.5, (80, 3)),
                                colors=np.full((80, 3), 0.25))
    m = METHODS.get("3dgs")()
    m.setup(scene, cfg)
    assert len(m.gaussians) == 50
    assert torch.allclose(m.gaussians.params["sh_dc"], torch.tensor((0.25 - 0.5) / 0.28209479177387814))


@pytest.mark.parametrize("name,res", [pytest.param("synthetic/thin-plate", (64, 48)),
                                      ("synthetic/spot-km", (64, 36))])
@pytest.mark.parametrize("method", ["3dgs", "2dgs"])
def test_hard_scenes_train_without_nan_and_mesh(method, name, res, tmp_path_factory):
    """Grazing views of a thin sheet, and kilometre coordinates: finite training and a non-empty mesh."""
    root = tmp_path_factory.getbasetemp() / f"{name.split('/')[1]}-{res[0]}x{res[1]}"
    scene_dir = make_scene(name, out=root, res=res)
    cfg = resolve_run(method, str(scene_dir), preset="quick",
                      overrides=["data.downscale=1", "train.iterations=100", "method.random_init_points=2000",
                                 "train.checkpoint_every=0", "mesh.voxel_size=0.02", "mesh.sdf_trunc=0.08"])
    scene = load_scene(cfg.scene, downscale=1)
    m = METHODS.get(method)()
    m.setup(scene, cfg)
    run_dir = tmp_path_factory.mktemp(f"{method}-{name.split('/')[1]}")
    result = Trainer(m, scene, cfg, run_dir).fit()
    assert result.steps == 100 and result.num_gaussians > 0
    assert all(torch.isfinite(p).all() for p in m.gaussians.params.values())
    size = m.extract_mesh(scene, cfg, run_dir / "mesh.ply")
    mesh = trimesh.load(run_dir / "mesh.ply", process=False)
    assert size["faces"] == len(mesh.faces) > 0 and np.isfinite(mesh.vertices).all()
    assert math.isfinite(float(np.abs(mesh.vertices).max()))
