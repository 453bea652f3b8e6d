"""Fused SuGaR neighbour field and normal average (methods/csrc/sugar_field.cpp via
`gsbench.methods.sugar_field`) vs their PyTorch references: gradcheck, agreement, determinism, fallbacks."""

from __future__ import annotations

import pytest
import torch

from gsbench.errors import ConfigError
from gsbench.methods import sugar_field
from gsbench.methods.sugar_field import neighbour_field, neighbour_normals
from gsbench.raster.payload import quat_to_rotmat
from gsbench.switches import SUGAR_FIELD

TOL = {torch.float32: 1e-6, torch.float64: 1e-10}


def field_inputs(m, k, n, dtype=torch.float64, seed=0):
    """(x, μ, R, s, o, idx): x near the means (some exactly on a mean), rotations from random quaternions."""
    gen = torch.Generator().manual_seed(seed)
    means = 0.5 * torch.randn(n, 3, generator=gen, dtype=torch.float64)
    rotations = quat_to_rotmat(torch.randn(n, 4, generator=gen, dtype=torch.float64))
    scales = 0.2 + 0.5 * torch.rand(n, 3, generator=gen, dtype=torch.float64)
    opacities = torch.rand(n, generator=gen, dtype=torch.float64)
    idx = torch.randint(n, (m, k), generator=gen)
    points = means[idx[:, 0]] + 0.3 * torch.randn(m, 3, generator=gen, dtype=torch.float64)
    points[0] = means[idx[0, 1]]  # a sample on one of its neighbours' centres: d = 0
    return [t.to(dtype).requires_grad_() for t in (points, means, rotations, scales, opacities)] + [idx]


def normal_inputs(m, k, n, dtype=torch.float64, seed=1):
    """(n, x, μ, σ, c, source, idx) with two orthogonal normals (flip 0) in sample 0's neighbourhood."""
    gen = torch.Generator().manual_seed(seed)
    normals = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=-1)
    normals[0] = torch.tensor([0.0, 0.0, 1.0])
    normals[1] = torch.tensor([1.0, 0.0, 0.0])
    points = torch.randn(m, 3, generator=gen, dtype=torch.float64)
    means = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    min_scales = 0.1 * torch.rand(n, generator=gen, dtype=torch.float64)
    min_scales[2] = 0.0  # clamped to scale_min
    contributions = torch.rand(m, k, generator=gen, dtype=torch.float64)
    source = torch.randint(n, (m,), generator=gen)
    idx = torch.randint(n, (m, k), generator=gen)
    source[0], idx[0, 0] = 0, 1
    return [normals.to(dtype).requires_grad_()] + [t.to(dtype) for t in (points, means, min_scales, contributions)] + [
        source, idx]


NORMAL_ARGS = (0.7, 1e-6, 1e-6)  # κ, scale_min, sum_min


def field_fn(impl, clamp_max, idx):
    return lambda *t: neighbour_field(*t, idx, clamp_max, impl=impl)


def normals_fn(impl, rest):
    return lambda normals: neighbour_normals(normals, *rest, *NORMAL_ARGS, impl=impl)


def value_and_grads(fn, inputs, seed=2):
    out = fn(*inputs)
    weights = torch.randn(out.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    grads = torch.autograd.grad((out * weights.to(out.dtype)).sum(), inputs)
    return [out.detach(), *grads]


def assert_relative(got, want, tol):
    for g, w in zip(got, want):
        assert g.dtype == w.dtype and g.shape == w.shape
        assert float((g - w).abs().max()) <= tol * max(float(w.abs().max()), 1e-30)


@pytest.mark.parametrize("clamp_max", [1e8, 10.0])  # 10: about half the pairs clamped
def test_field_gradcheck(clamp_max):
    *inputs, idx = field_inputs(7, 4, 5)
    assert torch.autograd.gradcheck(field_fn("fused", clamp_max, idx), inputs)


def float64(tensors):
    """The float32 inputs in float64 (leaves again where they were)."""
    return [t.detach().double().requires_grad_(t.requires_grad) if t.is_floating_point() else t for t in tensors]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("clamp_max", [1e8, 50.0])  # 50: about half the pairs clamped
def test_field_matches_reference(dtype, clamp_max):
    """float32: also against the reference in float64 on the same inputs, which the kernel (float64
    arithmetic) follows more closely than the float32 reference does."""
    *inputs, idx = field_inputs(300, 16, 200, dtype)
    fused = value_and_grads(field_fn("fused", clamp_max, idx), inputs)
    assert_relative(fused, value_and_grads(field_fn("reference", clamp_max, idx), inputs), TOL[dtype])
    exact = value_and_grads(field_fn("reference", clamp_max, idx), float64(inputs))
    assert_relative([t.double() for t in fused], exact, TOL[dtype])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_normals_match_reference(dtype):
    """No gradcheck here: the weights depend on the normals but are detached (SuGaR), so the backward is
    not the Jacobian; it must be the reference's."""
    normals, *rest = normal_inputs(300, 16, 200, dtype)
    fused = value_and_grads(normals_fn("fused", rest), (normals,))
    assert_relative(fused, value_and_grads(normals_fn("reference", rest), (normals,)), TOL[dtype])
    exact = value_and_grads(normals_fn("reference", float64(rest)), float64([normals]))
    assert_relative([t.double() for t in fused], exact, TOL[dtype])
    _, weights = sugar_field._normals_forward(normals.detach(), rest[:4], rest[4], rest[5], *NORMAL_ARGS)
    assert float(weights[0, 0]) == 0.0  # the orthogonal neighbour: flip 0


def test_gradients_do_not_depend_on_the_thread_count(restore_threads):
    *inputs, idx = field_inputs(500, 16, 300, torch.float32)  # M·K above the kernels' parallel threshold
    normals, *rest = normal_inputs(500, 16, 300, torch.float32)
    results = []
    for threads in (1, 2, 3):
        torch.set_num_threads(threads)
        results.append(value_and_grads(field_fn("fused", 1e8, idx), inputs)
                       + value_and_grads(normals_fn("fused", rest), (normals,)))
    for other in results[1:]:
        assert all(torch.equal(a, b) for a, b in zip(results[0], other))


def test_environment_and_fallbacks(monkeypatch):
    *inputs, idx = field_inputs(4, 3, 5)
    assert type(neighbour_field(*inputs, idx, 1e8).grad_fn).__name__ == "_FusedFieldBackward"
    monkeypatch.setenv(SUGAR_FIELD.name, "reference")
    assert type(neighbour_field(*inputs, idx, 1e8).grad_fn).__name__ != "_FusedFieldBackward"
    monkeypatch.setenv(SUGAR_FIELD.name, "fast")
    with pytest.raises(ConfigError, match=SUGAR_FIELD.name):
        neighbour_field(*inputs, idx, 1e8)
    monkeypatch.delenv(SUGAR_FIELD.name)
    mixed = [inputs[0].float(), *inputs[1:]]
    with pytest.raises(ValueError, match="mixed dtypes"):
        neighbour_field(*mixed, idx, 1e8, impl="fused")
    assert neighbour_field(*mixed, idx, 1e8).dtype == torch.float64  # the reference, as PyTorch promotes
    with pytest.raises(IndexError):
        neighbour_field(*inputs, idx + 5, 1e8)
