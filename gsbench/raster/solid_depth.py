"""The ``solid_depth`` output on the fast path (GGGS's stochastic-solid median depth, docs/methods/gggs.md §1–§2,
contract in `gsbench.raster.types`): each Gaussian's width along its centre ray, and `SolidFn`, the autograd
function around ``csrc/solid.cpp``, which runs after the compositing on its tile lists, its per-pixel last
blended position and final transmittance. The dense reference is `gsbench.raster.reference` with
`gsbench.raster.stochastic_solid`."""

from __future__ import annotations

import ctypes
import time

import torch

from gsbench.data.camera import Camera
from gsbench.geometry.depth import pixel_centres
from gsbench.raster import profiling
from gsbench.raster.abi import SolidArgs
from gsbench.raster.payload import camera_tensors, quat_to_rotmat
from gsbench.raster.types import RasterGaussians, RasterSettings


def ray_inv_sigma(gaussians: RasterGaussians, camera: Camera, dtype: torch.dtype) -> torch.Tensor:
    """1/σ_i = √(r̂ᵀ Σ_i⁻¹ r̂) (N,), r̂ the unit direction from the camera centre to the mean, Σ from the scales
    after the 3D filter (s_eff = √(s² + σ_f²)): the Gaussian's width along its centre ray, GGGS's ``rsigmat``.
    Differentiable in the means, rotations and scales."""
    _, _, centre = camera_tensors(camera, dtype)
    rotation = quat_to_rotmat(torch.nn.functional.normalize(gaussians.quats.to(dtype), dim=-1))
    scales = gaussians.scales.to(dtype)
    if gaussians.filter3d is not None:
        scales = torch.sqrt(scales * scales + gaussians.filter3d.to(dtype)[:, None])
    direction = torch.nn.functional.normalize(gaussians.means.to(dtype) - centre, dim=-1)
    along_axes = torch.einsum("ni,nik->nk", direction, rotation)  # r̂ · (k-th axis)
    return torch.sqrt(((along_axes / scales) ** 2).sum(-1))


def inverse_ray_norms(camera: Camera, dtype: torch.dtype) -> torch.Tensor:
    """1/‖r‖ (H, W) of each pixel's ray r = ((x − cx)/fx, (y − cy)/fy, 1): ray distance → camera z."""
    pix = pixel_centres(camera, dtype)
    rx, ry = (pix[..., 0] - camera.cx) / camera.fx, (pix[..., 1] - camera.cy) / camera.fy
    return 1.0 / torch.sqrt(rx * rx + ry * ry + 1.0)


class SolidFn(torch.autograd.Function):
    """The ray distance t (H, W) where the stochastic-solid transmittance crosses ½ (0: none), from the rade
    payload and 1/σ; the backward adds the mean-2D gradient to the render's densification statistics, as
    `gsbench.raster.composite.RasterFn` does for its outputs."""

    @staticmethod
    def forward(ctx, params, inv_sigma, state, settings: RasterSettings):  # noqa: D401
        ca = state.args
        a = SolidArgs()
        a.dtype, a.width, a.height, a.tiles_x, a.tiles_y = ca.dtype, ca.width, ca.height, ca.tiles_x, ca.tiles_y
        a.n_gauss, a.nthreads, a.rounds = ca.n_gauss, ca.nthreads, int(settings.solid_rounds)
        a.search_range, a.min_transmittance = float(settings.solid_search_range), float(settings.solid_min_transmittance)
        a.bounds, a.tile_offsets, a.tile_list = ca.bounds, ca.tile_offsets, ca.tile_list
        saved = state.saved
        params_c = saved["params"]  # the compositing's contiguous copy of this payload
        isg = inv_sigma.detach().to(state.dtype).contiguous()
        out_t = torch.zeros(state.height, state.width, dtype=state.dtype)
        a.params, a.last, a.T_final = params_c.data_ptr(), saved["last"].data_ptr(), saved["T"].data_ptr()
        a.inv_sigma, a.out_t = isg.data_ptr(), out_t.data_ptr()
        t0 = time.perf_counter()
        rc = state.lib.gs_solid_forward(ctypes.byref(a))
        profiling.record("solid_fwd", time.perf_counter() - t0)
        if rc != 0:
            raise RuntimeError(f"gsbench solid-depth forward failed (code {rc}); solid_rounds must be >= 1")
        ctx.save_for_backward(out_t)  # the output kept on ctx itself would be a reference cycle through the graph
        ctx.solid = (a, state, params_c, isg)
        ctx.set_materialize_grads(False)
        return out_t

    @staticmethod
    def backward(ctx, g_t):
        a, state, params_c, isg = ctx.solid
        (out_t,) = ctx.saved_tensors
        if g_t is None:
            return None, None, None, None
        dt = state.dtype
        g = g_t.to(dt).contiguous()
        n = int(a.n_gauss)
        grad_params = torch.zeros(n, params_c.shape[1], dtype=dt)
        grad_isg = torch.zeros(n, dtype=dt)
        absgrad = torch.zeros(n, dtype=dt)
        a.params, a.inv_sigma, a.out_t, a.g_t = params_c.data_ptr(), isg.data_ptr(), out_t.data_ptr(), g.data_ptr()
        a.grad_params, a.grad_inv_sigma, a.absgrad = grad_params.data_ptr(), grad_isg.data_ptr(), absgrad.data_ptr()
        t0 = time.perf_counter()
        rc = state.lib.gs_solid_backward(ctypes.byref(a))
        if state.profiled:
            profiling.record("solid_bwd", time.perf_counter() - t0, state.profile_tag)
        if rc != 0:
            raise RuntimeError(f"gsbench solid-depth backward failed (code {rc})")
        leaf = state.m2d_leaf
        m2g = grad_params[:, :2].to(leaf.dtype)
        leaf.grad = m2g.clone() if leaf.grad is None else leaf.grad + m2g
        state.absgrad += absgrad.to(state.absgrad.dtype)
        return grad_params, grad_isg, None, None
