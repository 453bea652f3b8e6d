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

The median depth is the t where T crosses 0.5, found as GGGS's rasterizer finds it: the search interval
[near, far] is split into ``split`` cells for ``rounds`` rounds (GGGS: 8 cells, 5 rounds in training, 8 for
meshing), each round keeping the cell [t_s, t_s+1] of the last sample s < split with T(t_s) ≥ ½, then the
crossing is interpolated linearly in the last cell, t = t_s + (T_s − ½)/(T_s − T_s+1)·(t_s+1 − t_s) (the
weight clamped to [0, 1]). A ray whose T is below ½ at ``near`` or above it at ``far`` gets depth 0 and
``valid`` False. The gradient is the implicit function's, in GGGS's log form: with ℓ = log T,
dt/dθ = −(∂ℓ/∂θ)/(∂ℓ/∂t), where ½|∂ℓ/∂t| is taken at least 1e-7 (GGGS's clamp; at T = ½, ½|∂ℓ/∂t| = |T'|).
The value is within one last cell, (far − near)/split^rounds, of the crossing (better where T is smooth).

One Gaussian has a closed form (`single_median`): no surface if α < ½; before the peak if α ≥ ¾
(g = 0.75/α); after it if ½ ≤ α < ¾ (g = (1 − 4(1 − α)²)/α); t = t* ∓ σ √(−2 ln g).
"""

from __future__ import annotations

import math

import torch

HALF = 0.5
SLOPE_FLOOR = 1e-7  # ½|∂ log T/∂t| below this is taken as this (GGGS's clamp of the implicit gradient's denominator)


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


def log_transmittance(t: torch.Tensor, alpha: torch.Tensor, t_star: torch.Tensor, inv_sigma: torch.Tensor) -> torch.Tensor:
    """ℓ = log T(t) = Σ_i log T_i(t) (R, S), arguments as `transmittance`."""
    return torch.log(single_transmittance(t[..., None], alpha[:, None, :], t_star[:, None, :], inv_sigma[:, None, :])).sum(-1)


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
        inner = torch.arange(1, split)
        for _ in range(rounds):
            grid = lo[:, None] + (hi - lo)[:, None] * steps  # (R, split + 1)
            T_grid = transmittance(grid, a, ts, s)
            start = ((T_grid[:, 1:split] >= HALF) * inner).max(1).values  # the last inner sample with T ≥ ½, else 0
            lo, hi = grid.gather(1, start[:, None])[:, 0], grid.gather(1, (start + 1)[:, None])[:, 0]
        t_lo, t_hi = transmittance(lo[:, None], a, ts, s)[:, 0], transmittance(hi[:, None], a, ts, s)[:, 0]
        share = ((t_lo - HALF) / (t_lo - t_hi).clamp_min(1e-30)).clamp(0.0, 1.0)
        t0 = lo + share * (hi - lo)
    t_param = t0.clone().requires_grad_(True)
    with torch.enable_grad():
        slope = torch.autograd.grad(log_transmittance(t_param[:, None], a, ts, s)[:, 0].sum(), t_param)[0]
    ell = log_transmittance(t0[:, None], alpha, t_star, inv_sigma)[:, 0]
    rate = torch.clamp(-0.5 * slope, min=SLOPE_FLOOR)  # GGGS: max(−½ ∂ℓ/∂t, 1e-7)
    depth = t0 + (ell - ell.detach()) / (2.0 * rate)  # the value t0; the gradient −(∂ℓ/∂θ)/(∂ℓ/∂t)
    return torch.where(valid, depth, torch.zeros_like(depth)), valid


def single_median(alpha: float, t_star: float, sigma: float) -> float | None:
    """The median depth of one Gaussian in closed form (module docstring); None when α < ½."""
    if alpha < HALF:
        return None
    if alpha >= 0.75:
        return t_star - sigma * math.sqrt(-2.0 * math.log(0.75 / alpha))
    return t_star + sigma * math.sqrt(-2.0 * math.log((1.0 - 4.0 * (1.0 - alpha) ** 2) / alpha))
