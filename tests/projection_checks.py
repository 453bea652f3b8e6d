"""The check both projection test files make: the fused C++ projection against the PyTorch one (its oracle),
payload, detached outputs and integer outputs, and the gradients of every parameter through a random
weighting of the payload."""

from __future__ import annotations

import torch

from gsbench.raster import RasterGaussians
from gsbench.raster.payload import NUM_PARAMS
from gsbench.raster.projection import project_fused, project_torch
from tests.raster_scenes import look_at_camera, with_grad

PARAMS = ("means", "quats", "scales", "opacities", "sh")
DETACHED = ("means2d", "depth", "bounds")
EXACT = ("radii", "visible", "rect", "rect_radius")


def posed_camera(W=64, H=48):
    return look_at_camera((0.3, 0.2, -0.5), (0.0, 0.0, 3.0), width=W, height=H)


def compare_projections(g: RasterGaussians, cam, kernel, settings, fwd_tol=1e-10, grad_tol=1e-8, seed=0,
                        per_element=False):
    """Fused vs PyTorch projection of ``g``; returns both. The payload agrees within ``fwd_tol`` relative to its
    largest entry, or, with ``per_element`` (columns that differ by orders of magnitude, e.g. c' ~ 1e16 for
    scales of 1e-8), relative to each entry (at least 1); gradients within ``grad_tol`` relative."""
    ga, gb = with_grad(g), with_grad(g)
    pa = project_torch(ga, cam, kernel, settings)
    pb = project_fused(gb, cam, kernel, settings)
    assert pb.params.shape == pa.params.shape == (len(g), NUM_PARAMS[kernel])
    assert pb.params.dtype == pa.params.dtype
    assert bool(torch.isfinite(pb.params).all()), "non-finite fused payload"
    a, b = pa.params.detach(), pb.params.detach()
    if per_element:
        rel = float(((a - b).abs() / a.abs().clamp_min(1.0)).max())
        assert rel <= fwd_tol, f"{kernel}: payload differs (relative {rel:.3g})"
    else:
        diff = float((a - b).abs().max())
        assert diff <= fwd_tol * max(1.0, float(a.abs().max())), f"{kernel}: payload differs by {diff:.3g}"
    for k in DETACHED:
        x, y = getattr(pa, k), getattr(pb, k)
        assert x.dtype == y.dtype and x.shape == y.shape, k
        assert float((x - y).abs().max()) <= fwd_tol * max(1.0, float(x.abs().max())), k
    for k in EXACT:
        assert torch.equal(getattr(pa, k), getattr(pb, k)), k
    gen = torch.Generator().manual_seed(seed)
    w = torch.randn(pa.params.shape, generator=gen, dtype=pa.params.dtype)
    (pa.params * w).sum().backward()
    (pb.params * w).sum().backward()
    for p in PARAMS:
        x, y = getattr(ga, p).grad, getattr(gb, p).grad
        x = torch.zeros_like(getattr(ga, p)) if x is None else x
        assert y is not None and y.shape == x.shape and bool(torch.isfinite(y).all()), f"{kernel}: grad of {p}"
        err = float((x - y).abs().max()) / max(float(x.abs().max()), 1e-30)
        assert err <= grad_tol, f"{kernel}: gradient of {p} differs (relative {err:.3g})"
    return pa, pb


def check_lanes_match_one_at_a_time(g: RasterGaussians, cam, kernel, settings, tol):
    """The fused projection runs 8 Gaussians at a time in vector lanes and the rest one at a time
    (csrc/project.cpp): the forward a scene's last n mod 8, the backward, which skips the Gaussians without a
    payload gradient, the last of each chunk's others. Projecting each Gaussian of ``g`` alone takes the
    one-at-a-time path. Every output of the two agrees, payload and detached outputs within ``tol`` relative to
    each entry (at least 1), integer outputs exactly; so do the gradients of a random weighting of the payload in
    which every third Gaussian has no gradient, within ``tol`` relative to the largest entry of the Gaussian's
    gradient (an edge-on Gaussian's quaternion gradient reaches 1e13, and its entries near 0 are round-off)."""
    gen = torch.Generator().manual_seed(3)
    whole_in = with_grad(g)
    whole = project_fused(whole_in, cam, kernel, settings)
    w = torch.randn(whole.params.shape, generator=gen, dtype=torch.float64).to(whole.params.dtype)
    w[::3] = 0
    (whole.params * w).sum().backward()
    alone_in = [with_grad(g.map(lambda t, i=i: t[i:i + 1])) for i in range(len(g))]
    alone = [project_fused(gi, cam, kernel, settings) for gi in alone_in]
    for i, p in enumerate(alone):
        (p.params * w[i:i + 1]).sum().backward()
    for k in ("params",) + DETACHED:
        a = getattr(whole, k).detach().double()
        b = torch.cat([getattr(p, k).detach() for p in alone]).double()
        rel = float(((a - b).abs() / b.abs().clamp_min(1.0)).max())
        assert rel <= tol, f"{kernel}: {k} differs between lanes and one at a time (relative {rel:.3g})"
    for k in EXACT:
        assert torch.equal(getattr(whole, k), torch.cat([getattr(p, k) for p in alone])), f"{kernel}: {k}"
    for name in PARAMS:
        a = getattr(whole_in, name).grad.double().reshape(len(g), -1)
        b = torch.cat([getattr(gi, name).grad for gi in alone_in]).double().reshape(len(g), -1)
        rel = float(((a - b).abs() / b.abs().amax(1, keepdim=True).clamp_min(1.0)).max())
        assert rel <= tol, f"{kernel}: gradient of {name} differs between lanes and one at a time ({rel:.3g})"
        assert float(a[::3].abs().max()) == 0.0, f"{kernel}: a Gaussian without payload gradient got one ({name})"
