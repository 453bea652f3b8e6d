"""PSNR / SSIM with the 3DGS formulation."""

import numpy as np
import pytest
from skimage.metrics import structural_similarity

from gsbench.data.camera import Scene
from gsbench.errors import EvaluationError
from gsbench.evaluators.image import ImageMetrics, evaluate_images, psnr, ssim


def test_psnr_known_value_and_mask():
    gt = np.zeros((8, 8, 3))
    pred = gt + 0.1
    assert psnr(pred, gt) == pytest.approx(20.0)
    mask = np.zeros((8, 8), bool)
    mask[:4] = True
    pred[4:] = 0.5
    assert psnr(pred, gt, mask) == pytest.approx(20.0)


def test_ssim_matches_gaussian_ssim_away_from_the_border():
    rng = np.random.default_rng(0)
    gt = rng.random((48, 64, 3))
    pred = np.clip(gt + rng.normal(0, 0.05, gt.shape), 0, 1)
    assert ssim(gt, gt) == pytest.approx(1.0)
    _, ref = structural_similarity(pred, gt, channel_axis=2, gaussian_weights=True, sigma=1.5,
                                   use_sample_covariance=False, data_range=1.0, full=True)
    inner = np.zeros((48, 64), bool)
    inner[8:-8, 8:-8] = True  # zero padding (3DGS) vs reflection (skimage) differ only at the border
    assert ssim(pred, gt, inner) == pytest.approx(ref.mean(axis=2)[inner].mean(), abs=1e-6)


def test_evaluate_images_and_evaluator():
    rng = np.random.default_rng(1)
    imgs = [rng.random((16, 16, 3)).astype(np.float32) for _ in range(3)]
    out = evaluate_images([i * 0.9 for i in imgs], imgs)
    assert len(out["per_view"]) == 3 and 0 < out["ssim"] < 1
    scene = Scene(name="s", fmt="synthetic", root=".", cameras=[], images=imgs, masks=None)
    res = ImageMetrics().evaluate([imgs[2], imgs[0] * 0.9], scene, indices=(2, 0))
    assert res["metrics"]["ssim"] < 1 and res["diagnostics"]["per_view"][0]["ssim"] == pytest.approx(1.0)
    with pytest.raises(EvaluationError, match="differ in shape"):
        evaluate_images([imgs[0][:8]], [imgs[0]])
