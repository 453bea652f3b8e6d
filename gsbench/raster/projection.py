"""Per-Gaussian quantities of one view: a fused C++ pass and its vectorised PyTorch (autograd) oracle.

`project(gaussians, camera, kernel, settings)` returns a `Projection`. For every kernel (ewa, rade, raymax,
surfel) it runs `project_fused` (csrc/project.cpp: one OpenMP pass over the Gaussians forward, a
hand-written backward, double precision inside) unless ``GSBENCH_PROJECTION=torch`` or
``projection.IMPL = "torch"``; `project_torch` (below) is the PyTorch version, the fused path's oracle
(tests/test_raster_projection.py, tests/test_projection_fused_raymax_surfel.py). A `Projection` holds
the per-Gaussian *payload* (one (N, P) tensor the C++ compositor reads, column layout below), the
screen radius, visibility, centre depth (the per-tile sort key), the tile rectangle and a conservative
pixel box outside which the Gaussian's alpha is certainly < 1/255 (used to skip rows and tiles; it never
changes a result).

Column layout of the payload (must match ``csrc/raster.cpp``):

    common   0 mx  1 my  2-4 conic (A, B, C)  5 opacity  6-8 rgb
    ewa      9 z        10-12 normal
    rade     9 l        10-11 p/f (pixel units)  12-14 normal
    raymax   9-14 A' = Σ⁻¹/c (00,01,02,11,12,22)  15-17 b' = Σ⁻¹μ/c  18-20 M' (00,01,11)  21 c  22-23 μxy/μz
    surfel   9-11 n (camera-facing normal)  12 d = n·μ  13-15 a_u = t_u/s_u  16 μ·a_u  17-19 a_v  20 μ·a_v

Raymax is evaluated without cancellation: with Δ = r − μ/μz (Δz = 0) the Mahalanobis distance from μ to
the ray r is ``q = c − (b·r)²/(rᵀAr) = ΔᵀMΔ/(rᵀAr)``, M = (c A − b bᵀ)_xy = Gram matrix of
``μ̃ × ẽ_x, μ̃ × ẽ_y`` in whitened coordinates; A, b, M are stored divided by c (resp. c²) so that
neither tiny nor huge scales overflow float32. Mathematically identical to the contract's A, b, c.
"""

from __future__ import annotations

import ctypes
import math
import os
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from gsbench.data.camera import Camera
from gsbench.raster.build import ProjArgs, omp_threads
from gsbench.raster.sh import sh_to_rgb
from gsbench.raster.types import RasterGaussians, RasterSettings

NUM_PARAMS = {"ewa": 13, "rade": 15, "raymax": 24, "surfel": 21}
ALPHA_MIN = 1.0 / 255.0
BIG = 1.0e6  # pixel-box sentinel (kept finite: the C++ is built with -ffinite-math-only)


@dataclass
class Projection:
    params: torch.Tensor  # (N, P) differentiable payload
    means2d: torch.Tensor  # (N, 2) pixels, detached, 0 where culled (the differentiable copy is params[:, :2])
    radii: torch.Tensor  # (N,) int64
    visible: torch.Tensor  # (N,) bool
    depth: torch.Tensor  # (N,) centre camera z, detached (sort key)
    bounds: torch.Tensor  # (N, 4) xmin, xmax, ymin, ymax pixel box of alpha >= 1/255 (detached)
    rect: torch.Tensor  # (N, 4) int32 tile rectangle x0, x1, y0, y1 (exclusive ends), refined by `bounds`
    rect_radius: torch.Tensor  # (N, 4) int32 tile rectangle of the 3σ radius only (integrate)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """(N,4) unit quaternions (w,x,y,z) -> (N,3,3) rotation matrices."""
    w, x, y, z = q.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return torch.stack(
        [
            1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
            2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
            2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)


def camera_tensors(camera: Camera, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    R = torch.as_tensor(camera.R, dtype=dtype)
    t = torch.as_tensor(camera.t, dtype=dtype).reshape(3)
    center = torch.as_tensor(camera.center, dtype=dtype).reshape(3)
    return R, t, center


def _rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a proper rotation matrix (Shepperd's method)."""
    m = np.asarray(R, dtype=np.float64)
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def _left_mult(camera: Camera, dtype: torch.dtype) -> torch.Tensor:
    """4×4 matrix L with q_cw ⊗ q = L q (Hamilton product), q_cw the quaternion of the camera rotation."""
    R = np.asarray(camera.R, dtype=np.float64)
    if np.linalg.det(R) < 0:
        raise ValueError("camera.R must be a proper rotation (det +1)")
    w, x, y, z = _rotmat_to_quat(R)
    L = np.array([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]])
    return torch.as_tensor(L, dtype=dtype)


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(-1)


def _ewa_cov2d(M: torch.Tensor, mu: torch.Tensor, zs: torch.Tensor, camera: Camera, eps2d: float):
    """EWA 2D covariance entries (a, b, c) with the clamped Jacobian; M = R_c·diag(s) (N,3,3)."""
    fx, fy = camera.fx, camera.fy
    limx = 1.3 * (0.5 * camera.width) / fx
    limy = 1.3 * (0.5 * camera.height) / fy
    u = torch.clamp(mu[:, 0] / zs, -limx, limx)
    v = torch.clamp(mu[:, 1] / zs, -limy, limy)
    r0 = (fx / zs)[:, None] * (M[:, 0, :] - u[:, None] * M[:, 2, :])
    r1 = (fy / zs)[:, None] * (M[:, 1, :] - v[:, None] * M[:, 2, :])
    a0 = _dot(r0, r0)
    b = _dot(r0, r1)
    c0 = _dot(r1, r1)
    cr = torch.linalg.cross(r0, r1, dim=-1)
    g_det = _dot(cr, cr)  # det(J Σ Jᵀ) = |r0 × r1|² (Binet–Cauchy), no cancellation for elongated Σ
    return a0, b, c0, g_det


def _tile_rect(lo_x, hi_x, lo_y, hi_y, tile: int, gx: int, gy: int) -> torch.Tensor:
    """Tiles [x0, x1) × [y0, y1): floor(lo/T) .. floor((hi + T − 1)/T), clamped (docs/methods/3dgs.md §3.2, +0.5 pixels)."""
    x0 = torch.clamp(torch.floor(lo_x / tile), 0, gx)
    x1 = torch.clamp(torch.floor((hi_x + tile - 1) / tile), 0, gx)
    y0 = torch.clamp(torch.floor(lo_y / tile), 0, gy)
    y1 = torch.clamp(torch.floor((hi_y + tile - 1) / tile), 0, gy)
    return torch.stack([x0, x1, y0, y1], -1)


FUSED_KERNELS = ("ewa", "rade", "raymax", "surfel")  # index = the kernel id of csrc/project.cpp

# Which projection `project` uses: "fused" (C++, csrc/project.cpp) or "torch" (this module's vectorised
# PyTorch, also the oracle of the fused one). None = the GSBENCH_PROJECTION environment variable,
# default "fused".
IMPL: str | None = None


def projection_impl(kernel: str) -> str:
    """"fused" or "torch": the projection `project` will use for ``kernel``."""
    impl = IMPL if IMPL is not None else os.environ.get("GSBENCH_PROJECTION", "fused")
    impl = impl.strip().lower() or "fused"
    if impl not in ("fused", "torch"):
        raise ValueError(f"GSBENCH_PROJECTION / projection.IMPL must be 'fused' or 'torch', got '{impl}'")
    return impl if kernel in FUSED_KERNELS else "torch"


def project(gaussians: RasterGaussians, camera: Camera, kernel: str, settings: RasterSettings) -> Projection:
    """Per-Gaussian projection of one view (fused C++ unless disabled, else PyTorch)."""
    if projection_impl(kernel) == "fused":
        return project_fused(gaussians, camera, kernel, settings)
    return project_torch(gaussians, camera, kernel, settings)


class _FusedProjectFn(torch.autograd.Function):
    """Fused projection (csrc/project.cpp): (means, quats, scales (N,3), opacities, sh, sh_rest or None) -> payload.

    For surfel the third scale column is padding (never read; its gradient is 0)."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, sh, sh_rest, cfg):  # noqa: D401
        lib, args, n, npar, filter3d = cfg
        dtype = means.dtype
        ins = [t.detach().contiguous() for t in (means, quats, scales, opacities, sh)]
        rest = None if sh_rest is None else sh_rest.detach().contiguous()
        params = torch.empty(n, npar, dtype=dtype)
        means2d = torch.empty(n, 2, dtype=dtype)
        radii = torch.empty(n, dtype=torch.int64)
        visible = torch.empty(n, dtype=torch.bool)
        depth = torch.empty(n, dtype=dtype)
        bounds = torch.empty(n, 4, dtype=dtype)
        rect = torch.empty(n, 4, dtype=torch.int32)
        rect_radius = torch.empty(n, 4, dtype=torch.int32)
        args.means, args.quats, args.scales, args.opac, args.sh = (t.data_ptr() for t in ins)
        args.sh_rest = None if rest is None else rest.data_ptr()
        args.filter3d = None if filter3d is None else filter3d.data_ptr()
        args.params, args.means2d, args.radii, args.visible = (
            params.data_ptr(), means2d.data_ptr(), radii.data_ptr(), visible.data_ptr())
        args.depth, args.bounds, args.rect, args.rect_radius = (
            depth.data_ptr(), bounds.data_ptr(), rect.data_ptr(), rect_radius.data_ptr())
        rc = lib.gs_project_forward(ctypes.byref(args))
        if rc != 0:
            raise RuntimeError(f"gsbench fused projection forward failed (code {rc})")
        ctx.cfg = cfg
        ctx.ins = ins
        ctx.rest = rest
        ctx.set_materialize_grads(False)
        ctx.mark_non_differentiable(means2d, radii, visible, depth, bounds, rect, rect_radius)
        return params, means2d, radii, visible, depth, bounds, rect, rect_radius

    @staticmethod
    def backward(ctx, g_params, *_unused):
        if g_params is None:
            return None, None, None, None, None, None, None
        lib, args, n, npar, filter3d = ctx.cfg
        means, quats, scales, opac, sh = ctx.ins
        rest = ctx.rest
        dtype = means.dtype
        g_params = g_params.to(dtype).contiguous()
        g_means = torch.empty_like(means)
        g_quats = torch.empty_like(quats)
        g_scales = torch.empty_like(scales)
        g_opac = torch.empty_like(opac)
        g_sh = torch.empty_like(sh)  # every row written by the C++ backward
        g_rest = None if rest is None else torch.empty_like(rest)
        args.means, args.quats, args.scales, args.opac, args.sh = (t.data_ptr() for t in (means, quats, scales, opac, sh))
        args.sh_rest = None if rest is None else rest.data_ptr()
        args.g_sh_rest = None if g_rest is None else g_rest.data_ptr()
        args.filter3d = None if filter3d is None else filter3d.data_ptr()
        args.g_params = g_params.data_ptr()
        args.g_means, args.g_quats, args.g_scales, args.g_opac, args.g_sh = (
            t.data_ptr() for t in (g_means, g_quats, g_scales, g_opac, g_sh))
        rc = lib.gs_project_backward(ctypes.byref(args))
        if rc != 0:
            raise RuntimeError(f"gsbench fused projection backward failed (code {rc})")
        need = ctx.needs_input_grad
        grads = (g_means, g_quats, g_scales, g_opac, g_sh, g_rest)
        return tuple(g if need[k] else None for k, g in enumerate(grads)) + (None,)


def project_fused(gaussians: RasterGaussians, camera: Camera, kernel: str, settings: RasterSettings) -> Projection:
    """`project_torch` in one C++/OpenMP pass with a hand-written backward (every kernel)."""
    from gsbench.raster.build import load_library  # noqa: PLC0415

    if kernel not in FUSED_KERNELS:
        raise ValueError(f"the fused projection supports {FUSED_KERNELS}, not '{kernel}'")
    if not 0 <= settings.sh_degree <= 3:
        raise ValueError(f"SH degree must be in 0..3, got {settings.sh_degree}")
    lib = load_library()
    dtype = gaussians.means.dtype
    n = len(gaussians)
    sh = gaussians.sh.to(dtype)
    sh_rest = None if gaussians.sh_rest is None else gaussians.sh_rest.to(dtype)
    k_have = sh.shape[1] + (0 if sh_rest is None else sh_rest.shape[1])
    k_need = (settings.sh_degree + 1) ** 2
    if k_have < k_need or sh.shape[1] < 1:
        raise ValueError(f"sh has {k_have} coefficients per colour, degree {settings.sh_degree} needs {k_need}")
    W, H = int(camera.width), int(camera.height)
    ts = int(settings.tile_size)
    a = ProjArgs()
    a.n, a.dtype, a.kernel = n, 0 if dtype == torch.float32 else 1, FUSED_KERNELS.index(kernel)
    a.sh_degree, a.sh_k = int(settings.sh_degree), int(sh.shape[1])
    a.sh_rest_k = 0 if sh_rest is None else int(sh_rest.shape[1])
    a.width, a.height, a.tile = W, H, ts
    a.gx, a.gy = (W + ts - 1) // ts, (H + ts - 1) // ts
    a.nthreads = omp_threads()
    a.fx, a.fy, a.cx, a.cy = float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)
    a.near_z = float(settings.near)
    a.eps2d = float(settings.eps2d_for(kernel))
    a.aa = float(settings.antialias2d)
    a.surfel_k = float(settings.surfel_filter)
    a.limx = 1.3 * (0.5 * W) / camera.fx
    a.limy = 1.3 * (0.5 * H) / camera.fy
    a.R[:] = [float(x) for x in np.asarray(camera.R, dtype=np.float64).reshape(9)]
    a.t[:] = [float(x) for x in np.asarray(camera.t, dtype=np.float64).reshape(3)]
    a.C[:] = [float(x) for x in np.asarray(camera.center, dtype=np.float64).reshape(3)]
    a.L[:] = [float(x) for x in _left_mult(camera, torch.float64).numpy().reshape(16)]
    f3 = None
    if gaussians.filter3d is not None:
        f3 = gaussians.filter3d.detach().reshape(-1).to(dtype).contiguous()
        a.has_filter = 1
    npar = NUM_PARAMS[kernel]
    if kernel == "surfel":  # two scale columns used; a constant third keeps the (N, 3) layout
        scales = F.pad(gaussians.scales[:, :2].to(dtype), (0, 1), value=1.0)
    else:
        scales = gaussians.scales[:, :3].to(dtype)
    params, means2d, radii, visible, depth, bounds, rect, rect_radius = _FusedProjectFn.apply(
        gaussians.means, gaussians.quats.to(dtype), scales,
        gaussians.opacities.reshape(-1).to(dtype), sh, sh_rest, (lib, a, n, npar, f3),
    )
    return Projection(params=params, means2d=means2d, radii=radii, visible=visible, depth=depth, bounds=bounds,
                      rect=rect, rect_radius=rect_radius)


def project_torch(
    gaussians: RasterGaussians, camera: Camera, kernel: str, settings: RasterSettings
) -> Projection:
    """The vectorised PyTorch projection (autograd does the chain rules); every kernel."""
    dtype = gaussians.means.dtype
    n = len(gaussians)
    W, H = int(camera.width), int(camera.height)
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    near = settings.near
    Rcw, tcw, center = camera_tensors(camera, dtype)

    means = gaussians.means
    q = F.normalize(gaussians.quats, dim=-1)
    ncols = 2 if kernel == "surfel" else 3
    s = gaussians.scales[:, :ncols]
    o = gaussians.opacities.reshape(-1)
    if gaussians.filter3d is not None:
        f3 = gaussians.filter3d.detach().reshape(-1, 1).to(dtype)
        s2 = s * s
        s2f = s2 + f3
        o = o * torch.sqrt(torch.prod(s2 / s2f, dim=-1))
        s = torch.sqrt(s2f)

    mu = means @ Rcw.T + tcw  # camera space
    z = mu[:, 2]
    culled = z <= near
    zs = torch.where(culled, torch.ones_like(z), z)
    Rc = quat_to_rotmat(q @ _left_mult(camera, dtype).T)  # (N,3,3) = R_cw·R(q): Gaussian axes in camera space

    # SH colour at the world viewing direction.
    dirs = F.normalize(means - center, dim=-1)
    rgb = sh_to_rgb(gaussians.all_sh(), dirs, settings.sh_degree)

    u = mu[:, 0] / zs
    v = mu[:, 1] / zs
    gx = (W + settings.tile_size - 1) // settings.tile_size
    gy = (H + settings.tile_size - 1) // settings.tile_size
    ts = settings.tile_size
    with torch.no_grad():
        tau = torch.log(torch.clamp(255.0 * o.detach(), min=1e-30)).to(torch.float64)  # alpha >= 1/255 iff q <= 2 tau

    if kernel in ("ewa", "rade", "raymax"):
        M = Rc * s[:, None, :]
        a0, b, c0, g_det = _ewa_cov2d(M, mu, zs, camera, settings.eps2d_for(kernel))

        def shifted_det(e):  # det(J Σ Jᵀ + e I)
            return g_det + e * (a0 + c0) + e * e

        eps = settings.eps2d_for(kernel)
        k = settings.antialias2d
        a, c = a0 + (eps + k), c0 + (eps + k)
        det = shifted_det(eps + k)
        if k > 0:
            det0 = shifted_det(eps)
            okk = (det > 0) & (det0 > 0) & ~culled
            factor = torch.sqrt(torch.where(okk, det0, torch.ones_like(det0)) / torch.where(okk, det, torch.ones_like(det)))
            o = o * torch.where(okk, factor, torch.zeros_like(factor))
        ok = (det > 0) & ~culled
        # conic = adj/det evaluated on Σ2D/m (m = trace/2, constant) so that tiny covariances
        # (eps2d = 0, scales ~1e-8) do not overflow the backward of 1/det in float32
        msc = torch.where(ok, 0.5 * (a + c), torch.ones_like(a)).detach()
        a_n, b_n, c_n = a / msc, b / msc, c / msc
        det_n = det / (msc * msc)
        dets = torch.where(ok, det_n, torch.ones_like(det_n)) * msc
        conic = torch.stack([c_n / dets, -b_n / dets, a_n / dets], -1)
        means2d = torch.stack([fx * u + cx, fy * v + cy], -1)
        with torch.no_grad():
            mid = 0.5 * (a + c)
            lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
            radius = torch.ceil(3.0 * torch.sqrt(torch.clamp(lam, min=0.0)))
            radius = torch.where(ok, radius, torch.zeros_like(radius))
            valid = ok
            if kernel != "raymax":
                # alpha support: 0.5 dᵀ conic d <= tau  ->  |dx| <= sqrt(2 tau Σ_xx)
                t2 = torch.clamp(2.0 * tau, min=0.0)
                hx = torch.sqrt(t2 * a.detach().double()) * 1.001 + 0.01
                hy = torch.sqrt(t2 * c.detach().double()) * 1.001 + 0.01
                m2 = means2d.detach().double()
                bounds = torch.stack([m2[:, 0] - hx, m2[:, 0] + hx, m2[:, 1] - hy, m2[:, 1] + hy], -1)
            else:
                bounds = _raymax_bounds(M.detach().double(), mu.detach().double(), tau, camera)
            bounds = torch.where((tau > 0)[:, None], bounds, torch.tensor([BIG, -BIG, BIG, -BIG], dtype=torch.float64))
    else:  # surfel
        tu, tv, tw = Rc[:, :, 0], Rc[:, :, 1], Rc[:, :, 2]
        cols_u = s[:, 0:1] * tu
        cols_v = s[:, 1:2] * tv
        X = torch.stack([cols_u, cols_v, mu], -1)  # (N,3,3): rows = camera x,y,z; cols = u, v, 1
        cos = -_dot(mu, tw)
        sign = torch.where(cos >= 0, torch.ones_like(cos), -torch.ones_like(cos)).detach()
        normal = tw * sign[:, None]
        X0, X1, X2 = X[:, 0, :], X[:, 1, :], X[:, 2, :]
        cut2 = 9.0
        dd = cut2 * (X2[:, 0] ** 2 + X2[:, 1] ** 2) - X2[:, 2] ** 2
        ok = (dd != 0) & (cos != 0) & ~culled
        dds = torch.where(ok, dd, -torch.ones_like(dd))
        fvec = torch.stack([torch.full_like(dds, cut2), torch.full_like(dds, cut2), -torch.ones_like(dds)], -1) / dds[:, None]
        cnx = _dot(fvec, X0 * X2)
        cny = _dot(fvec, X1 * X2)
        means2d = torch.stack([fx * cnx + cx, fy * cny + cy], -1)
        with torch.no_grad():
            hnx = cnx * cnx - _dot(fvec, X0 * X0)
            hny = cny * cny - _dot(fvec, X1 * X1)
            ext_x = torch.sqrt(torch.clamp(fx * fx * hnx, min=1e-4))
            ext_y = torch.sqrt(torch.clamp(fy * fy * hny, min=1e-4))
            k = settings.surfel_filter  # the low-pass disc's 3σ, σ = 1/√k (2DGS: 3·0.707106)
            floor = 3.0 / math.sqrt(k) if k > 0 else 0.0
            radius = torch.ceil(torch.maximum(torch.maximum(ext_x, ext_y), torch.full_like(ext_x, floor)))
            radius = torch.where(ok, radius, torch.zeros_like(radius))
            valid = ok
            bounds = _surfel_bounds(X.detach().double(), means2d.detach().double(), tau, camera, settings.surfel_filter)
        conic = torch.zeros(n, 3, dtype=dtype)

    # kernel payload
    if kernel == "ewa":
        with torch.no_grad():
            idx = torch.argmin(s.detach(), dim=-1)
        nrm = torch.gather(Rc, 2, idx.view(-1, 1, 1).expand(-1, 3, 1)).squeeze(-1)
        sgn = torch.where(_dot(nrm, mu) > 0, -torch.ones_like(z), torch.ones_like(z)).detach()
        extra = torch.cat([z[:, None], nrm * sgn[:, None]], -1)
    elif kernel == "rade":
        # RaDe plane (reference Decision 9): J_r at the Jacobian-clamped centre d_c = (u_c, v_c, 1);
        # m = Σ⁻¹ d_c via whitening, p = −l_c (m_xy/(d_c·m) − (u_c, v_c)/nn²), l_c = z·nn.
        limx = 1.3 * (0.5 * W) / fx
        limy = 1.3 * (0.5 * H) / fy
        uc = torch.clamp(u, -limx, limx)
        vc = torch.clamp(v, -limy, limy)
        dc = torch.stack([uc, vc, torch.ones_like(uc)], -1)
        dt_ = (dc[:, :, None] * Rc).sum(1) / s  # S⁻¹ R_cᵀ d_c
        dm = _dot(dt_, dt_)
        mvec = (Rc * (dt_ / s)[:, None, :]).sum(-1)  # Σ⁻¹ d_c
        nn2 = uc * uc + vc * vc + 1.0
        lc = zs * torch.sqrt(nn2)
        dms = torch.where(culled, torch.ones_like(dm), dm)
        p0 = -lc * (mvec[:, 0] / dms - uc / nn2)
        p1 = -lc * (mvec[:, 1] / dms - vc / nn2)
        mut = (mu[:, :, None] * Rc).sum(1) / s  # whitened μ̃ = S⁻¹ R_cᵀ μ
        bvec = (Rc * (mut / s)[:, None, :]).sum(-1)  # b = Σ⁻¹ μ
        l = torch.linalg.vector_norm(mu, dim=-1)
        nrm = -F.normalize(bvec, dim=-1)
        extra = torch.cat([l[:, None], (p0 / fx)[:, None], (p1 / fy)[:, None], nrm], -1)
    elif kernel == "raymax":
        mut = (mu[:, :, None] * Rc).sum(1) / s  # μ̃ (N,3)
        E = Rc / s[:, None, :]  # rows ẽ_i = S⁻¹ R_cᵀ e_i  (E[:, i, :])
        c_ = _dot(mut, mut)
        c_s = torch.where(culled, torch.ones_like(c_), c_)
        A = E @ E.transpose(1, 2) / c_s[:, None, None]
        bvec = (E * mut[:, None, :]).sum(-1) / c_s[:, None]
        muh = mut / torch.sqrt(c_s)[:, None]
        vx = torch.linalg.cross(muh, E[:, 0, :], dim=-1)
        vy = torch.linalg.cross(muh, E[:, 1, :], dim=-1)
        Mp = torch.stack([_dot(vx, vx), _dot(vx, vy), _dot(vy, vy)], -1) / c_s[:, None]
        extra = torch.cat(
            [
                torch.stack([A[:, 0, 0], A[:, 0, 1], A[:, 0, 2], A[:, 1, 1], A[:, 1, 2], A[:, 2, 2]], -1),
                bvec,
                Mp,
                c_s[:, None],
                torch.stack([u, v], -1),
            ],
            -1,
        )
    else:
        # plane n·x = d through μ; local coordinates u = (x − μ)·t_u/s_u, v likewise (docs/methods/2dgs.md §3.1, §3.2, same math as
        # the homogeneous form, better conditioned in float32)
        dpl = _dot(normal, mu)
        au = tu / s[:, 0:1]
        av = tv / s[:, 1:2]
        extra = torch.cat([normal, dpl[:, None], au, _dot(mu, au)[:, None], av, _dot(mu, av)[:, None]], -1)

    o = torch.where(valid, o, torch.zeros_like(o))
    # Invalid (culled) Gaussians are never binned, so their payload is never read; only the opacity is zeroed.
    params = torch.cat([means2d, conic, o[:, None], rgb, extra], -1)

    with torch.no_grad():
        m2 = means2d.detach().double()
        r = radius.double()
        rect_r = _tile_rect(m2[:, 0] - r, m2[:, 0] + r, m2[:, 1] - r, m2[:, 1] + r, ts, gx, gy)
        bb = torch.clamp(bounds, -BIG, BIG)
        rect_b = torch.stack(
            [
                torch.clamp(torch.floor((bb[:, 0] - 0.5) / ts), 0, gx),
                torch.clamp(torch.floor((bb[:, 1] - 0.5) / ts) + 1, 0, gx),
                torch.clamp(torch.floor((bb[:, 2] - 0.5) / ts), 0, gy),
                torch.clamp(torch.floor((bb[:, 3] - 0.5) / ts) + 1, 0, gy),
            ],
            -1,
        )
        rect_area_r = (rect_r[:, 1] - rect_r[:, 0]) * (rect_r[:, 3] - rect_r[:, 2])
        visible = valid & (radius > 0) & (rect_area_r > 0)
        rect = torch.stack(
            [
                torch.maximum(rect_r[:, 0], rect_b[:, 0]),
                torch.minimum(rect_r[:, 1], rect_b[:, 1]),
                torch.maximum(rect_r[:, 2], rect_b[:, 2]),
                torch.minimum(rect_r[:, 3], rect_b[:, 3]),
            ],
            -1,
        )
        rect[:, 1] = torch.maximum(rect[:, 1], rect[:, 0])
        rect[:, 3] = torch.maximum(rect[:, 3], rect[:, 2])
        rect = torch.where(visible[:, None], rect, torch.zeros_like(rect)).to(torch.int32)
        rect_radius = torch.where(visible[:, None], rect_r, torch.zeros_like(rect_r)).to(torch.int32)
        radii = torch.where(visible, radius, torch.zeros_like(radius)).to(torch.int64)
        bounds = torch.clamp(bounds, -BIG, BIG).to(dtype)
    return Projection(
        params=params,
        means2d=torch.where(valid[:, None], means2d.detach(), torch.zeros_like(means2d.detach())),
        radii=radii,
        visible=visible,
        depth=z.detach(),
        bounds=bounds,
        rect=rect,
        rect_radius=rect_radius,
    )


def _raymax_bounds(M: torch.Tensor, mu: torch.Tensor, tau: torch.Tensor, camera: Camera) -> torch.Tensor:
    """Pixel box of the rays whose Mahalanobis distance to μ is <= 2·tau (tangent planes of the ellipsoid).

    A vertical image line x/z = x0 is the plane with normal n = (1, 0, -x0) through the camera; it touches
    the ellipsoid {(x-μ)ᵀΣ⁻¹(x-μ) <= k} iff (n·μ)² = k nᵀΣn: a quadratic in x0 (no cancellation form).
    Unbounded (the whole image) when the ellipsoid reaches the camera plane.
    """
    k = torch.clamp(2.0 * tau, min=0.0)
    S = M @ M.transpose(1, 2)
    out = []
    mz = mu[:, 2]
    for axis, f, c0 in ((0, camera.fx, camera.cx), (1, camera.fy, camera.cy)):
        ma = mu[:, axis]
        a2 = mz * mz - k * S[:, 2, 2]
        bq = ma * mz - k * S[:, axis, 2]
        disc = k * (mz * mz * S[:, axis, axis] - 2 * ma * mz * S[:, axis, 2] + ma * ma * S[:, 2, 2]) - k * k * (
            S[:, axis, axis] * S[:, 2, 2] - S[:, axis, 2] ** 2
        )
        sq = torch.sqrt(torch.clamp(disc, min=0.0))
        ok = a2 > 1e-12 * mz * mz
        a2s = torch.where(ok, a2, torch.ones_like(a2))
        lo = (bq - sq) / a2s
        hi = (bq + sq) / a2s
        lo_p = f * lo + c0
        hi_p = f * hi + c0
        pad = 1e-3 * (hi_p - lo_p).abs() + 0.01
        lo_p = torch.where(ok, lo_p - pad, torch.full_like(lo_p, -BIG))
        hi_p = torch.where(ok, hi_p + pad, torch.full_like(hi_p, BIG))
        out += [lo_p, hi_p]
    return torch.stack(out, -1)


def _surfel_bounds(X: torch.Tensor, m2: torch.Tensor, tau: torch.Tensor, camera: Camera,
                   filter_k: float) -> torch.Tensor:
    """Pixel box of u²+v² <= 2 tau (the exact box of the splat's ellipse, cutoff² = 2 tau) ∪ the low-pass
    disc k|Δ|² <= 2 tau (none when the filter is off, k = 0)."""
    k = torch.clamp(2.0 * tau, min=0.0)
    X0, X1, X2 = X[:, 0, :], X[:, 1, :], X[:, 2, :]
    dd = k * (X2[:, 0] ** 2 + X2[:, 1] ** 2) - X2[:, 2] ** 2
    ok = dd < -1e-12 * X2[:, 2] ** 2
    dds = torch.where(ok, dd, -torch.ones_like(dd))
    fvec = torch.stack([k, k, -torch.ones_like(k)], -1) / dds[:, None]
    out = []
    for Xa, f, c0 in ((X0, camera.fx, camera.cx), (X1, camera.fy, camera.cy)):
        cn = _dot(fvec, Xa * X2)
        h = cn * cn - _dot(fvec, Xa * Xa)
        ext = torch.sqrt(torch.clamp(h, min=0.0))
        lo = f * (cn - ext) + c0
        hi = f * (cn + ext) + c0
        pad = 1e-3 * (hi - lo).abs() + 0.01
        out += [torch.where(ok, lo - pad, torch.full_like(lo, -BIG)), torch.where(ok, hi + pad, torch.full_like(hi, BIG))]
    box = torch.stack(out, -1)
    if filter_k <= 0:
        return box
    # low-pass disc: k|Δ|² <= 2 tau  ->  |Δ| <= sqrt(2 tau / k)
    r = torch.sqrt(torch.clamp(2.0 * tau / filter_k, min=0.0)) * 1.001 + 0.01
    disc = torch.stack([m2[:, 0] - r, m2[:, 0] + r, m2[:, 1] - r, m2[:, 1] + r], -1)
    return torch.stack(
        [
            torch.minimum(box[:, 0], disc[:, 0]),
            torch.maximum(box[:, 1], disc[:, 1]),
            torch.minimum(box[:, 2], disc[:, 2]),
            torch.maximum(box[:, 3], disc[:, 3]),
        ],
        -1,
    )


def pixel_rays(camera: Camera, dtype=torch.float64) -> torch.Tensor:
    """(H, W, 3) camera-space rays ((i+0.5-cx)/fx, (j+0.5-cy)/fy, 1)."""
    xs = (torch.arange(camera.width, dtype=dtype) + 0.5 - camera.cx) / camera.fx
    ys = (torch.arange(camera.height, dtype=dtype) + 0.5 - camera.cy) / camera.fy
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([xx, yy, torch.ones_like(xx)], -1)


__all__ = ["NUM_PARAMS", "Projection", "project", "project_fused", "project_torch", "projection_impl", "quat_to_rotmat",
           "pixel_rays", "math"]
