"""What GOF and RaDe-GS (and IBGS on top of RaDe-GS) share: the Mip-Splatting 3D filter and the
abs-gradient densification (docs/methods/gof.md §2, §5, docs/methods/radegs.md §2.1, §2.2).

- `FilteredConfig`: `GSConfig` (3DGS learning rates, init, schedule: docs/methods/gof.md §4.4
  defaults") with prune opacity 0.05 (docs/methods/gof.md §5.3) and ``use_filter3d`` (RaDe ``--disable_filter3D``, docs/methods/radegs.md §2.1).
- `FilteredMethod`: a `Filter3D` over the training cameras with the raster near plane, computed at
  setup (docs/methods/gof.md §2.4) and passed to every render; `AbsGradStrategy` shares it and
  recomputes it after each densification and on GOF's post-densification schedule, and resets the
  filtered opacity. The variance is part of the checkpoint, so a resumed run renders identically.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from gsbench.config.run_config import RunConfig
from gsbench.data.camera import Scene
from gsbench.geometry.filter3d import Filter3D
from gsbench.methods.base import GSConfig, Method
from gsbench.training.strategies.absgrad import AbsGradStrategy
from gsbench.training.strategies.base import Strategy


@dataclass
class FilteredConfig(GSConfig):
    """`GSConfig` with GOF/RaDe-GS's prune opacity 0.05 (docs/methods/gof.md §5.3) and the 3D filter switch (docs/methods/radegs.md §2.1)."""

    prune_opacity: float = 0.05
    use_filter3d: bool = True


class FilteredMethod(Method):
    """Base of the methods with the 3D filter and `AbsGradStrategy` (module docstring)."""

    Config = FilteredConfig

    def setup(self, scene: Scene, cfg: RunConfig) -> None:
        super().setup(scene, cfg)
        views = scene.train_views
        self.filter = Filter3D([scene.cameras[i] for i in views], near=self.raster_settings().near,
                               enabled=self.params.use_filter3d)
        self.filter.update(self.gaussians.means)

    def filter3d(self) -> torch.Tensor | None:
        return self.filter.variance

    def strategy(self) -> Strategy:
        """GOF's densification (docs/methods/gof.md §5) at the paper's 30k-step schedule, sharing the 3D filter."""
        return AbsGradStrategy(**self.densify_settings(), filter3d=self.filter)

    def state_dict(self) -> dict:
        variance = self.filter.variance
        return {**super().state_dict(), "filter3d": None if variance is None else variance.clone()}

    def load_state_dict(self, state: dict) -> None:
        """`Method.load_state_dict` plus the filter variance (in place: the strategy holds the same filter)."""
        super().load_state_dict(state)
        variance = state["filter3d"]
        self.filter.variance = None if variance is None else variance.clone()
