"""The ray tracer of 2D Gaussian surfels (gsbench/raster/surfel_rays.py): one surfel against its closed form,
camera rays against the rasterizer's dense reference, float64 gradients against finite differences, and
the hard rays (in the plane, behind the origin, coincident surfels)."""

from __future__ import annotations

import math

import numpy as np
import torch

from gsbench.data.camera import Camera
from gsbench.raster import reference
from gsbench.raster.surfel_rays import candidate_pairs, pair_hits, surfel_axes, trace, trace_pairs
from gsbench.raster.types import RasterGaussians, RasterSettings

SH_C0 = 0.28209479177387814


def _one_surfel(dtype=torch.float64):
    means = torch.tensor([[0.1, -0.2, 2.0]], dtype=dtype)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype)  # t_w = +z: facing rays along z
    scales = torch.tensor([[0.3, 0.1]], dtype=dtype)
    opacities = torch.tensor([0.8], dtype=dtype)
    return means, quats, scales, opacities


def test_one_surfel_matches_its_closed_form():
    """A ray along +z from (x, y, 0) meets the surfel at t = 2 with u = (x − 0.1)/0.3, v = (y + 0.2)/0.1:
    alpha = 0.8 exp(−(u² + v²)/2), depth alpha·t, normal −z (facing the ray); none beyond 3σ."""
    means, quats, scales, opacities = _one_surfel()
    xy = torch.tensor([[0.1, -0.2], [0.25, -0.15], [0.1, 0.05], [1.5, 0.0]], dtype=torch.float64)
    origins = torch.cat([xy, torch.zeros(4, 1, dtype=torch.float64)], 1)
    directions = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand(4, 3)
    out = trace(origins, directions, means, quats, scales, opacities, torch.ones(1, 1, dtype=torch.float64))
    u, v = (xy[:, 0] - 0.1) / 0.3, (xy[:, 1] + 0.2) / 0.1
    rho = u * u + v * v
    expected = torch.where(rho <= 9, 0.8 * torch.exp(-0.5 * rho), torch.zeros_like(rho))
    expected = torch.where(expected >= 1 / 255, expected, torch.zeros_like(expected))
    assert torch.allclose(out.alpha, expected, atol=1e-15) and out.alpha[3] == 0 and out.alpha[0] == 0.8
    assert torch.allclose(out.depth, 2.0 * expected, atol=1e-14)
    assert torch.allclose(out.normal[0], torch.tensor([0.0, 0.0, -0.8], dtype=torch.float64))


def test_camera_rays_reproduce_the_rasterizers_surfel_render():
    """Pixel rays of a camera through five surfels at distinct depths, the low-pass filter off: the traced
    colour and alpha equal the dense reference rasterizer's (same blending order; no early stop reached).
    The rasterizer bounds a surfel by its 3σ screen box, the tracer by ρ ≤ 9 per pair; opacities below
    0.35 make every pair between the two bounds fall under 1/255, so both skip it."""
    gen = torch.Generator().manual_seed(3)
    n = 5
    means = torch.cat([torch.rand(n, 2, generator=gen, dtype=torch.float64) - 0.5,
                       2.0 + 1.0 * torch.arange(n, dtype=torch.float64)[:, None]], 1)  # orders agree: no overlap in t
    quats = torch.nn.functional.normalize(torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
                                          + 0.2 * torch.randn(n, 4, generator=gen, dtype=torch.float64), dim=-1)
    scales = 0.15 + 0.2 * torch.rand(n, 2, generator=gen, dtype=torch.float64)
    opacities = 0.1 + 0.24 * torch.rand(n, generator=gen, dtype=torch.float64)  # beyond 3σ: α < 0.34 e^-4.5 < 1/255
    colours = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    camera = Camera(K=np.array([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]]), R=np.eye(3), t=np.zeros(3), width=32, height=24,
                    name="c")
    settings = RasterSettings(surfel_filter=0.0, sh_degree=0, near_plane=0.01, scene_radius=1.0)
    sh = ((colours - 0.5) / SH_C0)[:, None, :]
    ref = reference.render(RasterGaussians(means, quats, scales, opacities, sh), camera, kernel="surfel",
                           outputs=("rgb", "alpha"), settings=settings)
    jj, ii = np.mgrid[0:24, 0:32]
    pix = np.stack([ii + 0.5, jj + 0.5, np.ones_like(ii)], -1).reshape(-1, 3) @ np.linalg.inv(camera.K).T
    directions = torch.nn.functional.normalize(torch.from_numpy(pix), dim=-1)
    out = trace(torch.zeros_like(directions), directions, means, quats, scales, opacities, colours, near=0.01)
    assert float(out.alpha.max()) > 0.3  # the surfels cover part of the view
    assert torch.allclose(out.features, ref.rgb.reshape(-1, 3), atol=1e-10)
    assert torch.allclose(out.alpha, ref.alpha.reshape(-1), atol=1e-10)


def test_gradients_match_finite_differences_in_float64():
    """torch.autograd.gradcheck of the traced features, alpha and depth w.r.t. every surfel parameter and
    the rays, three overlapping surfels seen by rays from two origins."""
    gen = torch.Generator().manual_seed(0)
    means = torch.tensor([[0.0, 0.0, 1.0], [0.05, 0.02, 1.3], [-0.04, 0.03, 1.6]], dtype=torch.float64, requires_grad=True)
    quats = (torch.tensor([[1.0, 0.1, 0.0, 0.0], [0.9, 0.0, 0.2, 0.1], [1.0, -0.1, 0.1, 0.0]], dtype=torch.float64)
             ).requires_grad_()
    scales = torch.tensor([[0.2, 0.15], [0.25, 0.2], [0.3, 0.3]], dtype=torch.float64, requires_grad=True)
    opacities = torch.tensor([0.5, 0.6, 0.7], dtype=torch.float64, requires_grad=True)
    features = torch.rand(3, 2, generator=gen, dtype=torch.float64).requires_grad_()
    origins = torch.tensor([[0.01, 0.02, 0.0], [0.3, -0.1, -0.2]], dtype=torch.float64, requires_grad=True)
    directions = torch.tensor([[0.02, -0.01, 1.0], [-0.25, 0.1, 1.0]], dtype=torch.float64, requires_grad=True)

    def f(m, q, s, o, feat, a, d):
        out = trace(a, torch.nn.functional.normalize(d, dim=-1), m, q, s, o, feat)
        return out.features, out.alpha, out.depth

    with torch.no_grad():
        assert float(f(means, quats, scales, opacities, features, origins, directions)[1].min()) > 0.3
    assert torch.autograd.gradcheck(f, (means, quats, scales, opacities, features, origins, directions), eps=1e-6, atol=1e-7)


def test_hard_rays_are_defined():
    """A ray in the surfel's plane, a surfel behind the ray's origin, a ray from a kilometre away, and two
    coincident surfels: finite outputs; the first two see nothing; the coincident pair blends as two
    layers (1 − (1 − α)²)."""
    means, quats, scales, opacities = _one_surfel()
    origins = torch.tensor([[-5.0, -0.2, 2.0], [0.1, -0.2, 3.0], [0.1, -0.2, -1000.0]], dtype=torch.float64)
    directions = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    out = trace(origins, directions, means, quats, scales, opacities, torch.ones(1, 1, dtype=torch.float64))
    assert out.alpha[0] == 0 and out.alpha[1] == 0 and math.isclose(float(out.alpha[2]), 0.8)
    assert all(torch.isfinite(x).all() for x in (out.features, out.alpha, out.depth, out.normal))
    twin = trace(origins[2:], directions[2:], means.repeat(2, 1), quats.repeat(2, 1), scales.repeat(2, 1),
                 opacities.repeat(2), torch.ones(2, 1, dtype=torch.float64))
    assert math.isclose(float(twin.alpha[0]), 1 - 0.2**2)
    t, alpha, normal, ok = pair_hits(origins, directions, means.expand(3, 3), surfel_axes(quats).expand(3, 3, 3), scales.expand(3, 2),
                                     opacities.expand(3))
    assert torch.isfinite(t).all() and not ok[0] and not ok[1] and ok[2]


def test_candidate_pairs_from_the_bvh_give_the_dense_result():
    """300 random surfels, 400 random rays: the pairs open3d's BVH lists blend to the dense reference's
    features, alpha, depth and normal (float64), and every pair the dense pass blends is among them."""
    gen = torch.Generator().manual_seed(7)
    n, r = 300, 400
    means = torch.rand(n, 3, generator=gen, dtype=torch.float64) * 2 - 1
    quats = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    scales = 0.02 + 0.08 * torch.rand(n, 2, generator=gen, dtype=torch.float64)
    opacities = 0.2 + 0.7 * torch.rand(n, generator=gen, dtype=torch.float64)
    features = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    origins = torch.rand(r, 3, generator=gen, dtype=torch.float64) * 2 - 1 + torch.tensor([0.0, 0.0, -3.0], dtype=torch.float64)
    directions = torch.nn.functional.normalize(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
                                               + 0.3 * torch.randn(r, 3, generator=gen, dtype=torch.float64), dim=-1)
    dense = trace(origins, directions, means, quats, scales, opacities, features)
    ray, surfel = candidate_pairs(origins, directions, means, quats, scales)
    sparse = trace_pairs(origins, directions, means, quats, scales, opacities, features, ray, surfel)
    blended = set(zip(dense.ray[dense.weights > 0].tolist(), dense.surfel[dense.weights > 0].tolist()))
    assert len(blended) > 500 and blended <= set(zip(ray.tolist(), surfel.tolist()))
    for name in ("features", "alpha", "depth", "normal"):
        assert torch.allclose(getattr(sparse, name), getattr(dense, name), atol=1e-12), name
