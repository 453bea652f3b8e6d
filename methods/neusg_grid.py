"""NeuSG's grid encoding (`gsbench.methods.neusg_field.MultiGrid`): the features of points in [0, 1]³ interpolated
trilinearly in each level's dense grid, the levels concatenated.

Level l is a grid (1, F, N_l+1, N_l+1, N_l+1) with vertex i at i / N_l; a point u is clamped to the grid (border
padding) and blends its cell's 8 vertices: out[p, l·F + f] = Σ_corners w · grid_l[f, corner] (the weights and
the clamping: ``methods/csrc/neusg_grid.cpp``).

Two implementations:

* fused (default): ``gs_grid_forward`` / ``gs_grid_backward`` (``methods/csrc/neusg_grid.cpp``, float32 and
  float64, float64 arithmetic, OpenMP over points forward and over levels backward). The backward gives the
  grids' gradients only, accumulated in increasing point order per level, so it is bitwise the same for any
  thread count (training resumes exactly). Not twice differentiable.
* reference: `grid_features_reference`, ``torch.nn.functional.grid_sample`` (``align_corners=True``,
  ``padding_mode="border"``) per level. ``GSBENCH_NEUSG_GRID=reference`` or ``impl="reference"`` selects it.

Inputs the kernel does not take go to the reference when ``impl`` is None: points that require a gradient, a
non-CPU device, a dtype other than float32/float64, or mixed dtypes. Accuracy (tests/test_neusg_grid.py, relative
to the largest feature): float64 within 1e-12 of the reference, float32 within 1e-6.

Measured (docs/methods/neusg.md §5.1): torch's CPU ``grid_sampler_3d`` backward took 9–26 ms a level and call on
16 000–18 000 points, most of it zero-filling and scattering into the 129³ grid's gradient.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

import torch
import torch.nn.functional as F
from torch.autograd.function import once_differentiable

from gsbench.native.build import load_library, omp_threads
from gsbench.native.impl_choice import choose_impl
from gsbench.switches import NEUSG_GRID

__all__ = ["grid_features", "grid_features_reference"]

_i64, _ptr = ctypes.c_int64, ctypes.c_void_p
SIGNATURES = {
    "gs_grid_forward": ([_i64, _ptr, _i64, _i64, _i64, _ptr, _ptr, _ptr, _i64], ctypes.c_int),
    "gs_grid_backward": ([_i64, _ptr, _i64, _i64, _i64, _ptr, _ptr, _ptr, _i64], ctypes.c_int),
}


def grid_features(grids, unit: torch.Tensor, impl: str | None = None) -> torch.Tensor:
    """(P, L·F) features of points ``unit`` (P, 3) in the grids (a sequence of (1, F, N+1, N+1, N+1) tensors,
    one per level) (module docstring). ``impl``: None → fused unless ``GSBENCH_NEUSG_GRID=reference`` (and the
    reference for inputs the kernel cannot take); "fused" or "reference" to choose."""
    grids = list(grids)
    choice = choose_impl(impl, NEUSG_GRID, lambda: _unsupported(grids, unit), name="grid_features")
    if choice == "reference":
        return grid_features_reference(grids, unit)
    return _FusedGrid.apply(unit, *grids)


def grid_features_reference(grids, unit: torch.Tensor) -> torch.Tensor:
    """The PyTorch reference: ``grid_sample`` of each level at coordinates 2u − 1, concatenated."""
    coords = (unit * 2 - 1).reshape(1, -1, 1, 1, 3)
    return torch.cat([F.grid_sample(grid, coords, mode="bilinear", padding_mode="border", align_corners=True)
                      .reshape(grid.shape[1], -1).t() for grid in grids], dim=-1)


def levels_unsupported(levels: list[torch.Tensor], unit: torch.Tensor) -> str | None:
    """What the dense and the hash kernels both refuse in the points ``unit`` and the ``levels`` (feature dim 1),
    else None."""
    tensors = [unit, *levels]
    if unit.requires_grad:
        return "the points require a gradient (the kernel gives the levels' only)"
    if any(t.device.type != "cpu" for t in tensors):
        return "a tensor is not on the CPU"
    if unit.dtype not in (torch.float32, torch.float64) or any(t.dtype != unit.dtype for t in levels):
        return f"dtypes {sorted({str(t.dtype) for t in tensors})}: one of float32, float64 for all"
    if unit.dim() != 2 or unit.shape[1] != 3:
        return f"points of shape {tuple(unit.shape)}, not (P, 3)"
    if len({level.shape[1] for level in levels}) > 1:
        return "the levels have different feature counts"
    return None


def _unsupported(grids: list[torch.Tensor], unit: torch.Tensor) -> str | None:
    if not grids:
        return "no level"
    if (problem := levels_unsupported(grids, unit)) is not None:
        return problem
    for grid in grids:
        shape = tuple(grid.shape)
        if len(shape) != 5 or shape[0] != 1 or shape[2] < 2 or not shape[2] == shape[3] == shape[4]:
            return f"a grid of shape {shape}, not (1, F, N+1, N+1, N+1) with N >= 1"
    return None


def _library() -> ctypes.CDLL:
    """The native library of the grid encoding (``csrc/neusg_grid.cpp``, compiled on first use)."""
    return load_library("neusg_grid", [Path(__file__).parent / "csrc" / "neusg_grid.cpp"], SIGNATURES)


def _layout(grids: list[torch.Tensor]):
    """(levels, resolutions array, features) as the kernels take them."""
    res = (ctypes.c_int64 * len(grids))(*(grid.shape[2] - 1 for grid in grids))
    return len(grids), res, grids[0].shape[1]


def _pointers(tensors: list[torch.Tensor]):
    return (ctypes.c_void_p * len(tensors))(*(t.data_ptr() for t in tensors))


class _FusedGrid(torch.autograd.Function):
    """`grid_features` by ``gs_grid_forward``/``gs_grid_backward`` (csrc/neusg_grid.cpp)."""

    @staticmethod
    def forward(ctx, unit, *grids):
        unit = unit.detach().contiguous()
        grids = [g.detach().contiguous() for g in grids]
        levels, res, features = _layout(grids)
        out = torch.empty(unit.shape[0], levels * features, dtype=unit.dtype)
        rc = _library().gs_grid_forward(levels, res, features, unit.shape[0], int(unit.dtype == torch.float64),
                                        _pointers(grids), unit.data_ptr(), out.data_ptr(), omp_threads())
        if rc != 0:
            raise RuntimeError(f"gsbench grid forward failed (code {rc})")
        ctx.save_for_backward(unit)
        ctx.shapes = [g.shape for g in grids]
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, g_out):
        (unit,) = ctx.saved_tensors
        g = g_out.to(dtype=unit.dtype).contiguous()
        grads = [torch.empty(shape, dtype=unit.dtype) for shape in ctx.shapes]
        levels, res, features = _layout(grads)
        rc = _library().gs_grid_backward(levels, res, features, unit.shape[0], int(unit.dtype == torch.float64),
                                         unit.data_ptr(), g.data_ptr(), _pointers(grads), omp_threads())
        if rc != 0:
            raise RuntimeError(f"gsbench grid backward failed (code {rc})")
        return None, *grads
