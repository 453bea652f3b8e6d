"""GGGS (methods/gggs.py, methods/gggs_terms.py): a quick run to ok with its geometric terms on, exact resume,
the initial scale clamp, the depth–normal term's validity, the planes the multi-view terms warp, and the median
depth in place of the solid one (``method.surface_depth``, docs/methods/gggs.md §3.5)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from gsbench.cli import main
from gsbench.config.run_config import run_id
from gsbench.data.loader import load_scene
from gsbench.errors import ConfigError
from gsbench.geometry.depth import pixel_rays
from gsbench.losses.terms import Batch, active_terms, required_outputs
from gsbench.methods.gggs import depth_planes
from gsbench.methods.gggs_terms import NO_SURFACE_TRANSMITTANCE, depth_validity, gggs_normal_term, surface_depth
from gsbench.raster.types import RenderOutput
from gsbench.registry import METHODS
from gsbench.run_folder import RunFolder
from gsbench.runs.runner import resolve_run
from gsbench.runs.sweep import expand, load_sweep
from gsbench.training.trainer import Trainer, load_checkpoint
from tests.method_setup import interrupt_at
from tests.raster_scenes import make_camera
from tests.sweep_files import sweep_file

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


def test_depth_planes_pass_through_the_depth_points():
    """The plane (d, n̂) of each pixel holds its point D·r: n̂·(D r) = −d; a pixel without depth has d = 0."""
    cam = make_camera(8, 6)
    depth = 1.0 + torch.rand(6, 8, generator=torch.Generator().manual_seed(0))
    depth[0, 0] = 0.0
    normal = torch.nn.functional.normalize(torch.randn(6, 8, 3, generator=torch.Generator().manual_seed(1)), dim=-1)
    d, n = depth_planes(depth, 2.0 * normal, cam)
    points = depth[..., None] * pixel_rays(cam, depth.dtype)
    assert torch.allclose((n * points).sum(-1), -d, atol=1e-6) and float(d[0, 0]) == 0.0


def test_the_median_depth_keeps_the_solid_depths_no_surface_rule():
    """``median``: the median depth where the final transmittance 1 − α is at most 0.45, else 0; ``solid``: the solid
    depth as rendered."""
    median, solid = torch.full((2, 3), 2.0), torch.full((2, 3), 3.0)
    alpha = torch.tensor([[1.0, 0.56, 0.54], [0.0, 0.9, 0.55]])
    render = RenderOutput(solid_depth=solid, median_depth=median, alpha=alpha)
    assert NO_SURFACE_TRANSMITTANCE == 0.45
    assert torch.equal(surface_depth(render, "median"), torch.tensor([[2.0, 2.0, 0.0], [0.0, 2.0, 2.0]]))
    assert surface_depth(render, "solid") is solid
    with pytest.raises(ConfigError, match="surface depth must be one of solid, median"):
        surface_depth(render, "expected")


def _setup(tiny_spot, *overrides):
    cfg = resolve_run("gggs", str(tiny_spot), preset="quick",
                      overrides=["data.downscale=1", "method.random_init_points=400", "train.iterations=4",
                                 "train.checkpoint_every=0", "threads=1", *EARLY, *overrides])
    scene = load_scene(cfg.scene, downscale=cfg.data.downscale)
    method = METHODS.get("gggs")()
    method.setup(scene, cfg)
    return method, scene, cfg


def _two_depth_render(method, camera) -> RenderOutput:
    """The method's render with the solid and the median depth, the median made clearly different from the solid."""
    out = method.render(camera, {"solid_depth", "median_depth", "alpha", "normal", "rgb"})
    out.median_depth = out.median_depth * 1.3 + 0.05 * (out.median_depth > 0)
    return out


@pytest.mark.parametrize("depth", ["solid", "median"])
def test_the_surface_depth_option_is_the_depth_the_terms_and_planes_read(tiny_spot, depth, restore_threads):
    """With ``method.surface_depth`` the three geometric terms ask for and read that depth, and the multi-view planes
    (of the step's view and of its neighbour) are built from it: a method that ignored the option would read the
    solid depth and fail here."""
    method, scene, cfg = _setup(tiny_spot, f"method.surface_depth={depth}")
    active = active_terms(cfg.losses, 1, method.term_params())
    wanted = {"solid": {"solid_depth"}, "median": {"median_depth", "alpha"}}[depth]
    other = {"solid": "median_depth", "median": "solid_depth"}[depth]
    assert wanted <= required_outputs(active) and other not in required_outputs(active)
    assert wanted <= set(method.NEIGHBOUR_OUTPUTS) and other not in method.NEIGHBOUR_OUTPUTS
    view = scene.train_views[0]
    camera = scene.cameras[view]
    render = _two_depth_render(method, camera)
    used = surface_depth(render, depth)
    assert float((used - render.solid_depth).detach().abs().max()) > 0.01 if depth == "median" else \
        used is render.solid_depth
    batch = Batch(torch.as_tensor(np.asarray(scene.images[view], dtype=np.float32)), None, camera, 1, view)
    normal_term = next(t.spec for t in active if t.name == "gggs_normal")
    expected = gggs_normal_term(RenderOutput(solid_depth=used, alpha=render.alpha, normal=render.normal), batch, {})
    assert float(normal_term(render, batch, method.loss_state()).detach()) == pytest.approx(float(expected.detach()),
                                                                                             abs=1e-7)
    d, n = method.planes(render, camera)
    d_expected, n_expected = depth_planes(used, render.normal, camera)
    assert torch.equal(d, d_expected) and torch.equal(n, n_expected)


def test_a_training_step_with_the_median_depth_never_runs_the_solid_pass(tiny_spot, tmp_path, monkeypatch,
                                                                         restore_threads):
    """Two steps with every geometric term on: the step's render and the neighbour's ask for the median depth and
    never for the solid one (so its cost is gone), and the default asks for the solid depth."""
    for depth, wanted, absent in (("median", "median_depth", "solid_depth"), ("solid", "solid_depth", "median_depth")):
        method, scene, cfg = _setup(tiny_spot, f"method.surface_depth={depth}")
        asked: list[set] = []
        original = method.render
        monkeypatch.setattr(method, "render",
                            lambda camera, outputs: asked.append(set(outputs)) or original(camera, outputs))
        Trainer(method, scene, cfg, tmp_path / depth).fit()
        assert len(asked) >= 8, (depth, asked)
        assert all(wanted in outputs and absent not in outputs for outputs in asked[:8]), (depth, asked)


def test_a_solid_run_keeps_its_run_id_and_record(tiny_spot):
    """surface_depth solid (the default) is left out of the run id, so every run recorded before the option keeps its
    id, and it binds no term parameter, so the record's ``losses.params`` is unchanged; a value that is neither is a
    ConfigError naming the key."""
    method, _, cfg = _setup(tiny_spot)
    recorded = cfg.to_dict()
    before = {**recorded, "method": {k: v for k, v in recorded["method"].items() if k != "surface_depth"}}
    assert cfg.method["surface_depth"] == "solid" and run_id(before) == cfg.run_id
    assert method.term_params() == {"l1_exposure": {"ssim_gate": False}}
    assert _setup(tiny_spot, "method.surface_depth=median")[2].run_id != cfg.run_id
    with pytest.raises(ConfigError, match="method.surface_depth must be one of solid, median"):
        _setup(tiny_spot, "method.surface_depth=expected")


def test_the_claims_sweep_is_the_recipe_and_one_change_a_row_on_the_boards_runs():
    """gggs_claims (docs/methods/gggs.md §8.2): the gggs row's runs are the dtu_rig board's (same ids); each other row
    differs from it in its one change only."""
    runs = expand(load_sweep(sweep_file("gggs_claims")))
    board = {r.run_id for r in expand(load_sweep(sweep_file("dtu_rig"))) if r.label == "gggs"}
    rows = {r.label: r.config for r in runs if r.config.seed == 0 and r.config.scene.endswith("bunny")}
    assert {r.run_id for r in runs if r.label == "gggs"} <= board and len(runs) == 24
    base = rows["gggs"]
    median = rows["gggs_median_depth"]
    assert (median.method["surface_depth"], median.mesh.depth) == ("median", "median")
    changed = {label: {k for k, v in rows[label].losses.items() if v != base.losses[k]} for label in rows}
    assert changed["gggs_without_multiview"] == {"gggs_geo", "gggs_ncc"}
    assert changed["gggs_without_depth_normal"] == {"gggs_normal"} and not changed["gggs_median_depth"]
    assert all(term["weight"] == 0 for term in (rows["gggs_without_multiview"].losses["gggs_geo"],
                                                 rows["gggs_without_multiview"].losses["gggs_ncc"],
                                                 rows["gggs_without_depth_normal"].losses["gggs_normal"]))
