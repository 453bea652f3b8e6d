"""GOF opacity field at 3D points (``gsbench.raster.integrate``), C++ per view, min over views.

Same rule as `gsbench.raster.reference.integrate_reference` (GOF doc §1.7): per view, a point in front
of the near plane that projects inside the image sees the Gaussians binned to its pixel's tile (3σ
tile rectangle), each evaluated on the point's own ray at ``t = min(t*, z_point)``; the view's opacity
is ``1 − Π(1 − α)`` without early termination; the result is the minimum over the views that see the
point (1 where none does). No gradient.
"""

from __future__ import annotations

import ctypes
from collections.abc import Sequence

import torch

from gsbench.data.camera import Camera
from gsbench.raster.types import RasterGaussians, RasterSettings


class GsIntArgs(ctypes.Structure):
    _fields_ = [(n, ctypes.c_int64) for n in ("n_points", "n_params", "dtype", "nthreads")] + [
        ("near_z", ctypes.c_double)
    ] + [(n, ctypes.c_void_p) for n in ("params", "tile_offsets", "tile_list", "point_tile", "rays", "out")]


@torch.no_grad()
def integrate(
    gaussians: RasterGaussians,
    cameras: Sequence[Camera],
    points: torch.Tensor,
    *,
    kernel: str = "raymax",
    settings: RasterSettings = RasterSettings(),
    chunk: int = 1 << 20,
) -> torch.Tensor:
    from gsbench.raster import _check_finite, validate_gaussians  # noqa: PLC0415
    from gsbench.raster.build import load_library  # noqa: PLC0415
    from gsbench.raster.projection import NUM_PARAMS, project  # noqa: PLC0415

    if kernel != "raymax":
        raise NotImplementedError(
            f"integrate is GOF's opacity field, defined for kernel='raymax' only (got {kernel!r}); "
            "RaDe-GS and 2DGS mesh from rendered depth (TSDF)"
        )
    validate_gaussians(gaussians, kernel)
    if points.dim() != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (P, 3), got {tuple(points.shape)}")
    _check_finite("points", points)
    lib = load_library()
    dtype = gaussians.means.dtype
    g = type(gaussians)(*(None if x is None else x.detach() for x in (
        gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities, gaussians.sh, gaussians.filter3d)))
    pts = points.detach().to(torch.float64)
    result = torch.ones(pts.shape[0], dtype=dtype)
    ts = settings.tile_size
    for cam in cameras:
        W, H = int(cam.width), int(cam.height)
        gx, gy = (W + ts - 1) // ts, (H + ts - 1) // ts
        proj = project(g, cam, kernel, settings)
        vis_idx = torch.nonzero(proj.visible).reshape(-1)
        order = vis_idx[torch.sort(proj.depth[vis_idx], stable=True).indices].contiguous()
        rect = proj.rect_radius.contiguous()
        areas = (rect[:, 1] - rect[:, 0]).long() * (rect[:, 3] - rect[:, 2]).long()
        cap = int(areas.sum())
        offsets = torch.zeros(gx * gy + 1, dtype=torch.int32)
        tile_list = torch.empty(max(cap, 1), dtype=torch.int32)
        lib.gs_bin(order.numel(), order.data_ptr(), rect.data_ptr(), gx, gy, offsets.data_ptr(), tile_list.data_ptr(), cap,
                   max(1, torch.get_num_threads()))
        params = proj.params.detach().contiguous()
        R = torch.as_tensor(cam.R, dtype=torch.float64)
        t = torch.as_tensor(cam.t, dtype=torch.float64)
        for s in range(0, pts.shape[0], chunk):
            xc = pts[s : s + chunk] @ R.T + t
            z = xc[:, 2]
            front = z > settings.near
            zs = torch.where(front, z, torch.ones_like(z))
            rx, ry = xc[:, 0] / zs, xc[:, 1] / zs
            u = cam.fx * rx + cam.cx
            v = cam.fy * ry + cam.cy
            inview = front & (u >= 0) & (u < W) & (v >= 0) & (v < H)
            tx = torch.clamp(torch.floor(u), 0, W - 1).long() // ts
            ty = torch.clamp(torch.floor(v), 0, H - 1).long() // ts
            tile = torch.where(inview, ty * gx + tx, torch.full_like(tx, -1)).to(torch.int32).contiguous()
            rays = torch.stack([rx, ry, zs], -1).to(dtype).contiguous()
            out = torch.ones(xc.shape[0], dtype=dtype)
            a = GsIntArgs()
            a.n_points, a.n_params = xc.shape[0], NUM_PARAMS[kernel]
            a.dtype = 0 if dtype == torch.float32 else 1
            a.nthreads = max(1, torch.get_num_threads())
            a.near_z = settings.near
            a.params, a.tile_offsets, a.tile_list = params.data_ptr(), offsets.data_ptr(), tile_list.data_ptr()
            a.point_tile, a.rays, a.out = tile.data_ptr(), rays.data_ptr(), out.data_ptr()
            lib.gs_integrate(ctypes.byref(a))
            sl = result[s : s + chunk]
            sl.copy_(torch.where(inview, torch.minimum(sl, out), sl))
    return result
