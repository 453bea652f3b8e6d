"""GGGS's stochastic-solid transmittance and median depth (gsbench/raster/stochastic_solid.py): one Gaussian
against its closed form, the search against a dense reference, float64 gradients against finite differences,
and the hard rays (no surface, coincident Gaussians, a Gaussian behind the camera, a degenerate width)."""

from __future__ import annotations

import math

import torch

from gsbench.raster.stochastic_solid import median_depth, single_median, single_transmittance, transmittance


def _dense_median(alpha, t_star, inv_sigma, near, far, samples=200_001):
    t = torch.linspace(near, far, samples, dtype=torch.float64)
    T = transmittance(t[None].expand(alpha.shape[0], -1), alpha, t_star, inv_sigma)
    below = T <= 0.5
    index = below.float().argmax(1)
    return t[index], below.any(1)


def test_one_gaussian_matches_its_closed_form():
    """T_i falls from 1 to 1 − α continuously (√(1 − α) at the peak); the median depth of one Gaussian is the
    closed form for α = 0.6, 0.75, 0.9, 0.99 (after the peak, at it, before it); none for α = 0.4."""
    t = torch.tensor([-50.0, 2.0, 50.0], dtype=torch.float64)
    T = single_transmittance(t, torch.tensor(0.8, dtype=torch.float64), torch.tensor(2.0, dtype=torch.float64),
                             torch.tensor(4.0, dtype=torch.float64))
    assert torch.allclose(T, torch.tensor([1.0, math.sqrt(0.2), 0.2], dtype=torch.float64), atol=1e-12)
    for alpha in (0.6, 0.75, 0.9, 0.99):
        for rounds in (5, 8):  # GGGS's training and meshing searches
            depth, valid = median_depth(torch.tensor([[alpha]], dtype=torch.float64),
                                        torch.tensor([[2.0]], dtype=torch.float64),
                                        torch.tensor([[4.0]], dtype=torch.float64), 0.1, 10.0, rounds=rounds)
            cell = 9.9 / 8**rounds  # the stated tolerance: one last cell
            tolerance = cell if alpha == 0.75 or rounds == 5 else 1e-9  # at α = ¾ the median is the peak, T' = 0
            assert bool(valid[0]) and abs(float(depth[0]) - single_median(alpha, 2.0, 0.25)) < tolerance, (alpha, rounds)
    depth, valid = median_depth(torch.tensor([[0.4]], dtype=torch.float64), torch.tensor([[2.0]], dtype=torch.float64),
                                torch.tensor([[4.0]], dtype=torch.float64), 0.1, 10.0)
    assert not bool(valid[0]) and float(depth[0]) == 0.0 and single_median(0.4, 2.0, 0.25) is None


def _random_rays(rays=64, gaussians=6, seed=0):
    gen = torch.Generator().manual_seed(seed)
    alpha = 0.2 + 0.79 * torch.rand(rays, gaussians, generator=gen, dtype=torch.float64)
    t_star = 1.0 + 4.0 * torch.rand(rays, gaussians, generator=gen, dtype=torch.float64)
    inv_sigma = 2.0 + 10.0 * torch.rand(rays, gaussians, generator=gen, dtype=torch.float64)
    return alpha, t_star, inv_sigma


def test_the_search_is_within_its_tolerance_of_a_dense_reference():
    """Six Gaussians per ray, 64 rays: the 8-way search (5 rounds, GGGS's) with its linear interpolation lands
    within one final cell ((far − near)/8⁵) of the first of 200 001 dense samples where T ≤ ½, where T is ½
    to 1e-5; the valid rays are exactly those whose dense T reaches ½."""
    alpha, t_star, inv_sigma = _random_rays()
    depth, valid = median_depth(alpha, t_star, inv_sigma, 0.0, 8.0)
    dense, reached = _dense_median(alpha, t_star, inv_sigma, 0.0, 8.0)
    assert torch.equal(valid, reached) and int(valid.sum()) > 40
    cell, step = 8.0 / 8**5, 8.0 / 200_000
    assert float((depth - dense)[valid].abs().max()) < cell
    assert float((depth - dense)[valid].abs().max()) < step + cell
    T_at = transmittance(depth[valid][:, None], alpha[valid], t_star[valid], inv_sigma[valid])[:, 0]
    assert float((T_at - 0.5).abs().max()) < 1e-5


def test_gradients_are_the_implicit_functions():
    """gradcheck (float64) of the median depth in α, t* and 1/σ of every Gaussian, the search run to 12 rounds
    so the depth is the root to rounding: −(∂ℓ/∂θ)/(∂ℓ/∂t), ℓ = log T, agrees with finite differences."""
    alpha, t_star, inv_sigma = (x[:4].clone().requires_grad_() for x in _random_rays(seed=3))
    with torch.no_grad():
        _, valid = median_depth(alpha, t_star, inv_sigma, 0.0, 8.0)
    assert bool(valid.all())
    assert torch.autograd.gradcheck(lambda a, t, s: median_depth(a, t, s, 0.0, 8.0, rounds=12)[0], (alpha, t_star, inv_sigma),
                                    eps=1e-6, atol=1e-6)


def test_hard_rays_are_defined():
    """Two coincident Gaussians blend as T₁² (their median where T₁ = √½, the dense reference's); a Gaussian
    behind the ray's start (t* < near) is counted and no NaN; a ray whose Gaussians never bring T to ½ is
    invalid with depth 0; a degenerate width (1/σ = 0) is a step at t*: the median is at t* within a cell."""
    one = lambda *v: torch.tensor([list(v)], dtype=torch.float64)  # noqa: E731
    depth, valid = median_depth(one(0.6, 0.6), one(3.0, 3.0), one(5.0, 5.0), 0.0, 8.0)
    dense, _ = _dense_median(one(0.6, 0.6), one(3.0, 3.0), one(5.0, 5.0), 0.0, 8.0)
    assert bool(valid[0]) and abs(float(depth[0] - dense[0])) < 1e-4
    behind, ok = median_depth(one(0.3, 0.9), one(-1.0, 4.0), one(5.0, 5.0), 0.1, 8.0)
    assert torch.isfinite(behind).all() and bool(ok[0]) and 3.0 < float(behind[0]) < 4.0
    never, none = median_depth(one(0.2, 0.2), one(2.0, 4.0), one(5.0, 5.0), 0.0, 8.0)
    assert not bool(none[0]) and float(never[0]) == 0.0
    step, ok = median_depth(one(0.9), one(2.5), one(0.0), 0.0, 8.0)
    assert bool(ok[0]) and abs(float(step[0]) - 2.5) <= 8.0 / 8**5 and torch.isfinite(step).all()
