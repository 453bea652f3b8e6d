"""Fused C++ SSIM (gsbench/losses/csrc/ssim.cpp via `gsbench.losses.ssim`) vs the PyTorch reference.

Float32 note: the fused kernel computes in float64 for float32 images, so its float32 map is the float64
map rounded. The float32 *reference* cancels in E[x²] − μx² (≈6e-6 off per pixel on noise, up to ~1e-3 on
smooth images), so per-pixel float32 comparisons are made against the reference evaluated in float64 on
the same float32 images; the means are also compared with the float32 reference directly.

``python tests/test_ssim_fused.py`` prints forward+backward timings (fused vs reference, 1 and 2 threads).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from gsbench.errors import ConfigError
from gsbench.losses import ssim as ssim_module
from gsbench.losses import terms as losses
from gsbench.losses.ssim import (
    C1,
    C2,
    gaussian_window,
    ssim,
    ssim_map,
    ssim_map_reference,
    ssim_reference,
)
from gsbench.losses.terms import Batch
from gsbench.raster.types import RenderOutput
from gsbench.switches import SSIM

TOL = 1e-6
TOL64 = 1e-12
SHAPES = [(150, 200, 3), (7, 13, 3), (1, 1, 3), (4, 9, 3), (10, 3, 3), (11, 11, 1), (12, 5, 4), (33, 17, 3)]


def _pair(shape, dtype=torch.float32, seed=0, noise=0.1):
    """img1 uniform in [0, 1], img2 = img1 + noise clipped (a rendering and its ground truth)."""
    gen = torch.Generator().manual_seed(seed)
    a = torch.rand(shape, generator=gen, dtype=torch.float64)
    b = (a + noise * torch.randn(shape, generator=gen, dtype=torch.float64)).clamp(0, 1)
    return a.to(dtype), b.to(dtype)


def _smooth_pair(shape, dtype=torch.float32, seed=0):
    """Smooth images (small local variance): where the float32 reference cancels most."""
    H, W, C = shape
    gen = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, H, dtype=torch.float64),
                            torch.linspace(0, 1, W, dtype=torch.float64), indexing="ij")
    a = torch.stack([0.5 + 0.3 * torch.sin(6 * xx + c) * torch.cos(4 * yy) for c in range(C)], -1)
    b = (a + 0.01 * torch.randn(a.shape, generator=gen, dtype=torch.float64)).clamp(0, 1)
    return a.to(dtype), b.to(dtype)


def _mask(shape, seed=3):
    gen = torch.Generator().manual_seed(seed)
    return torch.rand(shape[:2], generator=gen) > 0.4


def _weights(shape, seed=5):
    return torch.rand(shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def _grad(fn, a, *args):
    x = a.detach().clone().requires_grad_(True)
    fn(x, *args).backward()
    return x.grad


def _fused(impl_fn):
    return lambda *a: impl_fn(*a, impl="fused")


# ---- forward ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", SHAPES)
def test_float64_map_and_means_equal_reference(shape):
    a, b = _pair(shape, torch.float64)
    mask = _mask(shape)
    f = ssim_map(a, b, impl="fused")
    assert f.shape == shape and f.dtype == torch.float64
    torch.testing.assert_close(f, ssim_map_reference(a, b), atol=TOL64, rtol=0)
    assert abs(float(ssim(a, b, impl="fused")) - float(ssim_reference(a, b))) <= TOL64
    assert abs(float(ssim(a, b, mask, impl="fused")) - float(ssim_reference(a, b, mask))) <= TOL64


@pytest.mark.parametrize("shape", SHAPES)
def test_float32_map_and_means_within_1e6(shape):
    a, b = _pair(shape, torch.float32)
    mask = _mask(shape)
    f = ssim_map(a, b, impl="fused")
    assert f.dtype == torch.float32
    exact = ssim_map_reference(a.double(), b.double())  # the reference on the same float32 images
    ref32 = ssim_map_reference(a, b)
    assert (f.double() - exact).abs().max() <= TOL
    # vs the float32 reference: its own float32 rounding (measured) plus 1e-6
    assert ((f.double() - ref32.double()).abs() <= (ref32.double() - exact).abs() + TOL).all()
    for m in (None, mask):
        fused_mean = float(ssim(a, b, m, impl="fused"))
        assert abs(fused_mean - float(ssim_reference(a.double(), b.double(), m))) <= TOL
        assert abs(fused_mean - float(ssim_reference(a, b, m))) <= TOL


def test_float32_smooth_image_is_float64_accurate():
    a, b = _smooth_pair((60, 80, 3))
    exact = ssim_map_reference(a.double(), b.double())
    fused_err = float((ssim_map(a, b, impl="fused").double() - exact).abs().max())
    ref32_err = float((ssim_map_reference(a, b).double() - exact).abs().max())
    print(f"smooth 60x80x3 float32: max |map − float64 map| fused {fused_err:.2e}, reference {ref32_err:.2e}")
    assert fused_err <= TOL


def test_identical_images_give_exactly_one():
    for dtype in (torch.float32, torch.float64):
        a, _ = _pair((23, 31, 3), dtype)
        assert bool((ssim_map(a, a, impl="fused") == 1).all())
        assert float(ssim(a, a, impl="fused")) == 1.0


def test_empty_mask_gives_one_and_full_mask_the_mean():
    a, b = _pair((12, 14, 3), torch.float64)
    assert float(ssim(a, b, torch.zeros(12, 14, dtype=torch.bool), impl="fused")) == 1.0
    full = float(ssim(a, b, torch.ones(12, 14, dtype=torch.bool), impl="fused"))
    assert full == pytest.approx(float(ssim(a, b, impl="fused")), abs=1e-15)


def _scipy_map(a: np.ndarray, b: np.ndarray, mode: str) -> np.ndarray:
    """Independent SSIM map with scipy's 2-D correlate and the given padding mode."""
    w = gaussian_window(dtype=torch.float64).numpy()

    def blur(x):
        return np.stack([ndimage.correlate(x[..., c], w, mode=mode, cval=0.0) for c in range(x.shape[-1])], -1)

    mx, my = blur(a), blur(b)
    vx, vy, cxy = blur(a * a) - mx**2, blur(b * b) - my**2, blur(a * b) - mx * my
    return ((2 * mx * my + C1) * (2 * cxy + C2)) / ((mx**2 + my**2 + C1) * (vx + vy + C2))


def test_border_pixels_use_zero_padding():
    """The 5-pixel border ring equals scipy's zero ('constant') padding and differs from other paddings."""
    a, b = _pair((20, 24, 3), torch.float64, seed=7)
    got = ssim_map(a, b, impl="fused").numpy()
    border = np.ones(got.shape[:2], dtype=bool)
    border[5:-5, 5:-5] = False
    zero = _scipy_map(a.numpy(), b.numpy(), "constant")
    np.testing.assert_allclose(got[border], zero[border], atol=1e-10, rtol=0)
    np.testing.assert_allclose(got[~border], zero[~border], atol=1e-10, rtol=0)
    for mode in ("reflect", "nearest", "mirror"):
        other = _scipy_map(a.numpy(), b.numpy(), mode)
        np.testing.assert_allclose(got[~border], other[~border], atol=1e-10, rtol=0)  # interior: no padding
        assert np.abs(got[border] - other[border]).max() > 1e-2, mode
    # also in float32 (the separable passes' border taps) and gradients at the border
    got32 = ssim_map(a.float(), b.float(), impl="fused").double().numpy()
    np.testing.assert_allclose(got32[border], zero[border], atol=TOL, rtol=0)
    w = _weights(a.shape)
    g = _grad(lambda x: (ssim_map(x, b, impl="fused") * w).sum(), a)
    g_ref = _grad(lambda x: (ssim_map_reference(x, b) * w).sum(), a)
    torch.testing.assert_close(g[torch.from_numpy(border)], g_ref[torch.from_numpy(border)], atol=TOL64, rtol=0)


# ---- backward --------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", SHAPES)
def test_float32_gradients_within_1e6(shape):
    a, b = _pair(shape, torch.float32)
    mask, w = _mask(shape), _weights(shape)
    cases = {
        "weighted map": (lambda x, y, impl: (ssim_map(x, y, impl=impl).double() * w).sum()),
        "1 - mean": (lambda x, y, impl: 1 - ssim(x, y, impl=impl)),
        "1 - masked mean": (lambda x, y, impl: 1 - ssim(x, y, mask, impl=impl)),
    }
    for name, loss in cases.items():
        g = _grad(loss, a, b, "fused")
        assert g.dtype == torch.float32 and g.shape == shape
        g_exact = _grad(loss, a.double(), b.double(), "reference")
        g_ref32 = _grad(loss, a, b, "reference")
        scale = max(1.0, float(g_exact.abs().max()))
        assert (g.double() - g_exact).abs().max() <= TOL * scale, name
        assert (g.double() - g_ref32.double()).abs().max() <= (g_ref32.double() - g_exact).abs().max() + TOL * scale
        if name != "weighted map":  # tiny per-pixel gradients (~1/N): compare relative to their size too
            assert (g.double() - g_exact).abs().max() <= 1e-5 * float(g_exact.abs().max()), name


@pytest.mark.parametrize("shape", SHAPES)
def test_float64_gradients_equal_reference(shape):
    a, b = _pair(shape, torch.float64)
    w, mask = _weights(shape), _mask(shape)
    g = _grad(lambda x: (ssim_map(x, b, impl="fused") * w).sum(), a)
    torch.testing.assert_close(g, _grad(lambda x: (ssim_map_reference(x, b) * w).sum(), a), atol=TOL64, rtol=0)
    g = _grad(lambda x: 1 - ssim(x, b, mask, impl="fused"), a)
    torch.testing.assert_close(g, _grad(lambda x: 1 - ssim_reference(x, b, mask), a), atol=TOL64, rtol=0)


@pytest.mark.parametrize("shape", [(9, 12, 3), (1, 1, 3), (4, 17, 2), (14, 6, 1)])
def test_gradcheck_float64(shape):
    a, b = _pair(shape, torch.float64, seed=11)
    x = a.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: ssim_map(t, b, impl="fused"), (x,), eps=1e-6, atol=1e-8)
    mask = _mask(shape)
    assert torch.autograd.gradcheck(lambda t: ssim(t, b, mask, impl="fused"), (x,), eps=1e-6, atol=1e-9)


def test_gradient_flows_to_img1_only():
    a, b = _pair((16, 18, 3), torch.float64)
    x = a.clone().requires_grad_(True)
    y = b.clone()
    out = ssim_map(x, y)
    assert type(out.grad_fn).__name__.startswith("_FusedSSIMMap")
    (1 - out.mean()).backward()
    assert x.grad is not None and y.grad is None
    # img2 requiring grad: the fused kernel refuses it explicitly, the default falls back to the reference
    y.requires_grad_(True)
    with pytest.raises(ValueError, match="img2 requires grad"):
        ssim_map(x, y, impl="fused")
    x.grad = None
    (1 - ssim(x, y)).backward()
    x2, y2 = a.clone().requires_grad_(True), b.clone().requires_grad_(True)
    (1 - ssim_reference(x2, y2)).backward()
    torch.testing.assert_close(x.grad, x2.grad, atol=TOL64, rtol=0)
    torch.testing.assert_close(y.grad, y2.grad, atol=TOL64, rtol=0)


def test_dssim_term_differentiates_the_render_through_the_fused_kernel(monkeypatch):
    a, b = _pair((20, 26, 3), torch.float32)
    mask = _mask(a.shape)

    def run(use_mask):
        rgb = a.clone().requires_grad_(True)
        out = RenderOutput(rgb=rgb, width=26, height=20)
        value = losses.dssim_term(out, Batch(b, mask, None, 0), {}, use_mask=use_mask)
        value.backward()
        return float(value.detach()), rgb.grad

    calls = []
    real = ssim_module._FusedSSIMMap.apply
    monkeypatch.setattr(ssim_module._FusedSSIMMap, "apply", lambda *args: calls.append(1) or real(*args))
    for use_mask in (False, True):
        v, g = run(use_mask)
        assert calls, "dssim_term did not use the fused kernel"
        calls.clear()
        with monkeypatch.context() as m:
            m.setenv(SSIM.name, "reference")
            v_ref, g_ref = run(use_mask)
        assert not calls
        assert v == pytest.approx(v_ref, abs=TOL)
        assert (g - g_ref).abs().max() <= TOL


# ---- selection, inputs, threads -------------------------------------------------------------------


def test_environment_switch_and_impl_argument(monkeypatch):
    a, b = _pair((8, 9, 3), torch.float64)
    x = a.clone().requires_grad_(True)
    assert type(ssim_map(x, b).grad_fn).__name__.startswith("_FusedSSIMMap")
    assert not type(ssim_map(x, b, impl="reference").grad_fn).__name__.startswith("_FusedSSIMMap")
    monkeypatch.setenv(SSIM.name, "reference")
    assert not type(ssim_map(x, b).grad_fn).__name__.startswith("_FusedSSIMMap")
    assert type(ssim_map(x, b, impl="fused").grad_fn).__name__.startswith("_FusedSSIMMap")
    monkeypatch.setenv(SSIM.name, "fast")
    with pytest.raises(ConfigError, match=SSIM.name):
        ssim_map(x, b)
    monkeypatch.delenv(SSIM.name)
    with pytest.raises(ValueError, match="impl"):
        ssim(x, b, impl="cuda")
    with pytest.raises(ValueError, match="float32 or float64"):
        ssim_map(a.half(), b.half(), impl="fused")


def test_forward_only_without_grad():
    a, b = _pair((30, 40, 3), torch.float32)
    x = a.clone().requires_grad_(True)
    with_grad = ssim_map(x, b)
    with torch.no_grad():
        no_grad = ssim_map(x, b)
    plain = ssim_map(a, b)
    assert no_grad.grad_fn is None and plain.grad_fn is None and not plain.requires_grad
    assert torch.equal(no_grad, with_grad.detach()) and torch.equal(plain, no_grad)


def test_non_contiguous_inputs():
    a, b = _pair((3, 21, 17), torch.float64)  # (C, H, W) storage, viewed as (H, W, C)
    x, y = a.permute(1, 2, 0), b.permute(1, 2, 0)
    assert not x.is_contiguous()
    torch.testing.assert_close(ssim_map(x, y, impl="fused"), ssim_map_reference(x, y), atol=TOL64, rtol=0)
    w = _weights(x.shape)
    g = _grad(lambda t: (ssim_map(t.permute(1, 2, 0), y, impl="fused") * w).sum(), a)
    g_ref = _grad(lambda t: (ssim_map_reference(t.permute(1, 2, 0), y) * w).sum(), a)
    torch.testing.assert_close(g, g_ref, atol=TOL64, rtol=0)


@pytest.mark.parametrize("shape", [(150, 200, 3), (40, 70, 3), (97, 29, 3)])
def test_results_do_not_depend_on_the_thread_count(monkeypatch, shape):
    """Bands of rows (one per thread, halo recomputed) give bitwise the same map and gradient."""
    a, b = _pair(shape, torch.float32)
    w = _weights(shape).float()
    results = []
    for n in (1, 2, 3, 8):
        monkeypatch.setattr(ssim_module, "omp_threads", lambda n=n: n)
        x = a.clone().requires_grad_(True)
        smap = ssim_map(x, b, impl="fused")
        (smap * w).sum().backward()
        results.append((smap.detach(), x.grad))
    for smap, g in results[1:]:
        assert torch.equal(smap, results[0][0]) and torch.equal(g, results[0][1])


# ---- timing (not a test) --------------------------------------------------------------------------


def _time_forward_backward(impl: str, threads: int, runs: int = 50, shape=(150, 200, 3)) -> float:
    import statistics  # noqa: PLC0415
    import time  # noqa: PLC0415

    torch.set_num_threads(threads)
    a, b = _pair(shape, torch.float32)
    times = []
    for i in range(runs + 5):
        x = a.clone().requires_grad_(True)
        t0 = time.perf_counter()
        (1 - ssim(x, b, impl=impl)).backward()
        if i >= 5:
            times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


if __name__ == "__main__":
    before = torch.get_num_threads()
    ssim(*_pair((16, 16, 3)), impl="fused")  # build/load the extension first
    for threads in (1, 2):
        ref = _time_forward_backward("reference", threads)
        fused = _time_forward_backward("fused", threads)
        print(f"150x200x3 float32, 1 - ssim forward+backward, {threads} thread(s), median of 50: "
              f"reference {ref:.2f} ms, fused {fused:.2f} ms ({ref / fused:.1f}x)")
    torch.set_num_threads(before)
