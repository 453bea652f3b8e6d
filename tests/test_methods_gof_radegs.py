"""The GOF and RaDe-GS plugins: paper defaults per dataset (the <method>.<dataset> config layer), their
loss-term parameters, the 3D filter in render/checkpoints, the tets mesh hook, and quick end-to-end runs."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh

import gsbench.config.files as config_files
import gsbench.config.run_config as config
import gsbench.methods.base as method_base
from gsbench.errors import ConfigError
from gsbench.geometry.depth import depth_to_normal
from gsbench.losses import terms as losses
from gsbench.losses.terms import Batch, active_terms, edge_weights, image_map
from gsbench.methods.pgsr_terms import image_gradient_weight
from gsbench.raster.types import RenderOutput
from gsbench.registry import METHODS
from gsbench.runs.runner import resolve_run
from gsbench.training.strategies.absgrad import AbsGradStrategy
from gsbench.training.trainer import load_checkpoint
from tests.method_setup import quick_run, setup_method, straight_and_resumed
from tests.raster_scenes import make_camera

METHOD_NAMES = ("gof", "radegs")
TERM_PARAMS = {  # docs/methods/gof.md §4.3docs/methods/gof.md §4.2: median-depth L_n, alpha²-normalised L_d; docs/methods/radegs.md §4.2, §4.3: 0.4/0.6 normal mix, v1 L_d
    "gof": {"normal_consistency": {"depth_ratio": 1.0, "normalize": True, "mix": "depth"},
            "depth_distortion": {"normalize": True}},
    "radegs": {"normal_consistency": {"depth_ratio": 0.6, "normalize": True, "mix": "normal"},
               "depth_distortion": {"normalize": True, "edge_aware": True}},
}


# ---- declarations and paper defaults ------------------------------------------------------------


def test_registered_methods_declare_kernel_primitive_and_terms():
    gof, rade = METHODS.get("gof"), METHODS.get("radegs")
    assert (gof.info().kernel, gof.info().primitive) == ("raymax", "3d")
    assert (rade.info().kernel, rade.info().primitive) == ("rade", "3d")
    for name, cls in (("gof", gof), ("radegs", rade)):
        cfg = resolve_run(name, "synthetic/spot", preset="paper")
        assert cfg.mesh.depth == "median" and cfg.mesh.extractor == "tsdf"
        assert set(cfg.losses) == {"l1", "dssim", "normal_consistency", "depth_distortion"}
        p = cls.Config()
        assert (p.prune_opacity, p.grad_threshold, p.refine_start, p.refine_stop, p.reset_every,
                p.use_filter3d) == (0.05, 0.0002, 500, 15000, 3000, True)
    assert rade.Config().depth_ratio == 0.6


def test_dtu_and_tnt_defaults_come_from_the_method_dataset_layer():
    dtu = resolve_run("gof", "synthetic/spot", preset="paper")
    assert dtu.losses["normal_consistency"] == {"weight": 0.05, "start": 15000, "end": -1}
    assert dtu.losses["depth_distortion"] == {"weight": 1000.0, "start": 15000, "end": -1}
    mesh = dtu.mesh
    assert (mesh.extractor, mesh.voxel_size, mesh.sdf_trunc, mesh.depth_trunc) == ("tsdf", 0.004, 0.016, 6.0)
    tnt = resolve_run("gof", "synthetic/spot-tnt", preset="paper")
    assert tnt.losses["depth_distortion"] == {"weight": 100.0, "start": 15000, "end": -1}
    assert (tnt.mesh.extractor, tnt.mesh.level, tnt.mesh.bisection_steps, tnt.data.holdout_every) == ("tets", 0.5, 8, 8)
    rade = resolve_run("radegs", "synthetic/spot", preset="paper")
    assert rade.losses["normal_consistency"] == {"weight": 0.05, "start": 15000, "end": -1}
    assert rade.losses["depth_distortion"]["weight"] == 0.0  # HEAD; v1 by --set
    assert (rade.mesh.voxel_size, rade.mesh.depth_trunc) == (0.004, 8.0)
    assert resolve_run("radegs", "synthetic/spot-tnt", preset="paper").mesh.extractor == "tsdf"
    # --set beats the method.dataset layer
    assert resolve_run("gof", "synthetic/spot", overrides=["losses.depth_distortion.weight=7"]).losses[
        "depth_distortion"]["weight"] == 7.0


def test_method_dataset_layer_sits_between_dataset_and_preset(tmp_path, monkeypatch):
    for folder, text in {"methods/toy.yaml": "train: {iterations: 1, log_every: 1, checkpoint_every: 1}\n",
                         "datasets/dtu.yaml": "train: {iterations: 2, log_every: 2}\n",
                         "methods/toy.dtu.yaml": "train: {iterations: 3, log_every: 3, max_gaussians: 3}\n",
                         "presets/quick.yaml": "train: {iterations: 4}\n"}.items():
        (tmp_path / folder).parent.mkdir(exist_ok=True)
        (tmp_path / folder).write_text(text)
    monkeypatch.setattr(config_files, "CONFIG_ROOT", tmp_path)
    cfg = config.resolve("toy", "synthetic/spot", preset="quick")
    train = cfg.train
    assert (train.checkpoint_every, train.log_every, train.max_gaussians, train.iterations) == (1, 3, 3, 4)
    assert config.resolve("toy", "synthetic/spot-tnt", preset="quick").train.max_gaussians == 0  # no toy.tnt.yaml


def test_term_params_and_raster_settings(tiny_spot):
    gof, _, _ = setup_method("gof", tiny_spot)
    assert gof.term_params() == TERM_PARAMS["gof"]
    assert gof.raster_settings().detach_distortion_weights is True
    rade, _, _ = setup_method("radegs", tiny_spot)
    assert rade.term_params() == TERM_PARAMS["radegs"]
    assert rade.raster_settings().detach_distortion_weights is False
    active = {t.name: t for t in active_terms(rade.cfg.losses | {"depth_distortion": {"weight": 100.0}}, 15000,
                                              rade.term_params())}
    assert active["normal_consistency"].spec.requires == {"normal", "depth", "median_depth"}
    assert active["depth_distortion"].spec.requires == {"distortion", "alpha"}


# ---- the loss-term parameters GOF and RaDe-GS use ------------------------------------------------


def two_plane_render(W=20, H=16):
    """Expected depth: the plane z = 2; median depth: z = 2 + 0.5·x (tilted); rendered normal: a fixed
    unnormalised direction; alpha 0.5; distortion 0.02 everywhere."""
    cam = make_camera(W, H)
    x = (torch.arange(W, dtype=torch.float64) + 0.5 - cam.cx) / cam.fx
    expected = torch.full((H, W), 2.0, dtype=torch.float64)
    median = (2.0 / (1.0 - 0.5 * x)).expand(H, W).clone()
    normal = torch.tensor([0.3, 0.1, -0.8], dtype=torch.float64).expand(H, W, 3).clone() * 0.5
    out = RenderOutput(alpha=torch.full((H, W), 0.5, dtype=torch.float64), depth=expected, median_depth=median,
                       normal=normal, distortion=torch.full((H, W), 0.02, dtype=torch.float64), width=W, height=H)
    return out, cam


def test_normal_consistency_mixes_normals_with_the_normalised_render():
    out, cam = two_plane_render()
    batch = Batch(torch.zeros(16, 20, 3, dtype=torch.float64), None, cam, 0)
    n = out.normal / out.normal.norm(dim=-1, keepdim=True)
    loss_exp = (1 - (n * depth_to_normal(out.depth, cam)).sum(-1)).mean()
    loss_med = (1 - (n * depth_to_normal(out.median_depth, cam)).sum(-1)).mean()
    (rade,) = active_terms({"normal_consistency": {"weight": 1.0}}, 0,
                           {"normal_consistency": {"depth_ratio": 0.6, "normalize": True, "mix": "normal"}})
    torch.testing.assert_close(rade.spec(out, batch, {}), 0.4 * loss_exp + 0.6 * loss_med)
    (gof,) = active_terms({"normal_consistency": {"weight": 1.0}}, 0,
                          {"normal_consistency": {"depth_ratio": 1.0, "normalize": True}})
    torch.testing.assert_close(gof.spec(out, batch, {}), loss_med)
    with pytest.raises(ConfigError, match="mix must be one of"):
        active_terms({"normal_consistency": {"weight": 1.0}}, 0, {"normal_consistency": {"mix": "both"}})


def test_depth_distortion_normalised_and_edge_aware():
    out, cam = two_plane_render()
    image = torch.zeros(16, 20, 3, dtype=torch.float64)
    image[:, 10:] = 0.3  # a vertical edge between columns 9 and 10: g = 0.3 there
    batch = Batch(image, None, cam, 0)
    value = 0.02 / (0.25 + 1e-7)
    (gof,) = active_terms({"depth_distortion": {"weight": 1.0}}, 0, {"depth_distortion": {"normalize": True}})
    assert gof.spec(out, batch, {}).item() == pytest.approx(value)
    weights = edge_weights(image)
    assert weights[0].abs().sum() == 0 and weights[:, 0].abs().sum() == 0  # 0 on the border
    assert weights[5, 9].item() == pytest.approx(math.exp(-0.3)) and weights[5, 5].item() == 1.0
    (rade,) = active_terms({"depth_distortion": {"weight": 1.0}}, 0,
                           {"depth_distortion": {"normalize": True, "edge_aware": True}})
    interior = 14 * 18 - 2 * 14 + 2 * 14 * math.exp(-0.3)  # two columns of 14 interior pixels see the edge
    assert rade.spec(out, batch, {}).item() == pytest.approx(value * interior / (16 * 20))
    # a GT map is computed once per image, map and dtype (it reads only the image)
    assert image_map(edge_weights, image, torch.float64) is image_map(edge_weights, image, torch.float64)
    assert torch.equal(image_map(edge_weights, image, torch.float32), weights.float())
    assert torch.equal(image_map(image_gradient_weight, image, torch.float64), image_gradient_weight(image))
    other = image.clone()
    other[:, :5] = 0.6  # another image is another entry; a freed image takes its entry with it
    assert not torch.equal(image_map(edge_weights, other, torch.float64), weights)
    key = id(other)
    assert key in losses._IMAGE_MAPS
    del other
    assert key not in losses._IMAGE_MAPS


# ---- the 3D filter in the method -----------------------------------------------------------------


def test_filter_is_computed_at_setup_rendered_and_shared_with_the_strategy(tiny_spot, monkeypatch):
    m, scene, cfg = setup_method("radegs", tiny_spot)
    assert m.filter3d().shape == (len(m.gaussians),) and bool((m.filter3d() > 0).all())
    views = scene.train_views
    assert m.filter.cameras == [scene.cameras[i] for i in views] and m.filter.near == pytest.approx(0.2 * scene.radius)
    strategy = m.strategy()
    assert isinstance(strategy, AbsGradStrategy) and strategy.filter3d is m.filter
    assert (strategy.prune_opacity, strategy.max_gaussians) == (0.05, cfg.train.max_gaussians)
    seen = {}
    real = method_base.rasterize

    def spy(g, camera, **kw):
        seen["filter3d"], seen["kernel"] = g.filter3d, kw["kernel"]
        return real(g, camera, **kw)

    monkeypatch.setattr(method_base, "rasterize", spy)
    m.render(scene.cameras[0], {"rgb"})
    assert seen["filter3d"] is m.filter3d() and seen["kernel"] == "rade"
    off, _, _ = setup_method("gof", tiny_spot, "method.use_filter3d=false")
    assert off.filter3d() is None


def test_resume_is_bit_identical_with_densification_and_the_filter(tiny_spot, tmp_path, monkeypatch, restore_threads):
    """GOF: 24 steps straight vs 12 + crash + resume + 12, densifying (and refiltering) every 4 steps."""
    overrides = ("threads=1", "train.iterations=24", "train.checkpoint_every=12", "method.refine_every=4",
                 "method.refine_stop=30000", "method.reset_every=30000")
    straight, resumed = straight_and_resumed("gof", tiny_spot, tmp_path, monkeypatch, *overrides, crash_after=12)
    assert len(resumed.method.gaussians) == len(straight.method.gaussians) != 400  # densified
    for k, v in straight.method.gaussians.params.items():
        assert torch.equal(v, resumed.method.gaussians.params[k]), k
    assert torch.equal(straight.method.filter3d(), resumed.method.filter3d())
    assert len(straight.method.filter3d()) == len(straight.method.gaussians)
    saved = load_checkpoint(tmp_path / "a" / "checkpoint-final.pt")
    assert torch.equal(saved["method"]["filter3d"], straight.method.filter3d())


# ---- meshes --------------------------------------------------------------------------------------


def test_tets_extractor_calls_tetra_mesh_with_the_filtered_gaussians(tiny_spot, tmp_path, monkeypatch):
    m, scene, cfg = setup_method("gof", tiny_spot, "mesh.extractor=tets", "mesh.bisection_steps=3")
    calls = {}

    def tetra_mesh(g, cameras, settings, *, kernel, level, bisection_steps):
        calls.update(g=g, cameras=cameras, settings=settings, kernel=kernel, level=level, steps=bisection_steps)
        return trimesh.creation.box()

    monkeypatch.setattr(method_base, "tetra_mesh", tetra_mesh)
    size = m.extract_mesh(scene, cfg, tmp_path / "mesh.ply")
    assert size == {"vertices": 8, "faces": 12} and (tmp_path / "mesh.ply").is_file()
    assert calls["g"].filter3d is m.filter3d() and len(calls["g"]) == len(m.gaussians)
    assert calls["cameras"] == [scene.cameras[i] for i in scene.train_views]
    assert (calls["kernel"], calls["level"], calls["steps"]) == ("raymax", 0.5, 3)
    assert calls["settings"].scene_radius == scene.radius
    for name in ("radegs", "3dgs"):
        with pytest.raises(ConfigError, match="supports mesh.extractor 'tsdf', got 'tets'"):
            METHODS.get(name).check_config(resolve_run(name, str(tiny_spot), preset="quick",
                                                       overrides=["mesh.extractor=tets"]))


# ---- quick end-to-end runs -----------------------------------------------------------------------

# A TSDF voxel of about one pixel at 64x48; one evaluator keeps the run short.
QUICK = ["data.downscale=1", "method.random_init_points=2000", "train.iterations=60", "train.checkpoint_every=0",
         "train.log_every=10", "mesh.voxel_size=0.02", "mesh.sdf_trunc=0.08", "eval.evaluators=[dtu_chamfer]",
         "threads=1"]


@pytest.mark.parametrize("name", METHOD_NAMES)
def test_quick_run_trains_meshes_evaluates_and_records(name, tiny_spot, tmp_path, restore_threads):
    record = quick_run(name, tiny_spot, tmp_path)
    assert set(record.eval_protocol) == {"dtu_chamfer"}
    schedule = record.losses["schedule"]  # starts are 15000 · 60/30000
    assert schedule["normal_consistency"] == {"weight": 0.05, "start": 30, "end": -1}
    assert schedule["depth_distortion"] == {"weight": 1000.0 if name == "gof" else 0.0, "start": 30, "end": -1}
    assert schedule["l1"]["weight"] == 0.8 and schedule["dssim"]["weight"] == 0.2
    assert record.losses["params"] == TERM_PARAMS[name]
