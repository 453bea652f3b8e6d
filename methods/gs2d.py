"""2DGS (Huang et al., SIGGRAPH 2024), docs/methods/2dgs.md.

Differences from 3DGS (docs/methods/2dgs.md §2, §4, §5, §6):

- oriented planar surfels (two log-scales, ``surfel`` kernel: exact ray–splat intersection), random
  unit-quaternion init (`gsbench.training.gaussians.Gaussians.from_points` with ``dims=2``);
- prune opacity (``opacity_cull``) 0.05 instead of 0.005; split samples in the surfel plane
  (`DefaultStrategy` does both from the primitive);
- L = 0.8·L1 + 0.2·(1 − SSIM) + λ_d·L_d + λ_n·L_n, λ_d from step 3000, λ_n = 0.05 from step 7000
  (scaled with the run length); weights in ``configs/methods/2dgs.yaml``;
- ``depth_ratio`` chooses the surface depth of the normal-consistency term: 1 = median depth, as
  the 2DGS DTU and TnT scripts use (the code default is 0 = expected depth);
- mesh: TSDF of the median depth (``mesh.depth: median``, depth_ratio 1).
"""

from __future__ import annotations

from dataclasses import dataclass

from gsbench.methods.base import GSConfig, Method, MethodInfo


@dataclass
class GS2DConfig(GSConfig):
    """`GSConfig` with 2DGS's prune opacity 0.05 (docs/methods/2dgs.md §2) and ``depth_ratio`` (DTU/TnT scripts: 1)."""

    prune_opacity: float = 0.05
    depth_ratio: float = 1.0


class GS2D(Method):
    """2D Gaussian Splatting."""

    name = "2dgs"
    Config = GS2DConfig
    INFO = MethodInfo(primitive="2d", kernel="surfel",
                      outputs=("rgb", "alpha", "depth", "median_depth", "normal", "distortion"))

    def term_params(self) -> dict[str, dict]:
        """normal_consistency differentiates the surface depth chosen by ``depth_ratio``."""
        if "normal_consistency" not in self.cfg.losses:
            return {}
        return {"normal_consistency": {"depth_ratio": self.params.depth_ratio}}
