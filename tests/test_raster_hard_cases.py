"""Hard cases of the fast rasterizer: every output and gradient finite, no crash, sane results."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))

from raster_scenes import concat, make_camera, random_gaussians, single_gaussian, with_grad  # noqa: E402

from gsbench.errors import NumericalError  # noqa: E402
from gsbench.raster import OUTPUTS, RasterGaussians, RasterSettings, rasterize, reference  # noqa: E402

KERNELS = ("ewa", "rade", "raymax", "surfel")
PARAMS = ("means", "quats", "scales", "opacities", "sh")


def _render_and_check(g, cam, kernel, settings=RasterSettings(), outputs=OUTPUTS):
    gg = with_grad(g)
    out = rasterize(gg, cam, kernel=kernel, outputs=outputs, settings=settings)
    loss = 0.0
    for o in outputs:
        t = getattr(out, o)
        assert t is not None and bool(torch.isfinite(t).all()), f"{kernel}: non-finite {o}"
        loss = loss + t.double().sum()
    loss.backward()
    for p in PARAMS:
        gr = getattr(gg, p).grad
        assert gr is None or bool(torch.isfinite(gr).all()), f"{kernel}: non-finite grad of {p}"
    assert bool(torch.isfinite(out.means2d.grad).all())
    assert bool(torch.isfinite(out.extras["absgrad"]).all())
    return out, gg


def _f32(g):
    f = lambda x: None if x is None else x.detach().float()  # noqa: E731
    return RasterGaussians(f(g.means), f(g.quats), f(g.scales), f(g.opacities), f(g.sh), f(g.filter3d))


@pytest.mark.parametrize("kernel", KERNELS)
def test_behind_camera_and_straddling_near_plane(kernel):
    cam = make_camera(24, 20)
    sc = (0.5, 0.4, 0.3)
    gs = [
        single_gaussian((0.1, 0.0, -1.0), kernel=kernel, scales=sc, opacity=0.8),  # behind
        single_gaussian((0.0, 0.1, 0.0), kernel=kernel, scales=sc, opacity=0.8),  # at the camera
        single_gaussian((0.0, 0.0, 0.2), kernel=kernel, scales=sc, opacity=0.8),  # exactly at near
        single_gaussian((0.05, 0.0, 0.21), kernel=kernel, scales=sc, opacity=0.8),  # just in front, straddles
        single_gaussian((0.0, -0.05, 0.5), kernel=kernel, scales=(2.0, 2.0, 2.0), opacity=0.8),  # huge, around the camera
        single_gaussian((0.0, 0.0, 2.0), kernel=kernel, scales=(0.2, 0.3, 0.1), opacity=0.6),
    ]
    g = _f32(concat(*gs))
    out, _ = _render_and_check(g, cam, kernel)
    assert not bool(out.visible[0]) and not bool(out.visible[1]) and not bool(out.visible[2])
    ref = reference.render(concat(*gs), cam, kernel=kernel, outputs=("rgb", "alpha"))
    assert float((out.alpha.detach().double() - ref.alpha).abs().max()) < 1e-4


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("scale", [1e-8, 1e4])
def test_extreme_scales(kernel, scale):
    cam = make_camera(24, 20)
    g = random_gaussians(30, kernel, seed=2, camera=cam, dtype=torch.float32)
    g.scales[::2] = scale
    g.scales[1::4, 0] = scale  # anisotropic mixes
    out, _ = _render_and_check(g, cam, kernel)
    if kernel == "raymax" and scale < 1:
        # The reference's q = (μ − t*r)ᵀΣ⁻¹(μ − t*r) loses ~2% in float64 when Σ⁻¹ ~ 1e16 (checked against
        # a 60-digit mpmath evaluation, which agrees with the fast path's cancellation-free form).
        return
    ref = reference.render(
        RasterGaussians(g.means.double(), g.quats.double(), g.scales.double(), g.opacities.double(), g.sh.double()),
        cam, kernel=kernel, outputs=("alpha", "rgb"),
    )
    assert float((out.alpha.detach().double() - ref.alpha).abs().max()) < 1e-4
    assert float((out.rgb.detach().double() - ref.rgb).abs().max()) < 1e-4


def test_surfel_exactly_edge_on():
    cam = make_camera(20, 16)
    half = math.sqrt(0.5)
    gs = [
        # normal t_w = R e_z rotated onto +x: the splat plane contains the viewing direction
        single_gaussian((0.0, 0.0, 2.0), kernel="surfel", quat=(half, 0.0, half, 0.0), scales=(0.3, 0.3), opacity=0.9),
        # the same, a hair away from edge-on
        single_gaussian((0.1, 0.0, 2.0), kernel="surfel", quat=(half, 0.0, half + 1e-6, 0.0), scales=(0.3, 0.3), opacity=0.9),
        single_gaussian((-0.1, 0.05, 2.5), kernel="surfel", quat=(half, half, 0.0, 0.0), scales=(0.3, 0.2), opacity=0.9),
    ]
    g64 = concat(*gs)
    for g in (_f32(g64), g64):
        out, _ = _render_and_check(g, cam, "surfel")
        ref = reference.render(g64, cam, kernel="surfel", outputs=("rgb", "alpha", "normal"))
        for o in ("rgb", "alpha", "normal"):
            assert float((getattr(out, o).detach().double() - getattr(ref, o)).abs().max()) < 1e-4, o


@pytest.mark.parametrize("kernel", KERNELS)
def test_transmittance_underflow_10k_gaussians_on_one_pixel(kernel):
    cam = make_camera(4, 4)
    n = 10_000
    gen = torch.Generator().manual_seed(0)
    z = 2.0 + 0.5 * torch.rand(n, generator=gen, dtype=torch.float64)
    x = (2.5 - cam.cx) / cam.fx * z  # centred on pixel (2, 2)
    y = (2.5 - cam.cy) / cam.fy * z
    means = torch.stack([x, y, z], -1)
    q = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    g = RasterGaussians(
        means=means.float(),
        quats=(q / q.norm(dim=-1, keepdim=True)).float(),
        scales=torch.full((n, 2 if kernel == "surfel" else 3), 0.2, dtype=torch.float32),
        opacities=torch.full((n,), 0.9, dtype=torch.float32),
        sh=(0.3 * torch.randn(n, 1, 3, generator=gen, dtype=torch.float64)).float(),
    )
    out, _ = _render_and_check(g, cam, kernel)
    assert float(out.alpha.detach().max()) <= 1.0 + 1e-6
    assert float(out.alpha.detach().max()) > 0.999


@pytest.mark.parametrize("kernel", KERNELS)
def test_coincident_gaussians_stable_and_deterministic(kernel):
    cam = make_camera(32, 24)
    base = random_gaussians(5, kernel, seed=4, camera=cam, dtype=torch.float64)
    # 6 copies of each Gaussian (equal depth), different colours: order = index order
    parts = []
    for c in range(6):
        g = RasterGaussians(base.means.clone(), base.quats.clone(), base.scales.clone(), base.opacities.clone(), base.sh + 0.2 * c)
        parts.append(g)
    g64 = concat(*parts)
    g = _f32(g64)
    outs = [rasterize(g, cam, kernel=kernel, outputs=OUTPUTS) for _ in range(3)]
    for o in OUTPUTS:
        for other in outs[1:]:
            assert torch.equal(getattr(outs[0], o), getattr(other, o)), o
    ref = reference.render(g64, cam, kernel=kernel, outputs=("rgb",))
    assert float((outs[0].rgb.double() - ref.rgb).abs().max()) < 1e-5
    # gradients are deterministic too
    grads = []
    for _ in range(2):
        gg = with_grad(g)
        rasterize(gg, cam, kernel=kernel, outputs=OUTPUTS)
        out = rasterize(gg, cam, kernel=kernel, outputs=("rgb", "depth"))
        (out.rgb.sum() + out.depth.sum()).backward()
        grads.append(gg.means.grad.clone())
    assert torch.equal(grads[0], grads[1])


@pytest.mark.parametrize("kernel", KERNELS)
def test_zero_opacity(kernel):
    cam = make_camera(24, 16)
    g = random_gaussians(20, kernel, seed=6, camera=cam, dtype=torch.float32)
    g.opacities[:] = 0.0
    out, gg = _render_and_check(g, cam, kernel, settings=RasterSettings(background=(0.3, 0.2, 0.1)))
    assert float(out.alpha.detach().abs().max()) == 0.0
    assert torch.allclose(out.rgb.detach(), torch.tensor([0.3, 0.2, 0.1]).expand(16, 24, 3))


@pytest.mark.parametrize("kernel", KERNELS)
def test_no_visible_gaussian(kernel):
    cam = make_camera(20, 12)
    g = random_gaussians(10, kernel, seed=1, camera=cam, dtype=torch.float32)
    g.means[:, 2] = -5.0  # all behind the camera
    bg = (0.25, 0.5, 0.75)
    out, gg = _render_and_check(g, cam, kernel, settings=RasterSettings(background=bg))
    assert torch.allclose(out.rgb.detach(), torch.tensor(bg).expand(12, 20, 3))
    assert not bool(out.visible.any())
    for p in PARAMS:
        gr = getattr(gg, p).grad
        assert gr is None or float(gr.abs().max()) == 0.0
    assert float(out.means2d.grad.abs().max()) == 0.0


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("size", [(1, 1), (17, 13)])
def test_odd_image_sizes(kernel, size):
    W, H = size
    cam = make_camera(W, H)
    g64 = random_gaussians(40, kernel, seed=8, camera=cam, dtype=torch.float64, scale_range=(0.1, 0.4))
    g = _f32(g64)
    out, _ = _render_and_check(g, cam, kernel)
    ref = reference.render(g64, cam, kernel=kernel, outputs=("rgb", "alpha", "normal"))
    for o in ("rgb", "alpha", "normal"):
        assert getattr(out, o).shape == getattr(ref, o).shape
        assert float((getattr(out, o).detach().double() - getattr(ref, o)).abs().max()) < 2e-5


@pytest.mark.parametrize("name", ["means", "quats", "scales", "opacities", "sh"])
def test_non_finite_inputs_raise_naming_the_parameter(name):
    cam = make_camera(16, 16)
    g = random_gaussians(30, "ewa", seed=0, camera=cam, dtype=torch.float32)
    t = getattr(g, name)
    t.view(t.shape[0], -1)[17, 0] = float("nan")
    t.view(t.shape[0], -1)[20, 0] = float("inf")
    t.view(t.shape[0], -1)[25, 0] = float("-inf")
    with pytest.raises(NumericalError, match=rf"gaussians\.{name} has 3 non-finite values \(first at index 17\)"):
        rasterize(g, cam, kernel="ewa", outputs=("rgb",))


def test_non_finite_filter3d_raises():
    cam = make_camera(16, 16)
    g = random_gaussians(5, "raymax", seed=0, camera=cam, dtype=torch.float32, filter3d=1e-3)
    g.filter3d[2] = float("nan")
    with pytest.raises(NumericalError, match="gaussians.filter3d"):
        rasterize(g, cam, kernel="raymax", outputs=("rgb",))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_near_large_surfel_covering_the_image_renders_as_the_reference(dtype):
    """A surfel 0.5 in front of the camera, 4 wide, tilted 60° so its 3σ disc reaches behind the camera plane
    (no bounded screen box): it covers the whole 32x24 image, and the fast path renders it where the dense
    reference does (alpha, colour, depth; gradients in float64), not culled and not cut to a tile rectangle."""
    cam = make_camera(32, 24, fov_x_deg=70.0)
    angle = math.radians(60.0)
    quat = (math.cos(angle / 2), math.sin(angle / 2), 0.0, 0.0)
    g = single_gaussian((0.05, 0.0, 0.5), kernel="surfel", quat=quat, scales=(4.0, 4.0, 1.0), opacity=0.8,
                        rgb=(0.7, 0.4, 0.2), dtype=dtype)
    settings = RasterSettings(near_plane=0.1)
    outputs = ("rgb", "alpha", "depth")
    fast_g, ref_g = with_grad(g), with_grad(g.map(lambda x: x.to(torch.float64)))
    fast = rasterize(fast_g, cam, kernel="surfel", outputs=outputs, settings=settings)
    ref = reference.render(ref_g, cam, kernel="surfel", outputs=outputs, settings=settings)
    assert bool(fast.visible[0]) and float((ref.alpha > 0.5).double().mean()) > 0.9  # covers the image
    tol = 1e-9 if dtype == torch.float64 else 1e-4
    for o in outputs:
        torch.testing.assert_close(getattr(fast, o).double(), getattr(ref, o), atol=tol, rtol=tol)
    if dtype == torch.float64:
        sum(getattr(fast, o).sum() for o in outputs).backward()
        sum(getattr(ref, o).sum() for o in outputs).backward()
        for p in ("means", "quats", "scales", "opacities"):
            torch.testing.assert_close(getattr(fast_g, p).grad, getattr(ref_g, p).grad, atol=1e-8, rtol=1e-7)
