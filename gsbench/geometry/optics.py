"""Light at a smooth dielectric interface (glass): mirror reflection, Snell refraction, the Fresnel
reflectance, and the bounded ray tree of a transparent object.

Conventions: ``d`` is the unit direction of travel, ``n`` the unit normal on the side the ray comes from
(``d·n < 0``), ``cos_i = −d·n``, and ``eta = n₁/n₂`` the ratio of the indices of the medium left and
the medium entered.

- reflection: r = d + 2 cos_i n;
- refraction (Snell, n₁ sin θ_i = n₂ sin θ_t): sin²θ_t = eta² (1 − cos²_i); total internal reflection
  when sin²θ_t > 1, else t = eta d + (eta cos_i − cos_t) n with cos_t = √(1 − sin²θ_t);
- Fresnel (unpolarised light, the mean of the two polarisations):
  R_s = ((n₁ cos_i − n₂ cos_t)/(n₁ cos_i + n₂ cos_t))², R_p = ((n₁ cos_t − n₂ cos_i)/(n₁ cos_t + n₂ cos_i))²,
  R = (R_s + R_p)/2, and R = 1 under total internal reflection; the refracted ray carries 1 − R (no
  absorption: clear glass).

At index 1 (eta = 1) the interface vanishes: R = 0 and t = d exactly.
"""

from __future__ import annotations

import torch


def reflect(d: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """Mirror direction r = d − 2 (d·n) n of (N,3) directions about (N,3) unit normals."""
    return d - 2.0 * (d * n).sum(-1, keepdim=True) * n


def refract(d: torch.Tensor, n: torch.Tensor, eta) -> tuple[torch.Tensor, torch.Tensor]:
    """(t, tir): Snell's refracted directions of unit ``d`` at unit ``n`` (facing the incoming ray) for
    index ratio ``eta`` = n₁/n₂ (scalar or (N,)), and the mask of total internal reflection (t = 0 there).
    Differentiable; cos_t is taken as √max(1 − sin²θ_t, 1e-12) so its gradient stays finite at the
    critical angle."""
    eta = torch.as_tensor(eta, dtype=d.dtype).expand(d.shape[:-1])[..., None]
    cos_i = (-(d * n).sum(-1, keepdim=True)).clamp(0.0, 1.0)
    sin2_t = eta**2 * (1.0 - cos_i**2)
    tir = sin2_t[..., 0] > 1.0
    cos_t = torch.sqrt((1.0 - sin2_t).clamp_min(1e-12))
    t = eta * d + (eta * cos_i - cos_t) * n
    return torch.where(tir[..., None], torch.zeros_like(t), t), tir


def fresnel(cos_i: torch.Tensor, n1, n2) -> torch.Tensor:
    """Unpolarised Fresnel reflectance R for incidence cosines ``cos_i`` (≥ 0) from index ``n1`` into ``n2``
    (module docstring); 1 under total internal reflection and at grazing incidence, 0 where n1 = n2."""
    cos_i = torch.as_tensor(cos_i).clamp(0.0, 1.0)
    n1, n2 = torch.as_tensor(n1, dtype=cos_i.dtype), torch.as_tensor(n2, dtype=cos_i.dtype)
    sin2_t = (n1 / n2) ** 2 * (1.0 - cos_i**2)
    cos_t = torch.sqrt((1.0 - sin2_t).clamp_min(1e-12))
    s_den, p_den = n1 * cos_i + n2 * cos_t, n1 * cos_t + n2 * cos_i
    rs = ((n1 * cos_i - n2 * cos_t) / s_den.clamp_min(1e-12)) ** 2
    rp = ((n1 * cos_t - n2 * cos_i) / p_den.clamp_min(1e-12)) ** 2
    r = (0.5 * (rs + rp)).clamp(0.0, 1.0)
    r = torch.where((sin2_t > 1.0) | (cos_i <= 0.0), torch.ones_like(r), r)
    return torch.where(n1 == n2, torch.zeros_like(r), r)  # no interface, no reflection, at grazing incidence too
