"""The Mip-Splatting 3D filter (gsbench.geometry.filter3d, docs/methods/gof.md §2) and the filtered opacity reset."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from gsbench.data.camera import Camera
from gsbench.errors import NumericalError
from gsbench.geometry.filter3d import Filter3D, filter3d_variance, filter_coefficient
from gsbench.training.gaussians import Gaussians
from gsbench.training.strategies.base import reset_opacity


def camera(f: float, tz: float) -> Camera:
    """100x80 image, principal point at the centre, looking down +z from world z = -tz."""
    K = np.array([[f, 0.0, 50.0], [0.0, f, 40.0], [0.0, 0.0, 1.0]])
    return Camera(K=K, R=np.eye(3), t=np.array([0.0, 0.0, tz]), width=100, height=80)


# A: f = 100 at the origin; B: f = 200 one unit behind it (camera z = world z + 1). f_max = 200.
CAMERAS = [camera(100.0, 0.0), camera(200.0, 1.0)]
POINTS = torch.tensor([
    [0.0, 0.0, 2.0],    # seen by A (z 2) and B (z 3): d_min = 2
    [0.0, 0.0, 0.1],    # A: z 0.1 <= near 0.2; B: z 1.1 -> d_min = 1.1
    [0.6, 0.0, 1.0],    # A: u = 110 <= 1.15 W = 115 (inside the margin), z 1; B: u = 110, z 2 -> d_min = 1
    [0.0, 0.5, 1.0],    # A: v = 90 <= 1.15 H = 92, z 1 -> d_min = 1
    [0.7, 0.0, 1.0],    # A: u = 120 > 115; B: u = 120 -> unseen: max d_min of the seen ones = 2
    [0.0, 0.0, -5.0],   # behind both cameras -> unseen: 2
], dtype=torch.float64)


def sigma2(d_min: float, f_max: float = 200.0) -> float:
    """σ_f² = (d_min / f_max · sqrt(0.2))²."""
    return (d_min / f_max * math.sqrt(0.2)) ** 2


def test_variance_follows_the_formula_on_constructed_cameras():
    got = filter3d_variance(POINTS, CAMERAS, near=0.2)
    expected = [sigma2(2.0), sigma2(1.1), sigma2(1.0), sigma2(1.0), sigma2(2.0), sigma2(2.0)]
    assert got.dtype == torch.float64
    torch.testing.assert_close(got, torch.tensor(expected, dtype=torch.float64), rtol=1e-12, atol=0)
    assert got[0].item() == pytest.approx(2e-5) and got[1].item() == pytest.approx(6.05e-6)  # by hand


def test_near_plane_is_a_parameter_and_the_focal_is_the_largest():
    got = filter3d_variance(POINTS[1:2], CAMERAS, near=0.05)  # A now sees the point at z 0.1
    assert got.item() == pytest.approx(sigma2(0.1))
    only_a = filter3d_variance(POINTS[:1], CAMERAS[:1], near=0.2)
    assert only_a.item() == pytest.approx(sigma2(2.0, f_max=100.0))


def test_no_visible_gaussian_is_an_error_and_empty_input_is_empty():
    with pytest.raises(NumericalError, match="no Gaussian centre is seen"):
        filter3d_variance(POINTS[4:], CAMERAS, near=0.2)
    assert filter3d_variance(torch.zeros(0, 3), CAMERAS, near=0.2).shape == (0,)


def test_filter3d_holder_updates_and_can_be_disabled():
    f = Filter3D(CAMERAS, near=0.2)
    assert f.variance is None
    assert f.update(POINTS.float()).shape == (6,) and f.variance.dtype == torch.float32
    off = Filter3D(CAMERAS, near=0.2, enabled=False)
    assert off.update(POINTS) is None and off.variance is None


def test_reset_sets_the_filtered_opacity():
    # s² = 0.01 per axis, σ_f² = 0.03: coef = sqrt((0.01 / 0.04)³) = 0.125
    logits = torch.logit(torch.tensor([0.5, 0.04, 0.5]))
    g = Gaussians(means=torch.zeros(3, 3), log_scales=torch.full((3, 3), math.log(0.1)),
                  quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(3, 1), opacity_logits=logits,
                  sh_dc=torch.zeros(3, 1, 3), sh_rest=torch.zeros(3, 0, 3), max_sh_degree=0)
    opt = torch.optim.Adam([{"params": [p], "name": k, "lr": 0.0} for k, p in g.params.items()])
    g.params["opacity_logits"].sum().backward()  # non-zero moments, unchanged values (lr 0)
    opt.step()
    variance = torch.tensor([0.03, 0.03, 0.0])
    assert filter_coefficient(g.scales.detach(), variance).tolist() == pytest.approx([0.125, 0.125, 1.0])
    reset_opacity(g, opt, 0.01, variance)
    # o_eff = 0.0625 -> 0.01 -> o = 0.08; o_eff = 0.005 < 0.01 stays; no filter: min(0.5, 0.01)
    assert g.opacities.detach().tolist() == pytest.approx([0.08, 0.04, 0.01], rel=1e-5)
    assert (opt.state[g.params["opacity_logits"]]["exp_avg"] == 0).all()


def test_reset_of_a_saturated_strongly_filtered_opacity_stays_finite():
    """A Gaussian with opacity 1 in float32 (logit 30) and a filter coefficient below the reset value: the
    public form logit(min(o·c, v) / c) = logit(c / c) is +inf (or NaN). The reset leaves it as it is; a row
    above the value is lowered to o_eff = v exactly as before, and a row below it keeps its logit bit for bit."""
    logits = torch.tensor([30.0, 0.0, -3.0])
    g = Gaussians(means=torch.zeros(3, 3), log_scales=torch.full((3, 3), math.log(0.1)),
                  quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(3, 1), opacity_logits=logits.clone(),
                  sh_dc=torch.zeros(3, 1, 3), sh_rest=torch.zeros(3, 0, 3), max_sh_degree=0)
    opt = torch.optim.Adam([{"params": [p], "name": k, "lr": 0.0} for k, p in g.params.items()])
    # s² = 0.01: σ_f² = 0.5 gives c = (0.01 / 0.51)^1.5 ≈ 0.0027 < 0.01; 0.03 gives c = 0.125
    variance = torch.tensor([0.5, 0.03, 0.03])
    coef = filter_coefficient(g.scales.detach(), variance)
    assert torch.sigmoid(logits[0]) == 1.0 and coef[0] < 0.01
    assert not torch.isfinite(torch.logit(torch.clamp(torch.sigmoid(logits) * coef, max=0.01) / coef))[0]
    reset_opacity(g, opt, 0.01, variance)
    new = g.params["opacity_logits"].detach()
    assert torch.isfinite(new).all()
    assert new[0] == logits[0] and new[2] == logits[2]  # not lowered: the logit itself, no round trip
    assert (g.opacities.detach()[1] * coef[1]).item() == pytest.approx(0.01, rel=1e-6)
