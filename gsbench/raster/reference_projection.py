"""The dense reference's per-Gaussian half (`gsbench.raster.reference` states the decisions both halves
follow): the projection of every Gaussian of one view, with the kernels' screen-space quantities, the
rade plane, SH colours and the tile rectangles, in plain PyTorch (autograd gradients)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from gsbench.data.camera import Camera
from gsbench.raster.sh import C0 as SH_C0
from gsbench.raster.sh import C1 as SH_C1
from gsbench.raster.sh import C2 as SH_C2
from gsbench.raster.sh import C3 as SH_C3
from gsbench.raster.types import KERNELS, RasterGaussians, RasterSettings

ALPHA_MAX = 0.99  # docs/methods/3dgs.md §3.3
ALPHA_MIN = 1.0 / 255.0  # docs/methods/3dgs.md §3.3
T_STOP = 1e-4  # docs/methods/3dgs.md §3.3
JACOBIAN_CLAMP = 1.3  # docs/methods/3dgs.md §3.1
SURFEL_CUTOFF = 3.0  # docs/methods/2dgs.md §3.3


# --------------------------------------------------------------------------------------------------
# Small numerically safe helpers
# --------------------------------------------------------------------------------------------------


def safe_div(num: torch.Tensor, den: torch.Tensor, ok: torch.Tensor, fill: float = 0.0) -> torch.Tensor:
    """``num/den`` where ``ok``, else ``fill``; the "double where" keeps gradients finite where not ok."""
    den_safe = torch.where(ok, den, torch.ones_like(den))
    return torch.where(ok, num / den_safe, torch.full_like(num / den_safe, fill))


def safe_normalize(v: torch.Tensor, tiny: float = 1e-30) -> torch.Tensor:
    """``v/‖v‖`` over the last axis; 0 (with zero gradient) where ``‖v‖² <= tiny``."""
    n2 = (v * v).sum(-1, keepdim=True)
    ok = n2 > tiny
    return torch.where(ok, v / torch.sqrt(torch.where(ok, n2, torch.ones_like(n2))), torch.zeros_like(v))


def _safe_sqrt(x: torch.Tensor) -> torch.Tensor:
    """``sqrt(max(x, 0))`` with a zero (not infinite) gradient at x <= 0."""
    ok = x > 0
    return torch.where(ok, torch.sqrt(torch.where(ok, x, torch.ones_like(x))), torch.zeros_like(x))


# --------------------------------------------------------------------------------------------------
# Per-Gaussian quantities
# --------------------------------------------------------------------------------------------------


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """(N,4) quaternions (w, x, y, z), normalised with F.normalize, to (N,3,3) rotations (docs/methods/3dgs.md §2.1)."""
    w, x, y, z = F.normalize(quats, dim=-1).unbind(-1)
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Σ_k basis_k(dir)·sh_k for k < (degree+1)² (docs/methods/3dgs.md §2.4; real SH, 3DGS sign convention).

    ``sh`` (N, K, 3), ``dirs`` (N, 3) unit vectors; returns (N, 3) without the +0.5 offset.
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {degree}")
    need = (degree + 1) ** 2
    if sh.shape[1] < need:
        raise ValueError(f"sh has {sh.shape[1]} coefficients, sh_degree {degree} needs {need}")
    x, y, z = (dirs[:, k : k + 1] for k in range(3))
    basis = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        basis += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        basis += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    B = torch.stack(basis, 1)  # (N, need, 1)
    return (B * sh[:, :need, :]).sum(1)


def rade_plane_closed_form(mu: torch.Tensor, cov_inv: torch.Tensor) -> torch.Tensor:
    """docs/methods/radegs.md §3.3 closed form of the depth-plane slope p (normalised-coordinate units), (N,2).

    d = (u, v, 1), m = Σ⁻¹d, w = m/(m·d), P = M w with rows (v²+1, −uv, −u), (−uv, u²+1, −v),
    p = −P·l/(u²+v²+1), l = ‖μ‖. Used by the tests to cross-check `project`'s −(Q20, Q21)/Q22.
    """
    u = mu[:, 0] / mu[:, 2]
    v = mu[:, 1] / mu[:, 2]
    d = torch.stack([u, v, torch.ones_like(u)], -1)
    m = (cov_inv @ d[..., None])[..., 0]
    w = m / (m * d).sum(-1, keepdim=True)
    M = torch.stack(
        [
            torch.stack([v * v + 1, -u * v, -u], -1),
            torch.stack([-u * v, u * u + 1, -v], -1),
        ],
        -2,
    )
    P = (M @ w[..., None])[..., 0]
    return -P * (mu.norm(dim=-1) / (u * u + v * v + 1))[:, None]


@dataclass
class Projected:
    """Per-Gaussian quantities of one view (camera space). Fields unused by a kernel are None."""

    kernel: str
    culled: torch.Tensor  # (N,) bool — contributes nothing
    mu: torch.Tensor  # (N,3) camera-space mean
    opacity: torch.Tensor  # (N,) o_eff × antialias factor
    color: torch.Tensor  # (N,3)
    means2d: torch.Tensor  # (N,2) pixels
    radii: torch.Tensor  # (N,) int64
    rect_min: torch.Tensor  # (N,2) int64 tile indices
    rect_max: torch.Tensor  # (N,2) int64
    conic: torch.Tensor | None = None  # (N,2,2) EWA Σ2D⁻¹ (ewa, rade, raymax)
    normal: torch.Tensor | None = None  # (N,3) constant normal (ewa, rade, surfel)
    cov_inv: torch.Tensor | None = None  # (N,3,3) camera-space Σ⁻¹ (raymax, rade)
    rade_l: torch.Tensor | None = None  # (N,) ‖μ‖
    rade_p: torch.Tensor | None = None  # (N,2) −(Q20, Q21)/Q22
    surfel_H: torch.Tensor | None = None  # (N,3,3) rows Tu, Tv, Tw (docs/methods/2dgs.md §3.1)
    surfel_crossing: torch.Tensor | None = None  # (N,) bool: the 3σ disc reaches the camera plane (Decision 4)


def camera_tensors(camera: Camera, dtype: torch.dtype):
    as_t = lambda a: torch.as_tensor(a, dtype=dtype)  # noqa: E731
    return as_t(camera.K), as_t(camera.R), as_t(camera.t), as_t(camera.center)


def _half_trace(a: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Half the trace of a 2×2 covariance, (a + c)/2."""
    return 0.5 * (a + c)


def _ewa_conic(mu, z_safe, cov, K, camera: Camera, kernel: str, settings: RasterSettings):
    """EWA 2D covariance, conic, antialias factor and radius (docs/methods/3dgs.md §3.1, §3.2, contract).

    Σ2D = J Σ Jᵀ + eps2d·I with J at the clamped centre; factor = sqrt(det Σ2D / det(Σ2D + kI)),
    Σ2D += kI; conic = Σ2D⁻¹; radius = ceil(3·sqrt(mid + sqrt(max(0.1, mid² − det)))).
    Returns (conic (N,2,2), factor (N,), radius (N,) float without grad, bad (N,) det <= 0).
    """
    fx, fy = K[0, 0], K[1, 1]
    lim_x = JACOBIAN_CLAMP * 0.5 * camera.width / camera.fx
    lim_y = JACOBIAN_CLAMP * 0.5 * camera.height / camera.fy
    tx = torch.clamp(mu[:, 0] / z_safe, -lim_x, lim_x) * z_safe
    ty = torch.clamp(mu[:, 1] / z_safe, -lim_y, lim_y) * z_safe
    zero = torch.zeros_like(z_safe)
    J = torch.stack(
        [
            torch.stack([fx / z_safe, zero, -fx * tx / z_safe**2], -1),
            torch.stack([zero, fy / z_safe, -fy * ty / z_safe**2], -1),
        ],
        -2,
    )
    eye = torch.eye(2, dtype=mu.dtype)
    cov2d = J @ cov @ J.transpose(-1, -2) + settings.eps2d_for(kernel) * eye
    k = settings.antialias2d
    det_before = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] * cov2d[:, 1, 0]
    cov2d = cov2d + k * eye
    a, b, c = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
    det = a * c - b * b
    bad = ~(det > 0)
    if k > 0:
        factor = _safe_sqrt(safe_div(det_before, det, ~bad))
    else:
        factor = torch.ones_like(det)
    # Σ2D⁻¹ = adj/det, evaluated on Σ2D/s with the constant s = trace/2 so that tiny (sub-pixel,
    # eps2d = 0) covariances do not overflow the backward of 1/det in float32.
    s = torch.where(bad, torch.ones_like(_half_trace(a, c)), _half_trace(a, c)).detach()
    a_n, b_n, c_n = a / s, b / s, c / s
    adj = torch.stack([torch.stack([c_n, -b_n], -1), torch.stack([-b_n, a_n], -1)], -2)
    conic = safe_div(adj, (a_n * c_n - b_n * b_n)[:, None, None], ~bad[:, None, None]) / s[:, None, None]
    with torch.no_grad():
        mid = _half_trace(a, c)
        lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
        radius = torch.ceil(3.0 * torch.sqrt(torch.clamp(lam, min=0.0)))
    return conic, factor, radius, bad


def _surfel_setup(mu, z_safe, rot_cam, scales, K, filter_k: float, width: int, height: int):
    """2DGS homography rows, box centre, radius and normal (docs/methods/2dgs.md §3.1, §3.3).

    H = K·[s_u R_cw t_u | s_v R_cw t_v | μ] (rows Tu, Tv, Tw); box with f = (9, 9, −1)/d,
    d = 9(Tw.x² + Tw.y²) − Tw.z²: centre = (Σ f Tu Tw, Σ f Tv Tw), h = centre² − Σ f T², extent
    = sqrt(max(1e-4, h)), radius = ceil(max(extent, 3/√k)) (k = ``surfel_filter``; 2DGS's k = 2 gives
    its 3·0.707106; k = 0: ceil(extent)). Normal n = R_cw t_w flipped by the
    constant sign(−μ·n). A disc with d ≥ 0 reaches the camera plane (*crossing*, Decision 4): its centre is
    the projected μ (no gradient) and its radius reaches every image corner (+1).
    Returns (H, centre, radius (no grad), normal, bad (N,) bool, crossing (N,) bool).
    """
    cols = torch.stack([rot_cam[:, :, 0] * scales[:, 0:1], rot_cam[:, :, 1] * scales[:, 1:2], mu], -1)  # (N,3,3)
    H = K @ cols
    Tu, Tv, Tw = H[:, 0, :], H[:, 1, :], H[:, 2, :]
    c2 = SURFEL_CUTOFF**2
    tvec = torch.tensor([c2, c2, -1.0], dtype=mu.dtype)
    d = (tvec * Tw * Tw).sum(-1)
    normal = rot_cam[:, :, 2]
    cos_theta = -(mu * normal).sum(-1)
    bad = cos_theta == 0
    crossing = ~bad & (d >= 0)
    f = safe_div(tvec.expand_as(Tw), d[:, None], ~(bad | crossing)[:, None])
    box_centre = torch.stack([(f * Tu * Tw).sum(-1), (f * Tv * Tw).sum(-1)], -1)
    projected = torch.stack([K[0, 0] * mu[:, 0] / z_safe + K[0, 2], K[1, 1] * mu[:, 1] / z_safe + K[1, 2]], -1)
    centre = torch.where(crossing[:, None], projected.detach(), box_centre)
    normal = normal * torch.sign(cos_theta).detach()[:, None]
    with torch.no_grad():
        h = box_centre**2 - torch.stack([(f * Tu * Tu).sum(-1), (f * Tv * Tv).sum(-1)], -1)
        extent = torch.sqrt(torch.clamp(h, min=1e-4))
        floor = SURFEL_CUTOFF / math.sqrt(filter_k) if filter_k > 0 else 0.0
        radius = torch.ceil(torch.clamp(extent.max(-1).values, min=floor))
        c = centre.detach()
        dx = torch.maximum(c[:, 0].abs(), (c[:, 0] - width).abs())
        dy = torch.maximum(c[:, 1].abs(), (c[:, 1] - height).abs())
        radius = torch.where(crossing, torch.ceil(torch.sqrt(dx * dx + dy * dy)) + 1.0, radius)
    return H, centre, radius, normal, bad, crossing


def project(gaussians: RasterGaussians, camera: Camera, kernel: str, settings: RasterSettings) -> Projected:
    """All per-Gaussian quantities of one view for ``kernel`` (contract "Per-Gaussian quantities")."""
    if kernel not in KERNELS:
        raise ValueError(f"unknown kernel {kernel!r}; expected one of {KERNELS}")
    dtype = gaussians.means.dtype
    K, R_cw, t_cw, cam_centre = camera_tensors(camera, dtype)
    n = len(gaussians)
    near = settings.near

    # 3D filter (docs/methods/gof.md §2.3) on the scales the kernel uses.
    ncols = 2 if kernel == "surfel" else 3
    scales = gaussians.scales[:, :ncols]
    opacity = gaussians.opacities
    if gaussians.filter3d is not None:
        s2 = scales * scales
        s2f = s2 + gaussians.filter3d.detach().to(dtype)[:, None]
        scales = torch.sqrt(s2f)
        opacity = opacity * torch.sqrt(torch.prod(s2 / s2f, dim=-1))

    mu = gaussians.means @ R_cw.T + t_cw
    culled = ~(mu[:, 2] > near)
    z_safe = torch.where(culled, torch.ones_like(mu[:, 2]), mu[:, 2])
    rot_cam = R_cw @ quat_to_rotmat(gaussians.quats)  # columns: Gaussian axes in camera space

    # SH colour (docs/methods/3dgs.md §2.4), world-space direction from the camera centre.
    dirs = safe_normalize(gaussians.means - cam_centre)
    color = torch.clamp(eval_sh(gaussians.all_sh(), dirs, settings.sh_degree) + 0.5, min=0.0)

    fields: dict = {}
    if kernel == "surfel":
        H, means2d, radius, normal, bad, crossing = _surfel_setup(mu, z_safe, rot_cam, scales, K, settings.surfel_filter,
                                                                  camera.width, camera.height)
        fields.update(surfel_H=H, normal=normal, surfel_crossing=crossing)
    else:
        cov = rot_cam @ torch.diag_embed(scales * scales) @ rot_cam.transpose(-1, -2)
        conic, aa_factor, radius, bad = _ewa_conic(mu, z_safe, cov, K, camera, kernel, settings)
        opacity = opacity * aa_factor
        means2d = torch.stack([K[0, 0] * mu[:, 0] / z_safe + K[0, 2], K[1, 1] * mu[:, 1] / z_safe + K[1, 2]], -1)
        fields.update(conic=conic)
        if kernel == "ewa":
            axis = torch.argmin(scales.detach(), dim=-1)
            normal = rot_cam[torch.arange(n), :, axis]
            flip = torch.where((normal * mu).sum(-1) > 0, -1.0, 1.0).to(dtype).detach()
            fields.update(normal=normal * flip[:, None])
        else:
            cov_inv = rot_cam @ torch.diag_embed(1.0 / (scales * scales)) @ rot_cam.transpose(-1, -2)
            fields.update(cov_inv=cov_inv)
            if kernel == "rade":
                fields.update(normal=-safe_normalize((cov_inv @ mu[..., None])[..., 0]))
                fields.update(_rade_plane(mu, z_safe, cov_inv, camera))

    culled = culled | bad
    means2d = torch.where(culled[:, None], torch.zeros_like(means2d), means2d)

    # Tile rectangle (Decision 2).
    ts = settings.tile_size
    grid = torch.tensor([math.ceil(camera.width / ts), math.ceil(camera.height / ts)])
    with torch.no_grad():
        r = radius.to(torch.float64)[:, None]
        m = means2d.detach().to(torch.float64)
        rect_min = torch.minimum(torch.clamp(torch.floor((m - r) / ts), min=0).to(torch.int64), grid)
        rect_max = torch.minimum(torch.clamp(torch.floor((m + r + ts - 1) / ts), min=0).to(torch.int64), grid)
        empty = ((rect_max - rect_min).prod(-1) == 0) | ~torch.isfinite(r[:, 0])
        culled = culled | empty
        radii = torch.where(culled, torch.zeros_like(radius), radius)
        radii = torch.nan_to_num(radii, nan=0.0, posinf=0.0).to(torch.int64)
    return Projected(
        kernel=kernel,
        culled=culled,
        mu=mu,
        opacity=opacity,
        color=color,
        means2d=means2d,
        radii=radii,
        rect_min=rect_min,
        rect_max=rect_max,
        **fields,
    )


def _rade_plane(mu, z_safe, cov_inv, camera: Camera) -> dict:
    """docs/methods/radegs.md §3.2 depth plane: l = ‖μ‖, p = −(Q20, Q21)/Q22 with Q = J_r⁻ᵀ Σ⁻¹ J_r⁻¹ (Decision 9).

    J_r = [[1/z, 0, −u/z], [0, 1/z, −v/z], [u z/l_c, v z/l_c, z/l_c]] at the clamped centre
    (u, v clamped to ±1.3·(W/2)/fx, ±1.3·(H/2)/fy), l_c = z·sqrt(u² + v² + 1).
    """
    lim_x = JACOBIAN_CLAMP * 0.5 * camera.width / camera.fx
    lim_y = JACOBIAN_CLAMP * 0.5 * camera.height / camera.fy
    u = torch.clamp(mu[:, 0] / z_safe, -lim_x, lim_x)
    v = torch.clamp(mu[:, 1] / z_safe, -lim_y, lim_y)
    z = z_safe
    l_c = z * torch.sqrt(u * u + v * v + 1)
    zero = torch.zeros_like(z)
    J_r = torch.stack(
        [
            torch.stack([1 / z, zero, -u / z], -1),
            torch.stack([zero, 1 / z, -v / z], -1),
            torch.stack([u * z / l_c, v * z / l_c, z / l_c], -1),
        ],
        -2,
    )
    J_inv = torch.linalg.inv(J_r)
    Q = J_inv.transpose(-1, -2) @ cov_inv @ J_inv
    p = -torch.stack([Q[:, 2, 0], Q[:, 2, 1]], -1) / Q[:, 2, 2:3]
    return {"rade_l": mu.norm(dim=-1), "rade_p": p}
