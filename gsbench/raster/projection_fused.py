"""The fused projection: one OpenMP pass over the Gaussians forward and a hand-written backward, in double
precision inside (``csrc/project.cpp``), for every kernel; `gsbench.raster.projection_torch` is its
oracle (tests/test_raster_projection.py, tests/test_projection_fused_raymax_surfel.py)."""

from __future__ import annotations

import ctypes

import numpy as np
import torch
import torch.nn.functional as F

from gsbench.data.camera import Camera
from gsbench.native.build import omp_threads
from gsbench.raster.abi import ProjArgs, library
from gsbench.raster.payload import NUM_PARAMS, Projection, left_mult
from gsbench.raster.types import RasterGaussians, RasterSettings

FUSED_KERNELS = ("ewa", "rade", "raymax", "surfel")  # index = the kernel id of csrc/project.cpp


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
    if kernel not in FUSED_KERNELS:
        raise ValueError(f"the fused projection supports {FUSED_KERNELS}, not '{kernel}'")
    if not 0 <= settings.sh_degree <= 3:
        raise ValueError(f"SH degree must be in 0..3, got {settings.sh_degree}")
    lib = library()
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
    a.L[:] = [float(x) for x in left_mult(camera, torch.float64).numpy().reshape(16)]
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
