"""``rasterize``: one differentiable render of the shared rasterizer (`gsbench.raster`, docs/rasterizer.md).

Validate (`gsbench.raster.validation`), project (`gsbench.raster.projection`), sort and bin into tiles
(`gsbench.raster.binning`), composite (`gsbench.raster.composite`), then, when asked, GGGS's stochastic-solid
depth on the same tile lists (`gsbench.raster.solid_depth`), each phase timed by
`gsbench.raster.profiling`; ``GSBENCH_RASTER=reference`` renders with the dense reference instead.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Iterable
from dataclasses import replace

import torch

from gsbench.data.camera import Camera
from gsbench.native.build import omp_threads
from gsbench.raster import profiling, reference
from gsbench.raster.abi import GsArgs, library
from gsbench.raster.binning import bin_tiles
from gsbench.raster.composite import RasterFn, RenderState
from gsbench.raster.payload import NUM_PARAMS, camera_tensors
from gsbench.raster.projection import project
from gsbench.raster.solid_depth import SolidFn, inverse_ray_norms, ray_inv_sigma
from gsbench.raster.types import OUTPUTS, RasterGaussians, RasterSettings, RenderOutput
from gsbench.raster.validation import background_color, check_kernel_outputs, validate_gaussians
from gsbench.switches import RASTER

KERNEL_ID = {"ewa": 0, "rade": 1, "raymax": 2, "surfel": 3}  # the kernel ids of csrc/composite.cpp


def rasterize(
    gaussians: RasterGaussians,
    camera: Camera,
    *,
    kernel: str,
    outputs: Iterable[str] = ("rgb",),
    background=None,
    settings: RasterSettings = RasterSettings(),
) -> RenderOutput:
    """Render ``outputs`` of ``gaussians`` seen by ``camera`` with ``kernel``; differentiable.

    See `gsbench.raster.types` for every definition. ``background`` (3,) overrides
    ``settings.background`` (a tensor may require grad). Only the requested outputs are returned
    (what the kernel accumulates alongside: `gsbench.raster.types`).
    """
    outs = check_kernel_outputs(kernel, outputs)
    validate_gaussians(gaussians, kernel)
    if camera.width < 1 or camera.height < 1:
        raise ValueError(f"camera image size must be >= 1x1, got {camera.width}x{camera.height}")
    if RASTER.value() == "reference":
        warnings.warn("GSBENCH_RASTER=reference: using the slow dense PyTorch rasterizer", stacklevel=2)
        return reference.render(gaussians, camera, kernel=kernel, outputs=outs, settings=_with_bg(settings, background))

    lib = library()
    dtype = gaussians.means.dtype
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"gaussians must be float32 or float64, got {dtype}")
    W, H = int(camera.width), int(camera.height)
    ts = int(settings.tile_size)
    if ts != 16:
        raise ValueError(f"the fast rasterizer uses 16x16 tiles; settings.tile_size={ts} is not supported")
    n = len(gaussians)
    bg = background_color(background, settings, dtype)

    t0 = time.perf_counter()
    proj = project(gaussians, camera, kernel, settings)
    profiling.record("projection", time.perf_counter() - t0)

    t0 = time.perf_counter()
    bins = bin_tiles(lib, proj, n, dtype, kernel, outs, W, H, ts, (camera.fx, camera.fy, camera.cx, camera.cy),
                     settings.surfel_filter)
    profiling.record("sort_bin", time.perf_counter() - t0)

    want = {o: (o in outs) for o in OUTPUTS}
    want_solid = "solid_depth" in outs
    bounds = proj.bounds.contiguous()
    a = GsArgs()
    a.kernel = KERNEL_ID[kernel]
    a.dtype = 0 if dtype == torch.float32 else 1
    a.width, a.height, a.tiles_x, a.tiles_y = W, H, bins.tiles_x, bins.tiles_y
    a.n_gauss = n
    a.n_params = NUM_PARAMS[kernel]
    a.nthreads = omp_threads()
    a.want_rgb = int(want["rgb"])
    a.want_depth = int(want["depth"])
    a.want_median = int(want["median_depth"])
    a.want_normal = int(want["normal"])
    a.want_dist = int(want["distortion"])
    a.detach_dist = int(bool(settings.detach_distortion_weights))
    a.fx, a.fy, a.cx, a.cy = camera.fx, camera.fy, camera.cx, camera.cy
    a.near_z, a.far_z = settings.near, settings.far
    a.surfel_k = float(settings.surfel_filter)
    a.bounds = bounds.data_ptr()
    a.depth_key = bins.depth_key.data_ptr()
    a.tile_offsets = bins.offsets.data_ptr()
    a.tile_list = bins.tile_list.data_ptr()

    m2d_leaf = proj.means2d.detach().clone().requires_grad_(True)
    absgrad = torch.zeros(n, dtype=dtype)
    # plane_distance = Σ w_i d_i (d_i = −n_i·μ_i), composited in the same pass as the colour, like a 4th channel
    plane_d = _plane_distances(proj.params, gaussians.means, camera, kernel) if want["plane_distance"] else None
    a.want_plane = int(want["plane_distance"])
    state = RenderState(lib, a, kernel, n, m2d_leaf, absgrad, H, W, dtype, (bounds, bins.depth_key, bins.offsets, bins.tile_list, bins.rect))
    state.want = want
    if kernel == "surfel":
        state.centre_z = proj.depth

    empty = torch.empty(0, dtype=dtype)
    plane_in = empty if plane_d is None else plane_d
    rgb, alpha, dacc, med, nrm, dist, plane = RasterFn.apply(proj.params, plane_in, state)

    res = RenderOutput(width=W, height=H)
    if want["rgb"]:
        if bool((bg != 0).any()) or bg.requires_grad:
            rgb = rgb + (1.0 - alpha).unsqueeze(-1) * bg
        res.rgb = rgb
    if want["alpha"]:
        res.alpha = alpha
    if want["depth"]:
        res.depth = dacc / torch.clamp(alpha, min=1e-10)
    if want["median_depth"]:
        res.median_depth = med
    if want["normal"]:
        res.normal = nrm
    if want["distortion"]:
        res.distortion = dist
    if want["plane_distance"]:
        res.plane_distance = plane
    if want_solid:
        t = SolidFn.apply(proj.params, ray_inv_sigma(gaussians, camera, dtype), state, settings)
        res.solid_depth = t * inverse_ray_norms(camera, dtype)
    res.means2d = m2d_leaf
    res.radii = proj.radii
    res.visible = proj.visible
    res.extras = {"absgrad": absgrad, "pairs": state.pairs_fwd, "tile_pairs": bins.capacity, "state": state}
    return res


# payload column of the first normal component per kernel (gsbench.raster.payload); raymax: b' = Σ⁻¹μ/c
_NORMAL_COLUMN = {"ewa": 10, "rade": 12, "surfel": 9, "raymax": 15}


def _plane_distances(params: torch.Tensor, means: torch.Tensor, camera: Camera, kernel: str) -> torch.Tensor:
    """d_i = −n_i·μ_i (N,), differentiable (contract ``plane_distance``, docs/methods/pgsr.md §3.1): n_i from
    the payload (raymax: −normalize(b'), its normal on the central ray), μ_i the camera-space centre.
    Culled rows are never binned, so their value is unused."""
    R, t, _ = camera_tensors(camera, params.dtype)
    mu = means.to(params.dtype) @ R.T + t
    c = _NORMAL_COLUMN[kernel]
    normal = params[:, c:c + 3]
    if kernel == "raymax":
        normal = -torch.nn.functional.normalize(normal, dim=-1)
    return -(normal * mu).sum(-1)


def _with_bg(settings: RasterSettings, background) -> RasterSettings:
    if background is None:
        return settings
    bg = background.detach().cpu().tolist() if isinstance(background, torch.Tensor) else list(background)
    return replace(settings, background=tuple(float(x) for x in bg))
