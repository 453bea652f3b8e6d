"""PSNR and SSIM of rendered held-out views (the 3DGS ``metrics.py`` formulation), protocol v1.

- PSNR per view: ``10 log10(1 / MSE)`` for images in [0, 1], MSE over all pixels and channels (over
  the mask's pixels when masks are given); the reported value is the mean over views.
- SSIM per view (Wang et al. 2004 as in 3DGS ``utils/loss_utils.ssim``): 11x11 Gaussian window with
  sigma 1.5, per-channel local statistics by a depthwise convolution with zero padding 5,
  ``C1 = 0.01^2``, ``C2 = 0.03^2``, ``SSIM = ((2 mu_x mu_y + C1)(2 s_xy + C2)) / ((mu_x^2 + mu_y^2 + C1)
  (s_x^2 + s_y^2 + C2))``, averaged over the map (over the mask's pixels when masks are given).
  Computed by `gsbench.losses.ssim` (the same code as the ``dssim`` training loss) in float64.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from gsbench.data.camera import Scene
from gsbench.errors import EvaluationError
from gsbench.evaluators.base import Diagnostics, Evaluator, MetricInfo
from gsbench.losses.ssim import ssim_map as torch_ssim_map


def _as_image(img, what: str) -> np.ndarray:
    arr = np.asarray(img, dtype=np.float64)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3 or not np.isfinite(arr).all():
        raise EvaluationError(f"{what}: expected a finite HxWxC image, got shape {arr.shape}")
    return arr


def psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """``10 log10(1 / MSE)`` (images in [0, 1]); MSE over ``mask`` pixels when given."""
    err = (_as_image(pred, "psnr pred") - _as_image(gt, "psnr gt")) ** 2
    if mask is not None:
        err = err[np.asarray(mask, bool)]
    mse = float(err.mean())
    return float("inf") if mse == 0 else float(10 * np.log10(1.0 / mse))


def ssim_map(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-pixel SSIM (HxW, mean over channels): `gsbench.losses.ssim.ssim_map` (the training loss's SSIM) in float64."""
    x, y = _as_image(pred, "ssim pred"), _as_image(gt, "ssim gt")
    if x.shape != y.shape:
        raise EvaluationError(f"ssim: image shapes differ: {x.shape} vs {y.shape}")
    with torch.no_grad():
        return torch_ssim_map(torch.from_numpy(x), torch.from_numpy(y)).mean(dim=-1).numpy()


def ssim(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean SSIM over the image (over ``mask`` pixels when given)."""
    m = ssim_map(pred, gt)
    return float(m[np.asarray(mask, bool)].mean() if mask is not None else m.mean())


def evaluate_images(pred_list, gt_list, masks=None) -> dict:
    """Mean PSNR and SSIM over paired views, plus the per-view values."""
    if len(pred_list) != len(gt_list) or len(pred_list) == 0:
        raise EvaluationError(f"evaluate_images: need equally many (>0) renders and GT images, got {len(pred_list)} and {len(gt_list)}")
    if masks is not None and len(masks) != len(gt_list):
        raise EvaluationError(f"evaluate_images: {len(masks)} masks for {len(gt_list)} images")
    per_view = []
    for i, (p, g) in enumerate(zip(pred_list, gt_list)):
        if np.shape(p) != np.shape(g):
            raise EvaluationError(f"evaluate_images: view {i}: render {np.shape(p)} and GT {np.shape(g)} differ in shape")
        m = None if masks is None else masks[i]
        per_view.append({"psnr": psnr(p, g, m), "ssim": ssim(p, g, m)})
    return {
        "psnr": float(np.mean([v["psnr"] for v in per_view])),
        "ssim": float(np.mean([v["ssim"] for v in per_view])),
        "per_view": per_view,
    }


@dataclass(frozen=True)
class ImageOptions:
    indices: tuple[int, ...] | None = None  # scene views the renders correspond to (default: all, in order)
    use_masks: bool = False  # restrict both metrics to the scene's masks


class ImageMetrics(Evaluator):
    """PSNR / SSIM of renders against the scene's images."""

    name = "image"
    version = 1
    requires = ("renders",)
    needs = ("held_out",)
    metrics = {"psnr": MetricInfo(True, "dB"), "ssim": MetricInfo(True, "")}
    Options = ImageOptions

    def validate(self, scene: Scene) -> None:
        if not scene.images:
            raise EvaluationError(f"image: scene '{scene.name}' has no images to compare against (fix: load its images)")

    def evaluate(self, renders, scene: Scene, **options) -> dict:
        opts = self.options(**options)
        self.validate(scene)
        idx = list(opts.indices) if opts.indices is not None else list(range(len(renders)))
        if opts.use_masks and scene.masks is None:
            raise EvaluationError(f"image: use_masks=True but scene '{scene.name}' has no masks")
        diag = Diagnostics()
        with diag.phase("score"):
            out = evaluate_images(list(renders), [scene.images[i] for i in idx],
                                  [scene.masks[i] for i in idx] if opts.use_masks else None)
        diag["per_view"] = out.pop("per_view")
        return {"metrics": out, "protocol": self.protocol(opts), "diagnostics": diag.finish()}
