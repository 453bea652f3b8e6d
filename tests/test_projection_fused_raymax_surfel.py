"""Fused C++ projection of the raymax and surfel kernels (csrc/project.cpp) vs the PyTorch projection (its oracle).

Mirrors tests/test_raster_projection.py (ewa/rade): float64 payload and every detached output to 1e-10
(rectangles, radii, visibility exactly), gradients of a random linear functional of the payload to 1e-8
relative; float32 within 1e-5 of the PyTorch float32 path (random scenes) and of the float64 result (hard
cases); `torch.autograd.gradcheck` of the fused autograd Function; hard cases (behind the camera, near
plane, scales 1e-8 / 1e4, edge-on and grazing surfels, surfel box denominator 0, large coordinates);
`rasterize` identical with either projection; the selection switch. Timings: `python
tests/test_projection_fused_raymax_surfel.py` prints projection forward+backward, fused vs torch.
"""

from __future__ import annotations

import functools
import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))

from raster_scenes import concat, make_camera, random_gaussians, single_gaussian, with_grad  # noqa: E402

from gsbench.raster import RasterGaussians, RasterSettings, projection, rasterize  # noqa: E402
from gsbench.raster.payload import NUM_PARAMS
from gsbench.raster.projection import project_fused, project_torch  # noqa: E402
from gsbench.raster.projection_fused import FUSED_KERNELS  # noqa: E402
from gsbench.switches import PROJECTION  # noqa: E402
from tests.projection_checks import (  # noqa: E402
    DETACHED,
    PARAMS,
    check_lanes_match_one_at_a_time,
    compare_projections,
    posed_camera,
)

KERNELS = ("raymax", "surfel")

SETTINGS = {
    "default": RasterSettings(sh_degree=1),
    "sh0": RasterSettings(sh_degree=0),
    "sh3-aa-eps-near-nofilter": RasterSettings(sh_degree=3, antialias2d=0.3, eps2d=0.1, near_plane=0.5,
                                               surfel_filter=0.0),
    "sh2-aa-filter0.5": RasterSettings(sh_degree=2, antialias2d=0.1, surfel_filter=0.5),
}


_compare = functools.partial(compare_projections, per_element=True)  # columns differ by orders of magnitude


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("name", list(SETTINGS))
@pytest.mark.parametrize("filter3d", [None, 1e-3], ids=["nofilter", "filter3d"])
def test_fused_matches_torch_float64(kernel, name, filter3d):
    cam = posed_camera()
    g = random_gaussians(200, kernel, seed=4, camera=make_camera(64, 48), dtype=torch.float64, sh_degree=3,
                         filter3d=filter3d)
    _compare(g, cam, kernel, SETTINGS[name])


@pytest.mark.parametrize("kernel", KERNELS)
def test_fused_matches_torch_identity_camera_float64(kernel):
    cam = make_camera(40, 30)
    g = random_gaussians(300, kernel, seed=9, camera=cam, dtype=torch.float64, sh_degree=1,
                         depth_range=(0.05, 6.0), spread=1.5)  # some behind near, some off-screen
    _compare(g, cam, kernel, RasterSettings(sh_degree=1))


def test_surfel_three_scale_columns_use_two():
    """surfel accepts (N, 3) scales; the third column is ignored (zero gradient), as in the PyTorch path."""
    cam = posed_camera()
    g = random_gaussians(50, "surfel", seed=1, camera=make_camera(64, 48), sh_degree=1)
    s3 = torch.cat([g.scales, torch.full((50, 1), 0.7, dtype=g.scales.dtype)], -1)
    g3 = RasterGaussians(g.means, g.quats, s3, g.opacities, g.sh)
    _, pb = _compare(g3, cam, "surfel", RasterSettings(sh_degree=1))
    p2 = project_fused(g, cam, "surfel", RasterSettings(sh_degree=1))
    assert torch.equal(p2.params, pb.params.detach())


def _hard_scene(kernel):
    sc = (0.5, 0.4, 0.3)
    half = math.sqrt(0.5)
    qx = (0.5, 0.5, 0.5, 0.5)  # exact: t_u = e_y, t_v = e_z, t_w = e_x (identity camera)
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
        single_gaussian((0.0, 0.0, 2.0), kernel=kernel, scales=(0.1, 0.1, 0.1), opacity=0.5),
        single_gaussian((1e3, -2e3, 5e3), kernel=kernel, quat=(0.3, -0.5, 0.2, 0.7), scales=(40.0, 10.0, 25.0),
                        opacity=0.6),  # large coordinates
        single_gaussian((-20.0, 35.0, 1e4), kernel=kernel, quat=(0.9, 0.1, -0.3, 0.2), scales=(5.0, 1.0, 2.0),
                        opacity=0.6),
        single_gaussian((0.0, 0.0, 3.0), kernel=kernel, quat=qx, scales=(0.3, 0.3, 0.3), opacity=0.9),  # edge-on
        single_gaussian((0.0, 0.0, 2.0), kernel=kernel, quat=(half, 0.0, half, 0.0), scales=(0.3, 0.3, 0.3),
                        opacity=0.9),  # (nearly) edge-on, rounded rotation
        single_gaussian((1e-7, 0.0, 3.0), kernel=kernel, quat=qx, scales=(0.3, 0.2, 0.3), opacity=0.9),  # grazing
        single_gaussian((0.1, 0.0, 2.0), kernel=kernel, quat=(half, 0.0, half + 1e-6, 0.0), scales=(0.3, 0.3, 0.3),
                        opacity=0.9),  # grazing
        single_gaussian((0.5, 0.0, 3.0), kernel=kernel, quat=qx, scales=(0.3, 1.0, 0.3), opacity=0.9),  # surfel dd = 0
        single_gaussian((0.5, 0.0, 3.0), kernel=kernel, quat=qx, scales=(0.3, 1.5, 0.3), opacity=0.9),  # reaches z = 0
    ]
    g = concat(*gs)
    sh = torch.randn(len(gs), 16, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    return RasterGaussians(g.means, g.quats, g.scales, g.opacities, sh)


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("name", ["default", "sh3-aa-eps-near-nofilter", "sh2-aa-filter0.5"])
@pytest.mark.parametrize("filter3d", [None, 1e-3], ids=["nofilter", "filter3d"])
def test_hard_cases_float64(kernel, name, filter3d):
    cam = make_camera(24, 20)
    g = _hard_scene(kernel)
    if filter3d is not None:
        g = RasterGaussians(g.means, g.quats, g.scales, g.opacities, g.sh, torch.full((len(g),), filter3d,
                                                                                       dtype=torch.float64))
    pa, pb = _compare(g, cam, kernel, SETTINGS[name])
    assert not bool(pb.visible[0]) and not bool(pb.visible[1]) and not bool(pb.visible[2])
    if kernel == "surfel":
        assert not bool(pb.visible[14]), "exactly edge-on surfel must be culled"
        assert bool(pb.visible[16]) and bool(pb.visible[17]), "grazing surfels stay visible"
        # discs reaching the camera plane (box denominator 0, and past it): visible, binned to the whole image
        for i in (18, 19):
            assert bool(pb.visible[i]) and pb.rect[i].tolist() == [0, 2, 0, 2], i


def _f32(g):
    f = lambda x: None if x is None else x.detach().float()  # noqa: E731
    return RasterGaussians(f(g.means), f(g.quats), f(g.scales), f(g.opacities), f(g.sh), f(g.filter3d))


def _rel(a, b):
    return ((a.double() - b.double()).abs() / b.double().abs().clamp_min(1.0))


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("filter3d", [None, 1e-3], ids=["nofilter", "filter3d"])
def test_float32_matches_torch_float32(kernel, filter3d):
    """Random scenes in float32: fused payload and gradients within 1e-5 of the PyTorch float32 path."""
    cam = posed_camera()
    g = _f32(random_gaussians(300, kernel, seed=5, camera=make_camera(64, 48), sh_degree=2, filter3d=filter3d))
    settings = RasterSettings(sh_degree=2)
    ga, gb = with_grad(g), with_grad(g)
    pa = project_torch(ga, cam, kernel, settings)
    pb = project_fused(gb, cam, kernel, settings)
    assert pb.params.dtype == torch.float32 and bool(torch.isfinite(pb.params).all())
    assert float(_rel(pb.params.detach(), pa.params.detach()).max()) < 1e-5
    for k in DETACHED:
        assert float(_rel(getattr(pb, k), getattr(pa, k)).max()) < 1e-5, k
    assert torch.equal(pa.visible, pb.visible)
    w = torch.randn(pa.params.shape, generator=torch.Generator().manual_seed(1))
    (pa.params * w).sum().backward()
    (pb.params * w).sum().backward()
    for p in PARAMS:
        x, y = getattr(ga, p).grad.double(), getattr(gb, p).grad.double()
        assert bool(torch.isfinite(y).all()), p
        err = float((x - y).abs().max()) / max(float(x.abs().max()), 1e-30)
        assert err < 1e-5, f"{kernel}: float32 gradient of {p} differs (relative {err:.3g})"


@pytest.mark.parametrize("kernel", KERNELS)
def test_hard_cases_float32_finite_and_close(kernel):
    """float32 storage (double inside): finite everywhere and within float32 rounding of the float64 result."""
    cam = make_camera(24, 20)
    g64 = _hard_scene(kernel)
    gf = with_grad(_f32(g64))
    p32 = project_fused(gf, cam, kernel, RasterSettings(sh_degree=1))
    p64 = project_fused(g64, cam, kernel, RasterSettings(sh_degree=1))
    assert bool(torch.isfinite(p32.params).all())
    (p32.params.double() * torch.linspace(-1, 1, p32.params.numel()).reshape(p32.params.shape)).sum().backward()
    for p in PARAMS:
        assert bool(torch.isfinite(getattr(gf, p).grad).all()), p
    assert torch.equal(p32.visible, p64.visible)
    vis = p64.visible.clone()
    if kernel == "surfel":
        # index 15 is edge-on up to rounding (μ·t_w ~ 1e-16): the side its normal faces (a sign) is arbitrary
        # and differs between float32 and float64 inputs; compare it without that sign
        a, b = p32.params.detach()[15].double(), p64.params[15]
        assert float(((a[9:13].abs() - b[9:13].abs()).abs()).max()) < 1e-5
        assert float(_rel(torch.cat([a[:9], a[13:]]), torch.cat([b[:9], b[13:]])).max()) < 1e-5
        vis[15] = False
    assert float(_rel(p32.params.detach()[vis], p64.params[vis]).max()) < 1e-5


def test_selection_switch_raymax_surfel(monkeypatch):
    monkeypatch.delenv(PROJECTION.name, raising=False)
    for k in ("ewa", "rade", "raymax", "surfel"):
        assert projection.projection_impl(k) == "fused"
    monkeypatch.setenv(PROJECTION.name, "torch")
    assert projection.projection_impl("raymax") == "torch" and projection.projection_impl("surfel") == "torch"
    monkeypatch.setenv(PROJECTION.name, "fused")
    assert projection.projection_impl("surfel") == "fused"


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("posed", [False, True], ids=["identity", "posed"])
def test_rasterize_same_with_either_projection(kernel, posed, monkeypatch):
    """The whole render (float64, all outputs and gradients) is the same whichever projection runs."""
    cam = posed_camera(33, 20) if posed else make_camera(33, 20)
    g = random_gaussians(60, kernel, seed=7, camera=make_camera(33, 20), dtype=torch.float64, sh_degree=1,
                         filter3d=1e-4 if posed else None)
    settings = RasterSettings(sh_degree=1)
    outs = ("rgb", "alpha", "depth", "median_depth", "normal", "distortion")
    res = {}
    for impl in ("torch", "fused"):
        monkeypatch.setenv(PROJECTION.name, impl)
        gg = with_grad(g)
        out = rasterize(gg, cam, kernel=kernel, outputs=outs, settings=settings)
        sum((getattr(out, o) * (k + 1)).sum() for k, o in enumerate(outs)).backward()
        res[impl] = (out, gg)
    (oa, ga), (ob, gb) = res["torch"], res["fused"]
    assert float(oa.alpha.detach().max()) > 0.1  # something is drawn
    for o in outs:
        x, y = getattr(oa, o).detach(), getattr(ob, o).detach()
        assert float((x - y).abs().max()) <= 1e-10 * max(1.0, float(x.abs().max())), o
    for p in PARAMS:
        x, y = getattr(ga, p).grad, getattr(gb, p).grad
        assert float((x - y).abs().max()) <= 1e-8 * max(1.0, float(x.abs().max())), p
    assert torch.allclose(oa.means2d.grad, ob.means2d.grad, rtol=1e-9, atol=1e-12)
    assert torch.allclose(oa.extras["absgrad"], ob.extras["absgrad"], rtol=1e-9, atol=1e-12)
    assert torch.equal(oa.radii, ob.radii) and torch.equal(oa.visible, ob.visible)


def _bench(sizes=(50_000, 200_000), repeats=5, threads=2):
    """Projection forward+backward (loss = a fixed linear functional of the payload), fused vs torch."""
    import time  # noqa: PLC0415

    from gsbench.bench.raster import standard_scene  # noqa: PLC0415

    torch.set_num_threads(threads)
    settings = RasterSettings(sh_degree=0)
    print(f"projection fwd+bwd, {threads} threads, median of {repeats} (ms)")
    for kernel in ("ewa", "raymax", "surfel"):
        for n in sizes:
            g, cam = standard_scene(n, 800 if n > 50_000 else 400, 600 if n > 50_000 else 300, kernel=kernel)
            w = torch.randn(n, NUM_PARAMS[kernel], generator=torch.Generator().manual_seed(0))
            row = {}
            for impl, fn in (("torch", project_torch), ("fused", project_fused)):
                tf, tb = [], []
                for _ in range(repeats + 1):
                    gg = with_grad(g)
                    t0 = time.perf_counter()
                    p = fn(gg, cam, kernel, settings)
                    t1 = time.perf_counter()
                    (p.params * w).sum().backward()
                    t2 = time.perf_counter()
                    tf.append(t1 - t0)
                    tb.append(t2 - t1)
                tf, tb = sorted(tf[1:]), sorted(tb[1:])
                row[impl] = (1e3 * tf[len(tf) // 2], 1e3 * tb[len(tb) // 2])
            (af, ab), (bf, bb) = row["torch"], row["fused"]
            print(f"{kernel:7s} N={n:7d}  torch fwd {af:7.1f} bwd {ab:7.1f} total {af + ab:7.1f} | "
                  f"fused fwd {bf:6.1f} bwd {bb:6.1f} total {bf + bb:6.1f} | speed-up {(af + ab) / (bf + bb):5.1f}x")


@pytest.mark.parametrize("kernel", FUSED_KERNELS)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("filter3d", [None, 1e-3], ids=["nofilter", "filter3d"])
def test_vector_lanes_match_one_gaussian_at_a_time(kernel, dtype, filter3d):
    """The hard cases and a random scene, 49 Gaussians, forward and backward in lanes (the hard cases among them)
    and one at a time, against each Gaussian projected alone (one at a time)."""
    cam = posed_camera(40, 30)
    rand = random_gaussians(29, kernel, seed=11, camera=make_camera(40, 30), dtype=torch.float64, sh_degree=3)
    g = concat(_hard_scene(kernel), rand)
    if filter3d is not None:
        g = RasterGaussians(g.means, g.quats, g.scales, g.opacities, g.sh, torch.full((len(g),), filter3d,
                                                                                       dtype=torch.float64))
    g = g.map(lambda t: t.to(dtype))
    for settings in (SETTINGS["sh3-aa-eps-near-nofilter"], SETTINGS["sh2-aa-filter0.5"]):
        check_lanes_match_one_at_a_time(g, cam, kernel, settings, tol=1e-12 if dtype == torch.float64 else 1e-6)


if __name__ == "__main__":
    _bench()

