"""Quaternion helpers in torch, differentiable: Hamilton product and rotation matrix -> quaternion.

Quaternions are (w, x, y, z) as in 3DGS (docs/methods/3dgs.md §2.1); ``quat_to_rotmat``
(`gsbench.raster.reference`) is the inverse of `rotmat_to_quat` on unit quaternions with w >= 0.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

import torch
import torch.nn.functional as F

from gsbench.native.build import load_library, omp_threads

_i64, _ptr, _dbl = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
SIGNATURES = {
    "gs_frame_alignment": ([_i64] * 2 + [_ptr] * 2 + [_i64] + [_ptr, _ptr, _i64], ctypes.c_int),
    "gs_rotmat_to_quat": ([_i64, _ptr, _ptr, _i64], ctypes.c_int),
    "gs_rotmat_to_quat_backward": ([_i64] + [_ptr] * 3 + [_i64], ctypes.c_int),
}


def frames_library() -> ctypes.CDLL:
    """The native library of IBGS's frame alignment and the rotation -> quaternion conversion (``csrc/frames.cpp``, compiled on first use)."""
    return load_library("frames", [Path(__file__).parent / "csrc" / "frames.cpp"], SIGNATURES)


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a ⊗ b of (..., 4) quaternions: R(a ⊗ b) = R(a) R(b)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], -1)


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternions (N,4) of proper rotations R (N,3,3) by Shepperd's method, with w >= 0.

    Of the four candidate forms (from 1 + tr, 1 + 2R₀₀ − tr, 1 + 2R₁₁ − tr, 1 + 2R₂₂ − tr) the one with
    the largest radicand is used, so the square root is of at least 1 and the gradient is bounded.
    For CPU float64 R by ``gs_rotmat_to_quat`` (csrc/frames.cpp, the same steps in one loop) with the
    hand-written backward ``gs_rotmat_to_quat_backward``; `rotmat_to_quat_reference` otherwise.
    """
    if R.device.type != "cpu" or R.dtype != torch.float64:
        return rotmat_to_quat_reference(R)
    return _FusedRotmatToQuat.apply(R)


class _FusedRotmatToQuat(torch.autograd.Function):
    @staticmethod
    def forward(ctx, R):
        m = R.detach().contiguous()
        q = torch.empty(m.shape[0], 4, dtype=torch.float64)
        rc = frames_library().gs_rotmat_to_quat(m.shape[0], m.data_ptr(), q.data_ptr(), omp_threads())
        if rc != 0:
            raise RuntimeError(f"gsbench rotmat_to_quat failed (code {rc})")
        ctx.save_for_backward(m)
        return q

    @staticmethod
    def backward(ctx, grad_q):
        (m,) = ctx.saved_tensors
        g = grad_q.to(torch.float64).contiguous()
        grad_R = torch.empty_like(m)
        rc = frames_library().gs_rotmat_to_quat_backward(m.shape[0], m.data_ptr(), g.data_ptr(), grad_R.data_ptr(),
                                                       omp_threads())
        if rc != 0:
            raise RuntimeError(f"gsbench rotmat_to_quat backward failed (code {rc})")
        return grad_R


def rotmat_to_quat_reference(R: torch.Tensor) -> torch.Tensor:
    """`rotmat_to_quat` in PyTorch ops (differentiable; the reference)."""
    m = R
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    radicands = torch.stack([1 + tr, 1 + 2 * m[:, 0, 0] - tr, 1 + 2 * m[:, 1, 1] - tr, 1 + 2 * m[:, 2, 2] - tr], -1)
    choice = radicands.detach().argmax(-1)
    s = 2 * torch.sqrt(radicands.gather(1, choice[:, None]).squeeze(1).clamp(min=1e-12))  # s = 4·|component|
    d21, d02, d10 = m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]
    s01, s02, s12 = m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1]
    quarter = s / 4
    candidates = torch.stack([
        torch.stack([quarter, d21 / s, d02 / s, d10 / s], -1),
        torch.stack([d21 / s, quarter, s01 / s, s02 / s], -1),
        torch.stack([d02 / s, s01 / s, quarter, s12 / s], -1),
        torch.stack([d10 / s, s02 / s, s12 / s, quarter], -1),
    ], 1)
    q = candidates.gather(1, choice[:, None, None].expand(-1, 1, 4)).squeeze(1)
    q = torch.where(q[:, :1] < 0, -q, q)
    return F.normalize(q, dim=-1)
