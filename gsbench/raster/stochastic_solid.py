"""Gaussians as stochastic solids (Geometry-Grounded Gaussian Splatting, GGGS, after "Objects as Volumes"):
the transmittance along a ray and its median depth. The dense PyTorch reference (docs/methods/gggs.md).

Along a ray each Gaussian i is a 1D Gaussian: peak opacity α_i (the rasterizer's α, ≤ 0.99), peak at t*_i,
width σ_i (given as 1/σ_i), g_i(t) = exp(−½ ((t − t*_i)/σ_i)²). As a stochastic solid of vacancy
1 − α_i g_i, its transmittance (read from the authors' public code, which the paper's derivation gives):

    T_i(t) = √(1 − α_i g_i(t))                     t ≤ t*_i
    T_i(t) = (1 − α_i) / √(1 − α_i g_i(t))         t > t*_i

continuous, falling from 1 to 1 − α_i (the alpha-blending factor of the Gaussian, reached as t → ∞); through
many Gaussians T(t) = Π_i T_i(t), monotone non-increasing. A Gaussian with 1/σ_i = 0 (a degenerate width)
is a step of 1 − α_i at t*_i.

The median depth is the t where T crosses 0.5. `median_depth` brackets it by splitting a search interval
into ``split`` cells for ``rounds`` rounds (GGGS: 8 cells, 5 rounds), then interpolates linearly in the last
cell; a ray whose T stays above 0.5 at the interval's far end (no surface, or the median outside the
interval) gets depth 0 and ``valid`` False. Its gradient is the implicit function's: the returned depth is
the bracket's t plus one Newton step −(T(t) − ½)/T'(t) kept inside the last cell, and its derivative in any
parameter θ is −(∂T/∂θ)/T'(t) with T' held fixed (|T'| at least 1e-7), the closed form GGGS's backward uses.
Where T' = 0 at the crossing (one Gaussian of α = ¾: the median is its peak; a degenerate width: a step)
the Newton step is 0 or clamped and the depth is within the last cell, (far − near)/split^rounds.

One Gaussian has a closed form (`single_median`): no surface if α < ½; before the peak if α ≥ ¾
(g = 0.75/α); after it if ½ ≤ α < ¾ (g = (1 − 4(1 − α)²)/α); t = t* ∓ σ √(−2 ln g).
"""

from __future__ import annotations

import math

import torch

HALF = 0.5
SLOPE_FLOOR = 1e-7  # |T'| below this is taken as this (GGGS's clamp of the implicit gradient's denominator)


def single_transmittance(t: torch.Tensor, alpha: torch.Tensor, t_star: torch.Tensor, inv_sigma: torch.Tensor) -> torch.Tensor:
    """T_i(t) of each Gaussian (module docstring); arguments broadcast (e.g. t (R, 1), the rest (R, N))."""
    z = (t - t_star) * inv_sigma
    gt = torch.where(inv_sigma > 0, alpha * torch.exp(-0.5 * z * z), torch.zeros_like(z))  # 1/σ = 0: a step at t*
    root = torch.sqrt(1.0 - gt)
    return torch.where(t <= t_star, root, (1.0 - alpha) / root)


def transmittance(t: torch.Tensor, alpha: torch.Tensor, t_star: torch.Tensor, inv_sigma: torch.Tensor) -> torch.Tensor:
    """T(t) = Π_i T_i(t) (R, S) at depths ``t`` (R, S) of rays whose Gaussians are ``alpha``, ``t_star``,
    ``inv_sigma`` (R, N); padding Gaussians have α = 0."""
    per = single_transmittance(t[..., None], alpha[:, None, :], t_star[:, None, :], inv_sigma[:, None, :])
    return per.prod(-1)


def median_depth(alpha: torch.Tensor, t_star: torch.Tensor, inv_sigma: torch.Tensor, near: torch.Tensor | float,
                 far: torch.Tensor | float, split: int = 8, rounds: int = 5) -> tuple[torch.Tensor, torch.Tensor]:
    """(depth (R,), valid (R,)) of T = ½ on [near, far] per ray (module docstring); differentiable in the
    Gaussians' α, t* and 1/σ by the implicit function."""
    R = alpha.shape[0]
    lo = torch.as_tensor(near, dtype=alpha.dtype).expand(R).clone()
    hi = torch.as_tensor(far, dtype=alpha.dtype).expand(R).clone()
    with torch.no_grad():
        a, ts, s = alpha.detach(), t_star.detach(), inv_sigma.detach()
        valid = transmittance(hi[:, None], a, ts, s)[:, 0] <= HALF
        valid &= transmittance(lo[:, None], a, ts, s)[:, 0] >= HALF
        steps = torch.linspace(0.0, 1.0, split + 1, dtype=alpha.dtype)
        for _ in range(rounds):
            grid = lo[:, None] + (hi - lo)[:, None] * steps  # (R, split + 1)
            below = transmittance(grid, a, ts, s) <= HALF
            first = torch.where(below.any(1), below.float().argmax(1), torch.full((R,), split)).clamp(1, split)
            lo, hi = grid.gather(1, (first - 1)[:, None])[:, 0], grid.gather(1, first[:, None])[:, 0]
        t_lo, t_hi = transmittance(lo[:, None], a, ts, s)[:, 0], transmittance(hi[:, None], a, ts, s)[:, 0]
        share = ((t_lo - HALF) / (t_lo - t_hi).clamp_min(1e-12)).clamp(0.0, 1.0)
        t0 = lo + share * (hi - lo)
    t_param = t0.clone().requires_grad_(True)
    with torch.enable_grad():
        slope = torch.autograd.grad(transmittance(t_param[:, None], a, ts, s)[:, 0].sum(), t_param)[0]
    value = transmittance(t0[:, None], alpha, t_star, inv_sigma)[:, 0]
    slope = torch.where(slope.abs() > SLOPE_FLOOR, slope, torch.full_like(slope, -SLOPE_FLOOR))  # GGGS clamps |T'|
    with torch.no_grad():  # one Newton step, kept inside the bracket (a flat or stepped T gets none)
        newton = (t0 - (value - HALF) / slope).clamp(torch.minimum(lo, hi), torch.maximum(lo, hi)) - t0
    depth = t0 + newton - (value - value.detach()) / slope  # the value t0 + newton; the gradient −(∂T/∂θ)/T'
    return torch.where(valid, depth, torch.zeros_like(depth)), valid


def single_median(alpha: float, t_star: float, sigma: float) -> float | None:
    """The median depth of one Gaussian in closed form (module docstring); None when α < ½."""
    if alpha < HALF:
        return None
    if alpha >= 0.75:
        return t_star - sigma * math.sqrt(-2.0 * math.log(0.75 / alpha))
    return t_star + sigma * math.sqrt(-2.0 * math.log((1.0 - 4.0 * (1.0 - alpha) ** 2) / alpha))
