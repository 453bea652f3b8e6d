"""NeuSG's multiresolution hash encoding (`gsbench.methods.neusg_field.HashGrid`; Instant-NGP, Müller et al. 2022,
eqs. 2–4): the features of points in [0, 1]³, per level the trilinear blend of the 8 vertices of the point's cell, each
vertex's feature vector a row of the level's table, the levels concatenated.

Level l has resolution N_l and a table (T_l, F). The cell, its weights and the border clamping are the dense grid's
(`gsbench.methods.neusg_grid`); a vertex v = (x, y, z) ∈ [0, N_l]³ is the row

    x + (N_l + 1)(y + (N_l + 1) z)                           if (N_l + 1)³ <= T_l (a level small enough not to hash),
    (x·1 ⊕ y·2654435761 ⊕ z·805459861) mod T_l             otherwise (Instant-NGP eq. 4, unsigned 32-bit),

so out[p, l·F + f] = Σ_corners w · table_l[row(corner), f] (``methods/csrc/neusg_hash.cpp`` states it once more
for the kernel).

Two implementations:

* fused (default): ``gs_hash_forward`` / ``gs_hash_backward`` (``methods/csrc/neusg_hash.cpp``, float32 and
  float64, float64 arithmetic, OpenMP over points forward and over levels backward). The backward gives the tables'
  gradients only, accumulated in increasing point order per level, so it is bitwise the same for any thread count.
  Not twice differentiable.
* reference: `hash_features_reference`, the formula above written out in PyTorch (gathers of the 8 corners),
  differentiable in the tables and the points. ``GSBENCH_NEUSG_GRID=reference`` (the switch of both NeuSG
  encodings) or ``impl="reference"`` selects it.

Inputs the kernel does not take go to the reference when ``impl`` is None: points that require a gradient, a
non-CPU device, a dtype other than float32/float64, or mixed dtypes (tests/test_neusg_hash.py).
"""

from __future__ import annotations

import ctypes
from pathlib import Path

import torch
from torch.autograd.function import once_differentiable

from gsbench.methods.neusg_grid import levels_unsupported
from gsbench.native.build import load_library, omp_threads
from gsbench.native.impl_choice import choose_impl
from gsbench.switches import NEUSG_GRID

__all__ = ["hash_features", "hash_features_reference"]

PRIMES = (1, 2654435761, 805459861)  # Instant-NGP's π₁, π₂, π₃ (eq. 4)
UINT32 = 0xFFFFFFFF

_i64, _ptr = ctypes.c_int64, ctypes.c_void_p
SIGNATURES = {
    "gs_hash_forward": ([_i64, _ptr, _ptr, _i64, _i64, _i64, _ptr, _ptr, _ptr, _i64], ctypes.c_int),
    "gs_hash_backward": ([_i64, _ptr, _ptr, _i64, _i64, _i64, _ptr, _ptr, _ptr, _i64], ctypes.c_int),
}


def hash_features(tables, resolutions, unit: torch.Tensor, impl: str | None = None) -> torch.Tensor:
    """(P, L·F) features of points ``unit`` (P, 3) in the levels of ``resolutions`` (N_l) with ``tables`` ((T_l, F)
    tensors) (module docstring). ``impl``: None → fused unless ``GSBENCH_NEUSG_GRID=reference`` (and the reference
    for inputs the kernel cannot take); "fused" or "reference" to choose."""
    tables, resolutions = list(tables), [int(n) for n in resolutions]
    choice = choose_impl(impl, NEUSG_GRID, lambda: _unsupported(tables, resolutions, unit), name="hash_features")
    if choice == "reference":
        return hash_features_reference(tables, resolutions, unit)
    return _FusedHash.apply(unit, resolutions, *tables)


def vertex_rows(vertices: torch.Tensor, resolution: int, size: int) -> torch.Tensor:
    """The table rows (int64, ...) of integer grid ``vertices`` (..., 3) of a level of ``resolution`` with ``size``
    rows: dense when the (N+1)³ vertices fit, else Instant-NGP's spatial hash (module docstring)."""
    side = resolution + 1
    x, y, z = vertices.unbind(-1)
    if side**3 <= size:
        return x + side * (y + side * z)
    hashed = ((x * PRIMES[0]) & UINT32) ^ ((y * PRIMES[1]) & UINT32) ^ ((z * PRIMES[2]) & UINT32)
    return hashed % size


def hash_features_reference(tables, resolutions, unit: torch.Tensor) -> torch.Tensor:
    """The PyTorch reference: per level, the cell (s = clamp(u N, 0, N), i = min(⌊s⌋, N − 1), t = s − i), the rows of
    its 8 corners (`vertex_rows`), and Σ w · table[row], the levels concatenated."""
    out = []
    for table, n in zip(tables, resolutions, strict=True):
        scaled = (unit * n).clamp(0, n)
        cell = scaled.detach().floor().clamp(0, n - 1).long()
        t = scaled - cell.to(unit.dtype)
        level = 0
        for corner in range(8):
            bits = torch.tensor([corner & 1, (corner >> 1) & 1, (corner >> 2) & 1])
            weight = torch.where(bits.bool(), t, 1 - t).prod(-1)
            rows = vertex_rows(cell + bits, n, table.shape[0])
            level = level + weight[:, None] * table[rows]
        out.append(level)
    return torch.cat(out, dim=-1)


def _unsupported(tables: list[torch.Tensor], resolutions: list[int], unit: torch.Tensor) -> str | None:
    if not tables or len(tables) != len(resolutions):
        return f"{len(tables)} tables for {len(resolutions)} resolutions"
    if any(t.dim() != 2 or not 1 <= t.shape[0] <= 1 << 31 for t in tables) or any(n < 1 for n in resolutions):
        return "a table not of shape (T, F) with 1 <= T <= 2^31, or a resolution < 1"
    return levels_unsupported(tables, unit)


def _library() -> ctypes.CDLL:
    """The native library of the hash encoding (``csrc/neusg_hash.cpp``, compiled on first use)."""
    return load_library("neusg_hash", [Path(__file__).parent / "csrc" / "neusg_hash.cpp"], SIGNATURES)


def _layout(tables: list[torch.Tensor], resolutions: list[int]):
    """(levels, resolutions array, table sizes array, features) as the kernels take them."""
    res = (ctypes.c_int64 * len(tables))(*resolutions)
    sizes = (ctypes.c_int64 * len(tables))(*(t.shape[0] for t in tables))
    return len(tables), res, sizes, tables[0].shape[1]


def _pointers(tensors: list[torch.Tensor]):
    return (ctypes.c_void_p * len(tensors))(*(t.data_ptr() for t in tensors))


class _FusedHash(torch.autograd.Function):
    """`hash_features` by ``gs_hash_forward``/``gs_hash_backward`` (csrc/neusg_hash.cpp)."""

    @staticmethod
    def forward(ctx, unit, resolutions, *tables):
        unit = unit.detach().contiguous()
        tables = [t.detach().contiguous() for t in tables]
        levels, res, sizes, features = _layout(tables, resolutions)
        out = torch.empty(unit.shape[0], levels * features, dtype=unit.dtype)
        rc = _library().gs_hash_forward(levels, res, sizes, features, unit.shape[0], int(unit.dtype == torch.float64),
                                        _pointers(tables), unit.data_ptr(), out.data_ptr(), omp_threads())
        if rc != 0:
            raise RuntimeError(f"gsbench hash forward failed (code {rc})")
        ctx.save_for_backward(unit)
        ctx.resolutions, ctx.shapes = resolutions, [t.shape for t in tables]
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, g_out):
        (unit,) = ctx.saved_tensors
        g = g_out.to(dtype=unit.dtype).contiguous()
        grads = [torch.empty(shape, dtype=unit.dtype) for shape in ctx.shapes]
        levels, res, sizes, features = _layout(grads, ctx.resolutions)
        rc = _library().gs_hash_backward(levels, res, sizes, features, unit.shape[0], int(unit.dtype == torch.float64),
                                         unit.data_ptr(), g.data_ptr(), _pointers(grads), omp_threads())
        if rc != 0:
            raise RuntimeError(f"gsbench hash backward failed (code {rc})")
        return None, None, *grads
