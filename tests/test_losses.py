"""Loss-term registry, built-in terms and SSIM (gsbench.losses.terms, gsbench.losses.ssim)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import ndimage

from gsbench.config.files import config_root
from gsbench.errors import ConfigError
from gsbench.geometry.depth import depth_to_normal, pixel_rays
from gsbench.losses import terms as losses
from gsbench.losses.ssim import C1, C2, gaussian_window, ssim, ssim_map
from gsbench.losses.terms import Batch, active_terms, get_term, required_outputs, total_loss
from gsbench.raster.reference import render
from gsbench.raster.types import RasterSettings, RenderOutput
from gsbench.registry import LOSS_TERMS
from gsbench.training.gaussians import Gaussians
from tests.raster_scenes import make_camera, random_gaussians

# ---- SSIM -----------------------------------------------------------------------------------------


def numpy_ssim_map(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Independent SSIM: scipy correlate with zero ('constant') padding, per channel."""
    w = gaussian_window(dtype=torch.float64).numpy()

    def blur(x):
        return np.stack([ndimage.correlate(x[..., c], w, mode="constant", cval=0.0) for c in range(x.shape[-1])], -1)

    mx, my = blur(a), blur(b)
    vx, vy, cxy = blur(a * a) - mx**2, blur(b * b) - my**2, blur(a * b) - mx * my
    return ((2 * mx * my + C1) * (2 * cxy + C2)) / ((mx**2 + my**2 + C1) * (vx + vy + C2))


def test_ssim_identical_is_one_and_matches_scipy():
    rng = np.random.default_rng(0)
    a = rng.uniform(size=(23, 31, 3))
    b = np.clip(a + rng.normal(0, 0.1, size=a.shape), 0, 1)
    ta, tb = torch.from_numpy(a), torch.from_numpy(b)
    assert float(ssim(ta, ta)) == pytest.approx(1.0, abs=1e-12)
    got = ssim_map(ta, tb).numpy()
    assert got.shape == a.shape
    np.testing.assert_allclose(got, numpy_ssim_map(a, b), atol=1e-10)
    assert float(ssim(ta, tb)) == pytest.approx(numpy_ssim_map(a, b).mean(), abs=1e-10)


def test_ssim_mask_and_gradient():
    a = torch.rand(12, 14, 3, dtype=torch.float64, requires_grad=True)
    b = torch.rand(12, 14, 3, dtype=torch.float64)
    empty = torch.zeros(12, 14, dtype=torch.bool)
    assert float(ssim(a, b, empty).detach()) == 1.0
    full = torch.ones(12, 14, dtype=torch.bool)
    assert float(ssim(a, b, full).detach()) == pytest.approx(float(ssim(a, b).detach()), abs=1e-12)
    (1 - ssim(a, b)).backward()
    assert torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0


# ---- registry -------------------------------------------------------------------------------------


def test_unknown_term_and_parameter_fail_with_suggestion():
    with pytest.raises(ConfigError, match="did you mean 'dssim'"):
        active_terms({"dsim": {"weight": 0.2}}, 0)
    with pytest.raises(ConfigError, match="did you mean 'depth_ratio'"):
        active_terms({"normal_consistency": {"weight": 0.0}}, 0, params={"normal_consistency": {"depth_rato": 1.0}})
    with pytest.raises(ConfigError, match="not in the loss config"):
        active_terms({"l1": {"weight": 1.0}}, 0, params={"dssim": {}})
    with pytest.raises(ConfigError, match="in \\[0, 1\\]"):
        active_terms({"normal_consistency": {"weight": 1.0}}, 0, params={"normal_consistency": {"depth_ratio": 2}})


def test_weight_zero_drops_term_and_outputs():
    cfg = {"l1": {"weight": 0.8}, "dssim": {"weight": 0.2}, "depth_distortion": {"weight": 0.0},
           "normal_consistency": {"weight": 0.05}}
    active = active_terms(cfg, 10)
    assert [t.name for t in active] == ["l1", "dssim", "normal_consistency"]
    assert required_outputs(active) == {"rgb", "normal", "alpha", "median_depth"}
    cfg["normal_consistency"]["weight"] = 0.0
    assert required_outputs(active_terms(cfg, 10)) == {"rgb"}


def test_start_end_schedule():
    cfg = {"l1": {"weight": 1.0}, "opacity_entropy": {"weight": 0.1, "start": 7001, "end": 9000},
           "normal_consistency": {"weight": 0.05, "start": 7001, "end": -1}}

    def names(step):
        return [t.name for t in active_terms(cfg, step)]

    assert names(7000) == ["l1"]
    assert names(7001) == ["l1", "opacity_entropy", "normal_consistency"]
    assert names(8999) == ["l1", "opacity_entropy", "normal_consistency"]
    assert names(9000) == ["l1", "normal_consistency"]
    assert names(10**9) == ["l1", "normal_consistency"]


def test_params_change_requires():
    for ratio, depth in ((0.0, {"depth"}), (1.0, {"median_depth"}), (0.5, {"depth", "median_depth"})):
        active = active_terms({"normal_consistency": {"weight": 1.0}}, 0,
                              params={"normal_consistency": {"depth_ratio": ratio}})
        assert active[0].spec.requires == {"normal", "alpha"} | depth


def test_terms_are_registered_like_methods(monkeypatch):
    """A term is a `TermSpec` in `gsbench.registry.LOSS_TERMS`: declared in configs/loss_terms/<name>.yaml (every
    built-in, listed without importing it) or added at run time; a registered object that is no TermSpec of that
    name is an error naming it."""
    declared = {path.stem for path in (config_root() / "loss_terms").glob("*.yaml")}
    assert declared == set(LOSS_TERMS.names()) and {"l1", "eigval", "neus_rgb", "normal_smoothness"} <= declared
    assert LOSS_TERMS.path("pgsr_ncc") == "gsbench.methods.pgsr_terms:PGSR_NCC"
    monkeypatch.setattr(LOSS_TERMS, "_entries", dict(LOSS_TERMS._entries))  # registrations below end with the test
    LOSS_TERMS.register("mine", losses.loss_term("mine", lambda r, b, s: torch.tensor(2.0)))
    active = active_terms({"mine": {"weight": 3.0}}, 0)
    total, values = total_loss(active, RenderOutput(), None, {})
    assert float(total) == 6.0 and values == {"mine": 2.0}
    with pytest.raises(ConfigError, match="unknown render outputs"):
        losses.loss_term("bad", losses.l1_term, {"rgbd"})
    LOSS_TERMS.register("misnamed", losses.L1)
    with pytest.raises(ConfigError, match="not a TermSpec named 'misnamed'"):
        get_term("misnamed")
    assert get_term("l1").requires == {"rgb"}


def test_a_methods_term_under_another_method_names_the_fix():
    """A term that reads its method's state (NeuSG's SDF, RT2DGS's neighbours, SuGaR's refinement) fails clearly
    when another method's loss config lists it."""
    for name in ("neus_rgb", "eikonal", "sdf_points", "sdf_align", "normal_smoothness", "mesh_normal_consistency"):
        with pytest.raises(ConfigError, match=f"remove losses.{name} for this method"):
            get_term(name)(RenderOutput(), None, {"gaussians": None})


def test_no_active_term_is_zero():
    total, values = total_loss([], RenderOutput(), None, {})
    assert float(total) == 0.0 and values == {}


# ---- built-in terms: ~0 on consistent input, > 0 on inconsistent, finite gradients -----------------


def plane_render(W=20, H=16, z=2.0, tilt=0.0, normal_error=0.0, alpha=1.0):
    """A render of a plane z = z0 + tilt·x (camera space), with its exact (or perturbed) normal."""
    cam = make_camera(W, H)
    rays = pixel_rays(cam, torch.float64)
    # plane n·X = d with n ∝ (tilt, 0, -1): X = t·ray, t = z0 / (1 - tilt·ray_x) gives camera z.
    depth = z / (1.0 - tilt * rays[..., 0])
    n = torch.tensor([tilt, 0.0, -1.0], dtype=torch.float64)
    n = n / n.norm()
    rot = torch.tensor([[math.cos(normal_error), 0, math.sin(normal_error)], [0, 1, 0],
                        [-math.sin(normal_error), 0, math.cos(normal_error)]], dtype=torch.float64)
    normal = (rot @ n).expand(H, W, 3).clone() * alpha
    out = RenderOutput(rgb=torch.rand(H, W, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)),
                       alpha=torch.full((H, W), alpha, dtype=torch.float64), depth=depth.clone(),
                       median_depth=depth.clone(), normal=normal, distortion=torch.zeros(H, W, dtype=torch.float64),
                       width=W, height=H)
    return out, cam


def test_depth_to_normal_of_a_tilted_plane_faces_the_camera():
    out, cam = plane_render(tilt=0.3)
    n = depth_to_normal(out.depth, cam)
    expected = torch.tensor([0.3, 0.0, -1.0], dtype=torch.float64)
    expected = expected / expected.norm()
    torch.testing.assert_close(n[1:-1, 1:-1], expected.expand(14, 18, 3), atol=1e-10, rtol=0)
    assert (n[0] == 0).all() and (n[:, -1] == 0).all()


def test_image_terms_zero_when_consistent_positive_otherwise():
    out, cam = plane_render()
    good = Batch(image=out.rgb.clone(), mask=None, camera=cam, step=0)
    bad = Batch(image=torch.clamp(out.rgb + 0.2, 0, 1), mask=None, camera=cam, step=0)
    for name in ("l1", "dssim"):
        spec = get_term(name)
        assert abs(float(spec(out, good, {}))) < 1e-12
        assert float(spec(out, bad, {})) > 1e-3


def test_masked_image_terms_ignore_outside_and_survive_empty_mask():
    out, cam = plane_render()
    image = out.rgb.clone()
    image[:, :10] = 1 - image[:, :10]
    mask = torch.zeros(16, 20, dtype=torch.bool)
    mask[:, 10:] = True
    l1 = get_term("l1").bind(use_mask=True)
    assert float(l1(out, Batch(image, mask, cam, 0), {})) == pytest.approx(0.0, abs=1e-12)
    empty = Batch(image, torch.zeros_like(mask), cam, 0)
    for name in ("l1", "dssim"):
        value = get_term(name).bind(use_mask=True)(out, empty, {})
        assert float(value) == 0.0


def test_normal_consistency_zero_when_consistent_positive_otherwise():
    W, H = 20, 16
    border = 1 - (W - 2) * (H - 2) / (W * H)  # 2DGS: the zero-normal border contributes 1 per pixel
    for ratio in (0.0, 1.0, 0.5):
        spec = get_term("normal_consistency").bind(depth_ratio=ratio)
        out, cam = plane_render(W, H, tilt=0.3)
        batch = Batch(out.rgb, None, cam, 0)
        assert float(spec(out, batch, {})) == pytest.approx(border, abs=1e-10)
        out_bad, _ = plane_render(W, H, tilt=0.3, normal_error=0.5)
        assert float(spec(out_bad, batch, {})) > border + 0.05
    # background (alpha 0) counts as 1 everywhere, without NaN
    out0, cam = plane_render(W, H, alpha=0.0)
    out0.depth.zero_()
    out0.median_depth.zero_()
    assert float(get_term("normal_consistency")(out0, Batch(out0.rgb, None, cam, 0), {})) == 1.0


def test_depth_distortion_term():
    out, cam = plane_render()
    spec = get_term("depth_distortion")
    assert float(spec(out, Batch(out.rgb, None, cam, 0), {})) == 0.0
    out.distortion[3, 4] = 0.5
    assert float(spec(out, Batch(out.rgb, None, cam, 0), {})) == pytest.approx(0.5 / (16 * 20))


def make_gaussians(log_scales, opacity_logits):
    n = len(log_scales)
    return Gaussians(means=torch.zeros(n, 3), log_scales=torch.as_tensor(log_scales, dtype=torch.float32),
                     quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                     opacity_logits=torch.as_tensor(opacity_logits, dtype=torch.float32),
                     sh_dc=torch.zeros(n, 1, 3), sh_rest=torch.zeros(n, 0, 3), max_sh_degree=0)


@torch.no_grad()
def test_flatten_and_entropy_terms():
    flat = make_gaussians([[0.0, 0.0, -30.0], [0.0, -1.0, -30.0]], [20.0, -20.0])
    thick = make_gaussians([[0.0, 0.0, 0.0], [0.0, -1.0, -0.5]], [0.0, 0.5])
    out = RenderOutput(visible=torch.tensor([True, True]))
    for name in ("flatten", "opacity_entropy"):
        spec = get_term(name)
        assert float(spec(out, None, {"gaussians": flat})) < 1e-6
        assert float(spec(out, None, {"gaussians": thick})) > 0.1
    with pytest.raises(ConfigError, match="state\\['gaussians'\\]"):
        get_term("flatten")(out, None, {})
    # entropy only over visible Gaussians; nothing visible gives 0
    none_visible = RenderOutput(visible=torch.tensor([False, False]))
    assert float(get_term("opacity_entropy")(none_visible, None, {"gaussians": thick})) == 0.0
    assert float(get_term("opacity_entropy")(RenderOutput(visible=torch.tensor([True, False])), None,
                                             {"gaussians": thick})) == pytest.approx(math.log(2), abs=1e-6)


def test_total_loss_gradients_finite_through_reference_render():
    """Every built-in term on a real (reference) surfel render: finite value and finite gradients."""
    cam = make_camera(16, 12)
    g = random_gaussians(12, "surfel", seed=3, camera=cam, dtype=torch.float64)
    params = {k: getattr(g, k).clone().requires_grad_(True) for k in ("means", "scales", "opacities")}
    g.means, g.scales, g.opacities = params["means"], params["scales"], params["opacities"]
    builtin = [name for name in LOSS_TERMS.names() if LOSS_TERMS.path(name).startswith("gsbench.losses.terms:")]
    cfg = {name: {"weight": 1.0} for name in builtin}  # method plugins' terms are tested with their methods
    active = active_terms(cfg, 0, params={"normal_consistency": {"depth_ratio": 0.5}})
    out = render(g, cam, kernel="surfel", outputs=required_outputs(active), settings=RasterSettings())
    gaussians = make_gaussians(torch.log(params["scales"].detach().float()),
                               torch.logit(params["opacities"].detach().float()))
    image = torch.rand(12, 16, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    total, values = total_loss(active, out, Batch(image, None, cam, 0), {"gaussians": gaussians})
    assert set(values) == set(builtin) and all(math.isfinite(v) for v in values.values())
    total.backward()
    for name, p in params.items():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    for p in gaussians.params.values():
        assert p.grad is None or torch.isfinite(p.grad).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_l1_term_equals_autograds_mean_abs_difference_with_ties(dtype):
    """The hand-written backward of `l1_term` against autograd through (rgb − image).abs().mean(); a quarter of
    the pixels equal the image (|x| has gradient 0 there), and a float64 gradcheck."""
    from gsbench.raster.types import RenderOutput  # noqa: PLC0415

    gen = torch.Generator().manual_seed(2)
    image = torch.rand(12, 10, 3, generator=gen, dtype=dtype)
    rgb = torch.where(torch.rand(12, 10, 3, generator=gen) < 0.25, image, torch.rand(12, 10, 3, generator=gen,
                                                                                       dtype=dtype))
    batch = Batch(image, None, None, 1)
    x = rgb.clone().requires_grad_(True)
    value = losses.l1_term(RenderOutput(rgb=x), batch, {})
    (grad,) = torch.autograd.grad(value, x)
    y = rgb.clone().requires_grad_(True)
    expected = (y - image).abs().mean()
    (grad_expected,) = torch.autograd.grad(expected, y)
    assert torch.equal(value, expected) and torch.equal(grad, grad_expected)
    if dtype == torch.float64:
        away = (rgb + 0.05 * torch.sign(rgb - image + 1e-3)).requires_grad_(True)  # no tie within the step
        assert torch.autograd.gradcheck(lambda t: losses.l1_term(RenderOutput(rgb=t), batch, {}), (away,))
