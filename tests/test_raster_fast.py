"""Fast C++ rasterizer vs the dense PyTorch reference, every kernel × output; float64 gradchecks.

The first test in a fresh cache compiles the extension (~30 s on 2 cores).
"""

from __future__ import annotations

import gc
import sys
import weakref
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))

from raster_scenes import make_camera, random_gaussians, with_grad  # noqa: E402

from gsbench.raster import OUTPUTS, RasterGaussians, RasterSettings, rasterize, reference  # noqa: E402
from gsbench.raster.types import KERNEL_OUTPUTS  # noqa: E402

PARAMS = ("means", "quats", "scales", "opacities", "sh")
KERNELS = ("ewa", "rade", "raymax", "surfel")
OUTPUT_SETS = [(o,) for o in OUTPUTS] + [OUTPUTS]
FWD_ATOL = 1e-5
GRAD_RTOL = 1e-3
# Documented exception: surfel depths are the ray–plane intersection depths, whose condition number is
# ~1/(n·r) and reaches 1e4 for near edge-on splats, so float32 rounding of the inputs alone moves them
# by ~1e-4 (checked: the float64 fast path matches the reference to 1e-9 on the same scenes).
SURFEL_DEPTH_ATOL = 1e-3


def _cast(g: RasterGaussians, dtype) -> RasterGaussians:
    f = lambda x: None if x is None else x.detach().to(dtype)  # noqa: E731
    return RasterGaussians(f(g.means), f(g.quats), f(g.scales), f(g.opacities), f(g.sh), f(g.filter3d))


def _weights(out, outs, seed=1):
    gen = torch.Generator().manual_seed(seed)
    return {o: torch.rand(getattr(out, o).shape, generator=gen, dtype=torch.float64) for o in outs}


def _loss(out, weights):
    return sum((getattr(out, o).double() * w).sum() for o, w in weights.items())


def _scene(kernel, seed=0, n=200, W=64, H=48, sh_degree=1, filter3d=None):
    cam = make_camera(W, H)
    g32 = random_gaussians(n, kernel, seed=seed, camera=cam, dtype=torch.float32, sh_degree=sh_degree, filter3d=filter3d)
    return cam, g32


@pytest.fixture(scope="module")
def reference_runs():
    """Per kernel: the reference render (float64, on the float32-rounded scene) with all outputs."""
    cache = {}

    def get(kernel, settings):
        key = (kernel, settings)
        if key not in cache:
            cam, g32 = _scene(kernel, sh_degree=settings.sh_degree)
            gr = with_grad(_cast(g32, torch.float64))
            ref = reference.render(gr, cam, kernel=kernel, outputs=OUTPUTS, settings=settings)
            cache[key] = (cam, g32, gr, ref)
        return cache[key]

    return get


def _grad_errors(fast_g, ref_g, loss_ref, gr):
    grads_ref = torch.autograd.grad(loss_ref, [getattr(gr, p) for p in PARAMS], retain_graph=True, allow_unused=True)
    scale = max(float(g.norm()) for g in grads_ref if g is not None)
    errs = {}
    for p, gref in zip(PARAMS, grads_ref):
        gf = getattr(fast_g, p).grad
        gref = torch.zeros_like(getattr(gr, p)) if gref is None else gref
        gf = torch.zeros_like(gref) if gf is None else gf.double()
        # relative to the parameter's gradient norm, with a floor at 1e-6 of the largest one (exact zeros)
        errs[p] = float((gf - gref).norm()) / max(float(gref.norm()), 1e-6 * scale, 1e-30)
    return errs


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("outs", OUTPUT_SETS, ids=lambda o: "all" if len(o) > 1 else o[0])
def test_fast_matches_reference(kernel, outs, reference_runs):
    settings = RasterSettings(sh_degree=1)
    cam, g32, gr, ref = reference_runs(kernel, settings)
    gf = with_grad(g32)
    out = rasterize(gf, cam, kernel=kernel, outputs=outs, settings=settings)
    for o in OUTPUTS:
        assert (getattr(out, o) is None) == (o not in outs), o
    for o in outs:
        diff = float((getattr(out, o).detach().double() - getattr(ref, o).detach()).abs().max())
        tol = SURFEL_DEPTH_ATOL if (kernel == "surfel" and o in ("depth", "median_depth")) else FWD_ATOL
        assert diff <= tol, f"{kernel}/{o}: forward max abs diff {diff:.3g} > {tol}"
    assert torch.equal(out.radii, ref.radii)
    assert torch.equal(out.visible, ref.visible)
    w = _weights(out, outs)
    _loss(out, w).backward()
    errs = _grad_errors(gf, None, _loss(ref, w), gr)
    bad = {p: e for p, e in errs.items() if not e <= GRAD_RTOL}
    assert not bad, f"{kernel}/{outs}: relative gradient errors {bad}"
    # densification statistics (the reference has the exact means2d gradient; raymax uses GOF's proxy and
    # surfel 2DGS's shortcut, each tested against its own formula below)
    if kernel not in ("raymax", "surfel"):
        gm_ref = torch.autograd.grad(_loss(ref, w), ref.means2d, retain_graph=True, allow_unused=True)[0]
        gm_ref = torch.zeros_like(ref.means2d) if gm_ref is None else gm_ref
        gm = out.means2d.grad.double()
        assert float((gm - gm_ref).norm()) <= GRAD_RTOL * float(gm_ref.norm()) + 1e-9
    else:
        assert out.means2d.grad is not None and out.means2d.grad.shape == (len(g32), 2)
    assert out.extras["absgrad"].shape == (len(g32),)
    assert bool(torch.isfinite(out.extras["absgrad"]).all())


@pytest.mark.parametrize("kernel", [k for k in KERNELS if k != "raymax"])  # raymax: next test
def test_absgrad_matches_reference(kernel):
    cam, g32 = _scene(kernel, seed=3, n=120, W=40, H=32)
    settings = RasterSettings(sh_degree=1)
    gr = with_grad(_cast(g32, torch.float64))
    ref = reference.render(gr, cam, kernel=kernel, outputs=("rgb", "depth"), settings=settings)
    gf = with_grad(g32)
    out = rasterize(gf, cam, kernel=kernel, outputs=("rgb", "depth"), settings=settings)
    w = _weights(out, ("rgb", "depth"))
    _loss(out, w).backward()
    _loss(ref, w).backward()
    a, b = out.extras["absgrad"].double(), ref.extras["absgrad"]
    assert float((a - b).norm()) <= 1e-3 * float(b.norm())
    g_ndc, abs_ndc = out.densify_grads()
    assert torch.allclose(abs_ndc, out.extras["absgrad"])
    assert g_ndc.shape == (len(g32), 2)


def test_raymax_densification_proxy_is_gofs_conic_formula():
    """docs/methods/gof.md §3.6: dL/dmeans2d = Σ_p dL/dα_p · ∂(o·G_ewa)/∂m with the EWA conic; absgrad = Σ_p |g_x|W/2 + |g_y|H/2.

    One Gaussian and loss = Σ alpha make dL/dα_p = 1 wherever the pixel blends it (α_p >= 1/255), so
    the proxy is Σ_p o·G_ewa(p)·C(p − m) over those pixels, computed here from the reference projection.
    """
    from raster_scenes import single_gaussian  # noqa: PLC0415

    cam = make_camera(32, 24)
    g = single_gaussian((0.05, -0.03, 2.0), kernel="raymax", quat=(0.9, 0.2, 0.3, 0.1), scales=(0.08, 0.05, 0.03),
                        opacity=0.6, dtype=torch.float64)
    settings = RasterSettings()
    out = rasterize(with_grad(g), cam, kernel="raymax", outputs=("alpha",), settings=settings)
    out.alpha.sum().backward()
    proj = reference.project(g, cam, "raymax", settings)
    ys, xs = torch.meshgrid(torch.arange(24, dtype=torch.float64), torch.arange(32, dtype=torch.float64), indexing="ij")
    d = torch.stack([xs + 0.5, ys + 0.5], -1) - proj.means2d[0]
    C = proj.conic[0]
    g_ewa = torch.exp(-0.5 * torch.einsum("hwi,ij,hwj->hw", d, C, d))
    blended = out.alpha.detach() >= 1 / 255
    per_pixel = proj.opacity[0] * g_ewa[..., None] * (d @ C)  # ∂(o·G)/∂m = o·G·C(p − m)
    expected = per_pixel[blended].sum(0)
    torch.testing.assert_close(out.means2d.grad[0].double(), expected, rtol=1e-6, atol=1e-9)
    expected_abs = (per_pixel[blended].abs() * torch.tensor([16.0, 12.0], dtype=torch.float64)).sum()
    torch.testing.assert_close(out.extras["absgrad"][0].double(), expected_abs, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("outs", [("rgb",), ("rgb", "depth", "normal", "distortion")])
def test_surfel_densification_statistic_is_2dgs_shortcut(outs):
    """docs/methods/2dgs.md §3.6: the surfel statistic is ∂L/∂(screen position of the centre) at fixed depth through
    the ray-splat intersection, (∂L/∂μ·R e_x·μz/fx, ∂L/∂μ·R e_y·μz/fy) with μ the camera-space centre. With the
    low-pass filter off the intersection is the only path, so it is the derivative of the reference's loss for a
    world-space move of the means along the camera's x and y axes (SH degree 0: no view-dependent colour, whose
    direction also moves with the mean)."""
    from gsbench.raster.payload import camera_tensors  # noqa: PLC0415

    cam, g32 = _scene("surfel", seed=5, n=80, W=40, H=32, sh_degree=0)
    settings = RasterSettings(sh_degree=0, surfel_filter=0.0)
    g64 = _cast(g32, torch.float64)
    gr = with_grad(g64)
    ref = reference.render(gr, cam, kernel="surfel", outputs=outs, settings=settings)
    w = _weights(ref, outs)
    grad_means = torch.autograd.grad(_loss(ref, w), gr.means)[0]
    R, t, _ = camera_tensors(cam, torch.float64)
    z = (g64.means @ R.T + t)[:, 2]
    expected = torch.stack([grad_means @ R[0] * z / cam.fx, grad_means @ R[1] * z / cam.fy], -1)
    expected = torch.where(ref.visible[:, None], expected, torch.zeros_like(expected))
    out = rasterize(with_grad(g64), cam, kernel="surfel", outputs=outs, settings=settings)
    _loss(out, w).backward()
    assert float(expected.abs().max()) > 1e-3  # the scene exercises the statistic
    torch.testing.assert_close(out.means2d.grad, expected, rtol=1e-7, atol=1e-10)
    g_ndc, _ = out.densify_grads()
    torch.testing.assert_close(g_ndc, expected * torch.tensor([cam.width / 2, cam.height / 2], dtype=torch.float64))


@pytest.mark.parametrize("kernel", KERNELS)
def test_settings_variants_match_reference(kernel):
    """3D filter, antialias, background, detached distortion weights, SH degree 3, eps2d override."""
    settings = RasterSettings(
        sh_degree=3, background=(0.2, 0.5, 0.9), antialias2d=0.3, detach_distortion_weights=True,
        eps2d=0.1 if kernel != "surfel" else None, near_plane=0.5, far_plane=20.0,
    )
    cam, g32 = _scene(kernel, seed=5, n=150, W=48, H=40, sh_degree=3, filter3d=1e-3)
    gr = with_grad(_cast(g32, torch.float64))
    ref = reference.render(gr, cam, kernel=kernel, outputs=OUTPUTS, settings=settings)
    gf = with_grad(g32)
    out = rasterize(gf, cam, kernel=kernel, outputs=OUTPUTS, settings=settings)
    for o in OUTPUTS:
        diff = float((getattr(out, o).detach().double() - getattr(ref, o).detach()).abs().max())
        tol = SURFEL_DEPTH_ATOL if (kernel == "surfel" and o in ("depth", "median_depth")) else FWD_ATOL
        assert diff <= tol, f"{kernel}/{o}: {diff:.3g}"
    w = _weights(out, OUTPUTS)
    _loss(out, w).backward()
    errs = _grad_errors(gf, None, _loss(ref, w), gr)
    assert all(e <= GRAD_RTOL for e in errs.values()), errs


@pytest.mark.parametrize("kernel", KERNELS)
def test_float64_fast_path_is_exact(kernel):
    """In float64 the fast path equals the reference to rounding (all outputs and gradients)."""
    cam, g32 = _scene(kernel, seed=7, n=60, W=33, H=20)
    settings = RasterSettings(sh_degree=1)
    gr = with_grad(_cast(g32, torch.float64))
    gf = with_grad(_cast(g32, torch.float64))
    ref = reference.render(gr, cam, kernel=kernel, outputs=OUTPUTS, settings=settings)
    out = rasterize(gf, cam, kernel=kernel, outputs=OUTPUTS, settings=settings)
    for o in OUTPUTS:
        assert float((getattr(out, o) - getattr(ref, o)).detach().abs().max()) <= 1e-9, o
    w = _weights(out, OUTPUTS)
    _loss(out, w).backward()
    errs = _grad_errors(gf, None, _loss(ref, w), gr)
    assert all(e <= 1e-7 for e in errs.values()), errs


@pytest.mark.parametrize("kernel", KERNELS)
def test_gradcheck_float64(kernel):
    cam = make_camera(16, 12)
    g = random_gaussians(6, kernel, seed=11, camera=cam, dtype=torch.float64, sh_degree=1, scale_range=(0.15, 0.4))
    settings = RasterSettings(sh_degree=1, background=(0.1, 0.2, 0.3))

    def fn(means, quats, scales, opacities, sh):
        out = rasterize(
            RasterGaussians(means, quats, scales, opacities, sh), cam, kernel=kernel, outputs=OUTPUTS, settings=settings
        )
        return tuple(getattr(out, o) for o in OUTPUTS if o != "median_depth")

    inputs = tuple(getattr(g, p).clone().requires_grad_(True) for p in PARAMS)
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-3, fast_mode=True)


# plane_distance (PGSR, docs/methods/pgsr.md §3.1): Σ w_i d_i composited in the kernel's own pass like one more
# colour channel; its reverse pass adds g_plane·d_i to ψ (the suffix of every Gaussian in front) and returns
# dL/dd_i = Σ_pixels w_i·g_plane. Losses mix it with colour so that both channels share one suffix.
PLANE_OUTS = ("plane_distance", "rgb", "normal", "alpha")


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=("f32", "f64"))
def test_plane_distance_native_matches_reference(kernel, dtype):
    """Value and the gradients w.r.t. every raster input (and means2d, absgrad) of the native output, alone and
    in a loss with colour, normal and alpha; float32 within the tolerances above, float64 to rounding."""
    settings = RasterSettings(sh_degree=1)
    cam, g32 = _scene(kernel, seed=9, n=150, W=48, H=40)
    fwd_tol, grad_tol = (FWD_ATOL, GRAD_RTOL) if dtype == torch.float32 else (1e-9, 1e-7)
    for outs in (("plane_distance",), PLANE_OUTS):
        gr = with_grad(_cast(g32, torch.float64))
        gf = with_grad(_cast(g32, dtype))
        ref = reference.render(gr, cam, kernel=kernel, outputs=outs, settings=settings)
        out = rasterize(gf, cam, kernel=kernel, outputs=outs, settings=settings)
        assert float(ref.plane_distance.detach().max()) > 0.1
        for o in outs:
            diff = float((getattr(out, o).detach().double() - getattr(ref, o).detach()).abs().max())
            assert diff <= fwd_tol, f"{kernel}/{o}: forward max abs diff {diff:.3g} > {fwd_tol}"
        w = _weights(out, outs, seed=2)
        _loss(out, w).backward()
        loss_ref = _loss(ref, w)
        errs = _grad_errors(gf, None, loss_ref, gr)  # one reverse pass of the reference: fills its absgrad
        bad = {p: e for p, e in errs.items() if not e <= grad_tol}
        assert not bad, f"{kernel}/{outs}: relative gradient errors {bad}"
        if kernel not in ("raymax", "surfel"):  # their densification statistics are GOF's proxy / 2DGS's shortcut
            a, b = out.extras["absgrad"].double(), ref.extras["absgrad"]
            assert float((a - b).norm()) <= grad_tol * float(b.norm())
            gm_ref = torch.autograd.grad(loss_ref, ref.means2d)[0]
            gm = out.means2d.grad.double()
            assert float((gm - gm_ref).norm()) <= grad_tol * float(gm_ref.norm())


@pytest.mark.parametrize("kernel", KERNELS)
def test_plane_distance_gradcheck_float64(kernel):
    """Full float64 gradcheck of the native output alone and of a loss mixing it with colour."""
    cam = make_camera(16, 12)
    g = random_gaussians(6, kernel, seed=12, camera=cam, dtype=torch.float64, sh_degree=1, scale_range=(0.15, 0.4))
    settings = RasterSettings(sh_degree=1)
    gen = torch.Generator().manual_seed(3)
    w_pl = torch.rand(12, 16, generator=gen, dtype=torch.float64)
    w_rgb = torch.rand(12, 16, 3, generator=gen, dtype=torch.float64)

    def fn(means, quats, scales, opacities, sh):
        gs = RasterGaussians(means, quats, scales, opacities, sh)
        alone = rasterize(gs, cam, kernel=kernel, outputs=("plane_distance",), settings=settings).plane_distance
        out = rasterize(gs, cam, kernel=kernel, outputs=("plane_distance", "rgb"), settings=settings)
        return alone, (out.plane_distance * w_pl).sum() + (out.rgb * w_rgb).sum()

    inputs = tuple(getattr(g, p).clone().requires_grad_(True) for p in PARAMS)
    assert float(fn(*inputs)[0].detach().max()) > 0.1
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-3)


def test_only_requested_outputs():
    cam, g32 = _scene("ewa", n=50, W=32, H=32)
    out = rasterize(g32, cam, kernel="ewa", outputs=("rgb",))
    assert out.rgb is not None and out.alpha is None and out.depth is None and out.distortion is None
    state = out.extras["state"]
    assert state.saved["M1"] is None and state.saved["medi"] is None


def test_errors_name_the_problem():
    cam, g32 = _scene("ewa", n=10, W=16, H=16)
    with pytest.raises(ValueError, match="valid kernels: ewa"):
        rasterize(g32, cam, kernel="nope", outputs=("rgb",))
    with pytest.raises(ValueError, match="valid outputs"):
        rasterize(g32, cam, kernel="ewa", outputs=("rgb", "colour"))




def _integrate_scene(n_cams: int = 3):
    """Cameras (40x30), 150 float64 raymax Gaussians and 2002 points near them, two of them seen by no view."""
    from raster_scenes import look_at_camera  # noqa: PLC0415

    cams = [look_at_camera((0.3 * i, 0.2, -0.5), (0, 0, 3), width=40, height=30) for i in range(n_cams)]
    g = random_gaussians(150, "raymax", seed=0, camera=make_camera(40, 30), dtype=torch.float64, filter3d=1e-4)
    gen = torch.Generator().manual_seed(0)
    pts = g.means[torch.randint(0, 150, (2000,), generator=gen)] + 0.1 * torch.randn(2000, 3, generator=gen, dtype=torch.float64)
    pts = torch.cat([pts, torch.tensor([[0.0, 0.0, -10.0], [50.0, 0.0, 3.0]], dtype=torch.float64)])  # seen by no view
    return cams, g, pts


def test_integrate_matches_reference():
    from gsbench.raster import integrate  # noqa: PLC0415

    cams, g, pts = _integrate_scene()
    ref = reference.integrate_reference(g, cams, pts)
    out = integrate(g, cams, pts)
    assert float((out - ref).abs().max()) < 1e-10
    assert float(out[-1]) == 1.0 and float(out[-2]) == 1.0
    out32 = integrate(_cast(g, torch.float32), cams, pts.float())
    assert float((out32.double() - ref).abs().max()) < 1e-4
    with pytest.raises(NotImplementedError):
        integrate(g, cams, pts, kernel="ewa")


@pytest.mark.parametrize("tile_size", [6, 8])
def test_integrate_cells_exact_for_other_tile_sizes(tile_size):
    """The 4x4 query cells (2x2 when the tile size is not a multiple of 4) never change the result."""
    from gsbench.raster import integrate  # noqa: PLC0415

    cams, g, pts = _integrate_scene(n_cams=5)
    settings = RasterSettings(tile_size=tile_size)
    ref = reference.integrate_reference(g, cams, pts, settings=settings)
    assert float((integrate(g, cams, pts, settings=settings) - ref).abs().max()) < 1e-10


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_opacity_field_below_is_the_exact_sign(dtype):
    """`OpacityField.below` (early exits within and across views) classifies exactly as ``values < level``."""
    from gsbench.raster.opacity_field import OpacityField  # noqa: PLC0415

    cams, g, pts = _integrate_scene(n_cams=5)
    g = _cast(g, dtype)
    field = OpacityField(g, cams)
    O = field.values(pts).double()
    for level in (0.05, 0.3, 0.5, 0.9):
        free = field.below(pts, level)
        assert torch.equal(free, O < level) and 0 < int(free.sum()) < len(pts)

def test_package_integrate_stays_the_function_after_the_field_module_loads():
    """Regression: a submodule named like the package's function used to replace it on import."""
    import gsbench.mesh.tets  # noqa: F401, PLC0415  (imports gsbench.raster.opacity_field)
    import gsbench.raster  # noqa: PLC0415

    assert callable(gsbench.raster.integrate) and gsbench.raster.integrate.__module__ == "gsbench.raster.opacity_field"


@pytest.mark.parametrize("surfel_filter", [0.0, 0.5, 8.0])
def test_surfel_filter_variants_match_reference(surfel_filter):
    """The surfel low-pass k (0 = off) reaches the C++ kernel, its backward and the binning: in float64
    (no float32 depth conditioning, see SURFEL_DEPTH_ATOL) the fast path equals the reference, and
    the image differs from 2DGS's k = 2."""
    settings = RasterSettings(sh_degree=1, surfel_filter=surfel_filter)
    cam, g32 = _scene("surfel", seed=9, n=150, W=48, H=40)
    g64 = _cast(g32, torch.float64)
    gr, gf = with_grad(g64), with_grad(g64)
    ref = reference.render(gr, cam, kernel="surfel", outputs=OUTPUTS, settings=settings)
    out = rasterize(gf, cam, kernel="surfel", outputs=OUTPUTS, settings=settings)
    for o in OUTPUTS:
        diff = float((getattr(out, o).detach() - getattr(ref, o).detach()).abs().max())
        assert diff <= 1e-8, f"surfel_filter={surfel_filter}/{o}: {diff:.3g}"
    assert torch.equal(out.radii, ref.radii)
    w = _weights(out, OUTPUTS)
    _loss(out, w).backward()
    errs = _grad_errors(gf, None, _loss(ref, w), gr)
    assert all(e <= 1e-6 for e in errs.values()), errs
    default = rasterize(g64, cam, kernel="surfel", outputs=("alpha",), settings=RasterSettings(sh_degree=1))
    assert float((default.alpha - out.alpha.detach()).abs().max()) > 1e-3


@pytest.mark.parametrize("kernel", ("ewa", "rade", "surfel"))
@pytest.mark.parametrize("case", ("far_offset", "tiny_flat", "faint", "crossing_near"))
def test_fast_matches_reference_on_hard_geometry(kernel, case):
    """float64 fast path vs the dense reference where the tile and lane culling are at their least accurate: a
    scene kilometres from the origin, tiny flat Gaussians, opacities just above 1/255, splats crossing the near
    plane."""
    cam = make_camera(48, 40)
    opts = dict(kernel=kernel, seed=3)
    if case == "far_offset":
        g = random_gaussians(60, depth_range=(2000.0, 3000.0), scale_range=(20.0, 200.0), **opts)
        settings = RasterSettings(scene_radius=1000.0, far_plane=10.0)
    elif case == "tiny_flat":
        g = random_gaussians(60, scale_range=(1e-4, 0.05), **opts)
        settings = RasterSettings()
    elif case == "faint":
        g = random_gaussians(60, opacity_range=(1.0 / 255.0, 1.2 / 255.0), scale_range=(0.1, 0.6), **opts)
        settings = RasterSettings()
    else:
        g = random_gaussians(40, depth_range=(0.25, 1.0), scale_range=(0.2, 1.5), **opts)
        settings = RasterSettings(near_plane=0.2)
    outs = ("rgb", "alpha", "depth")
    out = rasterize(g, cam, kernel=kernel, outputs=outs, settings=settings)
    ref = reference.render(g, cam, kernel=kernel, outputs=outs, settings=settings)
    for o in outs:
        scale = 1.0 if o != "depth" else float(ref.depth.abs().max()) + 1.0
        assert float((getattr(out, o) - getattr(ref, o)).abs().max()) <= 1e-9 * scale, (kernel, case, o)


@pytest.mark.parametrize("kernel", KERNELS)
def test_the_graph_is_freed_with_the_render(kernel):
    """Dropping a render frees its graph and the compositing state behind it at once, not at Python's next full
    garbage collection, with every output the kernel has: an output kept on an autograd context is a reference
    cycle. The solid depth's was one, and GGGS's training memory grew with every step (docs/methods/gggs.md §7)."""
    cam = make_camera(40, 32)
    g = with_grad(random_gaussians(40, kernel, seed=5))
    outs = OUTPUTS + KERNEL_OUTPUTS.get(kernel, ())
    gc.collect()
    gc.disable()
    try:
        out = rasterize(g, cam, kernel=kernel, outputs=outs, settings=RasterSettings(solid_search_range=1.0))
        state = weakref.ref(out.extras["state"])
        sum((getattr(out, o) * w).sum() for o, w in _weights(out, outs).items()).backward()
        del out
        assert state() is None
    finally:
        gc.enable()
