"""The projection in vectorised PyTorch (autograd): every kernel's payload (`gsbench.raster.payload`) from the
Gaussians, written from the contract (`gsbench.raster.types`); the oracle of the fused projection."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from gsbench.data.camera import Camera
from gsbench.raster.payload import Projection, camera_tensors, left_mult, quat_to_rotmat
from gsbench.raster.sh import sh_to_rgb
from gsbench.raster.types import RasterGaussians, RasterSettings

BIG = 1.0e6  # pixel-box sentinel (kept finite: the C++ is built with -ffinite-math-only)
SURFEL_OFF = 1.0e6  # px: the payload centre of a surfel whose disc reaches the camera plane (no low-pass term)


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
    Rc = quat_to_rotmat(q @ left_mult(camera, dtype).T)  # (N,3,3) = R_cw·R(q): Gaussian axes in camera space

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
        ok = (cos != 0) & ~culled
        crossing = ok & (dd >= 0)  # the 3σ disc reaches the camera plane: no screen box (contract, surfel)
        dds = torch.where(ok & ~crossing, dd, -torch.ones_like(dd))
        fvec = torch.stack([torch.full_like(dds, cut2), torch.full_like(dds, cut2), -torch.ones_like(dds)], -1) / dds[:, None]
        cnx = _dot(fvec, X0 * X2)
        cny = _dot(fvec, X1 * X2)
        box_centre = torch.stack([fx * cnx + cx, fy * cny + cy], -1)
        projected = torch.stack([fx * u + cx, fy * v + cy], -1).detach()
        means2d = torch.where(crossing[:, None], projected, box_centre)
        with torch.no_grad():
            hnx = cnx * cnx - _dot(fvec, X0 * X0)
            hny = cny * cny - _dot(fvec, X1 * X1)
            ext_x = torch.sqrt(torch.clamp(fx * fx * hnx, min=1e-4))
            ext_y = torch.sqrt(torch.clamp(fy * fy * hny, min=1e-4))
            k = settings.surfel_filter  # the low-pass disc's 3σ, σ = 1/√k (2DGS: 3·0.707106)
            floor = 3.0 / math.sqrt(k) if k > 0 else 0.0
            radius = torch.ceil(torch.maximum(torch.maximum(ext_x, ext_y), torch.full_like(ext_x, floor)))
            radius = torch.where(crossing, _corner_radius(means2d.double(), W, H).to(radius.dtype), radius)
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
    payload_centre = means2d
    if kernel == "surfel":  # a crossing disc's payload centre is moved off the image: no low-pass term (contract)
        payload_centre = means2d + torch.where(crossing, SURFEL_OFF, 0.0).to(dtype)[:, None] * torch.tensor([1.0, 0.0], dtype=dtype)
    params = torch.cat([payload_centre, conic, o[:, None], rgb, extra], -1)

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


def _corner_radius(centre: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """A radius from each screen centre (N,2) that reaches every image corner (+1): its tile rectangle is the
    whole image (a surfel disc that reaches the camera plane, contract)."""
    dx = torch.maximum(centre[:, 0].abs(), (centre[:, 0] - width).abs())
    dy = torch.maximum(centre[:, 1].abs(), (centre[:, 1] - height).abs())
    return torch.ceil(torch.sqrt(dx * dx + dy * dy)) + 1.0


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
