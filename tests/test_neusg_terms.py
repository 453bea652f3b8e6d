"""NeuSG's two cross terms (methods/neusg.py, NeuSG eqs. 14 and 15, docs/methods/neusg.md §5.5): the value of
`sdf_points` and `sdf_align` against their closed form on the sphere the field starts as, and which side each
trains: L_pt moves the SDF and holds the Gaussians' centres fixed, L_align turns the Gaussians and holds the SDF's
normal fixed. And the marching-cubes shortcut (`sdf_volume`) on a trained field steeper than |∇f| = 1."""

from __future__ import annotations

import math

import numpy as np
import torch

from gsbench.losses.terms import Batch
from gsbench.methods import neusg
from gsbench.methods.neusg import (
    COARSE,
    NeuSG,
    NeuSGConfig,
    coarse_slope,
    evaluate,
    sdf_align_term,
    sdf_points_term,
    sdf_volume,
)
from gsbench.methods.neusg_field import HashGrid, ImplicitScene, SDFField
from gsbench.training.gaussians import Gaussians

RADIUS = 1.0  # the field's sphere; at initialisation f(x) = |x| − RADIUS / 2 exactly (methods/neusg_field.py)


def _method(means: torch.Tensor, opacities: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor) -> NeuSG:
    """A NeuSG plugin holding these Gaussians and a field fresh from initialisation (the sphere of radius 0.5)."""
    method = NeuSG()
    method.params = NeuSGConfig(point_batch=4096, point_min_opacity=0.5)
    method.field = ImplicitScene(RADIUS, 0, levels=2, min_res=8, max_res=32, background_levels=2, background_max_res=8)
    n = len(means)
    method.gaussians = Gaussians(means=means.clone(), log_scales=log_scales.clone(), quats=quats.clone(),
                                 opacity_logits=torch.logit(opacities), sh_dc=torch.zeros(n, 1, 3),
                                 sh_rest=torch.zeros(n, 0, 3), max_sh_degree=0)
    return method


def _identity_quats(n: int) -> torch.Tensor:
    return torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1)


def _flat_along_z(n: int) -> torch.Tensor:
    """log-scales whose shortest axis is the local z (so n_w = R e_z)."""
    return torch.log(torch.tensor([[0.1, 0.1, 0.01]])).repeat(n, 1)


def _state(method: NeuSG) -> dict:
    return method.loss_state()


def _batch() -> Batch:
    return Batch(image=torch.zeros(1, 1, 3), mask=None, camera=None, step=0)


def _grads(loss: torch.Tensor, method: NeuSG) -> tuple[dict, dict]:
    """(the Gaussians' gradients, the field's gradients) of ``loss``, None where it does not reach."""
    gaussians = dict(method.gaussians.params.items())
    field = dict(method.field.named_parameters())
    names, params = zip(*[*gaussians.items(), *(("field." + k, v) for k, v in field.items())])
    grads = torch.autograd.grad(loss, params, allow_unused=True)
    by_name = dict(zip(names, grads))
    return ({k: by_name[k] for k in gaussians}, {k: by_name["field." + k] for k in field})


def _reached(grad) -> bool:
    return grad is not None and bool(grad.abs().sum() > 0)


def test_sdf_points_is_the_mean_distance_of_the_qualifying_centres_and_trains_the_sdf_only():
    """L_pt = mean |f(μ_i)| over the centres with opacity ≥ 0.5 inside the field's sphere (NeuSG eq. 14): on the
    initial sphere f = |μ| − 0.5; a faint Gaussian and one outside the sphere are left out. Its gradient reaches
    the field and no Gaussian parameter (the centres are held fixed)."""
    means = torch.tensor([[0.0, 0.0, 0.8], [0.3, 0.0, 0.0], [0.0, -0.6, 0.0], [0.0, 0.0, 0.2], [1.5, 0.0, 0.0]])
    opacities = torch.tensor([0.9, 0.6, 0.9, 0.2, 0.9])  # the fourth faint, the fifth outside the sphere
    method = _method(means, opacities, _identity_quats(5), _flat_along_z(5))
    loss = sdf_points_term(None, _batch(), _state(method))
    expected = (means[:3].norm(dim=-1) - 0.5).abs().mean()
    assert math.isclose(float(loss.detach()), float(expected), rel_tol=1e-5)
    gaussian_grads, field_grads = _grads(loss, method)
    assert not any(_reached(g) for g in gaussian_grads.values())
    assert _reached(field_grads["sdf.out.bias"]) and _reached(field_grads["sdf.out.weight"])
    assert not _reached(field_grads["variance"]) and not _reached(field_grads["colour.net.0.weight"])


def test_sdf_points_without_a_qualifying_centre_is_zero_and_still_differentiable():
    method = _method(torch.tensor([[0.0, 0.0, 0.8]]), torch.tensor([0.1]), _identity_quats(1), _flat_along_z(1))
    loss = sdf_points_term(None, _batch(), _state(method))
    assert float(loss.detach()) == 0.0 and loss.requires_grad


def test_sdf_align_is_one_minus_the_cosine_to_the_sdf_normal_and_turns_the_gaussians_only():
    """L_align = mean |1 − |n_wᵀ ∇f̂(μ_i)|| (NeuSG eq. 15). On the initial sphere ∇f̂(μ) = μ / |μ| (up to the 4-tap
    difference's O(ε) error); with identity rotations n_w = e_z: a centre on the z axis gives 0 (either side, the
    sign does not matter), one on the x axis gives 1, one at 45° gives 1 − cos 45°. Its gradient reaches the
    rotations only: not the centres, not the scales (the argmin is a choice), not the field (its normal is held
    fixed)."""
    means = torch.tensor([[0.0, 0.0, 0.6], [0.0, 0.0, -0.6], [0.6, 0.0, 0.0], [0.4, 0.0, 0.4]])
    method = _method(means, torch.full((4,), 0.9), _identity_quats(4), _flat_along_z(4))
    loss = sdf_align_term(None, _batch(), _state(method))
    expected = (0.0 + 0.0 + 1.0 + (1 - math.cos(math.pi / 4))) / 4
    assert abs(float(loss.detach()) - expected) < 2e-3
    gaussian_grads, field_grads = _grads(loss, method)
    assert _reached(gaussian_grads["quats"])
    assert not any(_reached(g) for name, g in gaussian_grads.items() if name != "quats")
    assert not any(_reached(g) for g in field_grads.values())


def test_sdf_align_uses_the_shortest_axis_of_each_gaussian():
    """A Gaussian flat along its local x, at a centre on the world x axis, is aligned (0); flat along z there it is
    perpendicular (1)."""
    means = torch.tensor([[0.6, 0.0, 0.0], [0.6, 0.0, 0.0]])
    log_scales = torch.log(torch.tensor([[0.01, 0.1, 0.1], [0.1, 0.1, 0.01]]))
    method = _method(means, torch.full((2,), 0.9), _identity_quats(2), log_scales)
    loss = sdf_align_term(None, _batch(), _state(method))
    assert abs(float(loss.detach()) - 0.5) < 2e-3


def _plate_field() -> SDFField:
    """A hash-grid SDF trained (Adam, L1, 80 steps) towards a thin steep plate, f* = 12 (|z| − 0.02): |∇f| ≈ 12, not
    1, and the plate lies between two layers of the meshing grid's coarse vertices (z = ±0.04 at voxel 0.02, where
    f* = 0.24, beyond a coarse cell's diagonal 0.139), so all 8 corners of its cells are positive."""
    with torch.random.fork_rng():  # the MLP's initial weights seeded, the global stream untouched
        torch.manual_seed(0)
        field = SDFField(1.0, HashGrid(4, 16, 96, 2, 15, seed=0))
    field.grid.set_active(4)
    optimizer = torch.optim.Adam(field.parameters(), lr=0.01)
    gen = torch.Generator().manual_seed(0)
    for _ in range(80):
        x = torch.rand(4096, 3, generator=gen) * 1.6 - 0.8
        x[:2048, 2] = (torch.rand(2048, generator=gen) - 0.5) * 0.2  # half the points near the plate
        loss = (field(x)[0] - 12.0 * (x[:, 2].abs() - 0.02)).abs().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return field


def test_the_marching_cubes_shortcut_on_a_trained_steep_field_is_the_full_evaluation(monkeypatch):
    """`sdf_volume` evaluates exactly only near the coarse grid's zero crossings, within the slope-scaled margin
    (`coarse_slope`); on a trained field much steeper than 1 its volume has the signs of the field evaluated at every
    vertex, so marching cubes gives the same mesh. With the margin of |∇f| <= 1 it misses the plate."""
    field = _plate_field()
    with torch.no_grad():
        values, spacing = sdf_volume(lambda x: field(x)[0], 1.0, 0.02)
        n = values.shape[0]
        axis = -1.0 + spacing * np.arange(n)
        vertices = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
        full = evaluate(lambda x: field(x)[0], vertices).reshape(n, n, n)
        assert (full < 0).sum() > 1000  # the plate is there (a layer of the grid is 101² vertices)
        assert float(coarse_slope(values[::COARSE, ::COARSE, ::COARSE], COARSE * spacing).max()) > 4
        assert np.array_equal(values < 0, full < 0)
        monkeypatch.setattr(neusg, "coarse_slope", lambda grid, step: np.ones([s - 1 for s in grid.shape]))
        unscaled, _ = sdf_volume(lambda x: field(x)[0], 1.0, 0.02)
    assert not np.array_equal(unscaled < 0, full < 0)
