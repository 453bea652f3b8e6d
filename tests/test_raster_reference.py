"""Tests of the dense reference rasterizer `gsbench.raster.reference` (float64, small scenes)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))

from raster_scenes import concat, make_camera, random_gaussians, single_gaussian, with_grad  # noqa: E402

from gsbench.raster import reference as ref  # noqa: E402
from gsbench.raster import reference_projection as ref_projection  # noqa: E402
from gsbench.raster.types import KERNELS, OUTPUTS, RasterSettings  # noqa: E402

D = torch.float64
PARAMS = ("means", "quats", "scales", "opacities", "sh")


def cov_inv_cam(g, i=0):
    """Σ⁻¹ of Gaussian i for the identity camera, computed independently of the reference."""
    q = g.quats[i].detach() / g.quats[i].detach().norm()
    w, x, y, z = q.tolist()
    R = torch.tensor(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ],
        dtype=D,
    )
    return R @ torch.diag(1 / g.scales[i].detach() ** 2) @ R.T


def render_fn(g, cam, kernel, output, settings):
    """A function of the five parameter tensors returning one output, for gradcheck."""

    def f(means, quats, scales, opacities, sh):
        gg = ref.RasterGaussians(means, quats, scales, opacities, sh, g.filter3d)
        return getattr(ref.render(gg, cam, kernel=kernel, outputs=(output,), settings=settings), output)

    return f


def assert_smooth(g, cam, kernel, settings, margin=1e-4):
    """The render is smooth at ``g``: no pair is near a hard threshold of the compositing rules."""
    out = ref.render(g, cam, kernel=kernel, settings=settings)
    x = out.extras
    cand, blended = x["candidate"], x["blended"]
    a = x["alpha_raw"]
    assert cand.any(), "nothing contributes: the scene is not a useful test"
    assert ((a[cand] - ref.ALPHA_MIN).abs() > margin * ref.ALPHA_MIN).all(), "alpha near 1/255"
    assert (a[cand] < ref.ALPHA_MAX - margin).all(), "alpha near the 0.99 clamp"
    T = x["transmittance"]
    alpha = torch.where(x["valid"], a, torch.zeros_like(a))
    assert ((T * (1 - alpha))[x["valid"]] > ref.T_STOP * 2).all(), "transmittance near the early stop"
    assert ((T[blended] - 0.5).abs() > margin).all(), "transmittance near the median threshold"
    terms = x["terms"]
    order = x["order"]
    if kernel == "surfel":
        gap = (terms["rho3d"] - terms["rho2d"])[:, order]
        assert (gap[cand].abs() > margin).all(), "surfel near the low-pass switch"
        assert ((terms["depth"][:, order][cand] - settings.near).abs() > margin).all()
    if kernel == "raymax":
        assert ((terms["tstar"][:, order][cand] - settings.near).abs() > margin).all()
    proj = ref.project(g, cam, kernel, settings)
    assert (proj.color > margin).all(), "SH colour near the clamp at 0"
    assert out.visible.all()


# ------------------------------------------------------------------------------------------------
# Gradient checks
# ------------------------------------------------------------------------------------------------

GRAD_CAM = make_camera(12, 10, fov_x_deg=50.0)  # one 16x16 tile: no tile-border effects


def grad_scene(kernel, seed=3, sh_degree=1, filter3d=None):
    return random_gaussians(
        6,
        kernel,
        seed,
        D,
        camera=GRAD_CAM,
        depth_range=(2.0, 3.0),
        scale_range=(0.15, 0.35),
        opacity_range=(0.25, 0.6),
        sh_degree=sh_degree,
        spread=0.5,
        filter3d=filter3d,
    )


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("output", OUTPUTS)
def test_gradcheck_every_kernel_and_output(kernel, output):
    settings = RasterSettings(sh_degree=1, background=(0.2, 0.4, 0.6), near_plane=0.5, far_plane=20.0)
    g = grad_scene(kernel)
    assert_smooth(g, GRAD_CAM, kernel, settings)
    wg = with_grad(g)
    inputs = tuple(getattr(wg, p) for p in PARAMS)
    assert torch.autograd.gradcheck(render_fn(g, GRAD_CAM, kernel, output, settings), inputs, fast_mode=True)


@pytest.mark.parametrize("kernel", KERNELS)
def test_gradcheck_filters_sh3_all_outputs(kernel):
    """Mip 3D filter + 2D antialias + SH degree 3, all outputs at once (tiny 4x3 image)."""
    cam = make_camera(4, 3, fov_x_deg=40.0)
    settings = RasterSettings(sh_degree=3, background=(0.3, 0.3, 0.3), antialias2d=0.2, eps2d=0.1)
    g = random_gaussians(3, kernel, 11, D, camera=cam, depth_range=(2.0, 3.0), scale_range=(0.1, 0.3),
                         opacity_range=(0.3, 0.5), sh_degree=3, spread=0.4, filter3d=0.002)
    g.sh = 0.5 * g.sh  # keep the SH colour away from its clamp at 0
    assert_smooth(g, cam, kernel, settings)
    wg = with_grad(g)

    def f(*params):
        gg = ref.RasterGaussians(*params, g.filter3d)
        out = ref.render(gg, cam, kernel=kernel, settings=settings)
        return tuple(getattr(out, o) for o in OUTPUTS)

    assert torch.autograd.gradcheck(f, tuple(getattr(wg, p) for p in PARAMS), fast_mode=True)


def test_detached_distortion_weights():
    """With detached weights the ewa distortion (z = μz) has no gradient w.r.t. opacity (docs/methods/gof.md §3.5)."""
    g = with_grad(grad_scene("ewa"))
    for detach, expect_zero in ((True, True), (False, False)):
        settings = RasterSettings(detach_distortion_weights=detach, far_plane=20.0)
        out = ref.render(g, GRAD_CAM, kernel="ewa", outputs=("distortion",), settings=settings)
        (gop,) = torch.autograd.grad(out.distortion.sum(), g.opacities, allow_unused=True)
        assert (gop is None or gop.abs().max() == 0) == expect_zero


# ------------------------------------------------------------------------------------------------
# Analytic checks
# ------------------------------------------------------------------------------------------------


def test_flat_surfel_depth_and_normal():
    cam = make_camera(16, 16)
    # Facing the camera: plane z = 3.
    g = single_gaussian((0.1, -0.05, 3.0), kernel="surfel", scales=(0.6, 0.6), opacity=0.9)
    out = ref.render(g, cam, kernel="surfel", settings=RasterSettings())
    hit = out.alpha > 0.05
    assert hit.sum() > 20
    torch.testing.assert_close(out.depth[hit], torch.full_like(out.depth[hit], 3.0))
    n = out.normal[hit] / out.alpha[hit][:, None]
    torch.testing.assert_close(n, torch.tensor([0.0, 0.0, -1.0], dtype=D).expand_as(n))
    # Tilted by 30° about x: depth = (n·μ)/(n·r) along each pixel ray.
    ang = math.radians(30.0)
    quat = (math.cos(ang / 2), math.sin(ang / 2), 0.0, 0.0)
    g = single_gaussian((0.0, 0.0, 3.0), kernel="surfel", quat=quat, scales=(0.5, 0.5), opacity=0.9)
    out = ref.render(g, cam, kernel="surfel", settings=RasterSettings())
    nrm = torch.tensor([0.0, -math.sin(ang), math.cos(ang)], dtype=D)
    jj, ii = torch.meshgrid(torch.arange(16), torch.arange(16), indexing="ij")
    rays = ref.pixel_rays(torch.stack([ii.reshape(-1), jj.reshape(-1)], -1).to(D) + 0.5, cam).reshape(16, 16, 3)
    expected = (nrm @ torch.tensor([0.0, 0.0, 3.0], dtype=D)) / (rays @ nrm)
    hit = out.alpha > 0.05
    torch.testing.assert_close(out.depth[hit], expected[hit])
    torch.testing.assert_close(out.median_depth[hit], expected[hit])
    n = out.normal[hit] / out.alpha[hit][:, None]
    torch.testing.assert_close(n, (-nrm).expand_as(n))  # faces the camera


@pytest.mark.parametrize("kernel", ["raymax", "rade"])
def test_gof_rade_normal_at_centre_ray(kernel):
    cam = make_camera(16, 16)
    g = random_gaussians(5, kernel, 7, D, camera=cam)
    proj = ref.project(g, cam, kernel, RasterSettings())
    terms = ref.pair_terms(proj, proj.means2d.detach(), cam, RasterSettings())
    for i in range(5):
        expected = -torch.nn.functional.normalize(cov_inv_cam(g, i) @ g.means[i], dim=0)
        n = terms["normal"][i, i] if kernel == "raymax" else terms["normal"][i]
        torch.testing.assert_close(n, expected)
        assert float(n @ g.means[i]) < 0  # faces the camera


def test_ewa_normal_is_shortest_axis_facing_camera():
    ang = math.radians(20.0)
    g = single_gaussian((0.2, 0.1, 3.0), quat=(math.cos(ang / 2), 0.0, math.sin(ang / 2), 0.0), scales=(0.3, 0.2, 0.01))
    proj = ref.project(g, make_camera(), "ewa", RasterSettings())
    axis = torch.tensor([math.sin(ang), 0.0, math.cos(ang)], dtype=D)  # R e_z
    torch.testing.assert_close(proj.normal[0], -axis)


@pytest.mark.parametrize("kernel", KERNELS)
def test_single_opaque_gaussian_colour_and_depth(kernel):
    """At its centre pixel: rgb = 0.99·c + 0.01·bg, expected depth = median depth = μz."""
    cam = make_camera(16, 16, cx=7.3, cy=8.9)
    i, j, z = 4, 11, 2.5
    mean = ((i + 0.5 - cam.cx) / cam.fx * z, (j + 0.5 - cam.cy) / cam.fy * z, z)
    rgb, bg = (0.8, 0.3, 0.1), (0.2, 0.5, 1.0)
    g = single_gaussian(mean, kernel=kernel, scales=(0.2, 0.15, 0.1), opacity=1.0, rgb=rgb)
    out = ref.render(g, cam, kernel=kernel, settings=RasterSettings(background=bg))
    expected = 0.99 * torch.tensor(rgb, dtype=D) + 0.01 * torch.tensor(bg, dtype=D)
    torch.testing.assert_close(out.rgb[j, i], expected)
    torch.testing.assert_close(out.depth[j, i], torch.tensor(z, dtype=D))
    torch.testing.assert_close(out.median_depth[j, i], torch.tensor(z, dtype=D))
    if kernel == "ewa":  # z_i = μz at every pixel
        covered = out.alpha > 0
        torch.testing.assert_close(out.depth[covered], torch.full_like(out.depth[covered], z))


@pytest.mark.parametrize("kernel", KERNELS)
def test_pixel_centre_convention(kernel):
    """A Gaussian centred exactly at (i + 0.5, j + 0.5) peaks at pixel (i, j); means2d is that point."""
    cam = make_camera(17, 13, cx=8.0, cy=6.0)
    i, j, z = 11, 3, 3.0
    mean = ((i + 0.5 - cam.cx) / cam.fx * z, (j + 0.5 - cam.cy) / cam.fy * z, z)
    g = single_gaussian(mean, kernel=kernel, scales=(0.12, 0.12, 0.12), opacity=0.8)
    out = ref.render(g, cam, kernel=kernel, outputs=("alpha",), settings=RasterSettings())
    assert divmod(int(out.alpha.argmax()), 17) == (j, i)
    # The kernel is exactly 1 at that pixel, so α = o.
    torch.testing.assert_close(out.alpha[j, i], torch.tensor(0.8, dtype=D))
    if kernel != "surfel":
        torch.testing.assert_close(out.means2d[0], torch.tensor([i + 0.5, j + 0.5], dtype=D))


def test_surfel_means2d_is_box_centre():
    """docs/methods/2dgs.md §3.3: means2d is the centre of the 3σ screen box (not the projected centre when tilted)."""
    cam = make_camera(32, 32)
    ang = math.radians(60.0)
    g = single_gaussian((0.3, 0.2, 2.0), kernel="surfel", quat=(math.cos(ang / 2), math.sin(ang / 2), 0.0, 0.0), scales=(0.3, 0.3))
    proj = ref.project(g, cam, "surfel", RasterSettings())
    # Sample the 3σ ellipse boundary and project it.
    th = torch.linspace(0, 2 * math.pi, 20001, dtype=D)
    R = ref_projection.quat_to_rotmat(g.quats)[0]
    pts = g.means[0] + 3 * 0.3 * (torch.cos(th)[:, None] * R[:, 0] + torch.sin(th)[:, None] * R[:, 1])
    uv = torch.stack([cam.fx * pts[:, 0] / pts[:, 2] + cam.cx, cam.fy * pts[:, 1] / pts[:, 2] + cam.cy], -1)
    box_centre = 0.5 * (uv.min(0).values + uv.max(0).values)
    torch.testing.assert_close(proj.means2d[0], box_centre, atol=1e-4, rtol=0)
    half = 0.5 * (uv.max(0).values - uv.min(0).values)
    assert int(proj.radii[0]) == math.ceil(float(half.max()) - 1e-6)
    projected = torch.tensor([cam.fx * 0.3 / 2 + cam.cx, cam.fy * 0.2 / 2 + cam.cy], dtype=D)
    assert (proj.means2d[0] - projected).abs().max() > 0.1


def test_rade_plane_closed_form_agrees():
    cam = make_camera(16, 16)
    g = random_gaussians(20, "rade", 5, D, camera=cam, spread=0.9)
    proj = ref.project(g, cam, "rade", RasterSettings())
    torch.testing.assert_close(proj.rade_p, ref_projection.rade_plane_closed_form(proj.mu, proj.cov_inv), rtol=1e-9, atol=1e-12)


def test_rade_depth_matches_gof_tstar_to_first_order():
    """RaDe z = t/‖r‖ and GOF t* agree at the centre and differ by O(δ²) off it (docs/methods/radegs.md §3.3)."""
    cam = make_camera(32, 32)
    settings = RasterSettings()
    g = random_gaussians(4, "rade", 2, D, camera=cam, scale_range=(0.1, 0.4))
    pr, pg = ref.project(g, cam, "rade", settings), ref.project(g, cam, "raymax", settings)
    direction = torch.tensor([0.6, -0.8], dtype=D)
    errs = []
    for h in (0.0, 0.5, 0.25, 0.125):
        pix = pr.means2d.detach() + h * direction
        zr = torch.diagonal(ref.pair_terms(pr, pix, cam, settings)["depth"])
        zg = torch.diagonal(ref.pair_terms(pg, pix, cam, settings)["depth"])
        errs.append((zr - zg).abs())
        if h > 0:  # the first-order term itself is not trivially zero
            assert (zg - g.means[:, 2]).abs().max() > 10 * errs[-1].max()
    torch.testing.assert_close(errs[0], torch.zeros_like(errs[0]), atol=1e-12, rtol=0)
    ratio1, ratio2 = errs[1] / errs[2], errs[2] / errs[3]
    assert ((ratio1 > 3.0) & (ratio1 < 5.0) & (ratio2 > 3.0) & (ratio2 < 5.0)).all(), (ratio1, ratio2)


def test_sh_basis_orthonormal():
    """Real SH of degree ≤ 3 with the 3DGS constants are orthonormal on the sphere (docs/methods/3dgs.md §2.4)."""
    n = 20000
    k = torch.arange(n, dtype=D) + 0.5
    zc = 1 - 2 * k / n
    phi = math.pi * (1 + 5**0.5) * k
    dirs = torch.stack([torch.sqrt(1 - zc**2) * torch.cos(phi), torch.sqrt(1 - zc**2) * torch.sin(phi), zc], -1)
    basis = torch.stack([ref_projection.eval_sh(torch.eye(16, dtype=D)[b].reshape(1, 16, 1).expand(n, 16, 3), dirs, 3)[:, 0] for b in range(16)], 1)
    gram = 4 * math.pi * basis.T @ basis / n
    torch.testing.assert_close(gram, torch.eye(16, dtype=D), atol=2e-3, rtol=0)
    # Sign convention: degree-1 terms are (−C1 y, C1 z, −C1 x).
    d = torch.tensor([[0.6, 0.0, 0.8]], dtype=D)
    sh = torch.zeros(1, 4, 3, dtype=D)
    sh[0, 3] = 1.0
    torch.testing.assert_close(ref_projection.eval_sh(sh, d, 1), torch.full((1, 3), -ref_projection.SH_C1 * 0.6, dtype=D))


def test_filter3d_scales_and_opacity():
    g = single_gaussian((0.0, 0.0, 3.0), scales=(0.1, 0.2, 0.3), opacity=0.5)
    g.filter3d = torch.tensor([0.01], dtype=D)
    proj = ref.project(g, make_camera(), "raymax", RasterSettings())
    s2 = torch.tensor([0.01, 0.04, 0.09], dtype=D)
    torch.testing.assert_close(proj.opacity[0], 0.5 * torch.sqrt(torch.prod(s2 / (s2 + 0.01))))
    torch.testing.assert_close(torch.diagonal(proj.cov_inv[0]), 1 / (s2 + 0.01))


def test_early_stop_and_median():
    """α = 0.95 ×4 at pixel (4, 4): T = 1, .05, .0025, 1.25e-4; T(1−α4) < 1e-4 → the 4th is not blended."""
    cam = make_camera(8, 8, cx=4.5, cy=4.5)  # the optical axis passes through the centre of pixel (4, 4)
    gs = [single_gaussian((0.0, 0.0, 2.0 + 0.1 * k), scales=(0.3, 0.3, 0.3), opacity=0.95, rgb=(0.1 * k, 0.5, 0.5)) for k in range(4)]
    out = ref.render(concat(*gs), cam, kernel="ewa", settings=RasterSettings())
    pix = 4 * 8 + 4
    assert out.extras["blended"][pix].tolist() == [True, True, True, False]
    assert out.extras["valid"][pix].tolist() == [True, True, True, True]
    torch.testing.assert_close(out.alpha[4, 4], torch.tensor(1 - 0.05**3, dtype=D))
    expected_rgb = sum(0.95 * 0.05**k * torch.tensor([0.1 * k, 0.5, 0.5], dtype=D) for k in range(3))
    torch.testing.assert_close(out.rgb[4, 4], expected_rgb)
    # Median: T before the 2nd is 0.05 < 0.5 → the first Gaussian.
    assert float(out.median_depth[4, 4]) == 2.0
    # With α = 0.3 then 0.4 the median is the second Gaussian (T before it = 0.7 > 0.5).
    g2 = concat(single_gaussian((0.0, 0.0, 2.0), opacity=0.3, scales=(0.5, 0.5, 0.5)),
                single_gaussian((0.0, 0.0, 3.0), opacity=0.4, scales=(0.5, 0.5, 0.5)))
    out2 = ref.render(g2, cam, kernel="ewa", settings=RasterSettings())
    assert float(out2.median_depth[4, 4]) == 3.0


def test_distortion_two_gaussians():
    cam = make_camera(8, 8)
    settings = RasterSettings(near_plane=0.2, far_plane=100.0)
    g = concat(single_gaussian((0.0, 0.0, 2.0), opacity=0.5, scales=(0.5, 0.5, 0.5)),
               single_gaussian((0.0, 0.0, 4.0), opacity=0.5, scales=(0.5, 0.5, 0.5)))
    out = ref.render(g, cam, kernel="ewa", settings=settings)
    a = out.extras["alpha_raw"][4 * 8 + 4]
    w1, w2 = a[0], a[1] * (1 - a[0])
    m = lambda z: 100 / (100 - 0.2) * (1 - 0.2 / z)  # noqa: E731
    torch.testing.assert_close(out.distortion[4, 4], w1 * w2 * (m(4.0) - m(2.0)) ** 2)


def test_tile_rectangle_cuts_contributions():
    """A pixel outside the Gaussian's tile rectangle gets nothing even where o·G > 1/255 (Decision 2)."""
    cam = make_camera(32, 16)
    z = 3.0
    mean = ((9.9 - cam.cx) / cam.fx * z, (8.0 - cam.cy) / cam.fy * z, z)
    sigma_px = 2.0
    g = single_gaussian(mean, scales=(sigma_px * z / cam.fx,) * 3, opacity=0.99)
    settings = RasterSettings()
    out = ref.render(g, cam, kernel="ewa", settings=settings)
    assert out.radii.item() == 7 and out.extras["candidate"][7 * 32 + 16, 0].item() is False
    pix = 7 * 32 + 16  # pixel (16, 7), first pixel of tile 1, 6.6 px from the centre
    assert float(out.extras["alpha_raw"][pix, 0]) > ref.ALPHA_MIN
    assert float(out.alpha[7, 16]) == 0.0 and float(out.alpha[7, 15]) > 0.0


# ------------------------------------------------------------------------------------------------
# Hard cases
# ------------------------------------------------------------------------------------------------


def hard_scene(kernel, dtype):
    ncols = 2 if kernel == "surfel" else 3
    s = lambda v: (v,) * 3  # noqa: E731
    edge_on = (0.5, 0.5, 0.5, 0.5)  # exactly R e_z = (1, 0, 0), tangents (0, 1, 0), (0, 0, 1): ⟂ μ = (0, 0, 3)
    parts = [
        single_gaussian((0.0, 0.0, -1.0), kernel=kernel, dtype=dtype),  # behind the camera
        single_gaussian((0.1, 0.0, 0.0), kernel=kernel, dtype=dtype),  # at the camera plane
        single_gaussian((0.0, 0.1, 0.25), kernel=kernel, scales=s(1.0), dtype=dtype),  # straddles the near plane
        single_gaussian((0.2, 0.0, 2.0), kernel=kernel, scales=s(1e-8), dtype=dtype),  # tiny
        single_gaussian((0.0, 0.0, 5.0), kernel=kernel, scales=s(1e4), opacity=0.3, dtype=dtype),  # huge
        single_gaussian((-0.2, 0.1, 2.0), kernel=kernel, opacity=0.0, dtype=dtype),  # transparent
        single_gaussian((0.0, 0.0, 3.0), kernel=kernel, quat=edge_on, scales=(0.5, 0.5, 0.5), dtype=dtype),  # edge-on
        single_gaussian((1e-6, 0.05, 3.0), kernel=kernel, quat=edge_on, scales=(0.5, 0.5, 1e-8), dtype=dtype),  # nearly edge-on
        random_gaussians(4, kernel, 1, dtype),
    ]
    g = concat(*parts)
    g.scales = g.scales[:, :ncols]
    return g


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("size", [(1, 1), (17, 13)])
@pytest.mark.parametrize("kernel", KERNELS)
def test_hard_cases_finite(kernel, size, dtype):
    cam = make_camera(*size)
    g = with_grad(hard_scene(kernel, dtype))
    settings = RasterSettings(background=(0.1, 0.2, 0.3))
    out = ref.render(g, cam, kernel=kernel, settings=settings)
    loss = 0
    for name in OUTPUTS:
        value = getattr(out, name)
        assert torch.isfinite(value).all(), name
        loss = loss + value.sum()
    loss.backward()
    for p in PARAMS:
        assert torch.isfinite(getattr(g, p).grad).all(), p
    assert not out.visible[[0, 1]].any()  # behind / at the camera are culled
    if kernel == "surfel":
        assert not out.visible[6]  # exactly edge-on is culled
    _, absgrad = out.densify_grads()
    assert torch.isfinite(absgrad).all()


@pytest.mark.parametrize("kernel", KERNELS)
def test_nothing_visible_gives_background(kernel):
    cam = make_camera(17, 13)
    g = with_grad(concat(single_gaussian((0.0, 0.0, -2.0), kernel=kernel), single_gaussian((0.0, 0.0, 0.1), kernel=kernel)))
    bg = (0.1, 0.2, 0.3)
    out = ref.render(g, cam, kernel=kernel, settings=RasterSettings(background=bg))
    torch.testing.assert_close(out.rgb, torch.tensor(bg, dtype=D).expand(13, 17, 3))
    for name in ("alpha", "depth", "median_depth", "normal", "distortion"):
        assert (getattr(out, name) == 0).all()
    sum(getattr(out, o).sum() for o in OUTPUTS).backward()
    for p in PARAMS:
        grad = getattr(g, p).grad
        assert grad is None or (grad == 0).all()
    assert not out.visible.any() and (out.radii == 0).all()


def test_outputs_not_requested_are_none():
    out = ref.render(random_gaussians(3), make_camera(), kernel="ewa", outputs=("depth",))
    assert out.depth is not None and out.rgb is None and out.normal is None
    with pytest.raises(ValueError):
        ref.render(random_gaussians(3), make_camera(), kernel="ewa", outputs=("colour",))


def test_means2d_grad_and_absgrad():
    cam = make_camera(17, 13)
    g = with_grad(random_gaussians(5, "ewa", 4, camera=cam))
    out = ref.render(g, cam, kernel="ewa", outputs=("rgb",))
    out.rgb.sum().backward()
    grad, absgrad = out.densify_grads()
    ndc = torch.tensor([17 / 2, 13 / 2], dtype=D)
    torch.testing.assert_close(grad, out.means2d.grad * ndc)
    assert (absgrad >= grad.abs().sum(-1) - 1e-12).all() and (absgrad > 0).all()


# ------------------------------------------------------------------------------------------------
# GOF opacity field
# ------------------------------------------------------------------------------------------------


def test_integrate_reference_single_gaussian():
    cam = make_camera(16, 16)
    g = single_gaussian((0.1, -0.1, 3.0), scales=(0.2, 0.3, 0.25), opacity=0.8)
    mu = g.means[0]
    A = cov_inv_cam(g)
    pts = torch.stack([mu, mu * 2.0, mu * 0.9, torch.tensor([50.0, 0.0, 3.0], dtype=D)])
    O = ref.integrate_reference(g, [cam], pts, "raymax", RasterSettings())
    # On the centre ray: at or behind the maximum → the peak α = o; in front → o·exp(−q(z)/2).
    e = mu - 0.9 * mu
    torch.testing.assert_close(O[:3], torch.stack([torch.tensor(0.8, dtype=D), torch.tensor(0.8, dtype=D), 0.8 * torch.exp(-0.5 * e @ A @ e)]))
    assert float(O[3]) == 1.0  # projects outside the image: unchanged
    # Min over views: from a camera 2 units to the side, the ray to 2μ passes 1 unit from the Gaussian
    # (α < 1/255 → 0), so the point behind the Gaussian (0.8 in the first view) gets 0.
    cam2 = make_camera(16, 16, t=np.array([-2.0, 0.0, 0.0]))
    O2 = ref.integrate_reference(g, [cam, cam2], pts[1:2], "raymax", RasterSettings())
    assert float(O2[0]) == 0.0
    with pytest.raises(NotImplementedError):
        ref.integrate_reference(g, [cam], pts, "ewa", RasterSettings())


def test_integrate_consistent_with_rendered_alpha():
    """A point far behind everything on a pixel's centre ray sees 1 − Π(1 − α) of that pixel when nothing stops early."""
    cam = make_camera(16, 16)
    g = random_gaussians(5, "raymax", 9, D, camera=cam, opacity_range=(0.2, 0.4))
    out = ref.render(g, cam, kernel="raymax", outputs=("alpha",), settings=RasterSettings())
    i, j = 7, 9
    r = ref.pixel_rays(torch.tensor([[i + 0.5, j + 0.5]], dtype=D), cam)[0]
    O = ref.integrate_reference(g, [cam], (50.0 * r)[None], "raymax", RasterSettings())
    torch.testing.assert_close(O[0], out.alpha[j, i])


@pytest.mark.parametrize("surfel_filter", [0.0, 0.5, 8.0])
def test_gradcheck_surfel_filter_variants(surfel_filter):
    """The surfel low-pass filter switched off (k = 0), wider (0.5) and narrower (8) than 2DGS's k = 2."""
    settings = RasterSettings(sh_degree=1, background=(0.2, 0.4, 0.6), near_plane=0.5, far_plane=20.0,
                              surfel_filter=surfel_filter)
    g = grad_scene("surfel")
    assert_smooth(g, GRAD_CAM, "surfel", settings)
    wg = with_grad(g)
    inputs = tuple(getattr(wg, p) for p in PARAMS)
    for output in ("rgb", "depth"):
        assert torch.autograd.gradcheck(render_fn(g, GRAD_CAM, "surfel", output, settings), inputs, fast_mode=True)
