"""Densification strategies and optimizer-aware parameter surgery (gsbench.training.strategies)."""

from __future__ import annotations

import math

import pytest
import torch

from gsbench.errors import ConfigError
from gsbench.raster.types import RenderOutput
from gsbench.training.gaussians import PARAMETER_NAMES, Gaussians
from gsbench.training.strategies.base import append_params, keep_params
from gsbench.training.strategies.default import DefaultStrategy

SMALL, LARGE = math.log(0.002), math.log(0.2)  # max scale below / above percent_dense·extent = 0.01
HIGH, LOW = 1e-3, 1e-5  # NDC gradient norms above / below the 0.0002 threshold
OPAQUE, FAINT = 2.0, -8.0  # opacity logits: 0.88 and 0.0003 (< 0.005)


def make_setup(rows):
    """Gaussians from ``rows`` = [(log_scale, opacity_logit)], an Adam with one group per parameter and
    non-zero moments (lr 0 keeps the values); row i has mean x = i so rows can be traced through densification."""
    n = len(rows)
    means = torch.zeros(n, 3)
    means[:, 0] = torch.arange(n, dtype=torch.float32)
    g = Gaussians(means=means, log_scales=torch.tensor([[s, s, s] for s, _ in rows]),
                  quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                  opacity_logits=torch.tensor([o for _, o in rows]), sh_dc=torch.rand(n, 1, 3),
                  sh_rest=torch.zeros(n, 3, 3), max_sh_degree=1)
    opt = torch.optim.Adam([{"params": [p], "name": k, "lr": 0.0} for k, p in g.params.items()], eps=1e-15)
    loss = sum((p * torch.arange(1, p.numel() + 1, dtype=p.dtype).reshape(p.shape)).sum() for p in g.params.values())
    loss.backward()
    opt.step()
    opt.zero_grad(set_to_none=True)
    return g, opt


def fake_render(grad_norms, radii=None):
    """A RenderOutput whose means2d.grad has the given norms in NDC units (W = H = 2: scale 1)."""
    n = len(grad_norms)
    means2d = torch.zeros(n, 2, requires_grad=True)
    means2d.grad = torch.stack([torch.tensor(grad_norms, dtype=torch.float32), torch.zeros(n)], -1)
    radii = torch.full((n,), 5, dtype=torch.int32) if radii is None else torch.as_tensor(radii, dtype=torch.int32)
    return RenderOutput(means2d=means2d, radii=radii, visible=radii > 0, width=2, height=2)


def moments(opt, name):
    group = next(g for g in opt.param_groups if g["name"] == name)
    return opt.state[group["params"][0]]


def check_optimizer_follows(g, opt):
    for name in PARAMETER_NAMES:
        group = next(gr for gr in opt.param_groups if gr["name"] == name)
        assert group["params"][0] is g.params[name]
        state = opt.state[g.params[name]]
        assert state["exp_avg"].shape == g.params[name].shape == state["exp_avg_sq"].shape


def immediate(**kw):
    return DefaultStrategy(refine_start=0, refine_every=1, refine_stop=100, reset_every=1000, **kw)


def test_clone_split_prune_counts_and_optimizer_rows():
    rows = [(SMALL, OPAQUE), (LARGE, OPAQUE), (SMALL, OPAQUE), (LARGE, OPAQUE), (SMALL, FAINT)]
    grads = [HIGH, HIGH, LOW, LOW, HIGH]
    g, opt = make_setup(rows)
    before = {k: moments(opt, k)["exp_avg"].clone() for k in PARAMETER_NAMES}
    strategy = immediate()
    state = strategy.init_state(len(g))
    info = strategy.step_post_backward(g, opt, state, 1, fake_render(grads))
    # clone rows 0 and 4; split row 1 into 2; prune row 4 and its clone (faint)
    assert info == {"cloned": 2, "split": 1, "pruned": 2, "reset": False, "budget_cut": 0}
    assert len(g) == 5 + 2 + 2 - 1 - 2
    x = g.means.detach()[:, 0]
    assert x[:3].tolist() == [0.0, 2.0, 3.0]  # originals kept in order: 0, 2, 3
    assert x[3].item() == 0.0  # the clone of row 0, identical
    check_optimizer_follows(g, opt)
    for k in PARAMETER_NAMES:
        m = moments(opt, k)["exp_avg"]
        torch.testing.assert_close(m[:3], before[k][[0, 2, 3]])
        assert (m[3:] == 0).all()  # new rows start with zero moments
    # split children: scale / 1.6, copied rotation/colour, parents removed
    torch.testing.assert_close(g.params["log_scales"].detach()[4:], torch.full((2, 3), LARGE - math.log(1.6)))
    assert all(len(v) == len(g) for v in state.values()) and all(float(v.sum()) == 0 for v in state.values())
    # the next Adam step leaves the replaced (grad-less) parameters alone and does not fail
    means = g.params["means"].detach().clone()
    for group in opt.param_groups:
        group["lr"] = 1e-3
    opt.step()
    torch.testing.assert_close(g.params["means"].detach(), means)


def test_split_children_are_sampled_from_the_parent():
    torch.manual_seed(0)
    g, opt = make_setup([(LARGE, OPAQUE)] * 200)
    immediate().step_post_backward(g, opt, immediate().init_state(200), 1, fake_render([HIGH] * 200))
    assert len(g) == 400
    offsets = g.means.detach() - torch.arange(200, dtype=torch.float32).repeat(2)[:, None] * torch.tensor([1.0, 0, 0])
    assert offsets.std(0).sub(0.2).abs().max() < 0.03  # ε ~ N(0, I) scaled by the parent's s = 0.2


def test_2d_split_stays_in_plane():
    n = 50
    g = Gaussians(means=torch.zeros(n, 3), log_scales=torch.full((n, 2), LARGE),
                  quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), opacity_logits=torch.full((n,), OPAQUE), sh_dc=torch.zeros(n, 1, 3), sh_rest=torch.zeros(n, 0, 3),
                  max_sh_degree=0)
    opt = torch.optim.Adam([{"params": [p], "name": k} for k, p in g.params.items()])
    immediate().step_post_backward(g, opt, immediate().init_state(n), 1, fake_render([HIGH] * n))
    assert len(g) == 2 * n and g.params["log_scales"].shape == (2 * n, 2)
    assert (g.means.detach()[:, 2] == 0).all() and g.means.detach()[:, :2].abs().sum() > 0


def test_statistics_average_over_visible_renders():
    g, opt = make_setup([(SMALL, OPAQUE)] * 3)
    strategy = DefaultStrategy(refine_start=0, refine_every=3, refine_stop=100, reset_every=1000)
    state = strategy.init_state(3)
    # row 0: 3 renders with mean 0.0003 > threshold; row 1: 2 visible renders of 0.0003 + one invisible high grad
    # (ignored); row 2: mean 0.0001 < threshold.
    strategy.step_post_backward(g, opt, state, 1, fake_render([3e-4, 3e-4, 1e-4]))
    strategy.step_post_backward(g, opt, state, 2, fake_render([3e-4, 1.0, 1e-4], radii=[5, 0, 5]))
    assert state["count"].tolist() == [2.0, 1.0, 2.0]
    info = strategy.step_post_backward(g, opt, state, 3, fake_render([3e-4, 3e-4, 1e-4]))
    assert info["cloned"] == 2 and len(g) == 5


def test_budget_takes_highest_gradients():
    rows = [(SMALL, OPAQUE), (SMALL, OPAQUE), (LARGE, OPAQUE), (SMALL, OPAQUE)]
    g, opt = make_setup(rows)
    strategy = immediate(max_gaussians=6)
    info = strategy.step_post_backward(g, opt, strategy.init_state(4), 1, fake_render([2e-3, 5e-4, 1e-3, 3e-3]))
    # room 2: row 3 (clone, +1), row 0 (clone, +1); the split of row 2 (+1) and row 1 no longer fit
    assert info["cloned"] == 2 and info["split"] == 0 and len(g) == 6
    assert info["budget_cut"] == 2  # the candidates left out: rows 1 and 2
    assert sorted(g.means.detach()[4:, 0].tolist()) == [0.0, 3.0]
    full = immediate(max_gaussians=4)
    g, opt = make_setup(rows)
    info = full.step_post_backward(g, opt, full.init_state(4), 1, fake_render([1e-3] * 4))
    assert info["cloned"] == 0 and info["budget_cut"] == 4 and len(g) == 4
    g, opt = make_setup(rows)
    unbounded = immediate()
    assert unbounded.step_post_backward(g, opt, unbounded.init_state(4), 1, fake_render([1e-3] * 4))["budget_cut"] == 0


def test_world_size_pruning_after_first_reset_and_screen_size_option():
    rows = [(SMALL, OPAQUE), (math.log(0.5), OPAQUE), (SMALL, OPAQUE)]
    radii = [5, 5, 30]
    for step, screen, world, expected in ((1, False, True, 3), (1001, False, True, 2), (1001, True, True, 1),
                                          (1001, True, False, 3)):  # GGGS: no size pruning at all
        g, opt = make_setup(rows)
        strategy = DefaultStrategy(refine_start=0, refine_every=1, refine_stop=2000, reset_every=1000,
                                   prune_screen_size=screen, prune_world_size=world)
        strategy.step_post_backward(g, opt, strategy.init_state(3), step, fake_render([LOW] * 3, radii=radii))
        assert len(g) == expected, (step, screen, world)


def test_prune_grace_spares_faint_gaussians_right_after_a_reset():
    """With prune_grace 100 and resets every 1000 steps, a faint Gaussian survives refinements at
    steps 1001-1099 and is pruned from step 1100; grace 0 (the paper) prunes it at once."""
    rows = [(SMALL, OPAQUE), (SMALL, FAINT)]
    for step, grace, expected in ((1010, 100, 2), (1099, 100, 2), (1100, 100, 1), (1010, 0, 1), (500, 100, 1)):
        g, opt = make_setup(rows)
        strategy = DefaultStrategy(refine_start=0, refine_every=1, refine_stop=2000, reset_every=1000,
                                   prune_grace=grace)
        strategy.step_post_backward(g, opt, strategy.init_state(2), step, fake_render([LOW] * 2))
        assert len(g) == expected, (step, grace)


def test_opacity_reset_clamps_and_zeroes_moments():
    g, opt = make_setup([(SMALL, OPAQUE), (SMALL, FAINT)])
    opacities = g.opacities.detach().clone()
    means_moment = moments(opt, "means")["exp_avg"].clone()
    strategy = DefaultStrategy(refine_start=10_000, reset_every=3000)
    info = strategy.step_post_backward(g, opt, strategy.init_state(2), 3000, fake_render([LOW, LOW]))
    assert info["reset"] and len(g) == 2
    torch.testing.assert_close(g.opacities.detach(), torch.minimum(opacities, torch.tensor(0.01)))
    assert (moments(opt, "opacity_logits")["exp_avg"] == 0).all()
    assert (moments(opt, "opacity_logits")["exp_avg_sq"] == 0).all()
    torch.testing.assert_close(moments(opt, "means")["exp_avg"], means_moment)
    white = DefaultStrategy(white_background=True)
    assert white.step_post_backward(g, opt, white.init_state(2), 500, fake_render([LOW, LOW]))["reset"]


def test_schedule_bounds_and_scaling():
    s = DefaultStrategy()
    assert (s.refine_start, s.refine_stop, s.refine_every, s.reset_every) == (500, 15000, 100, 3000)
    short = s.scaled(3000)
    assert (short.refine_start, short.refine_stop, short.refine_every, short.reset_every) == (50, 1500, 10, 300)
    assert short.grad_threshold == s.grad_threshold and s.scaled(10).refine_every == 1
    g, opt = make_setup([(SMALL, OPAQUE)])
    state = s.init_state(1)
    for step in (500, 15000, 15100):  # not after refine_start, not from refine_stop on
        assert s.step_post_backward(g, opt, state, step, fake_render([HIGH]))["cloned"] == 0
    assert s.step_post_backward(g, opt, state, 600, fake_render([HIGH]))["cloned"] == 1
    with pytest.raises(ConfigError):
        DefaultStrategy(split_n=1)


def test_parameter_surgery_helpers():
    g, opt = make_setup([(SMALL, OPAQUE)] * 3)
    append_params(g, opt, {k: v.detach()[:1] * 0 + 7 for k, v in g.params.items()})
    assert len(g) == 4 and g.means.detach()[3, 0] == 7
    keep_params(g, opt, torch.tensor([False, True, True, True]))
    assert g.means.detach()[:, 0].tolist() == [1.0, 2.0, 7.0]
    check_optimizer_follows(g, opt)
    assert all(p.requires_grad for p in g.params.values())


def test_pre_backward_retains_means2d_grad():
    leaf = torch.zeros(2, 2, requires_grad=True)
    means2d = leaf * 2.0
    out = RenderOutput(means2d=means2d, radii=torch.ones(2, dtype=torch.int32), width=4, height=2)
    DefaultStrategy().step_pre_backward(out)
    (means2d * torch.tensor([[1.0, 2.0], [3.0, 4.0]])).sum().backward()
    grad, _ = out.densify_grads()
    torch.testing.assert_close(grad, torch.tensor([[2.0, 2.0], [6.0, 4.0]]))
