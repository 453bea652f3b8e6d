"""PGSR's geometry and loss terms (docs/methods/pgsr.md §3, §4); the terms are declared in configs/loss_terms/.

Geometry (camera space, the pixel-centre convention of docs/design.md §2.1, r̃ = K⁻¹(u, v, 1)):

- `unbiased_depth`: depth = D / (−N·r̃) from the ``plane_distance`` D = Σ wᵢdᵢ and ``normal`` N = Σ wᵢnᵢ
  outputs (docs/methods/pgsr.md §3.2). Pixels whose plane is seen at a grazing angle (cos < `GRAZING_COS`),
  that hold no normal (‖N‖ < `NORMAL_MIN`) or no positive distance are invalid: depth 0, no gradient.
- `plane_homography`: H = K_n (R − t nᵀ/d) K_r⁻¹ per pixel, for the plane nᵀX + d = 0 of camera r and the
  relative pose X_n = R X_r + t (docs/methods/pgsr.md §4.3). With PGSR's camera-facing normals the rendered
  plane is N·X = −D, so (n, d) = (N, D) unnormalised: H depends on N/D only, in which alpha cancels.
- `warp_to_neighbour`: the forward homography at every reference pixel, the neighbour's plane sampled at the
  warped position and the backward homography; the forward–backward error in pixels, its validity and
  PGSR's weight exp(−err) (docs/methods/pgsr.md §4.3).
- `patch_ncc` / `ncc_cost`: normalised cross-correlation of grey patches and PGSR's cost
  clamp(1 − cc², 0, 2) with cc² = cov² / (var_r var_n + 1e-8) on patch sums (docs/methods/pgsr.md §4.4).

Terms (the method binds nothing; their constants are this module's, PGSR's values):

- ``min_scale``: mean over the Gaussians visible in this render of their smallest scale (docs/methods/pgsr.md §4.1);
- ``l1_exposure``: L1 of exp(a_v)·I + b_v against the GT when the method's exposure compensation is on
  and active and (``ssim_gate``, PGSR) 1 − SSIM(I, GT) < 0.5, else L1 of I (docs/methods/pgsr.md §4.5);
- ``pgsr_normal``: mean over pixels of w · Σ_c |N_d·α − N| with N_d the normal of the unbiased depth's
  central differences and w = (1 − ĝ)², ĝ the min–max normalised image gradient (docs/methods/pgsr.md §4.2);
- ``pgsr_geo``: mean over the valid pixels with error < 1 px of exp(−err)·err (docs/methods/pgsr.md §4.3);
- ``pgsr_ncc``: mean over those pixels (cost < 0.9) of exp(−err)·ncc_cost of 7×7 grey patches, the
  neighbour's patch warped by the pixel's homography (docs/methods/pgsr.md §4.4).

The two multi-view terms read ``state["pgsr_multiview"](render, batch)``, the method's per-step shared
context (neighbour choice, neighbour render, warp), so they render the neighbour once per step; GGGS's
``gggs_geo`` / ``gggs_ncc`` (`gsbench.methods.gggs_terms`) are `multiview_geo` / `multiview_ncc` of its own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from gsbench.data.camera import Camera
from gsbench.errors import ConfigError
from gsbench.geometry.depth import depth_to_normal, pixel_centres, pixel_rays
from gsbench.losses.ssim import ssim
from gsbench.losses.terms import Batch, image_map, loss_term
from gsbench.raster.types import RenderOutput

GRAY = (0.299, 0.587, 0.114)  # PGSR process_image: the grey image of the NCC (ITU-R 601 luma)
GRAZING_COS = 1e-2  # unbiased depth only where −N̂·r̂ > this (about 89.4°); PGSR divides by N·r + 1e-8 unguarded
NORMAL_MIN = 1e-4  # ‖N‖ (≈ alpha) below which a pixel has no plane
NCC_EPS = 1e-8  # PGSR lncc: cc = cross² / (var_r var_n + 1e-8)
NCC_MAX_COST = 0.9  # PGSR lncc: pixels with 1 − cc >= 0.9 are left out
EXPOSURE_SSIM_GATE = 0.5  # PGSR train.py: the exposure-corrected image is used only when 1 − SSIM < 0.5


# ---- geometry --------------------------------------------------------------------------------------


def gray(image: torch.Tensor) -> torch.Tensor:
    """(H,W) luma 0.299 R + 0.587 G + 0.114 B of an (H,W,3) image."""
    return image @ torch.tensor(GRAY, dtype=image.dtype)


def intrinsics(camera: Camera, dtype=torch.float32) -> torch.Tensor:
    return torch.as_tensor(np.asarray(camera.K, dtype=np.float64), dtype=dtype)


def _safe_div(num: torch.Tensor, den: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
    """num/den where ``ok`` else 0, with finite gradients everywhere (double where)."""
    return torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(num))


def plane_validity(plane_distance: torch.Tensor, normal: torch.Tensor, rays: torch.Tensor) -> torch.Tensor:
    """Pixels (or samples) where the rendered plane gives a depth: D > 0, ‖N‖ >= `NORMAL_MIN` and
    −N·r̃ > `GRAZING_COS`·‖N‖‖r̃‖ (module docstring); no gradient."""
    with torch.no_grad():
        nn_ = normal.norm(dim=-1)
        facing = -(normal * rays).sum(-1)
        return (plane_distance > 0) & (nn_ >= NORMAL_MIN) & (facing > GRAZING_COS * nn_ * rays.norm(dim=-1))


def unbiased_depth(plane_distance: torch.Tensor, normal: torch.Tensor, camera: Camera
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """(depth (H,W), valid (H,W)): camera z = D / (−N·r̃) of PGSR's plane (docs/methods/pgsr.md §3.2), 0 where invalid."""
    rays = pixel_rays(camera, plane_distance.dtype)
    valid = plane_validity(plane_distance, normal, rays)
    return _safe_div(plane_distance, -(normal * rays).sum(-1), valid), valid


def render_depth(render: RenderOutput, camera: Camera) -> torch.Tensor:
    """`unbiased_depth` of a render with ``plane_distance`` and ``normal``."""
    return unbiased_depth(render.plane_distance, render.normal, camera)[0]


def relative_pose(ref: Camera, other: Camera, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """(R (3,3), t (3,)) with X_other = R X_ref + t (camera frames; world to camera x_c = R_w x + t_w)."""
    R = np.asarray(other.R, np.float64) @ np.asarray(ref.R, np.float64).T
    t = np.asarray(other.t, np.float64).reshape(3) - R @ np.asarray(ref.t, np.float64).reshape(3)
    return torch.as_tensor(R, dtype=dtype), torch.as_tensor(t, dtype=dtype)


def plane_homography(normal: torch.Tensor, distance: torch.Tensor, ok: torch.Tensor, K_src: torch.Tensor,
                     K_dst: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """(...,3,3) H = K_dst (R − t nᵀ/d) K_src⁻¹ for planes nᵀX + d = 0 (..., 3), (...) of the source camera;
    rows with ``ok`` false get H = K_dst R K_src⁻¹ (the plane at infinity) and no gradient. Formed as the
    rank-one update M − u vᵀ, M = K_dst R K_src⁻¹, u = K_dst t, v = K_src⁻ᵀ n/d (no batched matrix products)."""
    K_inv = torch.linalg.inv(K_src)
    M = K_dst @ R @ K_inv
    u = K_dst @ t
    v = _safe_div(normal, distance[..., None], ok[..., None]) @ K_inv
    return M - u[:, None] * v[..., None, :]


def apply_homography(H: torch.Tensor, pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(warped pixels (...,2), homogeneous depth w (...)) of ``pixels`` (...,2) under H (...,3,3); pixels with
    w <= 0 (behind the camera) are returned as 0 with no gradient."""
    x, y = pixels[..., 0], pixels[..., 1]
    q = H[..., :, 0] * x[..., None] + H[..., :, 1] * y[..., None] + H[..., :, 2]
    w = q[..., 2]
    front = w > 0
    return _safe_div(q[..., :2], w[..., None], front[..., None]), w


def sample_image(image: torch.Tensor, pixels: torch.Tensor, padding: str = "border") -> torch.Tensor:
    """Bilinear samples of an (H,W) or (H,W,C) image at continuous pixel positions (...,2) (centres at +0.5),
    differentiable in both; returns (...) or (...,C)."""
    squeeze = image.dim() == 2
    img = image[None, None] if squeeze else image.permute(2, 0, 1)[None]
    H, W = image.shape[:2]
    scale = torch.tensor([2.0 / W, 2.0 / H], dtype=pixels.dtype)
    grid = (pixels * scale - 1.0).reshape(1, -1, 1, 2).to(img.dtype)
    out = F.grid_sample(img, grid, mode="bilinear", padding_mode=padding, align_corners=False)[0, :, :, 0]
    out = out.T.reshape(*pixels.shape[:-1], img.shape[1])  # the channel count named: no pixels is (0, C)
    return out[..., 0] if squeeze else out


@dataclass
class Warp:
    """The forward–backward warp (`warp_to_neighbour`) of the P reference pixels whose own plane gives a depth.

    ``pixels`` (P,2) their centres and ``index`` (P,) their flat indices in the image; ``error`` (P,) pixels,
    differentiable; ``valid`` (P,) the neighbour's plane usable too, the warp inside the neighbour image and in
    front of both cameras; ``mask`` = valid & error < threshold; ``weight`` (P,) exp(−error), detached, 0
    outside ``mask``; ``homography`` (P,3,3) reference → neighbour, differentiable."""

    error: torch.Tensor
    valid: torch.Tensor
    mask: torch.Tensor
    weight: torch.Tensor
    homography: torch.Tensor
    pixels: torch.Tensor
    index: torch.Tensor


def warp_to_neighbour(ref_plane: tuple[torch.Tensor, torch.Tensor], ref_cam: Camera,
                      nb_plane: tuple[torch.Tensor, torch.Tensor], nb_cam: Camera, *, near: float,
                      threshold: float) -> Warp:
    """Forward homography of every reference pixel with its own plane, the neighbour's plane (normal and
    distance maps, bilinear) at the warped position, backward homography with that plane, and the
    reprojection error ‖p − H_nr H_rn p‖ (docs/methods/pgsr.md §4.3). ``*_plane`` = (plane_distance (H,W),
    normal (H,W,3)) of each view; ``near``: the warped point must lie beyond it in the neighbour camera.
    Only the pixels whose own plane gives a depth (`plane_validity`) are warped."""
    D_r, N_r = ref_plane
    D_n, N_n = nb_plane
    dtype = D_r.dtype
    rays_all = pixel_rays(ref_cam, dtype).reshape(-1, 3)
    D_r, N_r = D_r.reshape(-1), N_r.reshape(-1, 3)
    index = torch.nonzero(plane_validity(D_r, N_r, rays_all)).flatten()
    pix = pixel_centres(ref_cam, dtype).reshape(-1, 2)[index]
    rays_r, D_r, N_r = rays_all[index], D_r[index], N_r[index]
    ok_r = torch.ones_like(D_r, dtype=torch.bool)
    K_r, K_n = intrinsics(ref_cam, dtype), intrinsics(nb_cam, dtype)
    R_rn, t_rn = relative_pose(ref_cam, nb_cam, dtype)
    R_nr, t_nr = relative_pose(nb_cam, ref_cam, dtype)

    H_rn = plane_homography(N_r, D_r, ok_r, K_r, K_n, R_rn, t_rn)
    p_n, w_n = apply_homography(H_rn, pix)
    z_n = w_n * D_r / -(N_r * rays_r).sum(-1)  # H p̃ = K_n X_n / depth_r: its third coordinate is z_n / depth_r
    with torch.no_grad():
        inside = (p_n[:, 0] > 0) & (p_n[:, 0] < nb_cam.width) & (p_n[:, 1] > 0) & (p_n[:, 1] < nb_cam.height)
    sampled = sample_image(torch.cat([D_n[..., None], N_n], -1), p_n, padding="border")
    D_s, N_s = sampled[:, 0], sampled[:, 1:]
    rays_n = torch.cat([(p_n[:, :1] - nb_cam.cx) / nb_cam.fx, (p_n[:, 1:] - nb_cam.cy) / nb_cam.fy,
                        torch.ones_like(p_n[:, :1])], -1)
    ok_n = plane_validity(D_s, N_s, rays_n)
    H_nr = plane_homography(N_s, D_s, ok_n, K_n, K_r, R_nr, t_nr)
    p_back, w_back = apply_homography(H_nr, p_n)
    with torch.no_grad():
        valid = ok_n & inside & (z_n > near) & (w_back > 0)
    diff = torch.where(valid[:, None], p_back - pix, torch.ones_like(pix))
    error = torch.where(valid, diff.norm(dim=-1), torch.zeros_like(D_r))
    with torch.no_grad():
        mask = valid & (error < threshold)
        weight = torch.where(mask, torch.exp(-error), torch.zeros_like(error))
    return Warp(error=error, valid=valid, mask=mask, weight=weight, homography=H_rn, pixels=pix, index=index)


def patch_offsets(half: int, dtype=torch.float32) -> torch.Tensor:
    """((2h+1)², 2) integer pixel offsets (dx, dy), rows of dy then dx."""
    r = torch.arange(-half, half + 1, dtype=dtype)
    dy, dx = torch.meshgrid(r, r, indexing="ij")
    return torch.stack([dx.reshape(-1), dy.reshape(-1)], -1)


def _patch_moments(ref: torch.Tensor, nea: torch.Tensor):
    """PGSR lncc's sums over a patch (last axis): cross, var_r, var_n (each × patch size)."""
    k = ref.shape[-1]
    sr, sn = ref.sum(-1), nea.sum(-1)
    cross = (ref * nea).sum(-1) - sn * sr / k
    var_r = (ref * ref).sum(-1) - sr * sr / k
    var_n = (nea * nea).sum(-1) - sn * sn / k
    return cross, var_r, var_n


def patch_ncc(ref: torch.Tensor, nea: torch.Tensor) -> torch.Tensor:
    """Normalised cross-correlation in [−1, 1] of patches (..., K); 0 where either patch is constant."""
    cross, var_r, var_n = _patch_moments(ref, nea)
    den = var_r * var_n
    return _safe_div(cross, torch.sqrt(torch.where(den > 0, den, torch.ones_like(den))), den > 0)


def ncc_cost(ref: torch.Tensor, nea: torch.Tensor) -> torch.Tensor:
    """PGSR's cost clamp(1 − cross²/(var_r var_n + 1e-8), 0, 2) of patches (..., K) (0 for identical textured
    patches, 1 for a textureless one)."""
    cross, var_r, var_n = _patch_moments(ref, nea)
    return torch.clamp(1.0 - cross * cross / (var_r * var_n + NCC_EPS), 0.0, 2.0)


def image_gradient_weight(image: torch.Tensor) -> torch.Tensor:
    """PGSR's edge weight (H,W) of an (H,W,3) GT image: ĝ = the larger of the mean-over-channels central
    differences |I(x+1) − I(x−1)| and |I(y−1) − I(y+1)|, min–max normalised over the interior, 1 on the
    border; weight = clamp(1 − ĝ, 0, 1)² (0 on the border and at the strongest edge)."""
    gx = (image[1:-1, 2:] - image[1:-1, :-2]).abs().mean(-1)
    gy = (image[:-2, 1:-1] - image[2:, 1:-1]).abs().mean(-1)
    g = torch.maximum(gx, gy)
    lo, hi = g.min(), g.max()
    g = (g - lo) / (hi - lo) if float(hi - lo) > 0 else torch.zeros_like(g)
    g = F.pad(g, (1, 1, 1, 1), value=1.0)
    return torch.clamp(1.0 - g, 0.0, 1.0) ** 2


# ---- terms -------------------------------------------------------------------------------------------


def _gaussians(state: dict, term: str):
    if "gaussians" not in state:
        raise ConfigError(f"loss term '{term}' needs the Gaussians in state['gaussians']; remove losses.{term}")
    return state["gaussians"]


def min_scale_term(render: RenderOutput, batch: Batch, state: dict) -> torch.Tensor:
    """L_s = mean over the Gaussians visible in this render (radius > 0) of min(s₁, s₂, s₃) (PGSR's scale loss,
    docs/methods/pgsr.md §4.1); 0 when none is visible."""
    scales = _gaussians(state, "min_scale").scales
    if render.visible is not None and render.visible.shape[0] == scales.shape[0]:
        scales = scales[render.visible]
    if scales.shape[0] == 0:
        return _gaussians(state, "min_scale").scales.sum() * 0.0
    return scales.min(dim=-1).values.mean()


def l1_exposure_term(render: RenderOutput, batch: Batch, state: dict, ssim_gate: bool = True) -> torch.Tensor:
    """L1 = mean |Ĩ − GT| with Ĩ = exp(a_v)·I + b_v when ``state["exposure"](batch)`` gives this view's (a_v, b_v)
    (compensation on and past its start) and, with ``ssim_gate`` (PGSR), 1 − SSIM(I, GT) < 0.5; otherwise
    Ĩ = I (docs/methods/pgsr.md §4.5; GGGS: no gate, docs/methods/gggs.md §3)."""
    rgb, gt = render.rgb, batch.image.to(render.rgb.dtype)
    exposure = state.get("exposure")
    ab = exposure(batch) if exposure is not None else None
    if ab is not None:
        use = True
        if ssim_gate:
            with torch.no_grad():
                use = 1.0 - float(ssim(rgb.detach(), gt)) < EXPOSURE_SSIM_GATE
        if use:
            rgb = torch.exp(ab[0]) * rgb + ab[1]
    return (rgb - gt).abs().mean()


def pgsr_normal_term(render: RenderOutput, batch: Batch, state: dict) -> torch.Tensor:
    """L_svgeo = mean over H×W of w · Σ_c |N_d·stopgrad(α) − N| (docs/methods/pgsr.md §4.2): N the rendered normal
    (Σ wᵢnᵢ, not normalised), N_d the unit normal of the unbiased depth's central differences
    (`gsbench.losses.terms.depth_to_normal`), w = `image_gradient_weight` of the GT image (computed once per view,
    `gsbench.losses.terms.image_map`)."""
    depth = render_depth(render, batch.camera)
    n_d = depth_to_normal(depth, batch.camera) * render.alpha.detach()[..., None]
    weight = image_map(image_gradient_weight, batch.image, depth.dtype)
    return (weight * (n_d - render.normal).abs().sum(-1)).mean()


def multiview_context(state: dict, term: str, render: RenderOutput, batch: Batch):
    fn = state.get("pgsr_multiview")
    if fn is None:
        raise ConfigError(f"loss term '{term}' needs a neighbouring view, which only the pgsr and gggs methods provide "
                          f"(state['pgsr_multiview']); remove losses.{term} for this method")
    return fn(render, batch)


def multiview_geo(ctx, zero: torch.Tensor) -> torch.Tensor:
    """Mean over the pixels with a valid forward–backward warp and error < 1 px of exp(−err)·err (weight
    detached; docs/methods/pgsr.md §4.3); ``zero`` without a neighbour or such pixels."""
    if ctx is None or not bool(ctx.warp.mask.any()):
        return zero
    w = ctx.warp
    return (w.weight * w.error)[w.mask].mean()


def multiview_ncc(ctx, zero: torch.Tensor) -> torch.Tensor:
    """Mean over the warped pixels (the geometric mask, at most ``sample`` of them) whose cost is < 0.9 of
    exp(−err)·ncc_cost(P_r, P_n): P_r the reference GT grey patch of (2h+1)² samples ``ctx.patch_step`` px apart
    (bilinear), P_n the neighbour's GT grey at those samples mapped by the centre pixel's homography
    (differentiable through H; docs/methods/pgsr.md §4.4); ``zero`` without such pixels."""
    if ctx is None or ctx.ncc_index.numel() == 0:
        return zero
    w, idx = ctx.warp, ctx.ncc_index
    offsets = patch_offsets(ctx.patch_half, w.pixels.dtype) * ctx.patch_step
    ref_pts = w.pixels[idx][:, None, :] + offsets[None]
    with torch.no_grad():  # border padding: a patch past the image edge repeats it (PGSR pads with zeros)
        ref_vals = sample_image(ctx.ref_gray, ref_pts, padding="border")
    H = w.homography[idx]
    nb_pts, _ = apply_homography(H[:, None], ref_pts)
    nb_vals = sample_image(ctx.nb_gray, nb_pts, padding="border")
    cost = ncc_cost(ref_vals, nb_vals)
    keep = cost.detach() < NCC_MAX_COST
    if not bool(keep.any()):
        return zero
    return (cost * w.weight[idx])[keep].mean()


def pgsr_geo_term(render: RenderOutput, batch: Batch, state: dict) -> torch.Tensor:
    """L_mvgeo = `multiview_geo` of the step's warp (docs/methods/pgsr.md §4.3)."""
    return multiview_geo(multiview_context(state, "pgsr_geo", render, batch), render.plane_distance.sum() * 0.0)


def pgsr_ncc_term(render: RenderOutput, batch: Batch, state: dict) -> torch.Tensor:
    """L_mvrgb = `multiview_ncc` of the step's warp, 7×7 patches of whole pixels (docs/methods/pgsr.md §4.4)."""
    return multiview_ncc(multiview_context(state, "pgsr_ncc", render, batch), render.plane_distance.sum() * 0.0)


MIN_SCALE = loss_term("min_scale", min_scale_term)
L1_EXPOSURE = loss_term("l1_exposure", l1_exposure_term, {"rgb"}, params={"ssim_gate": True})
PGSR_NORMAL = loss_term("pgsr_normal", pgsr_normal_term, {"plane_distance", "normal", "alpha"})
PGSR_GEO = loss_term("pgsr_geo", pgsr_geo_term, {"plane_distance", "normal"})
PGSR_NCC = loss_term("pgsr_ncc", pgsr_ncc_term, {"plane_distance", "normal"})
