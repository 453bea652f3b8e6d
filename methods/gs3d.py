"""3DGS (Kerbl et al. 2023), docs/methods/3dgs.md.

EWA splatting of 3D Gaussians (``ewa`` kernel), L = 0.8·L1 + 0.2·(1 − SSIM) (docs/methods/3dgs.md §4.1, weights in
``configs/methods/3dgs.yaml``), the 2023 densification (`gsbench.training.strategies.default.DefaultStrategy`, docs/methods/3dgs.md §5.3)
with prune opacity 0.005, identity rotations at init (docs/methods/3dgs.md §2.2). 3DGS has no mesh extractor of its own;
the benchmark fuses the *expected* depth Σ wᵢzᵢ / Σ wᵢ with the 2DGS TSDF settings (docs/methods/3dgs.md §6).
"""

from __future__ import annotations

from gsbench.methods.base import GSConfig, Method, MethodInfo


class GS3D(Method):
    """3D Gaussian Splatting; every hyper-parameter is `GSConfig` (the 2023 release defaults)."""

    name = "3dgs"
    Config = GSConfig
    INFO = MethodInfo(primitive="3d", kernel="ewa", outputs=("rgb", "alpha", "depth"))
