"""Fused C++ depth-normal consistency (csrc/normal_consistency.cpp via `gsbench.losses.normal_consistency`) against
its PyTorch reference: float64 gradcheck, value and gradients in float64 and float32, every mode the
methods use, a background of depth 0, maps too small to have an interior, and the implementation switch."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gsbench.data.camera import Camera
from gsbench.errors import ConfigError
from gsbench.losses.normal_consistency import normal_consistency, normal_consistency_reference
from gsbench.switches import NORMAL_CONSISTENCY

# (weights, normalize, alpha): 2DGS (one map, alpha), GOF (one map, normalised), RaDe-GS (two maps, normalised)
MODES = [([1.0], False, True), ([1.0], True, False), ([0.4, 0.6], True, False), ([0.3, 0.7], False, True)]


def _camera(H, W):
    K = np.array([[1.1 * W, 0.0, W / 2 + 0.3], [0.0, 1.05 * W, H / 2 - 0.2], [0.0, 0.0, 1.0]])
    return Camera(K=K, R=np.eye(3), t=np.zeros(3), width=W, height=H)


def _inputs(H, W, dtype, seed=0, background=True):
    """A tilted, bumpy depth surface (depth 0 outside a disc when ``background``), a second map near it,
    noisy rendered normals and alpha in (0, 1]; all requiring grad but alpha."""
    gen = torch.Generator().manual_seed(seed)
    r, c = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    d1 = 2.0 + 0.3 * r / H - 0.2 * c / W + 0.05 * torch.rand(H, W, generator=gen, dtype=torch.float64)
    if background:
        d1 = torch.where((r - H / 2) ** 2 + (c - W / 2) ** 2 < (0.4 * min(H, W)) ** 2, d1, torch.zeros_like(d1))
    d2 = d1 + 0.02 * torch.rand(H, W, generator=gen, dtype=torch.float64)
    normal = torch.randn(H, W, 3, generator=gen, dtype=torch.float64) + torch.tensor([0.0, 0.0, -2.0], dtype=torch.float64)
    alpha = 0.05 + 0.95 * torch.rand(H, W, generator=gen, dtype=torch.float64)
    return [t.to(dtype).requires_grad_(t is not alpha) for t in (normal, d1, d2, alpha)]


def _evaluate(impl, normal, d1, d2, alpha, weights, normalize, camera):
    depths = [d1, d2][: len(weights)]
    value = normal_consistency(normal, depths, weights, camera, normalize, alpha, impl=impl)
    grads = torch.autograd.grad(value, [normal, *depths])
    return value.detach(), grads


@pytest.mark.parametrize("weights, normalize, use_alpha", MODES)
def test_fused_gradcheck_float64(weights, normalize, use_alpha):
    normal, d1, d2, alpha = _inputs(7, 9, torch.float64, background=False)
    camera = _camera(7, 9)
    depths = [d1, d2][: len(weights)]

    def f(n, *maps):
        return normal_consistency(n, list(maps), weights, camera, normalize, alpha if use_alpha else None, impl="fused")

    assert torch.autograd.gradcheck(f, (normal, *depths), eps=1e-6, atol=1e-8, rtol=1e-6)


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 1e-6)])
@pytest.mark.parametrize("weights, normalize, use_alpha", MODES)
@pytest.mark.parametrize("shape", [(150, 200), (12, 17), (2, 5)])
def test_fused_equals_reference(shape, weights, normalize, use_alpha, dtype, tol):
    normal, d1, d2, alpha = _inputs(*shape, dtype)
    camera = _camera(*shape)
    args = (normal, d1, d2, alpha if use_alpha else None, weights, normalize, camera)
    fused, fused_grads = _evaluate("fused", *args)
    # float32: against the reference evaluated in float64 on the same float32 inputs (the fused kernel computes
    # in float64 and rounds once; the float32 reference rounds every op, ~3e-6 off on the gradients)
    wide = [t.detach().double().requires_grad_(t.requires_grad) for t in (normal, d1, d2, alpha)]
    ref, ref_grads = _evaluate("reference", *wide[:3], wide[3] if use_alpha else None, weights, normalize, camera)
    assert torch.isfinite(fused) and abs(float(fused) - float(ref)) <= tol * max(1.0, abs(float(ref)))
    for g_fused, g_ref in zip(fused_grads, ref_grads):
        assert torch.isfinite(g_fused).all()
        scale = max(float(g_ref.abs().max()), 1e-30)
        assert float((g_fused - g_ref).abs().max()) <= tol * scale


def test_one_and_two_threads_agree():
    normal, d1, d2, alpha = _inputs(150, 200, torch.float64)
    args = (normal, d1, d2, None, [0.4, 0.6], True, _camera(150, 200))
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = _evaluate("fused", *args)
        torch.set_num_threads(2)
        two = _evaluate("fused", *args)
    finally:
        torch.set_num_threads(before)
    assert abs(float(one[0]) - float(two[0])) < 1e-12
    assert all(torch.equal(a, b) for a, b in zip(one[1], two[1]))


def test_a_map_without_interior_is_all_border():
    normal, d1, _, _ = _inputs(2, 6, torch.float32, background=False)
    value = normal_consistency(normal, [d1], [1.0], _camera(2, 6), True, impl="fused")
    assert float(value.detach()) == 1.0  # n_d = 0 on every pixel


def test_environment_selects_the_reference_and_rejects_unknown_values(monkeypatch):
    normal, d1, _, _ = _inputs(6, 7, torch.float64)
    camera = _camera(6, 7)
    monkeypatch.setenv(NORMAL_CONSISTENCY.name, "reference")
    out = normal_consistency(normal, [d1], [1.0], camera, True)
    assert out.grad_fn is not None and "Fused" not in type(out.grad_fn).__name__
    monkeypatch.setenv(NORMAL_CONSISTENCY.name, "fast")
    with pytest.raises(ConfigError, match=NORMAL_CONSISTENCY.name):
        normal_consistency(normal, [d1], [1.0], camera, True)


def test_inputs_the_kernel_does_not_take():
    normal, d1, _, _ = _inputs(6, 7, torch.float64)
    camera = _camera(6, 7)
    with pytest.raises(ValueError, match="dtypes"):
        normal_consistency(normal, [d1.float()], [1.0], camera, True, impl="fused")
    mixed = normal_consistency(normal, [d1.float()], [1.0], camera, True)  # impl None: the reference takes it
    assert torch.isfinite(mixed)
    with pytest.raises(ValueError, match="one or two depth maps"):
        normal_consistency(normal, [d1, d1, d1], [1.0, 1.0, 1.0], camera, True)
    assert torch.isfinite(normal_consistency_reference(normal, [d1], [1.0], camera, True))
