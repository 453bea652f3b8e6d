"""The depth-normal consistency of a render: mean over all H×W pixels of 1 − n_r · n_d.

n_d = (Σ_j w_j N(D_j)) · a, with N(D) the unit normal of depth map D by central differences of its
back-projected points (`gsbench.losses.terms.depth_to_normal`, docs/methods/2dgs.md §4.3; 0 on the one-pixel
border), at most two maps, and a = stopgrad(alpha) when ``alpha`` is given, else 1; n_r = the rendered
normal, normalised when ``normalize``. `gsbench.losses.terms.normal_consistency_term` chooses the maps, weights
and flags of each method (2DGS: one map, alpha; GOF, RaDe-GS: normalised, RaDe-GS two maps).

Two implementations of the same function:

* fused (default): ``gs_normal_consistency_forward`` / ``_backward`` of the C++ extension
  (``gsbench/losses/csrc/normal_consistency.cpp``, float32 and float64 maps, float64 arithmetic, OpenMP
  over rows; its header derives the backward). One pass forward, two passes backward, no
  intermediate (H, W, 3) tensors.
* reference: `normal_consistency_reference`, the formula in PyTorch ops (autograd backward).
  ``GSBENCH_NORMAL_CONSISTENCY=reference`` or ``impl="reference"`` selects it; inputs the kernel does not
  take (a non-CPU device, a dtype other than float32 / float64, mixed dtypes) fall back to it.

Accuracy (tests/test_normal_consistency_fused.py): float64 gradcheck of the fused op; fused against the
reference within 1e-12 in float64 and 1e-6 in float32 (value and gradients), on maps with a background
of depth 0 and on each mode. The fused path is not twice differentiable.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

import torch
from torch.autograd.function import once_differentiable

from gsbench.data.camera import Camera
from gsbench.geometry.depth import depth_to_normal
from gsbench.native.build import load_library, omp_threads
from gsbench.native.impl_choice import choose_impl
from gsbench.switches import NORMAL_CONSISTENCY

_i64, _ptr, _dbl = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
_MAPS = [_i64] * 3 + [_ptr] * 4 + [_dbl] * 2 + [_i64] + [_dbl] * 4
SIGNATURES = {
    "gs_normal_consistency_forward": (_MAPS + [ctypes.POINTER(ctypes.c_double), _i64], ctypes.c_int),
    "gs_normal_consistency_backward": (_MAPS + [_dbl] + [_ptr] * 3 + [_i64], ctypes.c_int),
}


def _library() -> ctypes.CDLL:
    """The native library of the depth-normal consistency term and its backward (``csrc/normal_consistency.cpp``, compiled on first use)."""
    return load_library("normal_consistency", [Path(__file__).parent / "csrc" / "normal_consistency.cpp"], SIGNATURES)


def normal_consistency(normal: torch.Tensor, depths: list[torch.Tensor], weights: list[float], camera: Camera,
                       normalize: bool, alpha: torch.Tensor | None = None, impl: str | None = None) -> torch.Tensor:
    """Mean of 1 − n_r · n_d (module docstring); ``normal`` (H, W, 3), ``depths`` one or two (H, W) maps with
    their ``weights``, ``alpha`` (H, W) or None. ``impl`` None: fused unless the environment says otherwise."""
    if not 1 <= len(depths) <= 2 or len(weights) != len(depths):
        raise ValueError(f"normal_consistency takes one or two depth maps with one weight each, got "
                         f"{len(depths)} maps and {len(weights)} weights")
    if choose_impl(impl, NORMAL_CONSISTENCY, lambda: _unsupported(normal, depths, alpha),
                   "normal_consistency") == "reference":
        return normal_consistency_reference(normal, depths, weights, camera, normalize, alpha)
    d2 = depths[1] if len(depths) == 2 else None
    w2 = float(weights[1]) if d2 is not None else 0.0
    return _FusedNormalConsistency.apply(normal, depths[0], d2, None if alpha is None else alpha.detach(),
                                         float(weights[0]), w2, bool(normalize), camera)


def normal_consistency_reference(normal: torch.Tensor, depths: list[torch.Tensor], weights: list[float],
                                 camera: Camera, normalize: bool, alpha: torch.Tensor | None = None) -> torch.Tensor:
    """`normal_consistency` in PyTorch ops (the reference)."""
    n_d = sum(w * depth_to_normal(d, camera) for w, d in zip(weights, depths))
    if alpha is not None:
        n_d = n_d * alpha.detach()[..., None]
    n_r = torch.nn.functional.normalize(normal, dim=-1) if normalize else normal
    return (1.0 - (n_r * n_d).sum(-1)).mean()


def _unsupported(normal: torch.Tensor, depths: list[torch.Tensor], alpha: torch.Tensor | None) -> str | None:
    """Why the fused kernel cannot take these inputs, or None."""
    tensors = [normal, *depths] + ([alpha] if alpha is not None else [])
    if any(t.device.type != "cpu" for t in tensors):
        return "a tensor not on the CPU (the kernel is CPU only)"
    if normal.dtype not in (torch.float32, torch.float64) or any(t.dtype != normal.dtype for t in tensors):
        return f"dtypes {sorted({str(t.dtype) for t in tensors})} (one of float32 / float64 only)"
    H, W = depths[0].shape[:2]
    if normal.shape != (H, W, 3) or any(t.shape != (H, W) for t in tensors[1:]):
        return f"shapes {[tuple(t.shape) for t in tensors]} (normal (H, W, 3), maps (H, W))"
    return None


def _pointer(t: torch.Tensor | None):
    return None if t is None else t.data_ptr()


def _camera_args(camera: Camera) -> list[float]:
    return [float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)]


class _FusedNormalConsistency(torch.autograd.Function):
    """The mean by ``gs_normal_consistency_forward`` / ``_backward`` (csrc/normal_consistency.cpp)."""

    @staticmethod
    def forward(ctx, normal, d1, d2, alpha, w1, w2, normalize, camera):

        n, a, b = normal.detach().contiguous(), d1.detach().contiguous(), None if d2 is None else d2.detach().contiguous()
        al = None if alpha is None else alpha.contiguous()
        H, W = a.shape
        total = ctypes.c_double(0.0)
        rc = _library().gs_normal_consistency_forward(
            H, W, int(n.dtype == torch.float64), n.data_ptr(), a.data_ptr(), _pointer(b), _pointer(al), w1, w2,
            int(normalize), *_camera_args(camera), ctypes.byref(total), omp_threads())
        if rc != 0:
            raise RuntimeError(f"gsbench normal_consistency forward failed (code {rc})")
        ctx.save_for_backward(n, a, b, al)
        ctx.settings = (w1, w2, normalize, camera)
        return torch.tensor(total.value / (H * W), dtype=n.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        n, a, b, al = ctx.saved_tensors
        w1, w2, normalize, camera = ctx.settings
        H, W = a.shape
        needs = ctx.needs_input_grad
        g_n = torch.empty_like(n) if needs[0] else None
        g_a = torch.empty_like(a) if needs[1] else None
        g_b = torch.empty_like(b) if b is not None and needs[2] else None
        rc = _library().gs_normal_consistency_backward(
            H, W, int(n.dtype == torch.float64), n.data_ptr(), a.data_ptr(), _pointer(b), _pointer(al), w1, w2,
            int(normalize), *_camera_args(camera), float(grad) / (H * W), _pointer(g_n), _pointer(g_a), _pointer(g_b),
            omp_threads())
        if rc != 0:
            raise RuntimeError(f"gsbench normal_consistency backward failed (code {rc})")
        return g_n, g_a, g_b, None, None, None, None, None
