"""GOF / RaDe-GS abs-gradient densification (gsbench.training.strategies.absgrad.AbsGradStrategy, docs/methods/gof.md §5)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from gsbench.data.camera import Camera
from gsbench.geometry.filter3d import Filter3D, filter_coefficient
from gsbench.raster.types import RenderOutput
from gsbench.training.gaussians import Gaussians
from gsbench.training.strategies.absgrad import AbsGradStrategy, matched_threshold
from gsbench.training.strategies.default import DefaultStrategy
from gsbench.training.trainer import scaled_strategy

SMALL, LARGE = math.log(0.002), math.log(0.2)  # max scale below / above percent_dense·extent = 0.01
OPAQUE = 2.0  # opacity logit: 0.88


def make_setup(log_scales, z: float = 2.0):
    """Opaque Gaussians with the given isotropic log-scales on the line y = 0, z = ``z`` (x = 0.1·i) and an
    Adam (lr 0) with non-zero moments, one group per parameter."""
    n = len(log_scales)
    means = torch.zeros(n, 3)
    means[:, 0] = 0.1 * torch.arange(n, dtype=torch.float32)
    means[:, 2] = z
    g = Gaussians(means=means, log_scales=torch.tensor([[s, s, s] for s in log_scales]),
                  quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), opacity_logits=torch.full((n,), OPAQUE),
                  sh_dc=torch.rand(n, 1, 3), sh_rest=torch.zeros(n, 3, 3), max_sh_degree=1)
    opt = torch.optim.Adam([{"params": [p], "name": k, "lr": 0.0} for k, p in g.params.items()], eps=1e-15)
    sum(p.sum() for p in g.params.values()).backward()
    opt.step()
    opt.zero_grad(set_to_none=True)
    return g, opt


def fake_render(grad_norms, abs_grads, radii=None):
    """A RenderOutput with NDC mean-2D gradient norms ``grad_norms`` and abs-gradients ``abs_grads`` (W = H = 2)."""
    n = len(grad_norms)
    means2d = torch.zeros(n, 2, requires_grad=True)
    means2d.grad = torch.stack([torch.tensor(grad_norms, dtype=torch.float32), torch.zeros(n)], -1)
    radii = torch.full((n,), 5, dtype=torch.int32) if radii is None else torch.as_tensor(radii, dtype=torch.int32)
    return RenderOutput(means2d=means2d, radii=radii, visible=radii > 0, width=2, height=2,
                        extras={"absgrad": torch.tensor(abs_grads, dtype=torch.float32)})


def immediate(**kw):
    return AbsGradStrategy(refine_start=0, refine_every=1, refine_stop=100, reset_every=1000, **kw)


@pytest.mark.parametrize("n,k", [(10, 3), (1000, 1), (1000, 370), (7, 7), (50, 0)])
def test_matched_threshold_selects_as_many_as_the_standard_test(n, k):
    values = torch.rand(n, generator=torch.Generator().manual_seed(n + k))
    threshold = matched_threshold(values, k / n)
    assert int((values.double() >= threshold).sum()) == max(k, 1)  # ρ = 0 still selects the maximum (GOF)
    if 0 < k < n:
        expected = torch.quantile(values.double(), 1 - k / n)
        torch.testing.assert_close(torch.tensor(threshold, dtype=torch.float64), expected)


def test_selection_is_the_union_of_the_standard_and_the_matched_abs_test():
    # standard (g >= 2e-4): rows 0, 1 -> ρ = 2/6 -> the 2 largest g_abs: rows 4, 5
    grads = [3e-4, 5e-4, 1e-4, 1e-4, 1e-5, 1e-5]
    absg = [4e-4, 6e-4, 2e-4, 3e-4, 9e-4, 8e-4]
    g, opt = make_setup([SMALL, LARGE, SMALL, SMALL, SMALL, LARGE])
    strategy = immediate()
    state = strategy.init_state(6)
    info = strategy.step_post_backward(g, opt, state, 1, fake_render(grads, absg))
    # clone rows 0, 4 (small), split rows 1, 5 (large): 6 + 2 + 4 - 2
    assert info == {"cloned": 2, "split": 2, "pruned": 0, "reset": False, "budget_cut": 0}
    assert len(g) == 10
    assert set(state) == {"grad2d", "count", "radii", "absgrad"} and all(len(v) == 10 for v in state.values())
    # the same statistics select only rows 0, 1 with the 3DGS strategy
    g2, opt2 = make_setup([SMALL, LARGE, SMALL, SMALL, SMALL, LARGE])
    default = DefaultStrategy(refine_start=0, refine_every=1, refine_stop=100, reset_every=1000)
    assert default.step_post_backward(g2, opt2, default.init_state(6), 1, fake_render(grads, absg))["cloned"] == 1


def test_abs_statistics_average_over_visible_renders_and_unseen_rows_stay():
    g, opt = make_setup([SMALL] * 3)
    strategy = dataclasses.replace(immediate(), refine_every=2)
    state = strategy.init_state(3)
    strategy.step_post_backward(g, opt, state, 1, fake_render([0.0] * 3, [4e-4, 1.0, 0.0], radii=[5, 0, 0]))
    assert state["absgrad"].tolist() == pytest.approx([4e-4, 0.0, 0.0]) and state["count"].tolist() == [1, 0, 0]
    # ρ = 0: τ_abs = max g_abs -> row 0 only; rows 1, 2 (g_abs 0, never seen) are not selected
    info = strategy.step_post_backward(g, opt, state, 2, fake_render([0.0] * 3, [2e-4, 0.0, 0.0], radii=[5, 0, 0]))
    assert info["cloned"] == 1 and len(g) == 4


def test_clone_positions_are_sampled_from_the_parent():
    torch.manual_seed(0)
    n = 400
    g, opt = make_setup([SMALL] * n)
    parents = g.means.detach().clone()
    strategy = immediate()
    strategy.step_post_backward(g, opt, strategy.init_state(n), 1, fake_render([1e-3] * n, [1e-3] * n))
    assert len(g) == 2 * n
    torch.testing.assert_close(g.means.detach()[:n], parents)  # originals stay
    offsets = g.means.detach()[n:] - parents
    assert offsets.std(0).sub(0.002).abs().max() < 0.0003  # ε ~ N(0, I) scaled by s = 0.002
    torch.testing.assert_close(g.params["log_scales"].detach()[n:], g.params["log_scales"].detach()[:n])


def test_budget_takes_the_highest_abs_gradients():
    grads = [3e-4, 3e-4, 3e-4, 3e-4]
    absg = [1e-3, 4e-3, 2e-3, 3e-3]
    g, opt = make_setup([SMALL, SMALL, LARGE, SMALL])
    strategy = immediate(max_gaussians=6)
    info = strategy.step_post_backward(g, opt, strategy.init_state(4), 1, fake_render(grads, absg))
    # room 2: row 1 (clone, +1), row 3 (clone, +1); the split of row 2 and the clone of row 0 no longer fit
    assert (info["cloned"], info["split"], len(g)) == (2, 0, 6)
    full = immediate(max_gaussians=4)
    g, opt = make_setup([SMALL] * 4)
    assert full.step_post_backward(g, opt, full.init_state(4), 1, fake_render(grads, absg))["cloned"] == 0


class CountingFilter(Filter3D):
    def __init__(self, cameras):
        super().__init__(cameras, near=0.2)
        self.steps: list[int] = []
        self.step = 0

    def update(self, means):
        self.steps.append(self.step)
        return super().update(means)


def camera() -> Camera:
    K = np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]])
    return Camera(K=K, R=np.eye(3), t=np.zeros(3), width=100, height=80)


def test_filter_is_recomputed_after_refinement_before_the_reset_and_on_schedule():
    g, opt = make_setup([SMALL, SMALL, LARGE])
    filt = CountingFilter([camera()])
    filt.update(g.means)
    strategy = AbsGradStrategy(refine_start=0, refine_every=10, refine_stop=30, reset_every=30, filter3d=filt,
                               filter_every=10, iterations=100)
    state = strategy.init_state(3)
    for step in range(1, 101):
        filt.step = step
        n = len(g)
        info = strategy.step_post_backward(g, opt, state, step, fake_render([3e-4] * n, [3e-4] * n))
        assert len(filt.variance) == len(g) and not info["reset"]  # the filter follows every densification
    # start, refinements at 10 and 20 (none at 30 = refine_stop), then every 10 after 30 while step < 90
    assert filt.steps == [0, 10, 20, 40, 50, 60, 70, 80]


def test_reset_uses_the_filtered_opacity():
    g, opt = make_setup([SMALL] * 2, z=1.0)
    filt = Filter3D([camera()], near=0.2)
    variance = filt.update(g.means)  # σ_f² = (1/100)²·0.2 = 2e-5 >> s² = 4e-6
    strategy = AbsGradStrategy(refine_start=0, refine_every=5, refine_stop=100, reset_every=5, filter3d=filt,
                               prune_opacity=0.0)
    coef = filter_coefficient(g.scales.detach(), variance)
    info = strategy.step_post_backward(g, opt, strategy.init_state(2), 5, fake_render([0.0, 0.0], [0.0, 0.0]))
    assert info["reset"] and len(g) == 2
    torch.testing.assert_close(g.opacities.detach() * coef, torch.full((2,), 0.01))


def test_scaled_sets_the_run_length_and_keeps_absolute_intervals():
    s = scaled_strategy(AbsGradStrategy(), 3000)
    assert isinstance(s, AbsGradStrategy)
    assert (s.refine_start, s.refine_stop, s.refine_every, s.reset_every) == (50, 1500, 100, 300)
    assert (s.iterations, s.filter_every, s.prune_opacity) == (3000, 100, 0.05)
