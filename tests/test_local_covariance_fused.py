"""Fused C++ kNN neighbourhood covariance (csrc/local_covariance.cpp via
`gsbench.geometry.local_geometry.local_covariance`) against its PyTorch reference: float64 gradcheck,
values and gradients in float64 and float32, with and without the Gaussian's own mean, coincident
neighbours, one and two threads, and a bad index."""

from __future__ import annotations

import pytest
import torch

from gsbench.errors import ConfigError
from gsbench.geometry import local_geometry as lg
from gsbench.geometry.local_geometry import local_covariance, local_covariance_reference
from gsbench.switches import LOCAL_COVARIANCE


def _cloud(n=40, k=5, dtype=torch.float64, seed=0, scale=1.0):
    gen = torch.Generator().manual_seed(seed)
    means = (scale * torch.randn(n, 3, generator=gen, dtype=torch.float64)).to(dtype).requires_grad_(True)
    index = torch.randint(0, n, (n, k), generator=gen)
    return means, index


@pytest.mark.parametrize("include_self", [True, False])
def test_fused_gradcheck_float64(include_self):
    means, index = _cloud(12, 4)
    assert torch.autograd.gradcheck(lambda m: local_covariance(m, index, 0.7, include_self), (means,),
                                    eps=1e-6, atol=1e-9, rtol=1e-6)


@pytest.mark.parametrize("include_self", [True, False])
@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 1e-6)])
@pytest.mark.parametrize("n, k, scale", [(3000, 5, 1.0), (50, 16, 1e-3), (50, 3, 1e3)])
def test_fused_equals_reference(n, k, scale, dtype, tol, include_self):
    means, index = _cloud(n, k, dtype, scale=scale)
    fused = local_covariance(means, index, scale, include_self)
    ref = local_covariance_reference(means, index, scale, include_self)
    assert fused.dtype == ref.dtype == torch.float64
    assert float((fused - ref).detach().abs().max()) <= 1e-12 * float(ref.detach().abs().max())
    weight = torch.randn(ref.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    g_fused, = torch.autograd.grad((fused * weight).sum(), means)
    g_ref, = torch.autograd.grad((ref * weight).sum(), means)
    assert g_fused.dtype == means.dtype
    assert float((g_fused - g_ref).abs().max()) <= tol * float(g_ref.abs().max())


def test_coincident_neighbours_give_the_jitter_and_finite_gradients():
    means = torch.ones(6, 3, dtype=torch.float64, requires_grad=True)
    index = torch.zeros(6, 4, dtype=torch.int64)
    C = local_covariance(means, index, 2.0)
    assert torch.allclose(C, lg.COVARIANCE_JITTER * 4.0 * torch.eye(3, dtype=torch.float64).expand(6, 3, 3), atol=0)
    g, = torch.autograd.grad(C.sum(), means)
    assert torch.isfinite(g).all() and float(g.abs().max()) == 0.0


def test_one_and_two_threads_agree_bit_for_bit():
    means, index = _cloud(4000, 5)
    before = torch.get_num_threads()
    results = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            C = local_covariance(means, index, 1.0)
            results.append((C, torch.autograd.grad(C.square().sum(), means)[0]))
    finally:
        torch.set_num_threads(before)
    assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])


def test_an_index_out_of_range_is_an_error_and_the_environment_selects_the_reference(monkeypatch):
    means, index = _cloud(8, 3)
    with pytest.raises(ValueError, match="out of range"):
        local_covariance(means, index + 8, 1.0)
    monkeypatch.setenv(LOCAL_COVARIANCE.name, "reference")
    C = local_covariance(means, index, 1.0)
    assert "Fused" not in type(C.grad_fn).__name__


def test_impl_choice_typos_and_inputs_the_kernel_cannot_take(monkeypatch):
    """The environment variable is checked like its siblings' (`gsbench.native.impl_choice`); float16 falls back to the
    reference, unless the fused kernel is asked for by name."""
    means, index = _cloud(8, 3)
    half = means.detach().half().requires_grad_(True)
    assert "Fused" not in type(local_covariance(half, index, 1.0).grad_fn).__name__
    with pytest.raises(ValueError, match="local_covariance impl='fused' cannot take these inputs: means on cpu as torch.float16"):
        local_covariance(half, index, 1.0, impl="fused")
    monkeypatch.setenv(LOCAL_COVARIANCE.name, "refrence")
    with pytest.raises(ConfigError, match=LOCAL_COVARIANCE.name):
        local_covariance(means, index, 1.0)
