"""Stable, differentiable batched eigen-decomposition of symmetric 3×3 matrices (IBGS local covariances).

IBGS (docs/methods/ibgs.md §3.2) decomposes every training step the covariance
``C_i = (1/n) Σ (p − μ̄)(p − μ̄)ᵀ`` of each Gaussian's neighbour means and differentiates through it.
``torch.linalg.eigh`` is slow for that (~200 ms for 100k float64 matrices) and its eigenvector
gradient is NaN/inf for repeated eigenvalues (coplanar isotropic patches, collinear or duplicated
points, K = 2), all of which occur in training (docs/methods/ibgs.md §7). This module implements recipe docs/methods/ibgs.md §3.2, §3.3:

* forward: a float64 closed form in the C++ extension (``gsbench/geometry/csrc/eigen3.cpp``, OpenMP
  over the batch): trigonometric eigenvalues, the isolated eigenvector by Kopp's cross products, the
  remaining pair by deflation to a 2×2 solved in closed form (see `sym3_eigh`);
* backward: ``gC = V · sym(diag(gλ) + F ∘ (Vᵀ gV)) · Vᵀ`` with the gap-regularised
  ``F_ij = (λ_j − λ_i)/((λ_j − λ_i)² + ε²)``, ``ε = gap_eps·max_k|λ_k| + GAP_EPS_FLOOR``: eigenvalue
  gradients exact, eigenvector gradients finite everywhere (a pair of equal eigenvalues contributes 0).

``GSBENCH_EIGEN=reference`` (or ``impl="reference"``) switches to `sym3_eigh_reference`: the same
function with ``torch.linalg.eigh`` forward and the backward written plainly in PyTorch.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from gsbench.errors import NumericalError
from gsbench.native.build import load_library, omp_threads
from gsbench.native.impl_choice import choose_impl
from gsbench.switches import EIGEN

# Absolute part of the gap regulariser ε (docs/methods/ibgs.md §3.3); keeps F finite for C = 0. It dominates ε, and so
# damps eigenvector gradients, when max|λ| < GAP_EPS_FLOOR/gap_eps (1e-9 at the default gap_eps).
GAP_EPS_FLOOR = 1e-12


_i64, _ptr, _dbl = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
SIGNATURES = {
    "gs_sym3_eigh_forward": ([_i64] + [_ptr] * 3 + [_i64], ctypes.c_int),
    "gs_sym3_eigh_backward": ([_i64] + [_ptr] * 4 + [_dbl] * 2 + [_ptr, _i64], ctypes.c_int),
}


def _library() -> ctypes.CDLL:
    """The native library of the batched symmetric 3x3 eigen-solver (``csrc/eigen3.cpp``, compiled on first use)."""
    return load_library("eigen3", [Path(__file__).parent / "csrc" / "eigen3.cpp"], SIGNATURES)


def sym3_eigh(C: torch.Tensor, gap_eps: float = 1e-3, impl: str | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Eigen-decomposition ``S = V diag(λ) Vᵀ`` of ``S = (C + Cᵀ)/2``, batched and differentiable.

    ``C`` (..., 3, 3) float32 or float64, any batch shape (also empty); computed in float64 and returned in
    ``C``'s dtype: ``lam`` (..., 3) descending ``λ1 >= λ2 >= λ3`` and ``V`` (..., 3, 3) whose columns
    ``v1, v2, v3`` are orthonormal eigenvectors with ``det V = +1`` (``v3 = v1 × v2``). Column signs are
    otherwise arbitrary: use only sign-invariant functions of ``V`` (``|v·a|``, ``(v·a)²``, ``V D Vᵀ``).

    Forward (C++, float64; docs/methods/ibgs.md §3.2), per matrix with ``s = max|S_ij|``
    and ``A = S/s − qI``, ``q = tr(S/s)/3``, ``p = sqrt(‖A‖²_F/6)``:

    * ``p <= 1e-14`` (incl. ``S = 0``; the anisotropy is at the rounding level of ``S``): isotropic,
      ``λ1 = λ2 = λ3 = tr(S)/3`` (within 2e-14·s of the exact ones), ``V = I``;
    * eigenvalues of ``A/p`` (trigonometric method): ``r = det(A/p)/2`` clamped to [−1, 1],
      ``φ = acos(r)/3``, ``θ1 = 2cos φ``, ``θ3 = 2cos(φ + 2π/3)``, ``θ2 = −θ1 − θ3``;
    * the isolated one, with the larger gap to its neighbour: ``θ1`` if ``r >= 0`` (⟺ ``θ1 − θ2 >=
      θ2 − θ3``), else ``θ3``. It is accurate (the acos is ill-conditioned only where two eigenvalues
      meet, and then blurs only their split). Its eigenvector = the largest-norm cross product of two
      rows of ``A − pθ I`` (Kopp), its eigenvalue = that vector's Rayleigh quotient;
    * the other two: ``B = [u w]ᵀ A [u w]`` for an orthonormal basis ``u, w`` of the plane ⊥ ``v_iso``;
      eigenvalues ``m ± ρ``, ``m = (B11 + B22)/2``, ``h = (B11 − B22)/2``, ``ρ = sqrt(h² + B12²)``;
      the larger one's eigenvector is the column of ``B − (m − ρ)I`` without cancellation
      (``(h + ρ, B12)`` if ``h >= 0``, else ``(B12, ρ − h)``), the smaller one's its 90° rotation;
    * sort descending, ``v3 := v1 × v2``, ``λ = s(λ_A + q)``.

    No iterative refinement is needed: eigenvalues come out within ~2e-15·max|λ| of numpy.linalg.eigh,
    eigenvectors of a relative gap ``g`` (to the nearest other eigenvalue, over max|λ|) within ~1e-15/g,
    the conditioning of the problem. The two eigenvectors of a (near-)degenerate pair are some orthonormal
    basis of their plane, with residual ``‖S v − λ v‖`` at rounding level.

    Backward (hand-written, both implementations): for upstream ``gλ``, ``gV``,
    ``gC = V · sym(M) · Vᵀ``, ``M = diag(gλ) + F ∘ (Vᵀ gV)``,
    ``F_ij = (λ_j − λ_i)/((λ_j − λ_i)² + ε²)`` (``F_ii = 0``), ``ε = gap_eps·max_k|λ_k| + GAP_EPS_FLOOR``,
    ``sym(M) = (M + Mᵀ)/2``. This is the exact gradient of ``λ`` (``∂λ_k/∂C = v_k v_kᵀ``) and, for
    gaps ≫ ε, of ``V`` (``dv_j = Σ_i v_i (v_iᵀ dC v_j)/(λ_j − λ_i)``); it is finite for repeated
    eigenvalues (Lorentzian broadening). Not twice differentiable.

    ``impl``: ``None`` → ``"fast"`` (C++) unless ``GSBENCH_EIGEN=reference``; ``"reference"`` →
    `sym3_eigh_reference`. Raises `NumericalError` for NaN/inf entries (naming their count and the first
    batch index), ``ValueError`` for a bad shape, dtype, ``gap_eps`` or ``impl``, `ConfigError` for a bad
    ``GSBENCH_EIGEN``.
    """
    _check_input(C, gap_eps)
    if choose_impl(impl, EIGEN) == "reference":
        return _ReferenceSym3Eigh.apply(C, float(gap_eps))
    return _FastSym3Eigh.apply(C, float(gap_eps))


def sym3_eigh_reference(C: torch.Tensor, gap_eps: float = 1e-3) -> tuple[torch.Tensor, torch.Tensor]:
    """`sym3_eigh` by ``torch.linalg.eigh`` in float64 (slow, obviously right).

    Forward: ``eigh((C + Cᵀ)/2)`` reordered descending, then ``v3 := v1 × v2``. Backward: the same
    regularised formula as `sym3_eigh`, written in PyTorch (eigh's own backward, infinite for repeated
    eigenvalues, is never used). For (near-)degenerate pairs and isotropic ``C`` its basis of the
    degenerate eigenspace may differ from the fast path's.
    """
    _check_input(C, gap_eps)
    return _ReferenceSym3Eigh.apply(C, float(gap_eps))


def _check_input(C: torch.Tensor, gap_eps: float) -> None:
    if not gap_eps >= 0 or not np.isfinite(gap_eps):
        raise ValueError(f"gap_eps must be a finite number >= 0, got {gap_eps}")
    if not isinstance(C, torch.Tensor) or C.dim() < 2 or tuple(C.shape[-2:]) != (3, 3):
        shape = tuple(C.shape) if isinstance(C, torch.Tensor) else type(C).__name__
        raise ValueError(f"sym3_eigh expects a tensor of shape (..., 3, 3), got {shape}")
    if C.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"sym3_eigh expects float32 or float64, got {C.dtype}")
    if torch.isfinite(C.detach().sum()):  # a finite sum implies finite entries (cheap common case)
        return
    bad = ~torch.isfinite(C.detach()).reshape(-1, 9).all(dim=1)
    count = int(bad.sum())
    if count:
        first = int(bad.nonzero()[0, 0])
        index = tuple(int(i) for i in np.unravel_index(first, tuple(C.shape[:-2])))
        raise NumericalError(
            f"sym3_eigh: {count} of {bad.numel()} matrices contain NaN or inf, the first at batch index {index}; "
            "fix the non-finite values upstream (e.g. NaN Gaussian means)"
        )


def _regularised_gradient(lam, V, g_lam, g_V, gap_eps: float) -> torch.Tensor:
    """``gC = V · sym(diag(gλ) + F ∘ (Vᵀ gV)) · Vᵀ`` with the regularised ``F`` (see `sym3_eigh`)."""
    eps = gap_eps * lam.abs().amax(dim=-1) + GAP_EPS_FLOOR
    gap = lam[..., None, :] - lam[..., :, None]  # gap[..., i, j] = λ_j − λ_i
    F = gap / (gap * gap + (eps * eps)[..., None, None])
    M = torch.diag_embed(g_lam) + F * (V.mT @ g_V)
    return V @ (0.5 * (M + M.mT)) @ V.mT


class _ReferenceSym3Eigh(torch.autograd.Function):
    """torch.linalg.eigh forward (descending, det fix) and `_regularised_gradient` backward, in float64."""

    @staticmethod
    def forward(ctx, C, gap_eps):
        S = C.detach().to(torch.float64)
        lam, V = torch.linalg.eigh(0.5 * (S + S.mT))
        lam, V = lam.flip(-1), V.flip(-1).clone()
        V[..., 2] = torch.linalg.cross(V[..., 0], V[..., 1], dim=-1)
        ctx.gap_eps = gap_eps
        ctx.save_for_backward(lam, V)
        return lam.to(C.dtype), V.to(C.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_lam, g_V):
        lam, V = ctx.saved_tensors
        g = _regularised_gradient(lam, V, g_lam.to(torch.float64), g_V.to(torch.float64), ctx.gap_eps)
        return g.to(g_lam.dtype), None


class _FastSym3Eigh(torch.autograd.Function):
    """Forward and backward by ``gs_sym3_eigh_forward``/``gs_sym3_eigh_backward`` (csrc/eigen3.cpp), float64."""

    @staticmethod
    def forward(ctx, C, gap_eps):
        lib = _library()
        batch = C.shape[:-2]
        flat = C.detach().reshape(-1, 3, 3).to(device="cpu", dtype=torch.float64).contiguous()
        n = flat.shape[0]
        lam = torch.empty(n, 3, dtype=torch.float64)
        V = torch.empty(n, 3, 3, dtype=torch.float64)
        rc = lib.gs_sym3_eigh_forward(n, flat.data_ptr(), lam.data_ptr(), V.data_ptr(), omp_threads())
        if rc != 0:
            raise RuntimeError(f"gsbench sym3_eigh forward failed (code {rc})")
        ctx.gap_eps, ctx.batch = gap_eps, batch
        ctx.save_for_backward(lam, V)
        return (lam.reshape(*batch, 3).to(C.device, C.dtype), V.reshape(*batch, 3, 3).to(C.device, C.dtype))

    @staticmethod
    @once_differentiable
    def backward(ctx, g_lam, g_V):
        lam, V = ctx.saved_tensors
        n = lam.shape[0]
        g_lam64 = g_lam.reshape(n, 3).to(device="cpu", dtype=torch.float64).contiguous()
        g_V64 = g_V.reshape(n, 3, 3).to(device="cpu", dtype=torch.float64).contiguous()
        g_C = torch.empty(n, 3, 3, dtype=torch.float64)
        rc = _library().gs_sym3_eigh_backward(
            n, lam.data_ptr(), V.data_ptr(), g_lam64.data_ptr(), g_V64.data_ptr(), ctx.gap_eps, GAP_EPS_FLOOR,
            g_C.data_ptr(), omp_threads(),
        )
        if rc != 0:
            raise RuntimeError(f"gsbench sym3_eigh backward failed (code {rc})")
        return g_C.reshape(*ctx.batch, 3, 3).to(g_lam.device, g_lam.dtype), None
