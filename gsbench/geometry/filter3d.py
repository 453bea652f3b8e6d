"""Mip-Splatting 3D smoothing filter as GOF and RaDe-GS compute it (docs/methods/gof.md §2.2, docs/methods/radegs.md §2.1).

For each Gaussian centre μ and each *training* camera, μ is *seen* when its camera z > ``near`` and its
projection (u, v) = (fx·x/z + cx, fy·y/z + cy) lies in the image enlarged by 15 % on every side,
``u ∈ [−0.15 W, 1.15 W]``, ``v ∈ [−0.15 H, 1.15 H]``. With ``d_min`` = the smallest camera z over the
views that see μ (Gaussians seen by none get the largest ``d_min`` of the seen ones) and ``f_max`` =
the largest ``fx`` of the training cameras, the filter standard deviation is

    σ_f = d_min / f_max · sqrt(0.2)        (variance 0.2 px² projected to depth d_min)

and this module returns the *variance* σ_f², the `gsbench.raster.RasterGaussians.filter3d` the
rasterizer applies (``s_eff = sqrt(s² + σ_f²)``, ``o_eff = o·sqrt(Π s² / Π (s² + σ_f²))``). σ_f carries
no gradient. GOF/Mip-Splatting use ``near`` = 0.2 in their normalised frame; gsbench passes the
raster near plane (``raster.near_plane`` × scene radius, docs/design.md §12.1), 0.2 for a unit scene.

`Filter3D` holds the current variance of one training run; the method renders with it, the
`gsbench.training.strategies.absgrad.AbsGradStrategy` recomputes it on GOF's schedule and uses it in the opacity reset.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from gsbench.data.camera import Camera
from gsbench.errors import NumericalError

FILTER_VARIANCE_PX2 = 0.2  # Mip-Splatting: the filter's variance in pixels² at the highest sampling rate
SCREEN_MARGIN = 0.15  # the image is enlarged by 15 % on every side


@torch.no_grad()
def filter3d_variance(means: torch.Tensor, cameras: Sequence[Camera], *, near: float) -> torch.Tensor:
    """σ_f² (N,) of the centres ``means`` (N,3) over ``cameras`` (module docstring, docs/methods/gof.md §2.2)."""
    if not cameras:
        raise NumericalError("the 3D filter needs at least one training camera, got none; check data.holdout_every")
    xyz = means.detach().to(torch.float64)
    d_min = torch.full((xyz.shape[0],), float("inf"), dtype=torch.float64)
    for cam in cameras:
        R = torch.as_tensor(np.asarray(cam.R), dtype=torch.float64)
        xc = xyz @ R.T + torch.as_tensor(np.asarray(cam.t), dtype=torch.float64)
        z = xc[:, 2]
        zs = torch.clamp(z, min=1e-3)  # only used where z > near
        u = xc[:, 0] / zs * cam.fx + cam.cx
        v = xc[:, 1] / zs * cam.fy + cam.cy
        seen = ((z > near) & (u >= -SCREEN_MARGIN * cam.width) & (u <= (1 + SCREEN_MARGIN) * cam.width)
                & (v >= -SCREEN_MARGIN * cam.height) & (v <= (1 + SCREEN_MARGIN) * cam.height))
        d_min = torch.where(seen, torch.minimum(d_min, z), d_min)
    seen_any = torch.isfinite(d_min)
    if not bool(seen_any.all()):
        if not bool(seen_any.any()):
            raise NumericalError(f"no Gaussian centre is seen by any of the {len(cameras)} training cameras (camera "
                                 f"z > {near:g} and inside the image ±15 %); check the cameras and the scene "
                                 "normalisation")
        d_min[~seen_any] = d_min[seen_any].max()
    f_max = max(cam.fx for cam in cameras)
    return ((d_min / f_max) ** 2 * FILTER_VARIANCE_PX2).to(means.dtype)


def filter_coefficient(scales: torch.Tensor, variance: torch.Tensor) -> torch.Tensor:
    """The opacity factor sqrt(Π_k s_k² / Π_k (s_k² + σ_f²)) (N,) of the filter (docs/methods/gof.md §2.3)."""
    s2 = scales * scales
    return torch.sqrt(torch.prod(s2 / (s2 + variance.reshape(-1, 1)), dim=-1))


class Filter3D:
    """The 3D-filter variance of one run's Gaussians over its training ``cameras`` (module docstring).

    ``variance`` is None until `update` runs; ``enabled`` False (RaDe ``--disable_filter3D``) keeps
    it None, so the rasterizer applies no filter.
    """

    def __init__(self, cameras: Sequence[Camera], near: float, enabled: bool = True):
        self.cameras = list(cameras)
        self.near = float(near)
        self.enabled = bool(enabled)
        self.variance: torch.Tensor | None = None

    def update(self, means: torch.Tensor) -> torch.Tensor | None:
        """Recompute the variance for the centres ``means`` (N,3); returns it (None when disabled)."""
        if self.enabled:
            self.variance = filter3d_variance(means, self.cameras, near=self.near)
        return self.variance
