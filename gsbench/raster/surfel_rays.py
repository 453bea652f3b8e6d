"""Arbitrary rays through 2D Gaussian surfels: the dense PyTorch reference of the ray tracer the
transparent-object method bends rays with (docs/methods/rt2dgs.md).

The rasterizer (`gsbench.raster`) renders rays through pixels of a pinhole camera; a ray reflected or
refracted at a glass interface starts anywhere and points anywhere. This module evaluates every
(ray, surfel) pair as an (R, N) tensor, as `gsbench.raster.reference` does for pixels, so it is slow and
obviously right; autograd gives the gradients, float64 for the gradient checks.

A surfel i (2DGS, docs/methods/2dgs.md §2): centre μ, rotation R = [t_u t_v t_w], scales s_u, s_v,
opacity o. For a ray x(t) = a + t d (|d| = 1):

- the ray meets the surfel's plane at t_i = ((μ − a)·t_w)/(d·t_w); a pair is skipped if |d·t_w| < 1e-12
  (the ray runs in the plane) or t_i <= ``near``;
- local coordinates u = (x(t_i) − μ)·t_u / s_u, v = (x(t_i) − μ)·t_v / s_v, ρ = u² + v², skipped
  beyond the 3σ cutoff ρ > 9 (the rasterizer's surfel box); the screen-space low-pass branch of the
  rasterizer has no meaning without a pixel and is not applied;
- α_i = min(0.99, o·exp(−ρ/2)), skipped when below 1/255 (the rasterizer's bounds);
- pairs are blended front to back in t: w_i = α_i Π_{j before i} (1 − α_j); the output for per-surfel
  features f (N, F) is Σ w_i f_i, with Σ w_i (the ray's alpha) and Σ w_i t_i; the normal of a pair is
  t_w turned to face the ray (−sign(d·t_w) t_w).

No early stop (the rasterizer stops at transmittance 1e-4; a ray tracer that compares against it must
allow that difference). Ties in t keep the surfels' index order (stable sort).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from gsbench.raster.reference_projection import ALPHA_MAX, ALPHA_MIN, quat_to_rotmat

SURFEL_CUTOFF_SQ = 9.0  # ρ beyond which a pair is skipped (3σ, the rasterizer's surfel box)
PARALLEL = 1e-12  # |d·t_w| below which the ray runs in the surfel's plane


@dataclass
class SurfelTrace:
    """What rays see through the surfels: ``features`` (R, F) = Σ w_i f_i, ``alpha`` (R,) = Σ w_i,
    ``depth`` (R,) = Σ w_i t_i (not divided by alpha), ``normal`` (R, 3) = Σ w_i n_i (facing the ray),
    and the per-pair ``weights`` (R, N) in the surfels' order (0 for skipped pairs)."""

    features: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    normal: torch.Tensor
    weights: torch.Tensor


def pair_hits(origins: torch.Tensor, directions: torch.Tensor, means: torch.Tensor, quats: torch.Tensor,
              scales: torch.Tensor, opacities: torch.Tensor, near: float = 0.0):
    """(t, alpha, normal, ok) of every (ray, surfel) pair (module docstring): t, alpha and ok (R, N), the
    facing normal (R, N, 3). ``directions`` must be unit; ``scales`` (N, 2) or (N, 3) (first two used)."""
    rot = quat_to_rotmat(torch.nn.functional.normalize(quats, dim=-1))  # (N,3,3), columns t_u, t_v, t_w
    tu, tv, tw = rot[..., 0], rot[..., 1], rot[..., 2]
    d_dot_w = directions @ tw.T  # (R,N)
    offset = means[None] - origins[:, None]  # (R,N,3) μ − a
    along = (offset * tw[None]).sum(-1)
    ok = d_dot_w.abs() >= PARALLEL
    t = along / torch.where(ok, d_dot_w, torch.ones_like(d_dot_w))
    ok = ok & (t > near)
    local = directions[:, None] * t[..., None] - offset  # x(t) − μ
    u = (local * tu[None]).sum(-1) / scales[None, :, 0]
    v = (local * tv[None]).sum(-1) / scales[None, :, 1]
    rho = u * u + v * v
    ok = ok & (rho <= SURFEL_CUTOFF_SQ)
    alpha = torch.clamp(opacities[None] * torch.exp(-0.5 * torch.where(ok, rho, torch.zeros_like(rho))), max=ALPHA_MAX)
    ok = ok & (alpha >= ALPHA_MIN)
    normal = -torch.sign(d_dot_w).detach()[..., None] * tw[None]
    return t, torch.where(ok, alpha, torch.zeros_like(alpha)), normal, ok


def trace(origins: torch.Tensor, directions: torch.Tensor, means: torch.Tensor, quats: torch.Tensor,
          scales: torch.Tensor, opacities: torch.Tensor, features: torch.Tensor, near: float = 0.0) -> SurfelTrace:
    """Blend ``features`` (N, F) of the surfels along each ray (module docstring)."""
    t, alpha, normal, ok = pair_hits(origins, directions, means, quats, scales, opacities, near)
    key = torch.where(ok, t, torch.full_like(t, float("inf"))).detach()
    order = torch.sort(key, dim=1, stable=True).indices
    a = torch.gather(alpha, 1, order)
    before = torch.cumprod(torch.cat([torch.ones_like(a[:, :1]), 1.0 - a[:, :-1]], dim=1), dim=1)
    w_sorted = a * before
    weights = torch.zeros_like(w_sorted).scatter(1, order, w_sorted)
    return SurfelTrace(features=weights @ features, alpha=weights.sum(1), depth=(weights * torch.where(ok, t, 0.0)).sum(1),
                       normal=(weights[..., None] * normal).sum(1), weights=weights)
