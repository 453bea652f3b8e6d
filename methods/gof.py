"""GOF, Gaussian Opacity Fields (Yu, Sattler, Geiger 2024), docs/methods/gof.md.

Differences from 3DGS:

- ``raymax`` kernel: each 3D Gaussian is evaluated at its maximum along the pixel ray (docs/methods/gof.md §3.2), with the
  Mip-Splatting 3D filter (docs/methods/gof.md §2) and GOF's abs-gradient densification (docs/methods/gof.md §5), both from
  `gsbench.methods.filtered`; prune opacity 0.05;
- L = 0.8·L1 + 0.2·(1 − SSIM) + λ_n·L_n + λ_d·L_d (docs/methods/gof.md §4): L_n on the *median* depth against the
  normalised rendered normal (``normal_consistency`` with depth_ratio 1, normalize), λ_n = 0.05 from
  step 15000; L_d the distortion divided by stopgrad(alpha)² with detached weights (``depth_distortion``
  normalize, `RasterSettings.detach_distortion_weights`), λ_d = 100 (code default, TnT) or 1000 (DTU
  script) from step 15000. Weights in ``configs/methods/gof.yaml`` and ``gof.dtu.yaml``;
- mesh (docs/methods/gof.md §7, §8): TSDF of the median depth on DTU (depth_max 6.0; the voxel is the dataset's, see
  ``configs/methods/gof.dtu.yaml``), marching tetrahedra (``mesh.extractor: tets``, 8 bisection steps,
  level 0.5) on TnT (``gof.tnt.yaml``).

Not implemented: the decoupled appearance model of the L1 term (docs/methods/gof.md §9.1), on in both GOF scripts.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from gsbench.methods.base import MethodInfo
from gsbench.methods.filtered import FilteredConfig, FilteredMethod
from gsbench.raster import RasterSettings


@dataclass
class GOFConfig(FilteredConfig):
    """GOF's hyper-parameters are `FilteredConfig`'s (3DGS values, prune opacity 0.05, docs/methods/gof.md §5.3, §4.4)."""


class GOF(FilteredMethod):
    """Gaussian Opacity Fields."""

    name = "gof"
    Config = GOFConfig
    INFO = MethodInfo(primitive="3d", kernel="raymax", outputs=("rgb", "alpha", "median_depth", "normal", "distortion"))
    MESH_EXTRACTORS = ("tsdf", "tets")

    def raster_settings(self) -> RasterSettings:
        """GOF detaches the blending weights in the distortion gradient (docs/methods/gof.md §3.5)."""
        return dataclasses.replace(super().raster_settings(), detach_distortion_weights=True)

    def term_params(self) -> dict[str, dict]:
        """L_n on the median depth with the normalised rendered normal; L_d normalised by alpha² (docs/methods/gof.md §4.3, §4.2)."""
        params = {"normal_consistency": {"depth_ratio": 1.0, "normalize": True, "mix": "depth"},
                  "depth_distortion": {"normalize": True}}
        return {k: v for k, v in params.items() if k in self.cfg.losses}
