"""`gsbench.geometry.eigen3.sym3_eigh`: the C++ closed form vs the torch.linalg.eigh reference vs numpy.linalg.eigh,
and the gap-regularised backward (docs/methods/ibgs.md §3.2, §3.3).

Degenerate inputs are the ones IBGS meets (docs/methods/ibgs.md §7): coplanar, collinear and duplicated neighbour
points, K = 2 (rank 1), isotropic covariances; scenes in mm or km give the 1e±9 and 1e±18 scales.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gsbench.errors import ConfigError, NumericalError
from gsbench.geometry.eigen3 import _ReferenceSym3Eigh, sym3_eigh, sym3_eigh_reference
from gsbench.switches import EIGEN

IMPLS = EIGEN.values
N = 200
ROUNDING_TOL = 1e-13  # eigenvalues and residuals relative to max|λ|; orthonormality; det − 1
VECTOR_TOL = 1e-13  # ‖v − v_numpy‖ <= VECTOR_TOL / (relative gap of v's eigenvalue)
MIN_COMPARED_GAP = 1e-7  # eigenvectors with a smaller relative gap are only checked by residual


def _generator(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _randn(*shape, seed: int) -> torch.Tensor:
    return torch.randn(*shape, generator=_generator(seed), dtype=torch.float64)


def _with_spectrum(lam, seed: int = 0) -> torch.Tensor:
    """Q diag(lam) Qᵀ for N random rotations Q."""
    Q, _ = torch.linalg.qr(_randn(N, 3, 3, seed=seed))
    return Q @ torch.diag_embed(torch.as_tensor(lam, dtype=torch.float64).expand(N, 3)) @ Q.mT


def _covariance(points: torch.Tensor) -> torch.Tensor:
    """C = (1/n) Σ (p − μ̄)(p − μ̄)ᵀ of (..., n, 3) points (IBGS Eq. 4)."""
    d = points - points.mean(dim=-2, keepdim=True)
    return d.mT @ d / points.shape[-2]


def random_points(seed=1):
    return _randn(N, 6, 3, seed=seed) + 10 * _randn(N, 1, 3, seed=seed + 1)


def coplanar_points(seed=2):
    return _randn(N, 6, 2, seed=seed) @ _randn(N, 2, 3, seed=seed + 1) + _randn(N, 1, 3, seed=seed + 2)


def collinear_points(seed=3):
    return _randn(N, 6, 1, seed=seed) * _randn(N, 1, 3, seed=seed + 1) + _randn(N, 1, 3, seed=seed + 2)


def duplicated_points(seed=4):
    return _randn(N, 1, 3, seed=seed).expand(N, 6, 3).clone()


def two_points(seed=5):
    return _randn(N, 2, 3, seed=seed)


POINT_SETS = {
    "random": random_points, "coplanar": coplanar_points, "collinear": collinear_points,
    "duplicated": duplicated_points, "two_points": two_points,
}


def _isotropic():
    return torch.exp(_randn(N, 1, 1, seed=6)) * torch.eye(3, dtype=torch.float64)


CASES = {
    "spd": lambda: _covariance(random_points()),
    "indefinite": lambda: _randn(N, 3, 3, seed=7) + _randn(N, 3, 3, seed=7).mT,
    "nonsymmetric": lambda: _randn(N, 3, 3, seed=17),  # its symmetric part is decomposed
    "gap_1e-6_low_pair": lambda: _with_spectrum([1.0, 0.3 + 1e-6, 0.3]),
    "gap_1e-6_high_pair": lambda: _with_spectrum([1.0, 1.0 - 1e-6, 0.3]),
    "gap_1e-10_low_pair": lambda: _with_spectrum([1.0, 0.3 + 1e-10, 0.3]),
    "gap_1e-10_high_pair": lambda: _with_spectrum([1.0, 1.0 - 1e-10, 0.3]),
    "gap_1e-10_triple": lambda: _with_spectrum([1.0 + 2e-10, 1.0 + 1e-10, 1.0]),
    "equal_low_pair": lambda: _with_spectrum([2.0, -1.0, -1.0]),
    "coplanar": lambda: _covariance(coplanar_points()),
    "collinear": lambda: _covariance(collinear_points()),
    "duplicated": lambda: _covariance(duplicated_points()),
    "two_points": lambda: _covariance(two_points()),
    "isotropic": _isotropic,
    "isotropic_rotated": lambda: _with_spectrum([0.7, 0.7, 0.7]),
    "zero": lambda: torch.zeros(N, 3, 3, dtype=torch.float64),
    **{f"spd_scale_{s:g}": (lambda s=s: s * _covariance(random_points())) for s in (1e-18, 1e-9, 1e9, 1e18)},
    **{f"coplanar_scale_{s:g}": (lambda s=s: s * _covariance(coplanar_points())) for s in (1e-18, 1e18)},
}
DEGENERATE = ("equal_low_pair", "coplanar", "collinear", "duplicated", "two_points", "isotropic",
              "isotropic_rotated", "zero")


def _numpy_eigh(C: torch.Tensor):
    """numpy.linalg.eigh of (C + Cᵀ)/2, descending."""
    lam, V = np.linalg.eigh(0.5 * (C + C.mT).numpy())
    return lam[..., ::-1], V[..., ::-1]


def _relative_gaps(lam: np.ndarray) -> np.ndarray:
    """Distance of each eigenvalue to the nearest other one, relative to max|λ| (0 for λ = 0)."""
    gaps = (np.abs(lam[..., :, None] - lam[..., None, :]) + np.diag([np.inf] * 3)).min(-1)
    scale = np.abs(lam).max(-1, keepdims=True)
    return gaps / np.where(scale > 0, scale, np.inf)


def _check_decomposition(C: torch.Tensor, lam: torch.Tensor, V: torch.Tensor) -> None:
    """Finite, descending, eigenvalues and well-separated eigenvectors as numpy's, small residual,
    orthonormal, det V = +1."""
    assert torch.isfinite(lam).all() and torch.isfinite(V).all()
    assert (lam[..., :-1] >= lam[..., 1:]).all()
    lam_np, V_np = _numpy_eigh(C)
    scale = np.abs(lam_np).max(-1, keepdims=True)
    assert (np.abs(lam.numpy() - lam_np) <= ROUNDING_TOL * scale).all()
    S = 0.5 * (C + C.mT)
    residual = torch.linalg.vector_norm(S @ V - V * lam[..., None, :], dim=-2).numpy()
    assert (residual <= ROUNDING_TOL * scale).all()
    eye = torch.eye(3, dtype=torch.float64)
    assert (V.mT @ V - eye).abs().max() <= ROUNDING_TOL
    assert (torch.linalg.det(V) - 1).abs().max() <= ROUNDING_TOL
    sign = np.sign((V.numpy() * V_np).sum(-2, keepdims=True))
    error = np.linalg.norm(V.numpy() - sign * V_np, axis=-2)
    gaps = _relative_gaps(lam_np)
    compared = gaps >= MIN_COMPARED_GAP
    assert (error[compared] <= VECTOR_TOL / gaps[compared]).all()


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("impl", IMPLS)
def test_matches_numpy(case, impl):
    C = CASES[case]()
    _check_decomposition(C, *sym3_eigh(C, impl=impl))


def test_reference_entry_point():
    C = CASES["indefinite"]()
    for got, expected in zip(sym3_eigh_reference(C), sym3_eigh(C, impl="reference")):
        assert torch.equal(got, expected)


@pytest.mark.parametrize("impl", IMPLS)
def test_isolated_eigenvector_of_a_degenerate_pair(impl):
    Q, _ = torch.linalg.qr(_randn(N, 3, 3, seed=8))
    _, V = sym3_eigh(Q @ torch.diag_embed(torch.tensor([3.0, 1.0, 1.0]).double().expand(N, 3)) @ Q.mT, impl=impl)
    assert (1 - (V[..., 0] * Q[..., 0]).sum(-1).abs()).abs().max() <= 1e-15
    _, V = sym3_eigh(Q @ torch.diag_embed(torch.tensor([3.0, 3.0, 1.0]).double().expand(N, 3)) @ Q.mT, impl=impl)
    assert (1 - (V[..., 2] * Q[..., 2]).sum(-1).abs()).abs().max() <= 1e-15


@pytest.mark.parametrize("impl", IMPLS)
def test_plane_normal_and_line_direction(impl):
    basis = _randn(N, 2, 3, seed=3)
    normal = torch.nn.functional.normalize(torch.linalg.cross(basis[:, 0], basis[:, 1]), dim=-1)
    _, V = sym3_eigh(_covariance(_randn(N, 6, 2, seed=2) @ basis), impl=impl)
    assert (V[..., 2] * normal).sum(-1).abs().min() >= 1 - 1e-13
    direction = torch.nn.functional.normalize(_randn(N, 3, seed=9), dim=-1)
    _, V = sym3_eigh(_covariance(_randn(N, 6, 1, seed=10) * direction[:, None]), impl=impl)
    assert (V[..., 0] * direction).sum(-1).abs().min() >= 1 - 1e-13


def test_fast_isotropic_is_identity():
    C = torch.cat([_isotropic(), torch.zeros(3, 3, 3, dtype=torch.float64)])
    lam, V = sym3_eigh(C, impl="fast")
    assert torch.equal(V, torch.eye(3, dtype=torch.float64).expand_as(V))
    assert torch.allclose(lam, C.diagonal(dim1=-2, dim2=-1), rtol=1e-15, atol=0)


@pytest.mark.parametrize("impl", IMPLS)
def test_float32_in_float32_out(impl):
    """float32 is computed in float64 (the inputs are exact there) and rounded once, also the gradient."""
    C = CASES["spd"]().float().requires_grad_(True)
    lam, V = sym3_eigh(C, impl=impl)
    assert lam.dtype == V.dtype == torch.float32
    C64 = C.detach().double().requires_grad_(True)
    lam64, V64 = sym3_eigh(C64, impl=impl)
    assert torch.equal(lam, lam64.float()) and torch.equal(V, V64.float())
    (grad,) = torch.autograd.grad(_sign_invariant_loss(lam, V), C)
    (grad64,) = torch.autograd.grad(_sign_invariant_loss(lam64, V64), C64)
    assert grad.dtype == torch.float32
    assert torch.allclose(grad.double(), grad64, rtol=0, atol=1e-5 * grad64.abs().max())


@pytest.mark.parametrize("shape", [(0,), (2, 0), (), (2, 3, 4)])
@pytest.mark.parametrize("impl", IMPLS)
def test_batch_shapes(shape, impl):
    C = _covariance(_randn(*shape, 6, 3, seed=11)).requires_grad_(True)
    lam, V = sym3_eigh(C, impl=impl)
    assert lam.shape == (*shape, 3) and V.shape == (*shape, 3, 3)
    flat_lam, flat_V = sym3_eigh(C.detach().reshape(-1, 3, 3), impl=impl)
    assert torch.equal(lam.detach().reshape(-1, 3), flat_lam) and torch.equal(V.detach().reshape(-1, 3, 3), flat_V)
    (lam.sum() + (V[..., 2] ** 2).sum()).backward()
    assert C.grad.shape == C.shape and torch.isfinite(C.grad).all()


@pytest.mark.parametrize("impl", IMPLS)
def test_non_finite_input_raises(impl):
    C = torch.eye(3, dtype=torch.float64).repeat(4, 5, 1, 1)
    C[2, 3, 0, 1] = float("nan")
    C[3, 1, 2, 2] = float("inf")
    with pytest.raises(NumericalError, match=r"2 of 20 matrices .* batch index \(2, 3\)"):
        sym3_eigh(C, impl=impl)


def test_bad_arguments():
    C = torch.eye(3)
    with pytest.raises(ValueError, match="shape"):
        sym3_eigh(torch.eye(3)[:, :2])
    with pytest.raises(ValueError, match="float32 or float64"):
        sym3_eigh(C.half())
    with pytest.raises(ValueError, match="gap_eps"):
        sym3_eigh(C, gap_eps=-1.0)
    with pytest.raises(ValueError, match="impl"):
        sym3_eigh(C, impl="lapack")


def test_environment_selects_the_implementation(monkeypatch):
    calls = []
    monkeypatch.setattr(_ReferenceSym3Eigh, "apply", lambda C, gap_eps: calls.append(gap_eps))
    monkeypatch.setenv(EIGEN.name, "reference")
    sym3_eigh(torch.eye(3), gap_eps=0.5)
    assert calls == [0.5]
    monkeypatch.setenv(EIGEN.name, "fast")
    sym3_eigh(torch.eye(3))
    assert calls == [0.5]
    monkeypatch.setenv(EIGEN.name, "lapack")
    with pytest.raises(ConfigError, match=EIGEN.name):
        sym3_eigh(torch.eye(3))


# -- gradients ------------------------------------------------------------------------------------


def _sign_invariant_loss(lam: torch.Tensor, V: torch.Tensor, seed: int = 12) -> torch.Tensor:
    """Σ λ·w + (v3·a)² + (v1·b)²: independent of the arbitrary column signs."""
    w, a, b = (_randn(*lam.shape, seed=seed + k).to(lam.dtype) for k in range(3))
    return (lam * w).sum() + ((V[..., 2] * a).sum(-1) ** 2).sum() + ((V[..., 0] * b).sum(-1) ** 2).sum()


def _separated(n: int, seed: int) -> torch.Tensor:
    """Non-symmetric matrices whose symmetric parts have eigenvalue gaps >= 0.3."""
    Q, _ = torch.linalg.qr(_randn(n, 3, 3, seed=seed))
    lam = torch.tensor([2.0, 0.9, -0.4], dtype=torch.float64) + 0.2 * torch.rand(n, 3, generator=_generator(seed))
    return Q @ torch.diag_embed(lam) @ Q.mT + 0.1 * _randn(n, 3, 3, seed=seed + 1)


@pytest.mark.parametrize("impl", IMPLS)
def test_gradcheck(impl):
    C = _separated(4, seed=13).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda C: _sign_invariant_loss(*sym3_eigh(C, impl=impl), seed=3), (C,))


@pytest.mark.parametrize("impl", IMPLS)
def test_gradient_equals_eigh_autograd_for_separated_eigenvalues(impl):
    C = _separated(N, seed=14).requires_grad_(True)
    (grad,) = torch.autograd.grad(_sign_invariant_loss(*sym3_eigh(C, gap_eps=0.0, impl=impl)), C)
    lam, V = torch.linalg.eigh(0.5 * (C + C.mT))
    (expected,) = torch.autograd.grad(_sign_invariant_loss(lam.flip(-1), V.flip(-1)), C)
    assert torch.allclose(grad, expected, rtol=0, atol=1e-10 * expected.abs().max())


# Where the eigenvectors are determined to ~1e-10 (relative gaps >= 1e-6); with a gap of 1e-10 they are
# only determined to ~1e-6, and so is every eigenvector-dependent gradient.
@pytest.mark.parametrize("case", [c for c in CASES if c not in DEGENERATE and not c.startswith("gap_1e-10")])
def test_fast_and_reference_gradients_agree(case):
    grads = []
    for impl in IMPLS:
        C = CASES[case]().requires_grad_(True)
        lam, V = sym3_eigh(C, impl=impl)
        scale = lam.detach().abs().amax(-1)[:, None]
        grads.append(torch.autograd.grad(_sign_invariant_loss(lam / scale, V), C)[0] * scale[..., None])
    assert torch.allclose(grads[0], grads[1], rtol=0, atol=1e-8 * grads[1].abs().max())


@pytest.mark.parametrize("case", DEGENERATE)
@pytest.mark.parametrize("impl", IMPLS)
def test_finite_gradients_on_degenerate_input(case, impl):
    C = CASES[case]().requires_grad_(True)
    lam, V = sym3_eigh(C, impl=impl)
    loss = (lam * _randn(N, 3, seed=15)).sum() + (V * _randn(N, 3, 3, seed=16)).sum()
    (grad,) = torch.autograd.grad(loss, C)
    assert torch.isfinite(grad).all()


@pytest.mark.parametrize("points", POINT_SETS)
@pytest.mark.parametrize("impl", IMPLS)
def test_smallest_eigenvalue_gradient_wrt_points(points, impl):
    """Acceptance criterion: ∂λ3/∂p = (2/n)(v3·(p − μ̄)) v3 for C = (1/n) Σ (p − μ̄)(p − μ̄)ᵀ (docs/methods/ibgs.md §5.2)."""
    P = POINT_SETS[points]().requires_grad_(True)
    lam, V = sym3_eigh(_covariance(P), impl=impl)
    (grad,) = torch.autograd.grad(lam[..., 2].sum(), P)
    v3 = V[..., 2].detach()[:, None, :]
    d = (P - P.mean(dim=-2, keepdim=True)).detach()
    expected = 2 / P.shape[-2] * (d * v3).sum(-1, keepdim=True) * v3
    assert torch.isfinite(grad).all()
    assert torch.allclose(grad, expected, rtol=0, atol=1e-13 * d.abs().max())
