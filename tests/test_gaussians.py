"""Gaussians container: kNN initial scales, activations, coincident points, non-finite guards."""

import math

import numpy as np
import pytest
import torch

from gsbench.errors import DataError, NumericalError
from gsbench.training.gaussians import SH_C0, Gaussians, knn_initial_scale


def test_knn_scale_matches_brute_force():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(200, 3))
    d2 = ((pts[:, None] - pts[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    expected = np.sqrt(np.sort(d2, axis=1)[:, :3].mean(1))
    np.testing.assert_allclose(knn_initial_scale(pts), expected, rtol=1e-10)


def test_coincident_points_get_the_clamped_positive_scale():
    pts = np.zeros((10, 3))
    s = knn_initial_scale(pts)
    assert np.all(s == math.sqrt(1e-7))
    g = Gaussians.from_points(pts, None)
    assert torch.isfinite(g.scales).all() and (g.scales > 0).all()


def test_activations_and_sh_round_trip_colour():
    colors = np.array([[0.2, 0.4, 0.9], [1.0, 0.0, 0.5]])
    g = Gaussians.from_points(np.array([[0, 0, 0], [1, 0, 0.0]]), colors, max_sh_degree=3)
    r = g.raster_input()
    assert r.sh.shape == (2, 1, 3) and r.sh_rest.shape == (2, 15, 3) and r.scales.shape == (2, 3)
    sh = r.all_sh()
    assert sh.shape == (2, 16, 3) and torch.equal(sh[:, 1:], torch.zeros(2, 15, 3))
    np.testing.assert_allclose((sh[:, 0] * SH_C0 + 0.5).detach().numpy(), colors, atol=1e-6)
    np.testing.assert_allclose(g.opacities.detach().numpy(), 0.1, atol=1e-6)
    assert torch.allclose(g.quats, torch.tensor([[1.0, 0, 0, 0]] * 2))


def test_surfels_have_two_scales_and_random_unit_rotations():
    g = Gaussians.random_in_sphere(50, 2.0, dims=2, seed=1)
    assert g.dims == 2 and g.scales.shape == (50, 2)
    assert torch.allclose(g.quats.norm(dim=-1), torch.ones(50))
    assert (g.means.norm(dim=-1) <= 2.0 + 1e-6).all()


def test_bad_inputs_name_the_problem():
    with pytest.raises(DataError, match="non-finite"):
        Gaussians.from_points(np.array([[0, 0, np.nan], [1, 1, 1.0]]), None)
    with pytest.raises(DataError, match="non-empty"):
        Gaussians.from_points(np.zeros((0, 3)), None)
    g = Gaussians.from_points(np.random.default_rng(0).normal(size=(5, 3)), None)
    with torch.no_grad():
        g.params["log_scales"][3, 1] = float("nan")
    with pytest.raises(NumericalError, match="'log_scales' has 1 non-finite rows \\(first at index 3\\)"):
        g.check_finite()
