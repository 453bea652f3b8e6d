"""Real spherical harmonics up to degree 3 (3DGS convention, docs/methods/3dgs.md §2.4).

``sh_to_rgb(sh, dirs, degree)`` evaluates ``Σ_k basis_k(dir) · sh_k + 0.5`` clamped at >= 0 for unit
directions ``dirs`` (N, 3) pointing from the camera to the Gaussian (world frame).
"""

from __future__ import annotations

import torch

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_bases(degree: int) -> int:
    return (degree + 1) ** 2


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """(N, (degree+1)²) basis values at unit directions ``dirs`` (N, 3)."""
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be in 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out += [
            C2[0] * xy,
            C2[1] * yz,
            C2[2] * (2.0 * zz - xx - yy),
            C2[3] * xz,
            C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            C3[0] * y * (3.0 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4.0 * zz - xx - yy),
            C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            C3[4] * x * (4.0 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def sh_to_rgb(sh: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Colour (N, 3) = max(Σ_k basis_k · sh[:, k] + 0.5, 0); ``sh`` is (N, K, 3) with K >= (degree+1)²."""
    k = num_bases(degree)
    if sh.shape[1] < k:
        raise ValueError(f"sh has {sh.shape[1]} coefficients per colour, degree {degree} needs {k}")
    if degree == 0:
        rgb = C0 * sh[:, 0, :]
    else:
        basis = sh_basis(dirs, degree)  # (N, k)
        rgb = (basis.unsqueeze(-1) * sh[:, :k, :]).sum(1)
    return torch.clamp_min(rgb + 0.5, 0.0)
