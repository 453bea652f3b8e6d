"""Differentiable SSIM as in 3DGS ``utils/loss_utils.py`` (docs/methods/3dgs.md §4.1).

Layout: images are ``(H, W, C)`` float tensors (C = 3 for RGB), values in [0, 1]; the map has the
same shape. Per channel, with a normalised 11x11 Gaussian window g (σ = 1.5) applied as a 'same'
convolution with zero padding 5 (grouped conv2d, one group per channel):

    μx = g*x, μy = g*y, σx² = g*x² − μx², σy² = g*y² − μy², σxy = g*(xy) − μx μy
    SSIM = ((2 μx μy + C1)(2 σxy + C2)) / ((μx² + μy² + C1)(σx² + σy² + C2)),  C1 = 0.01², C2 = 0.03²

and `ssim` is the mean of the map over H, W and C. Zero padding pulls the border statistics towards 0
exactly as the reference does; the denominators are >= C1·C2 > 0, so the map is always finite.

Two implementations of the same function:

* fused (default): ``gs_ssim_forward``/``gs_ssim_backward`` of the C++ extension
  (``gsbench/losses/csrc/ssim.cpp``, float32 and float64 images, OpenMP over bands of rows). The
  window is the outer product of the normalised 1-D Gaussian, so the blur is separable: a horizontal
  then a vertical 11-tap pass, each 'same' with zero padding (taps outside the image contribute 0, as
  in the zero-padded conv2d). The forward blurs x, y, x², y², xy in one pass structure (a ring of the 11
  horizontally blurred rows that the current output row needs) and forms the map in the same loop,
  without storing the moments. All arithmetic is float64, also for float32 images (converted on load,
  rounded once on store), so the float32 map is the float64 map rounded (within ~3e-8 of it).
* reference: `ssim_map_reference` / `ssim_reference`, the grouped 11x11 conv2d above in PyTorch
  (autograd backward). ``GSBENCH_SSIM=reference`` or ``impl="reference"`` selects it.

Fused backward (gradient w.r.t. ``img1`` only). With S = A1 A2 / (B1 B2), A1 = 2μxμy + C1,
A2 = 2σxy + C2, B1 = μx² + μy² + C1, B2 = σx² + σy² + C2, the partials of S with respect to the blurred
moments of x are

    ∂S/∂E[xy] = 2 A1/(B1 B2),   ∂S/∂E[x²] = −S/B2,
    ∂S/∂μx = 2μy (A2 − A1)/(B1 B2) + 2μx S (1/B2 − 1/B1)

(∂S/∂μx includes the −2μx of σx² = E[x²] − μx² and the −μy of σxy = E[xy] − μxμy). The forward keeps
these three per-pixel factors. For G = dL/dS, the adjoint of the blur is the same blur (each 1-D 'same'
zero-padded pass with a symmetric kernel has a symmetric matrix, and the two passes commute), so

    dL/dx = blur(G ∂S/∂μx) + 2x · blur(G ∂S/∂E[x²]) + y · blur(G ∂S/∂E[xy]).

``img2`` is the ground truth (`gsbench.losses.terms.dssim_term` calls ``ssim(render.rgb, image)``) and gets no
gradient. Inputs the kernel does not take fall back to the reference when ``impl`` is None: a non-CPU
device, a dtype other than float32/float64, two different dtypes, an empty image, or an ``img2`` that
requires grad (with grad enabled). The fused path is not twice differentiable.

Accuracy (tests/test_ssim_fused.py): in float64 the fused map and gradient equal the reference within
1e-12 (1e-10 against an independent scipy computation); for float32 images the fused map, the (masked)
mean and the gradient are within 1e-6 of the reference evaluated in float64 on the same images, and the
mean within 1e-6 of the float32 reference. The float32 reference itself is only that close per pixel
where σx² + σy² is not small: its float32 E[x²] − μx² cancels (~6e-6 off on noise, up to ~1e-3 on smooth
images), which the tests measure rather than hide.

Speed (``python tests/test_ssim_fused.py``; 150x200x3 float32, ``1 − ssim`` forward + backward, median of
50, 2-core AMD EPYC): fused ~2.0 ms vs reference ~33 ms on 1 thread, ~1.2 ms vs ~18–26 ms on 2.
"""

from __future__ import annotations

import ctypes
import functools
from pathlib import Path

import torch
import torch.nn.functional as F
from torch.autograd.function import once_differentiable

from gsbench.native.build import load_library, omp_threads
from gsbench.native.impl_choice import choose_impl
from gsbench.switches import SSIM

WINDOW_SIZE = 11
SIGMA = 1.5
C1 = 0.01**2
C2 = 0.03**2

__all__ = [
    "C1", "C2", "SIGMA", "WINDOW_SIZE", "gaussian_window", "ssim", "ssim_map",
    "ssim_map_reference", "ssim_reference",
]


_i64, _ptr, _dbl = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
SIGNATURES = {
    "gs_ssim_forward": ([_i64] * 4 + [_ptr] * 3 + [_dbl] * 2 + [_ptr, _ptr, _i64], ctypes.c_int),
    "gs_ssim_backward": ([_i64] * 4 + [_ptr] * 6 + [_i64], ctypes.c_int),
}


def _library() -> ctypes.CDLL:
    """The native library of the fused SSIM map and its backward (``csrc/ssim.cpp``, compiled on first use)."""
    return load_library("ssim", [Path(__file__).parent / "csrc" / "ssim.cpp"], SIGNATURES)


def gaussian_1d(size: int = WINDOW_SIZE, sigma: float = SIGMA) -> torch.Tensor:
    """(size,) float64 normalised 1-D Gaussian exp(−(i − size//2)² / (2σ²)) / Σ."""
    x = torch.arange(size, dtype=torch.float64) - size // 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def gaussian_window(size: int = WINDOW_SIZE, sigma: float = SIGMA, dtype=torch.float32) -> torch.Tensor:
    """(size, size) outer product of the normalised 1-D Gaussian exp(−(i − size//2)² / (2σ²))."""
    g = gaussian_1d(size, sigma)
    return torch.outer(g, g).to(dtype)


@functools.lru_cache(maxsize=1)
def _window_1d() -> torch.Tensor:
    """The fused kernel's taps (float64, contiguous; cached so the pointer stays valid)."""
    return gaussian_1d().contiguous()


def _check(img1: torch.Tensor, img2: torch.Tensor) -> None:
    if img1.shape != img2.shape or img1.dim() != 3:
        raise ValueError(f"ssim expects two (H, W, C) tensors of the same shape, got {tuple(img1.shape)} "
                         f"and {tuple(img2.shape)}")


def ssim_map(img1: torch.Tensor, img2: torch.Tensor, impl: str | None = None) -> torch.Tensor:
    """Per-pixel, per-channel SSIM, (H, W, C), of two (H, W, C) images (module docstring).

    ``impl``: ``None`` → fused unless ``GSBENCH_SSIM=reference`` (and the reference for inputs the kernel
    does not take); ``"fused"`` (``ValueError`` for such inputs) or ``"reference"`` to force one.
    """
    _check(img1, img2)
    if choose_impl(impl, SSIM, lambda: _unsupported(img1, img2), "ssim") == "reference":
        return ssim_map_reference(img1, img2)
    if torch.is_grad_enabled() and img1.requires_grad:
        return _FusedSSIMMap.apply(img1, img2)
    smap, _ = _fused_forward(img1.detach().contiguous(), img2.detach().contiguous(), need_coef=False)
    return smap


def ssim(img1: torch.Tensor, img2: torch.Tensor, mask: torch.Tensor | None = None,
         impl: str | None = None) -> torch.Tensor:
    """Mean SSIM (scalar tensor) of two (H, W, C) images; with an (H, W) bool ``mask``, the mean over it.

    An empty mask gives 1 (no pixel disagrees), so ``1 − ssim`` is 0 rather than NaN. ``impl`` as in
    `ssim_map`; the mean (and the masked mean) is taken in PyTorch from the map, so gradients flow
    through the map.
    """
    return _masked_mean(ssim_map(img1, img2, impl=impl), mask)


def ssim_map_reference(img1: torch.Tensor, img2: torch.Tensor) -> torch.Tensor:
    """`ssim_map` by the grouped 11x11 conv2d in PyTorch (autograd backward; the reference)."""
    _check(img1, img2)
    channels = img1.shape[-1]
    window = gaussian_window(dtype=img1.dtype).to(img1.device).expand(channels, 1, WINDOW_SIZE, WINDOW_SIZE)
    x = img1.permute(2, 0, 1)[None]
    y = img2.permute(2, 0, 1)[None]

    def blur(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(t, window, padding=WINDOW_SIZE // 2, groups=channels)

    mu_x, mu_y = blur(x), blur(y)
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    var_x = blur(x * x) - mu_xx
    var_y = blur(y * y) - mu_yy
    cov_xy = blur(x * y) - mu_xy
    num = (2 * mu_xy + C1) * (2 * cov_xy + C2)
    den = (mu_xx + mu_yy + C1) * (var_x + var_y + C2)
    return (num / den)[0].permute(1, 2, 0)


def ssim_reference(img1: torch.Tensor, img2: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """`ssim` from `ssim_map_reference`."""
    return _masked_mean(ssim_map_reference(img1, img2), mask)


def _masked_mean(smap: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    if mask is None:
        return smap.mean()
    m = mask.to(smap.dtype)[..., None]
    count = m.sum() * smap.shape[-1]
    return torch.where(count > 0, (smap * m).sum() / count.clamp(min=1), torch.ones((), dtype=smap.dtype))


def _unsupported(img1: torch.Tensor, img2: torch.Tensor) -> str | None:
    """Why the fused kernel cannot take these inputs, or None."""
    if img1.device.type != "cpu" or img2.device.type != "cpu":
        return f"tensors on {img1.device}/{img2.device} (the kernel is CPU only)"
    if img1.dtype not in (torch.float32, torch.float64):
        return f"dtype {img1.dtype} (float32 or float64 only)"
    if img2.dtype != img1.dtype:
        return f"different dtypes {img1.dtype} and {img2.dtype}"
    if img1.numel() == 0:
        return "an empty image"
    if img2.requires_grad and torch.is_grad_enabled():
        return "img2 requires grad (the kernel differentiates img1 only)"
    return None



def _fused_forward(x: torch.Tensor, y: torch.Tensor, need_coef: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Map (H, W, C) and, if ``need_coef``, the backward's factors (3, H, W, C) of contiguous CPU x, y."""

    H, W, C = x.shape
    smap = torch.empty_like(x)
    coef = torch.empty((3, H, W, C), dtype=x.dtype) if need_coef else None
    rc = _library().gs_ssim_forward(
        H, W, C, int(x.dtype == torch.float64), x.data_ptr(), y.data_ptr(), _window_1d().data_ptr(), C1, C2,
        smap.data_ptr(), None if coef is None else coef.data_ptr(), omp_threads(),
    )
    if rc != 0:
        raise RuntimeError(f"gsbench ssim forward failed (code {rc})")
    return smap, coef


class _FusedSSIMMap(torch.autograd.Function):
    """SSIM map by ``gs_ssim_forward``/``gs_ssim_backward`` (csrc/ssim.cpp); gradient w.r.t. img1 only."""

    @staticmethod
    def forward(ctx, img1, img2):
        x, y = img1.detach().contiguous(), img2.detach().contiguous()
        smap, coef = _fused_forward(x, y, need_coef=True)
        ctx.save_for_backward(x, y, coef)
        return smap

    @staticmethod
    @once_differentiable
    def backward(ctx, g_map):
        x, y, coef = ctx.saved_tensors
        H, W, C = x.shape
        g = g_map.to(dtype=x.dtype).contiguous()
        g_x = torch.empty_like(x)
        rc = _library().gs_ssim_backward(
            H, W, C, int(x.dtype == torch.float64), x.data_ptr(), y.data_ptr(), _window_1d().data_ptr(),
            coef.data_ptr(), g.data_ptr(), g_x.data_ptr(), omp_threads(),
        )
        if rc != 0:
            raise RuntimeError(f"gsbench ssim backward failed (code {rc})")
        return g_x, None
