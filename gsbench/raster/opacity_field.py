"""GOF opacity field at 3D points, `OpacityField` (behind `gsbench.raster.integrate`): C++, all views in one call,
no gradient, as docs/rasterizer.md §9 and docs/methods/gof.md §7.1 state it: ``O(x) = min_v (1 − Π(1 − α))``
over the views that see x (1 where none does), each Gaussian of x's tile evaluated on x's own ray at
``t = min(t*, z_x)``.

Every early exit of csrc/integrate.cpp is exact, and GOF's point pass has no transmittance cut either
(``forward.cu::integrateCUDA`` comments its ``test_T < 0.0001`` stop out), so there is no approximation to state.
GOF visits only the Gaussians that contributed to the pixel's 5 sub-rays; gsbench, like `integrate_reference`,
uses the tile list. Memory: per view the payload (100 B a Gaussian in float32) and the cell lists, 2.3 MB a view
for 15k Gaussians at 240x135; a query needs 32 B a point.
"""

from __future__ import annotations

import ctypes
import math
from collections.abc import Sequence

import torch

from gsbench.data.camera import Camera
from gsbench.native.build import omp_threads
from gsbench.raster.abi import library
from gsbench.raster.projection import project
from gsbench.raster.types import RasterGaussians, RasterSettings
from gsbench.raster.validation import check_finite, validate_gaussians

ALPHA_SKIP_MARGIN = 0.01  # added to 2 ln(255 o): pre-skip only when q exceeds the α = 1/255 bound by this
CELL = 4  # pixels per side of the query cells (gcd with the tile size, so that a cell lies in one tile)


class GsCellArgs(ctypes.Structure):
    """Mirror of ``struct GsCellArgs`` in csrc/integrate.cpp."""

    _fields_ = [(n, ctypes.c_int64) for n in ("width", "height", "tile_size", "cell", "nthreads")] + [
        (n, ctypes.c_void_p) for n in ("tile_offsets", "tile_list", "bounds", "cell_offsets", "cell_list")
    ]


class GsIntArgs(ctypes.Structure):
    """Mirror of ``struct GsIntArgs`` in csrc/integrate.cpp."""

    _fields_ = (
        [(n, ctypes.c_int64) for n in ("n_points", "n_views", "n_params", "dtype", "nthreads", "cell")]
        + [(n, ctypes.c_double) for n in ("near_z", "cap", "stop_below")]
        + [(n, ctypes.c_void_p) for n in ("cams", "dims", "view_ptrs", "points", "out")]
    )


class OpacityField:
    """GOF opacity field ``O(x) = min_v (1 − Π_k (1 − α_k))`` of ``gaussians`` over ``cameras`` (docs/methods/gof.md §7.1),
    with every view projected and binned once (module docstring: rule, exactness, memory)."""

    @torch.no_grad()
    def __init__(
        self,
        gaussians: RasterGaussians,
        cameras: Sequence[Camera],
        *,
        kernel: str = "raymax",
        settings: RasterSettings = RasterSettings(),
    ) -> None:
        if kernel != "raymax":
            raise NotImplementedError(
                f"integrate is GOF's opacity field, defined for kernel='raymax' only (got {kernel!r}); "
                "RaDe-GS and 2DGS mesh from rendered depth (TSDF)"
            )
        validate_gaussians(gaussians, kernel)
        self._lib = library()
        self.dtype = gaussians.means.dtype
        self.settings = settings
        self.cell = math.gcd(CELL, settings.tile_size)
        g = gaussians.map(torch.Tensor.detach)
        self._views = [self._bin_view(g, cam, kernel) for cam in cameras]  # keeps the buffers alive
        self._cams = torch.tensor([[*map(float, torch.as_tensor(c.R, dtype=torch.float64).reshape(-1)),
                                    *map(float, torch.as_tensor(c.t, dtype=torch.float64).reshape(-1)),
                                    c.fx, c.fy, c.cx, c.cy] for c in cameras], dtype=torch.float64).reshape(-1, 16)
        cs = self.cell
        self._dims = torch.tensor([[int(c.width), int(c.height), (int(c.width) + cs - 1) // cs] for c in cameras],
                                  dtype=torch.int64).reshape(-1, 3)
        self._ptrs = torch.tensor([[t.data_ptr() for t in v] for v in self._views], dtype=torch.int64).reshape(-1, 3)
        self.n_params = self._views[0][0].shape[1] if self._views else 0

    def _bin_view(self, g: RasterGaussians, cam: Camera, kernel: str) -> tuple[torch.Tensor, ...]:
        """(payload (N, 25) = raymax payload + column ``2 ln(255 o) + margin``, cell offsets, cell list) of a
        view: the visible Gaussians sorted by centre depth, binned to their 3σ tile rectangles, the tile
        lists then refined to cells by the α >= 1/255 pixel boxes (csrc/integrate.cpp header)."""
        ts, nthreads = self.settings.tile_size, omp_threads()
        W, H = int(cam.width), int(cam.height)
        gx, gy = (W + ts - 1) // ts, (H + ts - 1) // ts
        proj = project(g, cam, kernel, self.settings)
        vis_idx = torch.nonzero(proj.visible).reshape(-1)
        order = vis_idx[torch.sort(proj.depth[vis_idx], stable=True).indices].contiguous()
        rect = proj.rect_radius.contiguous()
        areas = (rect[:, 1] - rect[:, 0]).long() * (rect[:, 3] - rect[:, 2]).long()
        cap = int(areas[order].sum()) if order.numel() else 0
        offsets = torch.zeros(gx * gy + 1, dtype=torch.int32)
        tile_list = torch.empty(max(cap, 1), dtype=torch.int32)
        self._lib.gs_bin(order.numel(), order.data_ptr(), rect.data_ptr(), gx, gy, offsets.data_ptr(),
                         tile_list.data_ptr(), cap, nthreads)
        cs = self.cell
        cell_offsets = torch.zeros(((W + cs - 1) // cs) * ((H + cs - 1) // cs) + 1, dtype=torch.int32)
        bounds = proj.bounds.detach().to(torch.float64).contiguous()
        a = GsCellArgs(W, H, ts, cs, nthreads, offsets.data_ptr(), tile_list.data_ptr(), bounds.data_ptr(),
                       cell_offsets.data_ptr(), None)
        self._lib.gs_integrate_cells(ctypes.byref(a))  # count
        cell_list = torch.empty(max(int(cell_offsets[-1]), 1), dtype=torch.int32)
        a.cell_list = cell_list.data_ptr()
        self._lib.gs_integrate_cells(ctypes.byref(a))  # fill
        params = proj.params.detach()
        skip = 2.0 * torch.log(255.0 * params[:, 5:6].clamp(min=1e-30)) + ALPHA_SKIP_MARGIN
        return torch.cat([params, skip], 1).contiguous(), cell_offsets, cell_list

    def _run(self, points: torch.Tensor, cap: float, stop_below: float) -> torch.Tensor:
        """C++ query: (P,) float64 ``m = min(cap, min_v O_v)``, the view loop of a point stopping once
        ``m < stop_below``."""
        pts = points.detach().to(torch.float64).contiguous()
        out = torch.full((pts.shape[0],), cap, dtype=torch.float64)
        if pts.shape[0] == 0 or not self._views:
            return out
        a = GsIntArgs()
        a.n_points, a.n_views, a.n_params = pts.shape[0], len(self._views), self.n_params
        a.dtype = 0 if self.dtype == torch.float32 else 1
        a.nthreads, a.cell = omp_threads(), self.cell
        a.near_z, a.cap, a.stop_below = self.settings.near, cap, stop_below
        a.cams, a.dims, a.view_ptrs = self._cams.data_ptr(), self._dims.data_ptr(), self._ptrs.data_ptr()
        a.points, a.out = pts.data_ptr(), out.data_ptr()
        self._lib.gs_integrate(ctypes.byref(a))
        return out

    def values(self, points: torch.Tensor) -> torch.Tensor:
        """(P,) ``O(x)`` at (P, 3) world points, in the Gaussians' dtype (1 where no view sees x)."""
        _check_points(points)
        return self._run(points, 1.0, -math.inf).to(self.dtype)

    def below(self, points: torch.Tensor, level: float) -> torch.Tensor:
        """(P,) bool ``O(x) < level`` at (P, 3) world points: the same classification as
        ``values(points).double() < level``, computed as ``min(level, O) < level``, so that a view stops
        once its ``1 − T`` reaches ``level`` and a point at its first view with ``O_v < level``."""
        _check_points(points)
        return self._run(points, float(level), float(level)) < level


def _check_points(points: torch.Tensor) -> None:
    if points.dim() != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (P, 3), got {tuple(points.shape)}")
    check_finite("points", points)


def integrate(
    gaussians: RasterGaussians,
    cameras: Sequence[Camera],
    points: torch.Tensor,
    *,
    kernel: str = "raymax",
    settings: RasterSettings = RasterSettings(),
) -> torch.Tensor:
    """GOF opacity (P,) of 3D ``points`` (P, 3): min over views of 1 − Π(1 − α_k) (no gradient), by
    `gsbench.raster.opacity_field.OpacityField` (which serves many queries from one binning)."""
    with torch.no_grad():
        return OpacityField(gaussians, cameras, kernel=kernel, settings=settings).values(points)
