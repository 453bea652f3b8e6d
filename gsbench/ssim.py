"""Differentiable SSIM as in 3DGS ``utils/loss_utils.py`` (methods-3dgs-2dgs-sugar.md §1.7).

Layout: images are ``(H, W, C)`` float tensors (C = 3 for RGB), values in [0, 1]; the map has the
same shape. Per channel, with a normalised 11x11 Gaussian window g (σ = 1.5) applied as a 'same'
convolution with zero padding 5 (grouped conv2d, one group per channel):

    μx = g*x, μy = g*y, σx² = g*x² − μx², σy² = g*y² − μy², σxy = g*(xy) − μx μy
    SSIM = ((2 μx μy + C1)(2 σxy + C2)) / ((μx² + μy² + C1)(σx² + σy² + C2)),  C1 = 0.01², C2 = 0.03²

and `ssim` is the mean of the map over H, W and C. Zero padding pulls the border statistics towards 0
exactly as the reference does; the denominators are >= C1·C2 > 0, so the map is always finite.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

WINDOW_SIZE = 11
SIGMA = 1.5
C1 = 0.01**2
C2 = 0.03**2

__all__ = ["C1", "C2", "SIGMA", "WINDOW_SIZE", "gaussian_window", "ssim", "ssim_map"]


def gaussian_window(size: int = WINDOW_SIZE, sigma: float = SIGMA, dtype=torch.float32) -> torch.Tensor:
    """(size, size) outer product of the normalised 1-D Gaussian exp(−(i − size//2)² / (2σ²))."""
    x = torch.arange(size, dtype=torch.float64) - size // 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()
    return torch.outer(g, g).to(dtype)


def _check(img1: torch.Tensor, img2: torch.Tensor) -> None:
    if img1.shape != img2.shape or img1.dim() != 3:
        raise ValueError(f"ssim expects two (H, W, C) tensors of the same shape, got {tuple(img1.shape)} "
                         f"and {tuple(img2.shape)}")


def ssim_map(img1: torch.Tensor, img2: torch.Tensor) -> torch.Tensor:
    """Per-pixel, per-channel SSIM, (H, W, C), of two (H, W, C) images (module docstring)."""
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


def ssim(img1: torch.Tensor, img2: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean SSIM (scalar tensor) of two (H, W, C) images; with an (H, W) bool ``mask``, the mean over it.

    An empty mask gives 1 (no pixel disagrees), so ``1 − ssim`` is 0 rather than NaN.
    """
    smap = ssim_map(img1, img2)
    if mask is None:
        return smap.mean()
    m = mask.to(smap.dtype)[..., None]
    count = m.sum() * smap.shape[-1]
    return torch.where(count > 0, (smap * m).sum() / count.clamp(min=1), torch.ones((), dtype=smap.dtype))

