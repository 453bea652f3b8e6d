"""Fused C++ projection (csrc/project.cpp, kernels ewa and rade) vs the PyTorch projection (its oracle).

float64: forward payload and every detached output to 1e-10 (rectangles, radii, visibility exactly);
gradients to 1e-8 relative; `torch.autograd.gradcheck` of the fused autograd Function on tiny scenes;
hard cases (near plane, behind the camera, scales 1e-8 / 1e4, zero opacity) finite and equal to the
PyTorch path; the selection switch.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))

from raster_scenes import concat, make_camera, random_gaussians, single_gaussian, with_grad  # noqa: E402

from gsbench.errors import ConfigError  # noqa: E402
from gsbench.raster import RasterGaussians, RasterSettings, projection, rasterize  # noqa: E402
from gsbench.raster.projection import project_fused  # noqa: E402
from gsbench.raster.projection_fused import FUSED_KERNELS  # noqa: E402
from gsbench.switches import PROJECTION  # noqa: E402
from tests.projection_checks import PARAMS, compare_projections, posed_camera  # noqa: E402

KERNELS = ("ewa", "rade")

SETTINGS = {
    "default": RasterSettings(sh_degree=1),
    "sh0": RasterSettings(sh_degree=0),
    "sh3-aa-eps-near": RasterSettings(sh_degree=3, antialias2d=0.3, eps2d=0.1, near_plane=0.5),
    "sh2-aa": RasterSettings(sh_degree=2, antialias2d=0.1),
}


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("name", list(SETTINGS))
@pytest.mark.parametrize("filter3d", [None, 1e-3], ids=["nofilter", "filter3d"])
def test_fused_matches_torch_float64(kernel, name, filter3d):
    settings = SETTINGS[name]
    cam = posed_camera()
    g = random_gaussians(200, kernel, seed=4, camera=make_camera(64, 48), dtype=torch.float64, sh_degree=3,
                         filter3d=filter3d)
    compare_projections(g, cam, kernel, settings)


@pytest.mark.parametrize("kernel", KERNELS)
def test_fused_matches_torch_identity_camera_float64(kernel):
    cam = make_camera(40, 30)
    g = random_gaussians(200, kernel, seed=9, camera=cam, dtype=torch.float64, sh_degree=1)
    compare_projections(g, cam, kernel, RasterSettings(sh_degree=1))


def _hard_scene(kernel):
    sc = (0.5, 0.4, 0.3)
    gs = [
        single_gaussian((0.1, 0.0, -1.0), kernel=kernel, scales=sc, opacity=0.8),  # behind the camera
        single_gaussian((0.0, 0.1, 0.0), kernel=kernel, scales=sc, opacity=0.8),  # at the camera centre
        single_gaussian((0.0, 0.0, 0.2), kernel=kernel, scales=sc, opacity=0.8),  # exactly at near
        single_gaussian((0.05, 0.0, 0.21), kernel=kernel, scales=sc, opacity=0.8),  # straddles near
        single_gaussian((0.0, -0.05, 0.5), kernel=kernel, scales=(2.0, 2.0, 2.0), opacity=0.8),  # around the camera
        single_gaussian((0.0, 0.0, 2.0), kernel=kernel, scales=(0.2, 0.3, 0.1), opacity=0.0),  # zero opacity
        single_gaussian((0.3, 0.2, 2.0), kernel=kernel, scales=(1e-8, 1e-8, 1e-8), opacity=0.7),
        single_gaussian((-0.3, 0.1, 2.0), kernel=kernel, scales=(1e-8, 0.1, 1e-8), opacity=0.7),
        single_gaussian((0.1, -0.2, 3.0), kernel=kernel, scales=(1e4, 1e4, 1e4), opacity=0.7),
        single_gaussian((0.2, 0.2, 3.0), kernel=kernel, scales=(1e4, 1e-8, 0.1), opacity=0.7),
        single_gaussian((9.0, 0.0, 1.0), kernel=kernel, scales=(0.1, 0.1, 0.1), opacity=0.7),  # off-screen (clamped J)
        single_gaussian((0.0, 0.0, 2.0), kernel=kernel, scales=(0.1, 0.1, 0.1), opacity=0.5),  # ties in argmin
    ]
    g = concat(*gs)
    return RasterGaussians(g.means, g.quats, g.scales, g.opacities, torch.randn(len(gs), 16, 3, dtype=torch.float64,
                                                                                  generator=torch.Generator().manual_seed(0)))


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("name", ["default", "sh3-aa-eps-near"])
def test_hard_cases_float64(kernel, name):
    cam = make_camera(24, 20)
    pa, pb = compare_projections(_hard_scene(kernel), cam, kernel, SETTINGS[name], fwd_tol=1e-10, grad_tol=1e-8)
    assert not bool(pb.visible[0]) and not bool(pb.visible[1]) and not bool(pb.visible[2])


@pytest.mark.parametrize("kernel", KERNELS)
def test_hard_cases_float32_finite_and_close(kernel):
    """float32 storage (double inside): finite everywhere and within float32 rounding of the float64 result."""
    cam = make_camera(24, 20)
    g64 = _hard_scene(kernel)
    g32 = RasterGaussians(*(getattr(g64, p).float() for p in PARAMS))
    gf = with_grad(g32)
    p32 = project_fused(gf, cam, kernel, RasterSettings(sh_degree=1))
    p64 = project_fused(g64, cam, kernel, RasterSettings(sh_degree=1))
    assert bool(torch.isfinite(p32.params).all())
    (p32.params.double() * torch.linspace(-1, 1, p32.params.numel()).reshape(p32.params.shape)).sum().backward()
    for p in PARAMS:
        assert bool(torch.isfinite(getattr(gf, p).grad).all()), p
    assert torch.equal(p32.visible, p64.visible)
    vis = p64.visible
    rel = (p32.params.detach().double() - p64.params)[vis].abs() / p64.params[vis].abs().clamp_min(1.0)
    assert float(rel.max()) < 1e-5


@pytest.mark.parametrize("kernel", FUSED_KERNELS)  # float64 gradchecks for every fused projection
@pytest.mark.parametrize("n, fast_mode", [(5, False), (17, True)], ids=["one-at-a-time", "lanes"])
def test_gradcheck_fused_projection(kernel, n, fast_mode):
    """The full Jacobian of 5 Gaussians, whose backward runs one at a time (each column's payload gradient is one
    Gaussian's: csrc/project.cpp lists only those with one), and gradcheck's fast mode (a random projection of
    the Jacobian, so every Gaussian has a payload gradient) on 17: 16 in vector lanes, forward and backward."""
    cam = posed_camera(20, 16)
    g = random_gaussians(n, kernel, seed=2, camera=make_camera(20, 16), dtype=torch.float64, sh_degree=2,
                         scale_range=(0.1, 0.4), filter3d=1e-3)
    settings = RasterSettings(sh_degree=2, antialias2d=0.2)

    def fn(means, quats, scales, opacities, sh):
        gg = RasterGaussians(means, quats, scales, opacities, sh, g.filter3d)
        return project_fused(gg, cam, kernel, settings).params

    inputs = tuple(getattr(g, p).clone().requires_grad_(True) for p in PARAMS)
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=fast_mode)


def test_selection_switch(monkeypatch):
    monkeypatch.delenv(PROJECTION.name, raising=False)
    assert projection.projection_impl("ewa") == "fused" and projection.projection_impl("rade") == "fused"
    assert projection.projection_impl("raymax") == "fused" and projection.projection_impl("surfel") == "fused"
    monkeypatch.setenv(PROJECTION.name, "torch")
    assert projection.projection_impl("ewa") == "torch"
    monkeypatch.setenv(PROJECTION.name, "Fused")
    assert projection.projection_impl("ewa") == "fused"
    monkeypatch.setenv(PROJECTION.name, "bogus")
    with pytest.raises(ConfigError, match=f"{PROJECTION.name}='bogus' is not one of .*fused"):
        projection.projection_impl("ewa")


@pytest.mark.parametrize("kernel", KERNELS)
def test_rasterize_same_with_either_projection(kernel, monkeypatch):
    """The whole render (float64, all outputs and gradients) is the same whichever projection runs."""
    cam = make_camera(33, 20)
    g = random_gaussians(60, kernel, seed=7, camera=cam, dtype=torch.float64, sh_degree=1)
    settings = RasterSettings(sh_degree=1)
    outs = ("rgb", "alpha", "depth", "normal", "distortion")
    res = {}
    for impl in ("torch", "fused"):
        monkeypatch.setenv(PROJECTION.name, impl)
        gg = with_grad(g)
        out = rasterize(gg, cam, kernel=kernel, outputs=outs, settings=settings)
        sum((getattr(out, o) * (k + 1)).sum() for k, o in enumerate(outs)).backward()
        res[impl] = (out, gg)
    (oa, ga), (ob, gb) = res["torch"], res["fused"]
    for o in outs:
        assert float((getattr(oa, o) - getattr(ob, o)).detach().abs().max()) <= 1e-10, o
    for p in PARAMS:
        x, y = getattr(ga, p).grad, getattr(gb, p).grad
        assert float((x - y).abs().max()) <= 1e-8 * max(1.0, float(x.abs().max())), p
    assert torch.allclose(oa.means2d.grad, ob.means2d.grad, rtol=1e-9, atol=1e-12)
    assert torch.equal(oa.radii, ob.radii)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_depth_order_and_binning_match_torch_sort(dtype):
    """C++ radix sort by (depth, id) and the sequential binner equal torch's stable sort and the original gs_bin."""
    import ctypes  # noqa: PLC0415

    from gsbench.raster.abi import library  # noqa: PLC0415
    from gsbench.raster.composite import pointer as _ptr  # noqa: PLC0415

    lib = library()
    gen = torch.Generator().manual_seed(3)
    n, tx, ty = 5000, 13, 9
    depth = torch.round(torch.rand(n, generator=gen, dtype=torch.float64) * 50) / 7 + 0.2  # many exact ties
    depth[:20] = torch.tensor([-0.0, 0.0] * 10, dtype=torch.float64)
    depth[20:30] = -depth[20:30]
    depth = depth.to(dtype)
    visible = torch.rand(n, generator=gen) < 0.8
    x0 = torch.randint(0, tx, (n,), generator=gen)
    y0 = torch.randint(0, ty, (n,), generator=gen)
    rect = torch.stack([x0, torch.clamp(x0 + torch.randint(0, 4, (n,), generator=gen), max=tx),
                        y0, torch.clamp(y0 + torch.randint(0, 4, (n,), generator=gen), max=ty)], -1).to(torch.int32)
    rect[~visible] = 0
    order = torch.empty(n, dtype=torch.int32)
    rs = torch.empty(n, 4, dtype=torch.int32)
    cap = ctypes.c_int64(0)
    m = lib.gs_depth_order(n, _ptr(visible.view(torch.uint8)), _ptr(depth), 0 if dtype == torch.float32 else 1,
                           _ptr(rect), _ptr(order), _ptr(rs), ctypes.byref(cap))
    vis_idx = torch.nonzero(visible).reshape(-1)
    ref = vis_idx[torch.sort(depth[vis_idx], stable=True).indices]
    assert m == vis_idx.numel() and torch.equal(order[:m].long(), ref)
    assert torch.equal(rs[:m], rect[ref])
    areas = (rect[:, 1] - rect[:, 0]).long() * (rect[:, 3] - rect[:, 2]).long()
    assert cap.value == int(areas.sum())
    for threads in (1, 2, 3):
        off_a = torch.zeros(tx * ty + 1, dtype=torch.int32)
        off_b = torch.zeros_like(off_a)
        la = torch.empty(max(cap.value, 1), dtype=torch.int32)
        lb = torch.empty_like(la)
        ref_c = ref.contiguous()
        got_a = lib.gs_bin(m, _ptr(ref_c), _ptr(rect), tx, ty, _ptr(off_a), _ptr(la), cap.value, threads)
        got_b = lib.gs_bin_sorted(m, _ptr(order), _ptr(rs), tx, ty, _ptr(off_b), _ptr(lb), cap.value, threads)
        assert got_a == got_b == cap.value
        assert torch.equal(off_a, off_b) and torch.equal(la, lb)


@pytest.mark.parametrize("kernel", FUSED_KERNELS)
@pytest.mark.parametrize("degree", [0, 1, 3])
def test_sh_kept_apart_equals_sh_concatenated(kernel, degree):
    """`RasterGaussians.sh_rest` (the training parameters' layout: sh (N,1,3) and the other rows apart): the same
    payload and gradients as one (N,16,3) sh, the rows past the render's degree with gradient exactly 0."""
    cam = make_camera(40, 30)
    g = random_gaussians(60, kernel, seed=4, camera=cam, dtype=torch.float64, sh_degree=3)
    settings = RasterSettings(sh_degree=degree)
    whole = with_grad(g)
    dc = g.sh[:, :1].clone().requires_grad_(True)
    rest = g.sh[:, 1:].clone().requires_grad_(True)
    apart = RasterGaussians(*(x.detach().clone().requires_grad_(True) for x in (g.means, g.quats, g.scales,
                                                                               g.opacities)), dc, sh_rest=rest)
    pa, pb = project_fused(whole, cam, kernel, settings), project_fused(apart, cam, kernel, settings)
    assert torch.equal(pa.params, pb.params)
    w = torch.rand(pa.params.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    (pa.params * w).sum().backward()
    (pb.params * w).sum().backward()
    assert torch.equal(whole.sh.grad[:, :1], dc.grad) and torch.equal(whole.sh.grad[:, 1:], rest.grad)
    assert float(rest.grad[:, (degree + 1) ** 2 - 1:].abs().sum()) == 0.0
    assert float(rest.grad.abs().max()) > 0 or degree == 0
    for name in ("means", "quats", "scales", "opacities"):
        assert torch.equal(getattr(whole, name).grad, getattr(apart, name).grad), name


@pytest.mark.parametrize("kernel", FUSED_KERNELS)
def test_gaussians_without_payload_gradient_get_exact_zero_gradients(kernel):
    """The backward skips a Gaussian whose payload gradient is all zero (csrc/project.cpp): its gradients, SH rows
    kept apart included, are exactly 0 (the output buffers start uninitialised), and the others still match the
    PyTorch projection."""
    cam = make_camera(40, 30)
    g = random_gaussians(90, kernel, seed=5, camera=cam, dtype=torch.float64, sh_degree=3)
    settings = RasterSettings(sh_degree=3)
    ref = with_grad(g)
    dc = g.sh[:, :1].clone().requires_grad_(True)
    rest = g.sh[:, 1:].clone().requires_grad_(True)
    fused = RasterGaussians(*(x.detach().clone().requires_grad_(True) for x in (g.means, g.quats, g.scales,
                                                                               g.opacities)), dc, sh_rest=rest)
    pa, pb = projection.project_torch(ref, cam, kernel, settings), project_fused(fused, cam, kernel, settings)
    w = torch.randn(pa.params.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    skipped = torch.arange(len(g)) % 3 == 0
    w[skipped] = 0.0
    (pa.params * w).sum().backward()
    (pb.params * w).sum().backward()
    got = {"means": fused.means.grad, "quats": fused.quats.grad, "scales": fused.scales.grad,
           "opacities": fused.opacities.grad, "sh": torch.cat([dc.grad, rest.grad], dim=1)}
    for name, grad in got.items():
        assert float(grad[skipped].abs().max()) == 0.0, name
        want = getattr(ref, name).grad
        assert float((grad - want).abs().max()) <= 1e-8 * float(want.abs().max()), name
