"""The per-pair work of SuGaR's regularisers (`gsbench.methods.sugar_terms`): each sample's K neighbour terms.

Samples x (M,3) drawn in Gaussians g = source (M,), their neighbours idx (M,K) (j = idx[m,k]), and the
Gaussians' means μ (N,3), rotations R (N,3,3), scales s (N,3) (> 0), opacities o (N,), normals n (N,3) and
smallest scales σ (N,):

- `neighbour_field`: the contributions c[m,k] = o_j · exp(−½ · clamp(‖l‖², 0, clamp_max)),
  l = (x_m − μ_j)ᵀ A_j = diag(1/s_j) R_jᵀ (x_m − μ_j), A = R/s (R's columns divided by the scales);
  differentiable with respect to x, μ, R, s and o.
- `neighbour_normals`: SuGaR's weighted neighbour normal a_m = Σ_k ŵ_k f_k n_j, with the flip
  f = sign⟨n_j, n_g⟩, weights w = κ c |⟨x_m − μ_j, f n_j⟩| / max(σ_j, scale_min)² and
  ŵ = w / max(Σ_k w, sum_min); differentiable with respect to the n_j of the sum only (SuGaR's
  ``sdf_better_normal_gradient_through_normal_only``: the weights and the flip carry no gradient, and x, μ,
  σ, c are read without a graph).

Two implementations of each:

* fused (default): ``gs_sugar_field_*`` / ``gs_sugar_normal_*`` of the C++ extension
  (``methods/csrc/sugar_field.cpp``: float32 and float64, OpenMP, float64 arithmetic for both). The
  forwards evaluate the formulas per pair (the field packs each Gaussian's A = R/s, μ, o, s once); the
  backwards (the clamp's gradient 0 above ``clamp_max``, as torch's) sum ∂L/∂x over each sample's pairs and
  the per-Gaussian gradients over each Gaussian's pairs in a fixed order (a counting sort of idx, shared by
  the two backwards), so they are bitwise the same for any thread count (training resumes exactly). Not
  twice differentiable. Scratch, kept per calling thread between calls (fresh pages cost more than the
  kernels): about 48 bytes per pair and 170 per Gaussian in float32.
* reference: `neighbour_field_reference` / `neighbour_normals_reference`, the formulas in PyTorch
  (advanced-index gathers, an einsum, autograd backward). ``GSBENCH_SUGAR_FIELD=reference`` or
  ``impl="reference"`` selects them.

Inputs the kernels do not take fall back to the reference when ``impl`` is None: a non-CPU device, a dtype
other than float32/float64, mixed dtypes, no pair (M·K = 0 or N = 0), or M·K >= 2³¹. Accuracy
(tests/test_sugar_field.py, relative to the largest value): float64 within 1e-10 of the reference; float32
within 1e-6 of the float32 reference and of the float64 reference on the same inputs (the kernels follow the
latter, ~1e-7; the float32 reference is itself a few 1e-7 off it).
"""

from __future__ import annotations

import ctypes
from pathlib import Path

import torch
from torch.autograd.function import once_differentiable

from gsbench.native.build import load_library, omp_threads
from gsbench.native.impl_choice import choose_impl
from gsbench.switches import SUGAR_FIELD

__all__ = ["neighbour_field", "neighbour_field_reference", "neighbour_normals",
           "neighbour_normals_reference"]


def neighbour_field(points: torch.Tensor, means: torch.Tensor, rotations: torch.Tensor, scales: torch.Tensor,
                    opacities: torch.Tensor, idx: torch.Tensor, clamp_max: float,
                    impl: str | None = None) -> torch.Tensor:
    """Contributions c (M,K) (module docstring).

    ``impl``: ``None`` → fused unless ``GSBENCH_SUGAR_FIELD=reference`` (and the reference for inputs the
    kernel does not take); ``"fused"`` (``ValueError`` for such inputs) or ``"reference"`` to force one.
    """
    tensors = (points, means, rotations, scales, opacities)
    if not _fused(impl, tensors, idx, means.shape[0]):
        return neighbour_field_reference(*tensors, idx, clamp_max)
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return _FusedField.apply(*tensors, idx, clamp_max)
    return _field_forward([t.detach().contiguous() for t in tensors], _index(idx), clamp_max)


def neighbour_field_reference(points: torch.Tensor, means: torch.Tensor, rotations: torch.Tensor,
                              scales: torch.Tensor, opacities: torch.Tensor, idx: torch.Tensor,
                              clamp_max: float) -> torch.Tensor:
    """`neighbour_field` in PyTorch (autograd backward; the reference)."""
    inv_scaled = rotations / scales[:, None, :]
    offsets = points[:, None, :] - means[idx]
    local = torch.einsum("mkc,mkcd->mkd", offsets, inv_scaled[idx])
    mahalanobis = (local * local).sum(-1).clamp(0.0, clamp_max)
    return opacities[idx] * torch.exp(-0.5 * mahalanobis)


def neighbour_normals(normals: torch.Tensor, points: torch.Tensor, means: torch.Tensor, min_scales: torch.Tensor,
                      contributions: torch.Tensor, source: torch.Tensor, idx: torch.Tensor, kappa: float,
                      scale_min: float, sum_min: float, impl: str | None = None) -> torch.Tensor:
    """The weighted neighbour normals a (M,3) (module docstring); ``impl`` as in `neighbour_field`."""
    constants = [t.detach() for t in (points, means, min_scales, contributions)]
    args = (kappa, scale_min, sum_min)
    if not _fused(impl, (normals, *constants), idx, normals.shape[0]):
        return neighbour_normals_reference(normals, *constants, source, idx, *args)
    if torch.is_grad_enabled() and normals.requires_grad:
        return _FusedNormals.apply(normals, *constants, source, idx, *args)
    out, _ = _normals_forward(normals.detach().contiguous(), [t.contiguous() for t in constants], _index(source),
                              _index(idx), *args)
    return out


def neighbour_normals_reference(normals: torch.Tensor, points: torch.Tensor, means: torch.Tensor,
                                min_scales: torch.Tensor, contributions: torch.Tensor, source: torch.Tensor,
                                idx: torch.Tensor, kappa: float, scale_min: float, sum_min: float) -> torch.Tensor:
    """`neighbour_normals` in PyTorch (autograd backward; the reference)."""
    own = normals[source]
    others = normals[idx]
    others = others * torch.sign((others * own[:, None, :]).sum(-1, keepdim=True)).detach()
    with torch.no_grad():
        offsets = points[:, None, :] - means[idx]
        distance = (offsets * others).sum(-1).abs()
        weights = kappa * contributions * distance / min_scales[idx].clamp(min=scale_min) ** 2
        weights = weights / weights.sum(-1, keepdim=True).clamp(min=sum_min)
    return (weights[..., None] * others).sum(1)


def _fused(impl: str | None, tensors, idx: torch.Tensor, n: int) -> bool:
    """Whether to run the kernel: ``impl``/the environment choose, and inputs it cannot take fall back."""
    return choose_impl(impl, SUGAR_FIELD, lambda: _unsupported(tensors, idx, n), "sugar field") == "fused"


def _unsupported(tensors, idx: torch.Tensor, n: int) -> str | None:
    """Why the kernels cannot take these inputs (``n`` Gaussians), or None."""
    if any(t.device.type != "cpu" for t in (*tensors, idx)):
        return "tensors not on the CPU (the kernel is CPU only)"
    if tensors[0].dtype not in (torch.float32, torch.float64):
        return f"dtype {tensors[0].dtype} (float32 or float64 only)"
    if any(t.dtype != tensors[0].dtype for t in tensors):
        return "mixed dtypes"
    if idx.numel() == 0 or n == 0:
        return "no pair"
    if idx.numel() >= 2**31:
        return "2³¹ pairs or more (the kernels index pairs in int32)"
    return None


def _index(idx: torch.Tensor) -> torch.Tensor:
    return idx.to(torch.int64).contiguous()


_i64, _ptr, _dbl = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
SIGNATURES = {
    "gs_sugar_field_forward": ([_i64] * 4 + [_ptr] * 6 + [_dbl, _ptr, _i64], ctypes.c_int),
    "gs_sugar_field_backward": ([_i64] * 4 + [_ptr] * 6 + [_dbl] + [_ptr] * 6 + [_i64], ctypes.c_int),
    "gs_sugar_normal_forward": ([_i64] * 4 + [_ptr] * 7 + [_dbl] * 3 + [_ptr, _ptr, _i64], ctypes.c_int),
    "gs_sugar_normal_backward": ([_i64] * 4 + [_ptr] * 4 + [_i64], ctypes.c_int),
}


def _library() -> ctypes.CDLL:
    """The native library of SuGaR's neighbour field, normal average and their backwards (``csrc/sugar_field.cpp``, compiled on first use)."""
    return load_library("sugar_field", [Path(__file__).parent / "csrc" / "sugar_field.cpp"], SIGNATURES)


def _check(rc: int, what: str) -> None:
    if rc == -2:
        raise IndexError(f"sugar {what}: an index is outside [0, N)")
    if rc != 0:
        raise RuntimeError(f"gsbench sugar {what} failed (code {rc})")


def _sizes(idx: torch.Tensor, n: int, dtype: torch.dtype) -> tuple[int, int, int, int]:
    """(M, K, N, dtype code) as the kernels take them."""
    return idx.shape[0], idx.shape[1], n, int(dtype == torch.float64)


def _field_forward(inputs: list[torch.Tensor], idx: torch.Tensor, clamp_max: float) -> torch.Tensor:
    """Contiguous CPU (x, μ, R, s, o) and int64 idx → contributions (M,K)."""
    out = torch.empty(idx.shape, dtype=inputs[0].dtype)
    rc = _library().gs_sugar_field_forward(
        *_sizes(idx, inputs[1].shape[0], out.dtype), *(t.data_ptr() for t in inputs), idx.data_ptr(),
        float(clamp_max), out.data_ptr(), omp_threads(),
    )
    _check(rc, "field forward")
    return out


class _FusedField(torch.autograd.Function):
    """`neighbour_field` by ``gs_sugar_field_forward``/``gs_sugar_field_backward`` (csrc/sugar_field.cpp)."""

    @staticmethod
    def forward(ctx, points, means, rotations, scales, opacities, idx, clamp_max):
        inputs = [t.detach().contiguous() for t in (points, means, rotations, scales, opacities)]
        idx = _index(idx)
        ctx.save_for_backward(*inputs, idx)
        ctx.clamp_max = clamp_max
        return _field_forward(inputs, idx, clamp_max)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_out):
        *inputs, idx = ctx.saved_tensors
        g = g_out.to(dtype=inputs[0].dtype).contiguous()
        grads = [torch.empty_like(t) for t in inputs]
        rc = _library().gs_sugar_field_backward(
            *_sizes(idx, inputs[1].shape[0], g.dtype), *(t.data_ptr() for t in inputs), idx.data_ptr(),
            float(ctx.clamp_max), g.data_ptr(), *(t.data_ptr() for t in grads), omp_threads(),
        )
        _check(rc, "field backward")
        return *grads, None, None


def _normals_forward(normals: torch.Tensor, constants: list[torch.Tensor], source: torch.Tensor, idx: torch.Tensor,
                     kappa: float, scale_min: float, sum_min: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Contiguous CPU normals, (x, μ, σ, c), int64 source and idx → (a (M,3), weights ŵf (M,K))."""
    out = torch.empty((idx.shape[0], 3), dtype=normals.dtype)
    weights = torch.empty(idx.shape, dtype=normals.dtype)
    rc = _library().gs_sugar_normal_forward(
        *_sizes(idx, normals.shape[0], normals.dtype), normals.data_ptr(), *(t.data_ptr() for t in constants),
        source.data_ptr(), idx.data_ptr(), float(kappa), float(scale_min), float(sum_min), out.data_ptr(),
        weights.data_ptr(), omp_threads(),
    )
    _check(rc, "normal forward")
    return out, weights


class _FusedNormals(torch.autograd.Function):
    """`neighbour_normals` by ``gs_sugar_normal_forward``/``gs_sugar_normal_backward`` (csrc/sugar_field.cpp)."""

    @staticmethod
    def forward(ctx, normals, points, means, min_scales, contributions, source, idx, kappa, scale_min, sum_min):
        idx = _index(idx)
        out, weights = _normals_forward(normals.detach().contiguous(),
                                        [t.detach().contiguous() for t in (points, means, min_scales, contributions)],
                                        _index(source), idx, kappa, scale_min, sum_min)
        ctx.save_for_backward(idx, weights)
        ctx.n = normals.shape[0]
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, g_out):
        idx, weights = ctx.saved_tensors
        g = g_out.to(dtype=weights.dtype).contiguous()
        g_normals = torch.empty((ctx.n, 3), dtype=weights.dtype)
        rc = _library().gs_sugar_normal_backward(
            *_sizes(idx, ctx.n, weights.dtype), idx.data_ptr(), weights.data_ptr(), g.data_ptr(),
            g_normals.data_ptr(), omp_threads(),
        )
        _check(rc, "normal backward")
        return g_normals, *([None] * 9)
