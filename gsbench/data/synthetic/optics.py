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

import numpy as np


def reflect(d: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Mirror direction r = d − 2 (d·n) n of (N,3) directions about (N,3) unit normals."""
    return d - 2.0 * np.sum(d * n, axis=-1, keepdims=True) * n


def refract(d: np.ndarray, n: np.ndarray, eta) -> tuple[np.ndarray, np.ndarray]:
    """(t, tir): Snell's refracted directions of unit ``d`` at unit ``n`` (facing the incoming ray) for
    index ratio ``eta`` = n₁/n₂ (scalar or (N,)), and the mask of total internal reflection (t = 0 there)."""
    eta = np.broadcast_to(np.asarray(eta, dtype=np.float64), d.shape[:-1])[..., None]
    cos_i = np.clip(-np.sum(d * n, axis=-1, keepdims=True), 0.0, 1.0)
    sin2_t = eta**2 * (1.0 - cos_i**2)
    tir = sin2_t[..., 0] > 1.0
    cos_t = np.sqrt(np.clip(1.0 - sin2_t, 0.0, None))
    t = eta * d + (eta * cos_i - cos_t) * n
    return np.where(tir[..., None], 0.0, t), tir


def fresnel(cos_i: np.ndarray, n1, n2) -> np.ndarray:
    """Unpolarised Fresnel reflectance R for incidence cosines ``cos_i`` (≥ 0) from index ``n1`` into ``n2``
    (module docstring); 1 under total internal reflection."""
    cos_i = np.clip(np.asarray(cos_i, dtype=np.float64), 0.0, 1.0)
    n1, n2 = np.broadcast_arrays(np.asarray(n1, dtype=np.float64), np.asarray(n2, dtype=np.float64))
    sin2_t = (n1 / n2) ** 2 * (1.0 - cos_i**2)
    cos_t = np.sqrt(np.clip(1.0 - sin2_t, 0.0, None))
    with np.errstate(divide="ignore", invalid="ignore"):
        rs = ((n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)) ** 2
        rp = ((n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)) ** 2
    r = 0.5 * (np.nan_to_num(rs, nan=1.0) + np.nan_to_num(rp, nan=1.0))  # grazing (cos_i = cos_t = 0): R = 1
    r = np.where(sin2_t > 1.0, 1.0, np.clip(r, 0.0, 1.0))
    return np.where(n1 == n2, 0.0, r)  # no interface, no reflection, at grazing incidence too
