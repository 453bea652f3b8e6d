"""Compositing as a differentiable operation: `RasterFn` runs the C++ tile kernel (``csrc/composite.cpp``) forward
and backward on a projected, binned render (`RenderState`), and hands the densification statistics (the
screen-space gradient, its absolute value) to the caller's leaves."""

from __future__ import annotations

import ctypes
import time

import torch

from gsbench.raster import profiling


def pointer(t: torch.Tensor | None):
    return None if t is None else ctypes.c_void_p(t.data_ptr())


class RenderState:
    """Everything one render shares between the forward and the backward of the C++ kernel."""

    def __init__(self, lib, args, kernel, n, m2d_leaf, absgrad, height, width, dtype, proj_bufs):
        self.lib = lib
        self.args = args
        self.kernel = kernel
        self.n = n
        self.m2d_leaf = m2d_leaf
        self.absgrad = absgrad
        self.height = height
        self.width = width
        self.dtype = dtype
        self.bufs = proj_bufs  # keeps the tensors the args point to alive
        self.saved = {}
        self.pairs_fwd = 0
        self.pairs_bwd = 0
        self.profiled = profiling.profile is not None
        self.profile_tag = profiling.profile_tag  # the backward runs after `profile_as` has ended
        self.centre_z = None  # surfel: the centres' camera z, for the 2DGS densification shortcut


class RasterFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, params, plane_d, state):  # noqa: D401
        a = state.args
        H, W, dt = state.height, state.width, state.dtype
        want = state.want
        e = torch.empty(0, dtype=dt)
        rgb = torch.empty(H, W, 3, dtype=dt) if want["rgb"] else e
        alpha = torch.empty(H, W, dtype=dt)
        depth = torch.empty(H, W, dtype=dt) if want["depth"] else e
        med = torch.empty(H, W, dtype=dt) if want["median_depth"] else e
        nrm = torch.empty(H, W, 3, dtype=dt) if want["normal"] else e
        dist = torch.empty(H, W, dtype=dt) if want["distortion"] else e
        plane = torch.empty(H, W, dtype=dt) if want["plane_distance"] else e
        plane_c = plane_d.detach().contiguous() if want["plane_distance"] else None
        T_final = torch.empty(H, W, dtype=dt)
        last = torch.empty(H, W, dtype=torch.int32)
        medi = torch.empty(H, W, dtype=torch.int32) if want["median_depth"] else None
        M1 = torch.empty(H, W, dtype=dt) if want["distortion"] else None
        M2 = torch.empty(H, W, dtype=dt) if want["distortion"] else None
        params_c = params.detach().contiguous()
        a.params = params_c.data_ptr()
        a.out_rgb = rgb.data_ptr() if want["rgb"] else None
        a.out_alpha = alpha.data_ptr()
        a.out_depth = depth.data_ptr() if want["depth"] else None
        a.out_median = med.data_ptr() if want["median_depth"] else None
        a.out_normal = nrm.data_ptr() if want["normal"] else None
        a.out_dist = dist.data_ptr() if want["distortion"] else None
        a.plane_d = None if plane_c is None else plane_c.data_ptr()
        a.out_plane = plane.data_ptr() if want["plane_distance"] else None
        a.T_final = T_final.data_ptr()
        a.last = last.data_ptr()
        a.median_idx = None if medi is None else medi.data_ptr()
        a.M1 = None if M1 is None else M1.data_ptr()
        a.M2 = None if M2 is None else M2.data_ptr()
        t0 = time.perf_counter()
        rc = state.lib.gs_forward(ctypes.byref(a))
        profiling.record("raster_fwd", time.perf_counter() - t0)
        if rc != 0:
            raise RuntimeError(f"gsbench rasterizer forward failed (code {rc})")
        state.pairs_fwd = int(a.pairs)
        state.saved = {"T": T_final, "last": last, "medi": medi, "M1": M1, "M2": M2, "params": params_c,
                       "plane_d": plane_c}
        ctx.state = state
        ctx.set_materialize_grads(False)
        return rgb, alpha, depth, med, nrm, dist, plane

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_depth, g_med, g_nrm, g_dist, g_plane):
        state = ctx.state
        a = state.args
        dt = state.dtype
        want = state.want

        def prep(g, key):
            if g is None or not want[key] or g.numel() == 0:
                return None
            return g.to(dt).contiguous()

        grads = {
            "g_rgb": prep(g_rgb, "rgb"),
            "g_alpha": None if g_alpha is None else g_alpha.to(dt).contiguous(),
            "g_depth": prep(g_depth, "depth"),
            "g_median": prep(g_med, "median_depth"),
            "g_normal": prep(g_nrm, "normal"),
            "g_dist": prep(g_dist, "distortion"),
            "g_plane": prep(g_plane, "plane_distance"),
        }
        for k, v in grads.items():
            setattr(a, k, None if v is None else v.data_ptr())
        s = state.saved
        a.params = s["params"].data_ptr()
        a.T_final = s["T"].data_ptr()
        a.last = s["last"].data_ptr()
        a.median_idx = None if s["medi"] is None else s["medi"].data_ptr()
        a.M1 = None if s["M1"] is None else s["M1"].data_ptr()
        a.M2 = None if s["M2"] is None else s["M2"].data_ptr()
        a.plane_d = None if s["plane_d"] is None else s["plane_d"].data_ptr()
        n, npar = state.n, int(a.n_params)
        gp = torch.zeros(n, npar, dtype=dt)
        g_plane_d = torch.zeros(n, dtype=dt) if want["plane_distance"] else None
        a.grad_plane = None if g_plane_d is None else g_plane_d.data_ptr()
        absg = torch.zeros(n, dtype=dt)
        proxy = torch.zeros(n, 2, dtype=dt) if state.kernel == "raymax" else torch.zeros(1, 2, dtype=dt)  # raymax only
        a.grad_params = gp.data_ptr()
        a.absgrad = absg.data_ptr()
        a.proxy = proxy.data_ptr()
        t0 = time.perf_counter()
        if any(v is not None for v in grads.values()):
            rc = state.lib.gs_backward(ctypes.byref(a))
            if rc != 0:
                raise RuntimeError(f"gsbench rasterizer backward failed (code {rc})")
            state.pairs_bwd = int(a.pairs)
        if state.profiled:  # a render made while the timers were off stays out of them
            profiling.record("raster_bwd", time.perf_counter() - t0, state.profile_tag)
        # densification statistics
        if state.kernel == "raymax":
            m2g = proxy
        elif state.kernel == "surfel":
            m2g = surfel_shortcut_grad(gp, s["params"], state.centre_z.to(dt), a.fx, a.fy)
        else:
            m2g = gp[:, :2]
        leaf = state.m2d_leaf
        m2g = m2g.to(leaf.dtype)
        leaf.grad = m2g.clone() if leaf.grad is None else leaf.grad + m2g
        state.absgrad += absg.to(state.absgrad.dtype)
        return gp, g_plane_d, None


def surfel_shortcut_grad(grad_params: torch.Tensor, params: torch.Tensor, centre_z: torch.Tensor, fx: float,
                         fy: float) -> torch.Tensor:
    """2DGS's densification statistic for surfels, in pixels (N,2) (docs/methods/2dgs.md §3.6).

    2DGS takes ``(∂L/∂Tu.z·Tw.z, ∂L/∂Tv.z·Tw.z)`` (then × W/2, H/2 to NDC): the gradient of the loss for a
    screen-space move of the centre at fixed depth, through the ray-splat intersection only (the low-pass
    filter's ∂L/∂means2d is left out). Tu.z = fx·μx + cx·μz, so a move of δ pixels in x is μ += (δ·μz/fx) e_x
    with the frame fixed. The payload holds the plane n·x = d and the local offsets b_u = μ·a_u,
    b_v = μ·a_v (d = n·μ), so with g the gradient of those columns
    ``∂L/∂μ = g_d n + g_bu a_u + g_bv a_v`` and the statistic is ``(∂L/∂μx·μz/fx, ∂L/∂μy·μz/fy)``.
    """
    x = params[:, 9:21]  # n (3), d, a_u (3), b_u, a_v (3), b_v  (csrc/composite.cpp surfel payload)
    g = grad_params[:, 9:21]
    dmu = g[:, 3:4] * x[:, 0:3] + g[:, 7:8] * x[:, 4:7] + g[:, 11:12] * x[:, 8:11]
    return torch.stack([dmu[:, 0] * centre_z / fx, dmu[:, 1] * centre_z / fy], -1)
