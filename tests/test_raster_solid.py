"""The rasterizer's ``solid_depth`` output (GGGS's stochastic-solid median depth, docs/methods/gggs.md §1–§2):
the fast path (csrc/solid.cpp) against the dense reference in float64, values and gradients; finite
differences; one Gaussian against its closed form; the hard rays; only computed when asked."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))

from raster_scenes import concat, make_camera, random_gaussians, single_gaussian, with_grad  # noqa: E402

from gsbench.raster import RasterSettings, rasterize, reference  # noqa: E402
from gsbench.raster.stochastic_solid import single_median  # noqa: E402

PARAMS = ("means", "quats", "scales", "opacities")
SETTINGS = RasterSettings(solid_search_range=1.0)


def _scene(dtype=torch.float64, n=150, seed=0):
    cam = make_camera(40, 32)
    g = random_gaussians(n, "rade", seed=seed, camera=cam, dtype=dtype, opacity_range=(0.3, 0.95), filter3d=5e-4)
    return cam, g


def _weighted(depth, seed=1):
    w = torch.rand(depth.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return (depth.double() * w).sum()


def test_fast_path_matches_the_reference_in_float64():
    """Depth to 1e-10 and every parameter's gradient to 1e-9 (relative), on 150 overlapping Gaussians; most
    pixels have a surface."""
    cam, g = _scene()
    fast_g, ref_g = with_grad(g), with_grad(g)
    fast = rasterize(fast_g, cam, kernel="rade", outputs=("solid_depth",), settings=SETTINGS).solid_depth
    ref = reference.render(ref_g, cam, kernel="rade", outputs=("solid_depth",), settings=SETTINGS).solid_depth
    assert int((ref > 0).sum()) > 0.5 * ref.numel()
    assert torch.equal(fast > 0, ref > 0)
    assert float((fast - ref).detach().abs().max()) < 1e-10
    _weighted(fast).backward()
    _weighted(ref).backward()
    for p in PARAMS:
        a, b = getattr(fast_g, p).grad, getattr(ref_g, p).grad
        assert float((a - b).norm()) <= 1e-9 * float(b.norm()), p


def test_float32_agrees_with_float64():
    """The float32 fast path on the same scene: the same pixels have a surface but for a few at the crossing's
    edge, and the depths agree to 1e-4 of the depth."""
    cam, g = _scene()
    f64 = rasterize(g, cam, kernel="rade", outputs=("solid_depth",), settings=SETTINGS).solid_depth
    g32 = g.map(lambda x: x.to(torch.float32))
    f32 = rasterize(g32, cam, kernel="rade", outputs=("solid_depth",), settings=SETTINGS).solid_depth.double()
    both = (f64 > 0) & (f32 > 0)
    assert int(((f64 > 0) != (f32 > 0)).sum()) <= 3
    assert float(((f64 - f32).abs() / f64.clamp_min(1e-9))[both].max()) < 1e-4


def test_gradients_match_finite_differences():
    """gradcheck (float64) of the fast path with the search run to 12 rounds, so the depth is the root to
    rounding and finite differences see the implicit function's gradient."""
    cam = make_camera(12, 10)
    g = random_gaussians(30, "rade", seed=4, camera=cam, opacity_range=(0.6, 0.95), scale_range=(0.2, 0.4), spread=0.6)
    settings = RasterSettings(solid_search_range=1.5, solid_rounds=12)
    depth = rasterize(g, cam, kernel="rade", outputs=("solid_depth",), settings=settings).solid_depth
    assert int((depth > 0).sum()) > 60
    wg = with_grad(g)

    def f(*params):
        gg = type(g)(*params, g.sh, g.filter3d)
        return rasterize(gg, cam, kernel="rade", outputs=("solid_depth",), settings=settings).solid_depth

    assert torch.autograd.gradcheck(f, tuple(getattr(wg, p) for p in PARAMS), eps=1e-6, atol=1e-5, rtol=1e-3,
                                    fast_mode=True)


@pytest.mark.parametrize("opacity", [0.6, 0.9])
def test_one_gaussian_is_its_closed_form(opacity):
    """One Gaussian on the optical axis, seen by the pixel whose centre is its projection: the depth is the
    closed-form median of its transmittance curve (t* = ‖μ‖, 1/σ = √(μ̂ᵀΣ⁻¹μ̂)), to one last cell of the
    5-round search, and to 1e-9 with 8 rounds (GGGS's meshing search)."""
    cam = make_camera(15, 15, cx=7.5, cy=7.5)
    g = single_gaussian((0.0, 0.0, 3.0), kernel="rade", scales=(0.3, 0.2, 0.1), opacity=opacity,
                        quat=(math.cos(0.3), math.sin(0.3), 0.0, 0.0))
    c, s = math.cos(0.6), math.sin(0.6)  # the quaternion's rotation: 0.6 rad about x; the ray is z
    sigma = 1.0 / math.sqrt((s / 0.2) ** 2 + (c / 0.1) ** 2)
    expected = single_median(opacity, 3.0, sigma)
    for rounds, tolerance in ((5, 0.8 / 8**5), (8, 1e-9)):
        settings = RasterSettings(solid_search_range=0.4, solid_rounds=rounds)
        depth = rasterize(g, cam, kernel="rade", outputs=("solid_depth",), settings=settings).solid_depth
        assert abs(float(depth[7, 7]) - expected) < tolerance, rounds


def test_hard_rays_are_defined():
    """No surface (opacity < ½ everywhere: T never reaches ½) gives 0 and a zero gradient; a Gaussian behind
    the camera beside one in front, and two coincident Gaussians, give the reference's depth, finite
    gradients and no NaN; asking another kernel for the output names the kernel that has it."""
    cam = make_camera(15, 15, cx=7.5, cy=7.5)
    faint = with_grad(single_gaussian((0.0, 0.0, 3.0), kernel="rade", scales=(0.3, 0.3, 0.1), opacity=0.4))
    depth = rasterize(faint, cam, kernel="rade", outputs=("solid_depth",), settings=SETTINGS).solid_depth
    assert (depth == 0).all()
    depth.sum().backward()
    assert all(getattr(faint, p).grad is None or (getattr(faint, p).grad == 0).all() for p in PARAMS)
    behind = single_gaussian((0.0, 0.0, -2.0), kernel="rade", scales=(0.3, 0.3, 0.3), opacity=0.9)
    front = single_gaussian((0.1, 0.0, 3.0), kernel="rade", scales=(0.4, 0.3, 0.1), opacity=0.8)
    for scene in (concat(behind, front), concat(front, front)):
        fast_g, ref_g = with_grad(scene), with_grad(scene)
        fast = rasterize(fast_g, cam, kernel="rade", outputs=("solid_depth",), settings=SETTINGS).solid_depth
        ref = reference.render(ref_g, cam, kernel="rade", outputs=("solid_depth",), settings=SETTINGS).solid_depth
        assert bool((fast > 0).any()) and float((fast - ref).detach().abs().max()) < 1e-10
        fast.sum().backward()
        assert all(torch.isfinite(getattr(fast_g, p).grad).all() for p in PARAMS)
    with pytest.raises(ValueError, match="rade kernel only"):
        rasterize(front, cam, kernel="ewa", outputs=("solid_depth",))


def test_computed_only_when_asked():
    """Without the output there is no solid pass (no timer entry, no tensor); with it, the other outputs are
    unchanged."""
    cam, g = _scene(n=40)
    plain = rasterize(g, cam, kernel="rade", outputs=("rgb", "median_depth"))
    both = rasterize(g, cam, kernel="rade", outputs=("rgb", "median_depth", "solid_depth"), settings=RasterSettings())
    assert plain.solid_depth is None and both.solid_depth is not None
    assert torch.equal(plain.rgb, both.rgb) and torch.equal(plain.median_depth, both.median_depth)


@pytest.mark.parametrize("unit", [1e-3, 1e3])
def test_millimetres_and_kilometres_scale_the_depth(unit):
    """The same scene in units 1000 times smaller or larger (centres, scales, search range and near plane
    scaled): the solid depth scales with it to float64 round-off, its gradients stay finite, nothing is NaN."""
    cam, g = _scene(n=60)
    base = rasterize(g, cam, kernel="rade", outputs=("solid_depth",), settings=SETTINGS).solid_depth
    scaled = g.map(lambda x: x)
    scaled.means, scaled.scales = g.means * unit, g.scales * unit
    scaled.filter3d = None if g.filter3d is None else g.filter3d * unit**2
    settings = RasterSettings(solid_search_range=SETTINGS.solid_search_range * unit, scene_radius=unit)
    wg = with_grad(scaled)
    depth = rasterize(wg, cam, kernel="rade", outputs=("solid_depth",), settings=settings).solid_depth
    assert torch.isfinite(depth).all() and int((base > 0).sum()) > 100
    assert float((depth.detach() / unit - base).abs().max()) < 1e-9 * float(base.max())
    depth.sum().backward()
    assert all(torch.isfinite(getattr(wg, p).grad).all() for p in PARAMS)
