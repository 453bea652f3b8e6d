"""Dense, slow, independent PyTorch reference of `gsbench.raster` (every kernel, every output).

Written for clarity, not speed: every (pixel, Gaussian) pair is evaluated as a (P, N) tensor
(P = H·W pixels in row-major order, N Gaussians), Gaussians are sorted once globally by centre
camera z (stable, ties by index), and compositing uses cumulative products over the sorted axis.
Gradients come from autograd; the dtype follows ``gaussians.means`` (float64 for gradchecks).
The contract is the docstring of `gsbench.raster.types` and docs/rasterizer.md; the method documents
under docs/methods/ give each kernel's formulation.

Decisions (where the contract leaves room; the fast path must match these):

 1. Pixel (i, j) is evaluated at p = (i + 0.5, j + 0.5); its tile is (i // T, j // T), T = tile_size.
 2. Tile rectangle (docs/methods/3dgs.md §3.2) from the *pixel-unit* ``means2d`` m (the +0.5 convention, not
    DGR's integer-centre one) and the integer radius r:
    ``rect_min = clamp(floor((m − r)/T), 0, grid)``, ``rect_max = clamp(floor((m + r + T − 1)/T), 0, grid)``.
    A pair contributes only if the pixel's tile lies in [rect_min, rect_max). An empty rectangle culls
    the Gaussian (radius 0, not visible). ``visible = radius > 0``.
 3. Culling (radius 0, contributes nothing): centre z <= near (all kernels); EWA-conic determinant
    <= 0 after eps2d and antialias (ewa, rade, raymax); surfel: box denominator d == 0 or
    μ·n == 0 (edge-on, docs/methods/2dgs.md §3.1, §3.3). Culled Gaussians have ``means2d = 0``.
 4. ``means2d``: ewa/rade/raymax the projected centre ``(fx μx/μz + cx, fy μy/μz + cy)`` (unclamped);
    surfel the centre of the exact 3σ screen box (docs/methods/2dgs.md §3.3, cutoff 3), radius
    ``ceil(max(extent_x, extent_y, 3/√k))`` (k = ``surfel_filter``, 2DGS: 3·0.707106) with ``extent = sqrt(max(1e-4, h))``.
    ``means2d.grad`` is the exact partial derivative of the loss w.r.t. this tensor (other
    per-Gaussian quantities held fixed): zero for raymax (α does not depend on it), only the
    low-pass-filter branch for surfel. ``extras["absgrad"]`` is Σ_pixels |g_x|+|g_y| of the same
    exact per-pixel gradient, NDC units. The GOF conic proxy (docs/methods/gof.md §3.6) and the 2DGS H-row hack
    (docs/methods/2dgs.md §3.6) are densification heuristics of the fast path and are NOT reproduced here.
 5. Antialias (``antialias2d`` = k): factor ``sqrt(det Σ2D / det(Σ2D + kI))`` (Σ2D already includes
    eps2d) multiplies the opacity of ewa, rade and raymax (GOF's ``coef``); surfel ignores both
    ``antialias2d`` and ``eps2d``. The 3D filter is applied to the scales actually used (3 columns for
    3D kernels, the first 2 for surfel), with the product in ``o_eff`` over those columns.
 6. ``ewa`` normal: the camera-space axis of the smallest effective scale (``argmin``, first index on
    ties), flipped (constant sign) so that n·μ < 0; no flip when n·μ == 0.
 7. ``surfel`` normal: ``R_cw t_w`` times the constant ``sign(−μ·n)``. The per-pixel depth is the
    ray–splat intersection depth in both the ray-hit and low-pass branches (DSR @e0ed020).
    A pair is skipped if p.z == 0 (ray parallel to the splat) or if the intersection depth < near.
 8. ``raymax``: A = Σ⁻¹ is built directly as ``R_cw R S⁻² Rᵀ R_cwᵀ`` (exact 1/s², no +1e-7);
    q is evaluated in the mathematically identical, cancellation-free form
    ``q = (μ − t* r)ᵀ A (μ − t* r)`` (= c − (b·r)²/(rᵀAr) ≥ 0). Skip if t* <= near.
 9. ``rade`` plane (docs/methods/radegs.md §3.2): ray-space Jacobian J_r built at the Jacobian-clamped centre
    ``μ_c = (u_c μz, v_c μz, μz)`` (u_c, v_c clamped as in docs/methods/3dgs.md §3.1), ``Q = J_r⁻ᵀ Σ⁻¹ J_r⁻¹``
    (= (J_r Σ J_rᵀ)⁻¹ without inverting Σ), ``p = −(Q20, Q21)/Q22``. The plane base is the true
    distance ``l = ‖μ‖``. ``δ = (pixel − means2d) / (fx, fy)`` (pixel minus centre, normalised
    coordinates), ``t = l + p·δ``, depth ``z = t/‖r‖`` with the pixel ray r (r_z = 1).
    This equals the closed form of docs/methods/radegs.md §3.3 (`rade_plane_closed_form`, verified in the tests) and
    agrees with GOF's exact t* to first order in δ. No per-pixel near test for rade.
10. Distortion: ``m = far/(far−near)·(1 − near/z)`` for blended pairs with z > 0; a blended pair with
    z <= 0 (possible only for rade's linear depth far from its centre) gets m = 0. Not normalised
    by alpha (GOF's ``/((1−T)²+1e-7)`` is left to the method).
11. Median depth: z of the last *blended* Gaussian whose transmittance before it is > 0.5.
12. SH colour is evaluated in world space at ``normalize(μ_w − camera_centre)`` with degree
    ``settings.sh_degree`` (docs/methods/3dgs.md §2.4), + 0.5, clamped at >= 0 (zero gradient where clamped).
13. Early stop: with T_i the transmittance before i (over blended Gaussians only), pair i is the
    stop pair if it is not skipped and ``T_i·(1−α_i) < 1e-4``; it and every later pair of that
    pixel are not blended.
14. Plane distance (PGSR, docs/methods/pgsr.md §3.1): d_i = −n_i·μ_i with the kernel's per-Gaussian normal
    (ewa, rade, surfel); raymax, whose normal varies per pixel, uses its normal on the central ray
    −normalize(Σ⁻¹μ) (= rade's), so d_i = μᵀΣ⁻¹μ / ‖Σ⁻¹μ‖. d_i >= 0 by the normals' orientation.

Public functions: `render`, `integrate_reference`, `project` (per-Gaussian quantities),
`pair_terms` (per-(pixel, Gaussian) kernel evaluation at arbitrary pixel positions),
`rade_plane_closed_form`, `eval_sh`, `quat_to_rotmat`.
"""

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
from gsbench.raster.types import KERNELS, OUTPUTS, RasterGaussians, RasterSettings, RenderOutput

ALPHA_MAX = 0.99  # docs/methods/3dgs.md §3.3
ALPHA_MIN = 1.0 / 255.0  # docs/methods/3dgs.md §3.3
T_STOP = 1e-4  # docs/methods/3dgs.md §3.3
JACOBIAN_CLAMP = 1.3  # docs/methods/3dgs.md §3.1
SURFEL_CUTOFF = 3.0  # docs/methods/2dgs.md §3.3


# --------------------------------------------------------------------------------------------------
# Small numerically safe helpers
# --------------------------------------------------------------------------------------------------


def _safe_div(num: torch.Tensor, den: torch.Tensor, ok: torch.Tensor, fill: float = 0.0) -> torch.Tensor:
    """``num/den`` where ``ok``, else ``fill``; the "double where" keeps gradients finite where not ok."""
    den_safe = torch.where(ok, den, torch.ones_like(den))
    return torch.where(ok, num / den_safe, torch.full_like(num / den_safe, fill))


def _safe_normalize(v: torch.Tensor, tiny: float = 1e-30) -> torch.Tensor:
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


def _camera_tensors(camera: Camera, dtype: torch.dtype):
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
        factor = _safe_sqrt(_safe_div(det_before, det, ~bad))
    else:
        factor = torch.ones_like(det)
    # Σ2D⁻¹ = adj/det, evaluated on Σ2D/s with the constant s = trace/2 so that tiny (sub-pixel,
    # eps2d = 0) covariances do not overflow the backward of 1/det in float32.
    s = torch.where(bad, torch.ones_like(_half_trace(a, c)), _half_trace(a, c)).detach()
    a_n, b_n, c_n = a / s, b / s, c / s
    adj = torch.stack([torch.stack([c_n, -b_n], -1), torch.stack([-b_n, a_n], -1)], -2)
    conic = _safe_div(adj, (a_n * c_n - b_n * b_n)[:, None, None], ~bad[:, None, None]) / s[:, None, None]
    with torch.no_grad():
        mid = _half_trace(a, c)
        lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
        radius = torch.ceil(3.0 * torch.sqrt(torch.clamp(lam, min=0.0)))
    return conic, factor, radius, bad


def _surfel_setup(mu, rot_cam, scales, K, filter_k: float):
    """2DGS homography rows, box centre, radius and normal (docs/methods/2dgs.md §3.1, §3.3).

    H = K·[s_u R_cw t_u | s_v R_cw t_v | μ] (rows Tu, Tv, Tw); box with f = (9, 9, −1)/d,
    d = 9(Tw.x² + Tw.y²) − Tw.z²: centre = (Σ f Tu Tw, Σ f Tv Tw), h = centre² − Σ f T², extent
    = sqrt(max(1e-4, h)), radius = ceil(max(extent, 3/√k)) (k = ``surfel_filter``; 2DGS's k = 2 gives
    its 3·0.707106; k = 0: ceil(extent)). Normal n = R_cw t_w flipped by the
    constant sign(−μ·n). Returns (H, centre, radius (no grad), normal, bad (N,) bool).
    """
    cols = torch.stack([rot_cam[:, :, 0] * scales[:, 0:1], rot_cam[:, :, 1] * scales[:, 1:2], mu], -1)  # (N,3,3)
    H = K @ cols
    Tu, Tv, Tw = H[:, 0, :], H[:, 1, :], H[:, 2, :]
    c2 = SURFEL_CUTOFF**2
    tvec = torch.tensor([c2, c2, -1.0], dtype=mu.dtype)
    d = (tvec * Tw * Tw).sum(-1)
    normal = rot_cam[:, :, 2]
    cos_theta = -(mu * normal).sum(-1)
    bad = (d == 0) | (cos_theta == 0)
    f = _safe_div(tvec.expand_as(Tw), d[:, None], ~bad[:, None])
    centre = torch.stack([(f * Tu * Tw).sum(-1), (f * Tv * Tw).sum(-1)], -1)
    normal = normal * torch.sign(cos_theta).detach()[:, None]
    with torch.no_grad():
        h = centre**2 - torch.stack([(f * Tu * Tu).sum(-1), (f * Tv * Tv).sum(-1)], -1)
        extent = torch.sqrt(torch.clamp(h, min=1e-4))
        floor = SURFEL_CUTOFF / math.sqrt(filter_k) if filter_k > 0 else 0.0
        radius = torch.ceil(torch.clamp(extent.max(-1).values, min=floor))
    return H, centre, radius, normal, bad


def project(gaussians: RasterGaussians, camera: Camera, kernel: str, settings: RasterSettings) -> Projected:
    """All per-Gaussian quantities of one view for ``kernel`` (contract "Per-Gaussian quantities")."""
    if kernel not in KERNELS:
        raise ValueError(f"unknown kernel {kernel!r}; expected one of {KERNELS}")
    dtype = gaussians.means.dtype
    K, R_cw, t_cw, cam_centre = _camera_tensors(camera, dtype)
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
    dirs = _safe_normalize(gaussians.means - cam_centre)
    color = torch.clamp(eval_sh(gaussians.all_sh(), dirs, settings.sh_degree) + 0.5, min=0.0)

    fields: dict = {}
    if kernel == "surfel":
        H, means2d, radius, normal, bad = _surfel_setup(mu, rot_cam, scales, K, settings.surfel_filter)
        fields.update(surfel_H=H, normal=normal)
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
                fields.update(normal=-_safe_normalize((cov_inv @ mu[..., None])[..., 0]))
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


# --------------------------------------------------------------------------------------------------
# Per-(pixel, Gaussian) kernel evaluation
# --------------------------------------------------------------------------------------------------


def pixel_rays(pix: torch.Tensor, camera: Camera) -> torch.Tensor:
    """(P,3) camera-space rays ``((x−cx)/fx, (y−cy)/fy, 1)`` for pixel positions (P,2)."""
    return torch.stack([(pix[:, 0] - camera.cx) / camera.fx, (pix[:, 1] - camera.cy) / camera.fy, torch.ones_like(pix[:, 0])], -1)


def _raymax_q(mu, cov_inv, rays, t):
    """q(t) = (μ − t r)ᵀ A (μ − t r) for rays (P,3) and t (P,N) (docs/methods/gof.md §3.2, Decision 8)."""
    e = mu[None, :, :] - t[..., None] * rays[:, None, :]
    return torch.einsum("pni,nij,pnj->pn", e, cov_inv, e)


def pair_terms(
    proj: Projected, pix: torch.Tensor, camera: Camera, settings: RasterSettings, means2d: torch.Tensor | None = None
) -> dict:
    """Evaluate the kernel for every (pixel position, Gaussian) pair, ignoring tiles and culling.

    ``pix`` (P,2) continuous pixel positions; ``means2d`` optionally a (P,N,2) per-pair expansion of
    ``proj.means2d`` (lets `render` hook per-pixel gradients). Returns a dict with
    ``G`` (P,N) kernel value, ``ok`` (P,N) bool (False = kernel-specific skip), ``depth`` (P,N),
    ``normal`` (P,N,3) or (N,3), and kernel diagnostics (``rho3d``/``rho2d`` for surfel, ``tstar``
    for raymax). Formulas: contract, per-kernel bullets.
    """
    kernel = proj.kernel
    dtype = proj.mu.dtype
    pix = pix.to(dtype)
    rays = pixel_rays(pix, camera)
    near = settings.near
    m2d = proj.means2d[None, :, :] if means2d is None else means2d
    out: dict = {}
    if kernel in ("ewa", "rade"):
        d = pix[:, None, :] - m2d  # (P,N,2)
        power = -0.5 * torch.einsum("pni,nij,pnj->pn", d, proj.conic, d)
        ok = power <= 0
        out["G"] = torch.exp(torch.where(ok, power, torch.zeros_like(power)))
        if kernel == "ewa":
            out["depth"] = proj.mu[:, 2].expand(pix.shape[0], -1)
        else:
            delta = d / torch.tensor([camera.fx, camera.fy], dtype=dtype)
            t = proj.rade_l[None, :] + (delta * proj.rade_p[None, :, :]).sum(-1)
            out["depth"] = t / rays.norm(dim=-1, keepdim=True)
        out["normal"] = proj.normal
    elif kernel == "raymax":
        A = proj.cov_inv
        b = (A @ proj.mu[..., None])[..., 0]
        rAr = torch.einsum("pi,nij,pj->pn", rays, A, rays)
        rAr_ok = rAr > 0
        tstar = _safe_div(rays @ b.T, rAr, rAr_ok)
        q = torch.clamp(_raymax_q(proj.mu, A, rays, tstar), min=0.0)
        ok = rAr_ok & (tstar > near)
        out["G"] = torch.exp(-0.5 * torch.where(ok, q, torch.zeros_like(q)))
        out["depth"] = tstar
        out["normal"] = -_safe_normalize(torch.einsum("nij,pj->pni", A, rays))
        out["tstar"] = tstar
    else:  # surfel, docs/methods/2dgs.md §3.2, §3.4
        H = proj.surfel_H
        Tu, Tv, Tw = H[:, 0, :], H[:, 1, :], H[:, 2, :]
        k = pix[:, 0, None, None] * Tw[None] - Tu[None]  # (P,N,3)
        l = pix[:, 1, None, None] * Tw[None] - Tv[None]
        p = torch.linalg.cross(k, l)
        hit = p[..., 2] != 0
        s = _safe_div(p[..., :2], p[..., 2:3], hit[..., None])
        rho3d = (s * s).sum(-1)
        rho2d = settings.surfel_filter * ((m2d - pix[:, None, :]) ** 2).sum(-1)
        rho = torch.minimum(rho3d, rho2d) if settings.surfel_filter > 0 else rho3d
        depth = (s * Tw[None, :, :2]).sum(-1) + Tw[None, :, 2]
        ok = hit & (depth >= near)
        out["G"] = torch.exp(-0.5 * torch.where(ok, rho, torch.zeros_like(rho)))
        out["depth"] = depth
        out["normal"] = proj.normal
        out.update(rho3d=rho3d, rho2d=rho2d)
    out["ok"] = ok
    return out


# --------------------------------------------------------------------------------------------------
# Compositing
# --------------------------------------------------------------------------------------------------


def _exclusive_cumprod(x: torch.Tensor) -> torch.Tensor:
    """Π_{j<i} x_j along the last axis (1 for i = 0)."""
    ones = torch.ones_like(x[..., :1])
    return torch.cat([ones, torch.cumprod(x, dim=-1)[..., :-1]], dim=-1)


def _exclusive_cumsum(x: torch.Tensor) -> torch.Tensor:
    """Σ_{j<i} x_j along the last axis (0 for i = 0)."""
    return torch.cumsum(x, dim=-1) - x


def render(
    gaussians: RasterGaussians,
    camera: Camera,
    *,
    kernel: str,
    outputs=OUTPUTS,
    settings: RasterSettings = RasterSettings(),
) -> RenderOutput:
    """Dense reference render (contract: `gsbench.raster.types`; compositing docs/methods/3dgs.md §3.3; docs/methods/2dgs.md §3.5).

    For each pixel, with Gaussians in global centre-z order (stable):
    α_i = min(0.99, o_eff·G_i); skipped (α_i := 0) if α_i < 1/255, outside the tile rectangle,
    culled or a kernel skip; stop at the first non-skipped i with T_i(1−α_i) < 1e-4 (i and later
    not blended); w_i = α_i T_i. Outputs as listed in the contract; see the module Decisions.
    """
    outputs = set(outputs)
    unknown = outputs - set(OUTPUTS)
    if unknown:
        raise ValueError(f"unknown outputs {sorted(unknown)}; expected a subset of {OUTPUTS}")
    W, H = camera.width, camera.height
    dtype = gaussians.means.dtype
    proj = project(gaussians, camera, kernel, settings)
    n = len(gaussians)

    jj, ii = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    ii, jj = ii.reshape(-1), jj.reshape(-1)
    pix = torch.stack([ii, jj], -1).to(dtype) + 0.5  # (P,2), row-major

    # Per-pixel copy of means2d so that a hook can see per-pixel gradients (absgrad, Decision 4).
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    absgrad = torch.zeros(n, dtype=dtype)
    m2d_pairs = means2d.unsqueeze(0).expand(pix.shape[0], n, 2)
    if m2d_pairs.requires_grad:
        ndc = torch.tensor([W / 2.0, H / 2.0], dtype=dtype)

        def accumulate_absgrad(g: torch.Tensor | None) -> None:
            if g is not None:
                absgrad.add_((g * ndc).abs().sum(-1).sum(0))

        m2d_pairs.register_hook(accumulate_absgrad)
    terms = pair_terms(proj, pix, camera, settings, means2d=m2d_pairs)

    # Which pairs can contribute: tile rectangle, culling, kernel skips, α threshold.
    ts = settings.tile_size
    tile = torch.stack([ii // ts, jj // ts], -1)  # (P,2)
    in_rect = ((tile[:, None, :] >= proj.rect_min[None]) & (tile[:, None, :] < proj.rect_max[None])).all(-1)
    alpha_raw = proj.opacity[None, :] * terms["G"]
    candidate = in_rect & ~proj.culled[None, :] & terms["ok"]
    alpha = torch.clamp(alpha_raw, max=ALPHA_MAX)
    valid = candidate & (alpha >= ALPHA_MIN)
    alpha = torch.where(valid, alpha, torch.zeros_like(alpha))

    # Global stable sort by centre camera z.
    order = torch.sort(proj.mu[:, 2].detach(), stable=True).indices
    alpha, valid, alpha_raw, candidate = alpha[:, order], valid[:, order], alpha_raw[:, order], candidate[:, order]
    depth = terms["depth"][:, order]
    normal = terms["normal"]
    normal = normal[:, order] if normal.dim() == 3 else normal[order][None].expand(pix.shape[0], -1, -1)
    color = proj.color[order]

    # Early stop (Decision 13): T before i over the not-yet-stopped prefix equals T over all valid pairs.
    T_all = _exclusive_cumprod(1 - alpha)
    stop = valid & (T_all * (1 - alpha) < T_STOP)
    blended = valid & (torch.cumsum(stop.to(torch.int64), dim=-1) == 0)
    alpha_b = torch.where(blended, alpha, torch.zeros_like(alpha))
    T = _exclusive_cumprod(1 - alpha_b)
    w = alpha_b * T
    T_final = torch.prod(1 - alpha_b, dim=-1)
    depth = torch.where(blended, depth, torch.zeros_like(depth))
    normal = torch.where(blended[..., None], normal, torch.zeros_like(normal))

    out = RenderOutput(width=W, height=H, means2d=means2d, radii=proj.radii, visible=proj.radii > 0)
    out.extras.update(
        absgrad=absgrad,
        order=order,
        candidate=candidate,
        alpha_raw=alpha_raw,
        valid=valid,
        blended=blended,
        transmittance=T,
        terms=terms,
    )
    acc = 1 - T_final
    if "rgb" in outputs:
        bg = torch.tensor(settings.background, dtype=dtype)
        out.rgb = (w @ color + T_final[:, None] * bg).reshape(H, W, 3)
    if "alpha" in outputs:
        out.alpha = acc.reshape(H, W)
    if "depth" in outputs:
        out.depth = ((w * depth).sum(-1) / torch.clamp(acc, min=1e-10)).reshape(H, W)
    if "median_depth" in outputs:
        pos = torch.arange(1, n + 1)
        cand = blended & (T > 0.5)
        last = (cand * pos).max(-1, keepdim=True).values if n > 0 else torch.zeros(pix.shape[0], 1, dtype=torch.int64)
        onehot = cand & (pos[None, :] == last)
        out.median_depth = torch.where(onehot, depth, torch.zeros_like(depth)).sum(-1).reshape(H, W)
    if "normal" in outputs:
        out.normal = (w[..., None] * normal).sum(1).reshape(H, W, 3)
    if "plane_distance" in outputs:
        # d_i = −n_i·μ (contract); raymax's per-pixel normal is replaced by its normal on the central ray
        n_plane = -_safe_normalize((proj.cov_inv @ proj.mu[..., None])[..., 0]) if kernel == "raymax" else proj.normal
        plane_d = -(n_plane * proj.mu).sum(-1)[order]
        out.plane_distance = (w * plane_d[None, :]).sum(-1).reshape(H, W)
    if "distortion" in outputs:
        near, far = settings.near, settings.far
        pos_z = blended & (depth > 0)
        m = torch.where(pos_z, far / (far - near) * (1 - _safe_div(torch.full_like(depth, near), depth, pos_z)), torch.zeros_like(depth))
        wd = w.detach() if settings.detach_distortion_weights else w
        A_prev, M1, M2 = _exclusive_cumsum(wd), _exclusive_cumsum(wd * m), _exclusive_cumsum(wd * m * m)
        out.distortion = (wd * (m * m * A_prev + M2 - 2 * m * M1)).sum(-1).reshape(H, W)
    return out


# --------------------------------------------------------------------------------------------------
# GOF opacity field
# --------------------------------------------------------------------------------------------------


@torch.no_grad()
def integrate_reference(
    gaussians: RasterGaussians,
    cameras: list[Camera],
    points: torch.Tensor,
    kernel: str = "raymax",
    settings: RasterSettings = RasterSettings(),
    chunk: int = 4096,
) -> torch.Tensor:
    """GOF opacity field O(x) = min over views of O_v(x) at (P,3) world points (docs/methods/gof.md §7.1). No gradient.

    Per view: x is used only if its camera z > near and its projection (u, v) lies in
    [0, W) × [0, H); its pixel is (floor(u), floor(v)) and it sees every non-culled Gaussian whose
    tile rectangle contains that pixel's tile (the fast path's tile list). With the exact ray
    r_x = x_c / z_x (r_z = 1) and t = min(t*(r_x), z_x), each Gaussian gives
    α = min(0.99, o_eff·exp(−q(t)/2)) (q as in Decision 8), skipped if α < 1/255 or t* <= near
    (the render rule); O_v = 1 − Π(1 − α) with no early termination. Views where x does not
    project leave O unchanged; O starts at 1.

    Only ``kernel="raymax"`` is defined: the other kernels have no per-point 3D evaluation in
    their methods (RaDe/2DGS mesh by TSDF), so they raise NotImplementedError.
    """
    if kernel != "raymax":
        raise NotImplementedError(
            f"integrate_reference defines GOF's opacity field for kernel='raymax' only, not {kernel!r}"
        )
    dtype = gaussians.means.dtype
    points = points.to(dtype)
    opacity_field = torch.ones(points.shape[0], dtype=dtype)
    ts = settings.tile_size
    for camera in cameras:
        proj = project(gaussians, camera, kernel, settings)
        _, R_cw, t_cw, _ = _camera_tensors(camera, dtype)
        A = proj.cov_inv
        b = (A @ proj.mu[..., None])[..., 0]
        for start in range(0, points.shape[0], chunk):
            xc = points[start : start + chunk] @ R_cw.T + t_cw
            z = xc[:, 2]
            in_front = z > settings.near
            z_safe = torch.where(in_front, z, torch.ones_like(z))
            rays = xc / z_safe[:, None]
            u = camera.fx * rays[:, 0] + camera.cx
            v = camera.fy * rays[:, 1] + camera.cy
            in_view = in_front & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
            tile = torch.stack([torch.floor(u), torch.floor(v)], -1).clamp(min=0).to(torch.int64) // ts
            in_rect = ((tile[:, None, :] >= proj.rect_min[None]) & (tile[:, None, :] < proj.rect_max[None])).all(-1)
            rAr = torch.einsum("pi,nij,pj->pn", rays, A, rays)
            tstar = rays @ b.T / rAr
            t = torch.minimum(tstar, z_safe[:, None])
            q = torch.clamp(_raymax_q(proj.mu, A, rays, t), min=0.0)
            alpha = torch.clamp(proj.opacity[None, :] * torch.exp(-0.5 * q), max=ALPHA_MAX)
            keep = in_rect & ~proj.culled[None, :] & (tstar > settings.near) & (alpha >= ALPHA_MIN)
            o_view = 1 - torch.prod(1 - torch.where(keep, alpha, torch.zeros_like(alpha)), dim=-1)
            sl = opacity_field[start : start + chunk]
            sl.copy_(torch.where(in_view, torch.minimum(sl, o_view), sl))
    return opacity_field
