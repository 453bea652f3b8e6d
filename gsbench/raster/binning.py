"""Which Gaussians each 16x16 tile composites, in depth order: the C++ radix sort of the visible Gaussians
by (depth, id) and the per-tile lists (``csrc/sort_bin.cpp``), by the exact overlap of the tile with the
Gaussian's contributing ellipse (ewa, rade, surfel; ``csrc/bin_exact.cpp``) or every tile of the bounding
rectangle (raymax, and every kernel with ``GSBENCH_EXACT_OVERLAP=off``: more tile pairs, the same images and
gradients bit for bit, since a tile is dropped only where no pixel gets alpha >= 1/255)."""

from __future__ import annotations

import ctypes
from dataclasses import dataclass

import torch

from gsbench.native.build import omp_threads
from gsbench.raster.composite import pointer
from gsbench.raster.payload import Projection
from gsbench.switches import EXACT_OVERLAP

@dataclass
class Bins:
    """Per-tile lists of a render: ``offsets`` (tiles + 1,) into ``tile_list``, ``capacity`` entries sized,
    and the sort key and rectangles the compositing reads."""

    offsets: torch.Tensor
    tile_list: torch.Tensor
    capacity: int
    depth_key: torch.Tensor
    rect: torch.Tensor
    tiles_x: int
    tiles_y: int


def bin_tiles(lib, proj: Projection, n: int, dtype: torch.dtype, kernel: str, outs: tuple[str, ...], W: int, H: int,
              ts: int, intrinsics: tuple[float, float, float, float], surfel_k: float) -> Bins:
    """Sort the visible Gaussians of ``proj`` (``n`` Gaussians of ``dtype``) by depth and list them per tile of a
    ``W`` x ``H`` image (``ts``-pixel tiles; module docstring). ``intrinsics`` (fx, fy, cx, cy) and ``surfel_k``
    (the surfel low-pass k) place a surfel's ellipse."""
    tiles_x = (W + ts - 1) // ts
    tiles_y = (H + ts - 1) // ts
    # visible ids by (depth, id) (C++ radix sort) with their tile rectangles in that order, then per-tile lists
    rect = proj.rect.contiguous()
    depth_sort = proj.depth.to(dtype).contiguous()
    visible_u8 = proj.visible.contiguous().view(torch.uint8)
    order = torch.empty(n, dtype=torch.int32)
    rect_sorted = torch.empty(n, 4, dtype=torch.int32)
    cap = ctypes.c_int64(0)
    m_vis = lib.gs_depth_order(
        n, pointer(visible_u8), pointer(depth_sort), 0 if dtype == torch.float32 else 1, pointer(rect), pointer(order),
        pointer(rect_sorted), ctypes.byref(cap),
    )
    capacity = int(cap.value)
    offsets = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.int32)
    nthr = omp_threads()
    if kernel in ("ewa", "rade", "surfel") and EXACT_OVERLAP.value() == "on":
        # exact ellipse/tile overlap (csrc/bin_exact.cpp): a Gaussian is listed only in the tiles of its rectangle
        # that its alpha >= 1/255 ellipse meets; the count pass sizes tile_list exactly
        params_c = proj.params.detach().contiguous()
        keep_first = int("distortion" in outs)  # the distortion shift reads each tile's first rectangle Gaussian
        first = torch.empty(tiles_x * tiles_y if keep_first else 1, dtype=torch.int32)
        rec = torch.empty(max(n, 1) * 8, dtype=torch.int32)
        cursors = torch.empty(nthr * tiles_x * tiles_y, dtype=torch.int32)
        dt_id = 0 if dtype == torch.float32 else 1
        npar = int(params_c.shape[1])
        setup = torch.tensor([float(kernel == "surfel"), *map(float, intrinsics), float(surfel_k)], dtype=torch.float64)
        capacity = int(lib.gs_bin_exact_count(
            m_vis, pointer(order), pointer(rect_sorted), n, pointer(visible_u8), pointer(rect), pointer(params_c), npar, dt_id, H,
            tiles_x, tiles_y, keep_first, pointer(first), pointer(rec), pointer(offsets), pointer(cursors), nthr,
            pointer(setup),
        ))
        if capacity < 0:
            raise RuntimeError("gsbench rasterizer: tile list overflow")
        tile_list = torch.empty(max(capacity, 1), dtype=torch.int32)
        got = lib.gs_bin_exact_fill(
            m_vis, pointer(order), pointer(rect_sorted), pointer(rec), pointer(params_c), npar, dt_id, H, tiles_x, tiles_y,
            keep_first, pointer(first), pointer(offsets), pointer(cursors), pointer(tile_list), capacity, nthr,
            pointer(setup),
        )
    else:
        tile_list = torch.empty(max(capacity, 1), dtype=torch.int32)
        got = lib.gs_bin_sorted(
            m_vis, pointer(order), pointer(rect_sorted), tiles_x, tiles_y, pointer(offsets), pointer(tile_list), capacity, nthr,
        )
    if got < 0:
        raise RuntimeError("gsbench rasterizer: tile list overflow")
    return Bins(offsets, tile_list, capacity, depth_sort, rect, tiles_x, tiles_y)
