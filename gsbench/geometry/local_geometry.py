"""Local covariance of neighbour means, its eigen-decomposition, and frame continuity (IBGS,
docs/methods/ibgs.md §3, §4, §7.

- Covariance (paper Eq. 4): with P_i = {μ_i} ∪ {μ_j : j ∈ N(i)} (n = K + 1 points; without μ_i when
  ``include_self`` is false), μ̄_i = mean(P_i), ``C_i = (1/n) Σ_{p∈P_i} (p − μ̄_i)(p − μ̄_i)ᵀ + δI`` with
  δ = 1e-10·radius² (docs/methods/ibgs.md §3.4), in float64 from the *current* means, so gradients reach all n means.
- Eigen-decomposition (Eq. 5) by `gsbench.geometry.eigen3.sym3_eigh` of C / radius² (then λ × radius², so the
  solver's absolute floors are scale-free): λ1 ≥ λ2 ≥ λ3, columns v1, v2, v3, det V = +1,
  gap-regularised backward (docs/methods/ibgs.md §3.3). ``valid`` is false where λ1 <= 2δ, i.e. the neighbours' own
  spread is below the jitter (coincident points, docs/methods/ibgs.md §3.4); those rows use V = I and the IBGS losses
  skip them.
- Planarity (Eq. 10, [ASSUMED] formula): γ = (λ2 − λ3)/λ1 (λ1 >= δ > 0), detached (docs/methods/ibgs.md §5.3).
- Frame continuity (docs/methods/ibgs.md §4.2): eigenvector signs are arbitrary and the sorted order swaps
  when two eigenvalues cross, so the orientation would jump. `frame_alignment` picks, per Gaussian, the
  column permutation and signs of the new V that best agree with the previous frame (maximising
  Σ_k |v_new,π(k) · v_old,k|), then makes det = +1 by flipping the least aligned column. For surfels
  (2 scales) the permutation must keep v3 — the splat normal — in the third column.
"""

from __future__ import annotations

import ctypes
import itertools
from dataclasses import dataclass
from pathlib import Path

import torch
from torch.autograd.function import once_differentiable

from gsbench.geometry.eigen3 import sym3_eigh
from gsbench.geometry.rotations import frames_library
from gsbench.native.build import load_library, omp_threads
from gsbench.native.impl_choice import choose_impl
from gsbench.phase_timer import PhaseTimer
from gsbench.switches import LOCAL_COVARIANCE

COVARIANCE_JITTER = 1e-10  # δ = 1e-10·radius² added to C (docs/methods/ibgs.md §3.4); λ1 <= 2δ: coincident points

PERMUTATIONS_3D = tuple(itertools.permutations(range(3)))
PERMUTATIONS_2D = ((0, 1, 2), (1, 0, 2))  # surfels: v3 stays the normal


_i64, _ptr, _dbl = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
SIGNATURES = {
    "gs_local_covariance_forward": ([_i64] * 4 + [_ptr] * 2 + [_dbl] + [_ptr, _i64], ctypes.c_int),
    "gs_local_covariance_backward": ([_i64] * 4 + [_ptr] * 4 + [_i64], ctypes.c_int),
}


def _library() -> ctypes.CDLL:
    """The native library of the kNN neighbourhood covariance and its backward (``csrc/local_covariance.cpp``, compiled on first use)."""
    return load_library("local_covariance", [Path(__file__).parent / "csrc" / "local_covariance.cpp"], SIGNATURES)


@dataclass
class LocalGeometry:
    """Per-Gaussian neighbourhood eigen-structure: ``eigenvalues`` (N,3) descending, ``eigenvectors``
    (N,3,3) columns v1 v2 v3 (float64, differentiable w.r.t. the means), ``valid`` (N,) bool,
    ``index`` (N,K) the neighbour index they were computed with."""

    eigenvalues: torch.Tensor
    eigenvectors: torch.Tensor
    valid: torch.Tensor
    index: torch.Tensor

    @property
    def normals(self) -> torch.Tensor:
        """v3 (N,3): the direction of least spread, sign arbitrary."""
        return self.eigenvectors[:, :, 2]

    def planarity(self) -> torch.Tensor:
        """γ = (λ2 − λ3)/λ1 (N,), detached (Eq. 10, [ASSUMED] Demantké/Weinmann form)."""
        lam = self.eigenvalues.detach()
        return (lam[:, 1] - lam[:, 2]) / lam[:, 0]  # λ1 >= δ > 0 (the jitter)


def neighbourhood_points(means: torch.Tensor, neighbour_means: torch.Tensor, include_self: bool) -> torch.Tensor:
    """P_i (N, n, 3): the neighbour means (N,K,3), preceded by the Gaussian's own (N,3) if ``include_self``."""
    return torch.cat([means[:, None], neighbour_means], 1) if include_self else neighbour_means


def local_covariance(means: torch.Tensor, index: torch.Tensor, radius: float,
                     include_self: bool = True, impl: str | None = None) -> torch.Tensor:
    """C (N,3,3) float64 of each Gaussian's neighbourhood (module docstring, Eq. 4).

    By the fused C++ kernel (``csrc/local_covariance.cpp``: one pass forward, the backward
    dL/dp = (1/n)(G + Gᵀ)(p − μ̄) per member, scattered in member order) for CPU float32 / float64 means;
    `local_covariance_reference` otherwise, with ``impl="reference"`` or with
    ``GSBENCH_LOCAL_COVARIANCE=reference`` (`gsbench.native.impl_choice.choose_impl`).
    """
    def unsupported():
        if means.device.type != "cpu" or means.dtype not in (torch.float32, torch.float64):
            return f"means on {means.device.type} as {means.dtype} (the kernel takes CPU float32 / float64)"
        return None

    if choose_impl(impl, LOCAL_COVARIANCE, unsupported, "local_covariance") == "reference":
        return local_covariance_reference(means, index, radius, include_self)
    return _FusedLocalCovariance.apply(means, index, COVARIANCE_JITTER * radius**2, include_self)


def local_covariance_reference(means: torch.Tensor, index: torch.Tensor, radius: float,
                               include_self: bool = True) -> torch.Tensor:
    """`local_covariance` in PyTorch ops (gather, centre, batched product; autograd backward)."""
    x = means.to(torch.float64)
    points = neighbourhood_points(x, x[index], include_self)
    centred = points - points.mean(1, keepdim=True)
    cov = centred.transpose(1, 2) @ centred / max(points.shape[1], 1)
    return cov + (COVARIANCE_JITTER * radius**2) * torch.eye(3, dtype=torch.float64)


class _FusedLocalCovariance(torch.autograd.Function):
    """``gs_local_covariance_forward`` / ``_backward`` (csrc/local_covariance.cpp)."""

    @staticmethod
    def forward(ctx, means, index, jitter, include_self):
        x = means.detach().contiguous()
        idx = index.to(torch.int64).contiguous()
        N, K = idx.shape
        if N != x.shape[0]:
            raise ValueError(f"local_covariance: index has {N} rows for {x.shape[0]} means")
        C = torch.empty(N, 3, 3, dtype=torch.float64)
        rc = _library().gs_local_covariance_forward(N, K, int(include_self), int(x.dtype == torch.float64),
                                                        x.data_ptr(), idx.data_ptr(), jitter, C.data_ptr(), omp_threads())
        if rc != 0:
            raise ValueError(f"local_covariance: neighbour index out of range [0, {N}) or no members (code {rc})")
        ctx.include_self = include_self
        ctx.save_for_backward(x, idx)
        return C

    @staticmethod
    @once_differentiable
    def backward(ctx, g_C):
        x, idx = ctx.saved_tensors
        N, K = idx.shape
        g = g_C.to(torch.float64).contiguous()
        g_means = torch.empty(N, 3, dtype=torch.float64)
        rc = _library().gs_local_covariance_backward(N, K, int(ctx.include_self), int(x.dtype == torch.float64),
                                                         x.data_ptr(), idx.data_ptr(), g.data_ptr(), g_means.data_ptr(),
                                                         omp_threads())
        if rc != 0:
            raise RuntimeError(f"gsbench local_covariance backward failed (code {rc})")
        return g_means.to(x.dtype), None, None, None



def local_geometry(means: torch.Tensor, index: torch.Tensor, radius: float, include_self: bool = True,
                   gap_eps: float = 1e-3, timer: PhaseTimer | None = None) -> LocalGeometry:
    """Covariance and eigen-decomposition of every neighbourhood (module docstring); with a ``timer``
    their forward and backward time is added to its ``"local_geometry"`` phase."""

    def decompose(x):
        lam, vec = sym3_eigh(local_covariance(x, index, radius, include_self) / radius**2, gap_eps=gap_eps)
        return lam * radius**2, vec

    lam, vec = decompose(means) if timer is None else timer.run("local_geometry", decompose, means)
    valid = lam.detach()[:, 0] > 2 * COVARIANCE_JITTER * radius**2
    eye = torch.eye(3, dtype=vec.dtype).expand_as(vec)
    vec = torch.where(valid[:, None, None], vec, eye)
    return LocalGeometry(lam, vec, valid, index)


@torch.no_grad()
def frame_alignment(vectors: torch.Tensor, previous: torch.Tensor, surfel: bool = False
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """(column permutation (N,3) int64, signs (N,3)) that map ``vectors`` onto ``previous`` (docs/methods/ibgs.md §4.2).

    Apply as ``vectors[:, :, perm] * signs``: column k of the result is ± the new eigenvector that best
    matches previous column k; the signs make each dot product >= 0, then det is made +1 by flipping
    the least aligned column. By ``gs_frame_alignment`` (csrc/frames.cpp) for CPU float64 ``vectors``;
    `frame_alignment_reference` otherwise.
    """
    if vectors.device.type != "cpu" or vectors.dtype != torch.float64 or previous.dtype not in (torch.float32,
                                                                                                   torch.float64):
        return frame_alignment_reference(vectors, previous, surfel)

    V, prev = vectors.contiguous(), previous.contiguous()
    n = V.shape[0]
    perm = torch.empty(n, 3, dtype=torch.int64)
    signs = torch.empty(n, 3, dtype=torch.float64)
    rc = frames_library().gs_frame_alignment(n, int(surfel), V.data_ptr(), prev.data_ptr(), int(prev.dtype == torch.float64),
                                           perm.data_ptr(), signs.data_ptr(), omp_threads())
    if rc != 0:
        raise RuntimeError(f"gsbench frame_alignment failed (code {rc})")
    return perm, signs


@torch.no_grad()
def frame_alignment_reference(vectors: torch.Tensor, previous: torch.Tensor, surfel: bool = False
                              ) -> tuple[torch.Tensor, torch.Tensor]:
    """`frame_alignment` in PyTorch ops (the reference)."""
    perms = torch.tensor(PERMUTATIONS_2D if surfel else PERMUTATIONS_3D, dtype=torch.int64)
    dots = previous.transpose(1, 2).to(vectors.dtype) @ vectors  # (N, old k, new m)
    picks = torch.zeros(9, len(perms), dtype=dots.dtype)  # picks[3k + p(k), p] = 1: scores = |dots| · picks
    picks[torch.arange(3)[None, :] * 3 + perms, torch.arange(len(perms))[:, None]] = 1.0
    perm = perms[(dots.abs().reshape(-1, 9) @ picks).argmax(-1)]
    aligned = torch.gather(dots, 2, perm[:, :, None]).squeeze(-1)  # previous_k · v_perm(k)
    signs = torch.where(aligned < 0, -1.0, 1.0).to(vectors.dtype)
    frame = torch.gather(vectors, 2, perm[:, None, :].expand(-1, 3, -1)) * signs[:, None, :]
    flip = torch.linalg.det(frame) < 0
    weakest = (aligned.abs() + torch.tensor([0.0, 0.0, 1.0 if surfel else 0.0])).argmin(-1)
    signs[flip, weakest[flip]] *= -1
    return perm, signs


def apply_alignment(vectors: torch.Tensor, perm: torch.Tensor, signs: torch.Tensor) -> torch.Tensor:
    """``vectors[:, :, perm] * signs`` per row (differentiable in ``vectors``)."""
    return torch.gather(vectors, 2, perm[:, None, :].expand(-1, 3, -1)) * signs[:, None, :]
