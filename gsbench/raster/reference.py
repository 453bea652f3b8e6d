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
    <= 0 after eps2d and antialias (ewa, rade, raymax); surfel: μ·n == 0 (edge-on,
    docs/methods/2dgs.md §3.1; a disc reaching the camera plane is not culled, Decision 4). Culled Gaussians have ``means2d = 0``.
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
15. Solid depth (GGGS, ``rade`` only): over the *blended* pairs only (α = 0 for the others), as GGGS's
    renderer walks its pixel's contributors; its gradient reaches everything α and t* depend on through
    autograd (a clamped α passes none, as everywhere). The fast path adds the abs-gradient of this output apart
    from the compositing's (per pair |a| + |b|, not |a + b|); the reference's absgrad is the exact total.

Public functions: `render`, `integrate_reference`, `pair_terms` (per-(pixel, Gaussian) kernel evaluation at
arbitrary pixel positions); the per-Gaussian half is `gsbench.raster.reference_projection` (`project`,
`rade_plane_closed_form`, `eval_sh`, `quat_to_rotmat`).
"""

from __future__ import annotations

import math

import torch

from gsbench.data.camera import Camera
from gsbench.geometry.depth import pixel_centres
from gsbench.raster.reference_projection import (
    ALPHA_MAX,
    ALPHA_MIN,
    T_STOP,
    Projected,
    camera_tensors,
    project,
    safe_div,
    safe_normalize,
)
from gsbench.raster.stochastic_solid import median_depth as solid_median
from gsbench.raster.types import ALL_OUTPUTS, OUTPUTS, RasterGaussians, RasterSettings, RenderOutput

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
        tstar = safe_div(rays @ b.T, rAr, rAr_ok)
        q = torch.clamp(_raymax_q(proj.mu, A, rays, tstar), min=0.0)
        ok = rAr_ok & (tstar > near)
        out["G"] = torch.exp(-0.5 * torch.where(ok, q, torch.zeros_like(q)))
        out["depth"] = tstar
        out["normal"] = -safe_normalize(torch.einsum("nij,pj->pni", A, rays))
        out["tstar"] = tstar
    else:  # surfel, docs/methods/2dgs.md §3.2, §3.4
        H = proj.surfel_H
        Tu, Tv, Tw = H[:, 0, :], H[:, 1, :], H[:, 2, :]
        k = pix[:, 0, None, None] * Tw[None] - Tu[None]  # (P,N,3)
        l = pix[:, 1, None, None] * Tw[None] - Tv[None]
        p = torch.linalg.cross(k, l)
        hit = p[..., 2] != 0
        s = safe_div(p[..., :2], p[..., 2:3], hit[..., None])
        rho3d = (s * s).sum(-1)
        rho2d = settings.surfel_filter * ((m2d - pix[:, None, :]) ** 2).sum(-1)
        rho2d = torch.where(proj.surfel_crossing[None, :], torch.full_like(rho2d, math.inf), rho2d)  # Decision 4
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
    unknown = outputs - set(ALL_OUTPUTS)
    if unknown:
        raise ValueError(f"unknown outputs {sorted(unknown)}; expected a subset of {ALL_OUTPUTS}")
    if "solid_depth" in outputs and kernel != "rade":
        raise ValueError(f"solid_depth is defined for the rade kernel only, not {kernel!r}")
    W, H = camera.width, camera.height
    dtype = gaussians.means.dtype
    proj = project(gaussians, camera, kernel, settings)
    n = len(gaussians)

    pix = pixel_centres(camera, dtype).reshape(-1, 2)  # (P,2), row-major

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
    tile = torch.div(pix, ts, rounding_mode="floor").to(torch.int64)  # (P,2): pixel (i, j) lies in tile (i // T, j // T)
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
        n_plane = -safe_normalize((proj.cov_inv @ proj.mu[..., None])[..., 0]) if kernel == "raymax" else proj.normal
        plane_d = -(n_plane * proj.mu).sum(-1)[order]
        out.plane_distance = (w * plane_d[None, :]).sum(-1).reshape(H, W)
    if "solid_depth" in outputs:
        out.solid_depth = _solid_depth(proj, pixel_rays(pix, camera), depth, blended, alpha_b, T, T_final, order,
                                       settings).reshape(H, W)
    if "distortion" in outputs:
        near, far = settings.near, settings.far
        pos_z = blended & (depth > 0)
        m = torch.where(pos_z, far / (far - near) * (1 - safe_div(torch.full_like(depth, near), depth, pos_z)), torch.zeros_like(depth))
        wd = w.detach() if settings.detach_distortion_weights else w
        A_prev, M1, M2 = _exclusive_cumsum(wd), _exclusive_cumsum(wd * m), _exclusive_cumsum(wd * m * m)
        out.distortion = (wd * (m * m * A_prev + M2 - 2 * m * M1)).sum(-1).reshape(H, W)
    return out


def _solid_depth(proj: Projected, rays, depth, blended, alpha_b, T, T_final, order, settings: RasterSettings):
    """GGGS's stochastic-solid median depth per pixel (P,) (contract ``solid_depth``, Decision 15), from the
    sorted, blended pairs: t*_i = z_i‖r‖ (the rade ray distance), 1/σ_i = √(μ̂ᵀΣ⁻¹μ̂), the search of
    `gsbench.raster.stochastic_solid` in [init ± range] clipped at 0; camera z = t/‖r‖."""
    norms = rays.norm(dim=-1)
    t_star = depth * norms[:, None]
    direction = safe_normalize(proj.mu)
    inv_sigma = torch.sqrt(torch.einsum("ni,nij,nj->n", direction, proj.cov_inv, direction))[order]
    pos = torch.arange(1, depth.shape[1] + 1)
    cand = blended & (T > 0.5)
    last = (cand * pos).max(-1, keepdim=True).values
    init = torch.where(cand & (pos[None, :] == last), t_star, torch.zeros_like(t_star)).sum(-1).detach()
    r = settings.solid_search_range
    t, ok = solid_median(alpha_b, torch.where(blended, t_star, torch.zeros_like(t_star)),
                         inv_sigma[None, :].expand_as(t_star), (init - r).clamp_min(0.0), (init + r).clamp_min(0.0),
                         rounds=settings.solid_rounds)
    ok = ok & blended.any(-1) & (T_final <= settings.solid_min_transmittance)
    return torch.where(ok, t / norms, torch.zeros_like(t))


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
        _, R_cw, t_cw, _ = camera_tensors(camera, dtype)
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
