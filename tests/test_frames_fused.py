"""IBGS's frame bookkeeping in C++ (csrc/frames.cpp) against the PyTorch references: `frame_alignment`
(the same permutation and signs, 3D and surfel) and `rotmat_to_quat` with its backward (every Shepperd
branch; a float64 gradcheck)."""

from __future__ import annotations

import pytest
import torch

from gsbench.geometry.eigen3 import sym3_eigh
from gsbench.geometry.local_geometry import apply_alignment, frame_alignment, frame_alignment_reference
from gsbench.geometry.rotations import rotmat_to_quat, rotmat_to_quat_reference


def _frames(n, seed=0):
    """Eigenvector frames (det +1) of random symmetric matrices, float64."""
    gen = torch.Generator().manual_seed(seed)
    A = torch.randn(n, 3, 3, generator=gen, dtype=torch.float64)
    return sym3_eigh(A @ A.mT + 0.1 * torch.eye(3, dtype=torch.float64))[1]


@pytest.mark.parametrize("surfel", [False, True])
@pytest.mark.parametrize("previous_dtype", [torch.float32, torch.float64])
def test_frame_alignment_equals_the_reference(surfel, previous_dtype):
    V = _frames(5000)
    gen = torch.Generator().manual_seed(1)
    # the previous frame: the same axes permuted and sign-flipped at random, then perturbed
    perms = torch.stack([torch.randperm(3, generator=gen) for _ in range(len(V))])
    flips = torch.where(torch.rand(len(V), 3, generator=gen) < 0.5, -1.0, 1.0).double()
    previous = (apply_alignment(V, perms, flips) + 0.2 * torch.randn(V.shape, generator=gen, dtype=torch.float64))
    previous = previous.to(previous_dtype)
    perm, signs = frame_alignment(V, previous, surfel)
    perm_ref, signs_ref = frame_alignment_reference(V, previous, surfel)
    assert torch.equal(perm, perm_ref) and torch.equal(signs, signs_ref.to(signs.dtype))
    assert torch.all(torch.linalg.det(apply_alignment(V, perm, signs)) > 0)
    if surfel:
        assert torch.all(perm[:, 2] == 2)


def test_rotmat_to_quat_equals_the_reference_on_every_branch():
    R = _frames(4000, seed=3)
    # rotations by ~180° about each axis exercise the x, y and z branches
    R = torch.cat([R, torch.diag(torch.tensor([1.0, -1, -1], dtype=torch.float64)).expand(3, 3, 3),
                   torch.diag(torch.tensor([-1.0, 1, -1], dtype=torch.float64))[None],
                   torch.diag(torch.tensor([-1.0, -1, 1], dtype=torch.float64))[None]])
    q, q_ref = rotmat_to_quat(R), rotmat_to_quat_reference(R)
    assert float((q - q_ref).abs().max()) < 1e-14
    radicands = torch.stack([1 + R.diagonal(dim1=1, dim2=2).sum(-1), *(1 + 2 * R[:, i, i] - R.diagonal(dim1=1, dim2=2).sum(-1)
                                                                       for i in range(3))], -1)
    assert set(radicands.argmax(-1).tolist()) == {0, 1, 2, 3}


def _every_branch(n, seed):
    """Random frames plus rotations by 180° about each axis (the x, y and z branches)."""
    R = _frames(n, seed=seed)
    return torch.cat([R, torch.diag(torch.tensor([1.0, -1, -1], dtype=torch.float64))[None],
                      torch.diag(torch.tensor([-1.0, 1, -1], dtype=torch.float64))[None],
                      torch.diag(torch.tensor([-1.0, -1, 1], dtype=torch.float64))[None]])


def test_rotmat_to_quat_gradient_equals_the_references_on_every_branch():
    """The hand-written backward against autograd through `rotmat_to_quat_reference`, for a random dL/dq."""
    R = _every_branch(3000, seed=4)
    gq = torch.randn(len(R), 4, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    x = R.clone().requires_grad_(True)
    q = rotmat_to_quat(x)
    assert q.grad_fn is not None
    (g,) = torch.autograd.grad(q, x, gq)
    y = R.clone().requires_grad_(True)
    (g_ref,) = torch.autograd.grad(rotmat_to_quat_reference(y), y, gq)
    assert float((g - g_ref).abs().max()) < 1e-12


def test_rotmat_to_quat_gradcheck_float64():
    """Finite differences on general 3×3 matrices near rotations (away from branch switches)."""
    R = _frames(6, seed=7) + 0.01 * torch.randn(6, 3, 3, generator=torch.Generator().manual_seed(8), dtype=torch.float64)
    assert torch.autograd.gradcheck(rotmat_to_quat, (R.requires_grad_(True),))
