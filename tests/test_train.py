"""The Trainer (gsbench.training.trainer): schedule scaling, camera sampling, bit-exact resume, outputs that follow
the active terms, numerical errors, masks, metrics log."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

import gsbench.methods.base as method_base
from gsbench.data.loader import load_scene
from gsbench.errors import NumericalError
from gsbench.registry import METHODS
from gsbench.run_folder import RunFolder
from gsbench.runs.runner import resolve_run
from gsbench.training.strategies.default import DefaultStrategy
from gsbench.training.trainer import (
    CameraSampler,
    Trainer,
    _target_images,
    load_checkpoint,
    scale_step,
    scaled_losses,
    scaled_strategy,
)
from tests.method_setup import interrupt_at

# Idle OpenMP threads must sleep, not spin (see gsbench.training.trainer.set_threads); set at collection, before
# any test loads the rasterizer extension.
TINY = ["data.downscale=1", "method.random_init_points=400", "train.log_every=5"]


def make_trainer(method, scene_dir, run_dir, *overrides):
    cfg = resolve_run(method, str(scene_dir), preset="quick", overrides=[*TINY, *overrides])
    scene = load_scene(cfg.scene, downscale=cfg.data.downscale)
    m = METHODS.get(method)()
    m.setup(scene, cfg)
    return Trainer(m, scene, cfg, run_dir)


# ---- schedule scaling ---------------------------------------------------------------------------


def test_scale_step_keeps_unset_values_and_rounds_to_at_least_one():
    assert scale_step(7000, 0.1) == 700
    assert scale_step(3000, 1 / 300) == 10
    assert scale_step(1, 1e-4) == 1
    assert scale_step(0, 0.1) == 0 and scale_step(-1, 0.1) == -1


def test_losses_scale_start_and_end_but_not_weights():
    losses = {"normal_consistency": {"weight": 0.05, "start": 7000, "end": -1},
              "depth_distortion": {"weight": 1000, "start": 3000, "end": 20000}}
    assert scaled_losses(losses, 0.1) == {"normal_consistency": {"weight": 0.05, "start": 700, "end": -1},
                                          "depth_distortion": {"weight": 1000.0, "start": 300, "end": 2000}}


def test_strategy_window_scales_but_refine_interval_stays_and_resets_align_with_it():
    s = scaled_strategy(DefaultStrategy(), 3000)
    assert (s.refine_start, s.refine_stop, s.refine_every, s.reset_every) == (50, 1500, 100, 300)
    paper = scaled_strategy(DefaultStrategy(), 30000)
    assert paper == DefaultStrategy()
    short = scaled_strategy(DefaultStrategy(), 300)
    assert short.reset_every % short.refine_every == 0 and short.refine_every == 100
    rounds = scaled_strategy(DefaultStrategy(), 3000, scale_refine_interval=True)
    assert (rounds.refine_every, rounds.reset_every, rounds.prune_grace) == (10, 300, 100)
    assert scaled_strategy(DefaultStrategy(), 30000, scale_refine_interval=True) == dataclasses.replace(
        DefaultStrategy(), prune_grace=100)


def test_camera_sampler_draws_every_view_once_per_epoch_and_is_seeded():
    a, b = CameraSampler(range(7), seed=3), CameraSampler(range(7), seed=3)
    draws = [a.next() for _ in range(21)]
    assert draws == [b.next() for _ in range(21)]
    for epoch in range(3):
        assert sorted(draws[7 * epoch:7 * epoch + 7]) == list(range(7))
    state = a.state_dict()
    ahead = [a.next() for _ in range(5)]
    a.load_state_dict(state)
    assert [a.next() for _ in range(5)] == ahead


# ---- the loop -------------------------------------------------------------------------------------


@pytest.mark.parametrize("threads", [1, 2])
def test_resume_gives_bit_identical_parameters(tiny_spot, tmp_path, monkeypatch, restore_threads, threads):
    """24 steps straight vs 12 + crash + resume + 12, with densification (every 4 steps) in between, at
    the same thread count (the rasterizer's backward deals tiles to threads in a fixed order)."""
    overrides = (f"threads={threads}", "train.iterations=24", "train.checkpoint_every=12", "method.refine_every=4",
                 "method.refine_stop=30000", "method.reset_every=30000")
    straight = make_trainer("3dgs", tiny_spot, tmp_path / "a", *overrides)
    straight.fit()

    interrupted = make_trainer("3dgs", tiny_spot, tmp_path / "b", *overrides)
    interrupt_at(interrupted, 13, monkeypatch)  # after the checkpoint at step 12
    with pytest.raises(KeyboardInterrupt):
        interrupted.fit()
    assert (tmp_path / "b" / RunFolder.CHECKPOINT).is_file() and not (tmp_path / "b" / RunFolder.FINAL_CHECKPOINT).exists()
    monkeypatch.undo()
    resumed = make_trainer("3dgs", tiny_spot, tmp_path / "b", *overrides)
    result = resumed.fit()
    assert result.resumed_from == 12 and result.steps == 24
    assert not (tmp_path / "b" / RunFolder.CHECKPOINT).exists()
    assert len(straight.method.gaussians) != 400, "densification should have changed the count"
    for name, param in straight.method.gaussians.params.items():
        assert torch.equal(param, resumed.method.gaussians.params[name]), name
    a = load_checkpoint(tmp_path / "a" / RunFolder.FINAL_CHECKPOINT)["method"]["optimizer"]["state"]
    b = load_checkpoint(tmp_path / "b" / RunFolder.FINAL_CHECKPOINT)["method"]["optimizer"]["state"]
    assert all(torch.equal(a[k]["exp_avg_sq"], b[k]["exp_avg_sq"]) for k in a)
    steps = [json.loads(line)["step"] for line in (tmp_path / "b" / RunFolder.METRICS).read_text().splitlines()]
    assert steps == [5, 10, 15, 20, 24]


def test_render_requests_only_the_outputs_of_active_terms(tiny_spot, tmp_path, monkeypatch):
    """2DGS with normal_consistency weight 0: never 'normal'; 'distortion' only from its (scaled) start."""
    calls = []
    real = method_base.rasterize

    def spy(*args, outputs, **kwargs):
        calls.append(frozenset(outputs))
        return real(*args, outputs=outputs, **kwargs)

    monkeypatch.setattr(method_base, "rasterize", spy)
    trainer = make_trainer("2dgs", tiny_spot, tmp_path, "train.iterations=20", "losses.normal_consistency.weight=0",
                           "losses.depth_distortion.start=15000")  # scaled start: step 10
    trainer.fit()
    assert len(calls) == 20
    assert all("normal" not in c and "median_depth" not in c for c in calls)
    assert calls[:9] == [frozenset({"rgb"})] * 9
    assert calls[9:] == [frozenset({"rgb", "distortion"})] * 11


def test_non_finite_parameter_is_a_numerical_error_naming_it_and_the_step(tiny_spot, tmp_path):
    trainer = make_trainer("3dgs", tiny_spot, tmp_path, "train.iterations=10")

    def poison(optimizer, args, kwargs):
        trainer.method.gaussians.params["sh_dc"].data[3, 0, 1] = math.nan

    trainer.method.optimizer.register_step_post_hook(poison)
    # parameters are checked every PARAMETER_CHECK_EVERY steps; the next render tests its inputs at once
    with pytest.raises(NumericalError, match=r"step 2: .*gaussians.sh has 1 non-finite value"):
        trainer.fit()
    with pytest.raises(NumericalError, match=r"step 7: parameter 'sh_dc' has 1 non-finite rows \(first at index 3\)"):
        trainer.check_parameters(7)


def test_fused_adam_is_the_single_tensor_update_up_to_rounding(tiny_spot, tmp_path):
    trainer = make_trainer("2dgs", tiny_spot, tmp_path, "train.iterations=10")
    fast = trainer.method.optimizer
    assert all(group["fused"] for group in fast.param_groups)
    params = [p for group in fast.param_groups for p in group["params"]]
    copies = [p.detach().clone().requires_grad_(True) for p in params]
    slow = torch.optim.Adam([{**{k: v for k, v in g.items() if k not in ("params", "foreach", "fused")}, "params": [c]}
                             for g, c in zip(fast.param_groups, copies)], foreach=False)
    gen = torch.Generator().manual_seed(0)
    for _ in range(5):
        for p, c in zip(params, copies):
            p.grad = torch.randn(p.shape, generator=gen)
            c.grad = p.grad.clone()
        fast.step()
        slow.step()
    assert all(torch.allclose(p, c, rtol=1e-6, atol=1e-7) for p, c in zip(params, copies))


def test_masked_targets_show_the_background_outside_the_mask(tiny_spot):
    cfg = resolve_run("2dgs", str(tiny_spot), preset="quick", overrides=TINY)
    scene = load_scene(cfg.scene, downscale=1)
    scene.images = [np.full_like(img, 0.7) for img in scene.images]
    images, masks = _target_images(scene, cfg, (0.0, 0.0, 1.0))  # default: full images, masks to the terms
    assert masks[0] is not None and torch.allclose(images[0], torch.tensor(0.7))
    cfg.data.mask_target = True
    images, masks = _target_images(scene, cfg, (0.0, 0.0, 1.0))
    mask = masks[0]
    assert mask is not None and mask.any() and (~mask).any()
    assert torch.equal(images[0][~mask], torch.tensor([0.0, 0.0, 1.0]).expand(int((~mask).sum()), 3))
    assert torch.allclose(images[0][mask], torch.tensor(0.7))
    cfg.data.use_masks = False
    images, masks = _target_images(scene, cfg, (0.0, 0.0, 1.0))
    assert masks[0] is None and torch.allclose(images[0], torch.tensor(0.7))
