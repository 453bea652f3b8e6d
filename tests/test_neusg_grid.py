"""NeuSG's fused grid encoding (methods/csrc/neusg_grid.cpp via `gsbench.methods.neusg_grid`) against its
reference, ``grid_sample``: values and the grids' gradients, float64 gradcheck, points on the border and outside,
determinism over thread counts, the fallbacks."""

from __future__ import annotations

import pytest
import torch

from gsbench.errors import ConfigError
from gsbench.methods.neusg_grid import grid_features, grid_features_reference
from gsbench.switches import NEUSG_GRID

TOL = {torch.float32: 1e-6, torch.float64: 1e-12}


def grids_and_points(resolutions=(1, 3, 8), features=2, points=400, dtype=torch.float64, seed=0):
    """Grids (1, F, N+1, N+1, N+1) of random features, and points: most inside [0, 1]³, some outside (border
    padding), some exactly on vertices, faces and the corners 0 and 1."""
    gen = torch.Generator().manual_seed(seed)
    grids = [torch.randn(1, features, n + 1, n + 1, n + 1, generator=gen, dtype=torch.float64).to(dtype)
             .requires_grad_() for n in resolutions]
    unit = torch.rand(points, 3, generator=gen, dtype=torch.float64)
    unit[:20] = unit[:20] * 1.6 - 0.3  # outside the grid on some axes
    unit[20] = torch.tensor([0.0, 0.0, 0.0])
    unit[21] = torch.tensor([1.0, 1.0, 1.0])
    unit[22] = torch.tensor([0.5, 0.25, 1.0])  # a vertex of every level with N in {1, 2, 4, 8}, on a face
    unit[23] = torch.tensor([1.0 / 3.0, 0.0, 0.75])
    return grids, unit.to(dtype)


def value_and_grads(impl, grids, unit):
    out = grid_features(grids, unit, impl=impl)
    weights = torch.linspace(-1.0, 2.0, out.numel(), dtype=out.dtype).reshape(out.shape)
    grads = torch.autograd.grad((out * weights).sum(), grids)
    return [out.detach(), *grads]


def assert_relative(got, want, tol):
    for a, b in zip(got, want, strict=True):
        assert a.shape == b.shape
        scale = max(float(b.abs().max()), 1e-30)
        assert float((a.double() - b.double()).abs().max()) <= tol * scale


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fused_matches_grid_sample(dtype):
    grids, unit = grids_and_points(dtype=dtype)
    fused = value_and_grads("fused", grids, unit)
    assert_relative(fused, value_and_grads("reference", grids, unit), TOL[dtype])
    exact_grids = [g.detach().double().requires_grad_() for g in grids]
    assert_relative(fused, value_and_grads("reference", exact_grids, unit.double()), TOL[dtype])


def test_vertices_and_border_values_are_exact():
    """On a vertex the feature is the vertex's; outside, the border's (the nearest point of the grid)."""
    grids, _ = grids_and_points(resolutions=(4,))
    grid = grids[0].detach()
    unit = torch.tensor([[0.25, 0.5, 1.0], [1.7, -0.2, 0.5], [0.0, 0.0, 0.0]], dtype=torch.float64)
    out = grid_features(grids, unit, impl="fused").detach()
    assert torch.equal(out[0], grid[0, :, 4, 2, 1])  # x → the last axis, z → the first
    assert torch.equal(out[1], grid[0, :, 2, 0, 4])
    assert torch.equal(out[2], grid[0, :, 0, 0, 0])


def test_gradcheck_float64():
    grids, unit = grids_and_points(resolutions=(1, 2), features=2, points=30)
    assert torch.autograd.gradcheck(lambda *g: grid_features(g, unit, impl="fused"), grids)


def test_gradients_do_not_depend_on_the_thread_count(restore_threads):
    grids, unit = grids_and_points(resolutions=(3, 5, 9, 16, 17), points=5000, dtype=torch.float32)
    results = []
    for threads in (1, 2, 3):
        torch.set_num_threads(threads)
        results.append(value_and_grads("fused", grids, unit))
    for other in results[1:]:
        assert all(torch.equal(a, b) for a, b in zip(results[0], other))


def test_non_finite_points_stay_inside_the_grid():
    """A NaN or infinite coordinate must not index outside the grid (the kernel clamps the cell as an integer)."""
    grids, unit = grids_and_points(resolutions=(4,), points=30)
    unit[0] = torch.tensor([float("nan"), 0.5, 0.5])
    unit[1] = torch.tensor([float("inf"), -float("inf"), 0.5])
    out = grid_features(grids, unit, impl="fused")
    (grad,) = torch.autograd.grad(out[1:].sum(), grids)
    assert torch.isfinite(out[1:]).all() and torch.isfinite(grad).all()


def test_environment_and_fallbacks(monkeypatch):
    grids, unit = grids_and_points(points=30)
    assert type(grid_features(grids, unit).grad_fn).__name__ == "_FusedGridBackward"
    monkeypatch.setenv(NEUSG_GRID.name, "reference")
    assert type(grid_features(grids, unit).grad_fn).__name__ != "_FusedGridBackward"
    monkeypatch.setenv(NEUSG_GRID.name, "fast")
    with pytest.raises(ConfigError, match=NEUSG_GRID.name):
        grid_features(grids, unit)
    monkeypatch.delenv(NEUSG_GRID.name)
    moving = unit.clone().requires_grad_()
    with pytest.raises(ValueError, match="require a gradient"):
        grid_features(grids, moving, impl="fused")
    out = grid_features(grids, moving)  # the reference, which differentiates the points too
    assert torch.autograd.grad(out.sum(), moving)[0].abs().sum() > 0
    assert_relative([out.detach()], [grid_features_reference(grids, unit).detach()], 0.0)
    with pytest.raises(ValueError, match="dtypes"):
        grid_features(grids, unit.float(), impl="fused")
