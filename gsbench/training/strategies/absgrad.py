"""GOF / RaDe-GS densification: the abs-gradient criterion and the 3D filter (docs/methods/gof.md §5)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from gsbench.errors import ConfigError
from gsbench.geometry.filter3d import Filter3D
from gsbench.raster.types import RenderOutput
from gsbench.training.gaussians import Gaussians
from gsbench.training.strategies.base import REFERENCE_ITERATIONS, _sample_offsets, reset_opacity
from gsbench.training.strategies.default import DefaultStrategy


@dataclass(frozen=True)
class AbsGradStatistics(DefaultStrategy):
    """What the densifications of GOF / RaDe-GS and PGSR add to `DefaultStrategy` alike: the mean abs-gradient
    g_abs = mean Σ_pixels (|∂L_pix/∂m_x| + |∂L_pix/∂m_y|) (`RenderOutput.densify_grads`, NDC units) over the
    same visible renders as g (``state["absgrad"]``), and clones sampled at μ + R (s ⊙ ε), ε ~ N(0, I)."""

    def init_state(self, n: int) -> dict:
        return {**super().init_state(n), "absgrad": torch.zeros(n)}

    def _accumulate(self, state: dict, out: RenderOutput) -> torch.Tensor:
        visible = super()._accumulate(state, out)
        _, absgrad = out.densify_grads()
        values = absgrad.detach().to(state["absgrad"].dtype)
        state["absgrad"].add_(torch.where(visible, values, torch.zeros((), dtype=values.dtype)))
        return visible

    def _mean_absgrad(self, state: dict) -> torch.Tensor:
        """g_abs (N,): the accumulated abs-gradient over the visible count (0 where never seen)."""
        return torch.nan_to_num(state["absgrad"] / state["count"], nan=0.0, posinf=0.0)

    def _clones(self, gaussians: Gaussians, clone: torch.Tensor) -> dict:
        rows = super()._clones(gaussians, clone)
        rows["means"] = rows["means"] + _sample_offsets(rows, self._orientations(rows))
        return rows


@dataclass(frozen=True)
class AbsGradStrategy(AbsGradStatistics):
    """GOF / RaDe-GS densification: `DefaultStrategy` with the abs-gradient criterion, sampled clone
    positions and the 3D filter's recomputation, as docs/methods/gof.md §5 and §2.4 state them
    (docs/methods/radegs.md §2.2).

    Selected = (g >= τ) OR (g_abs >= τ_abs AND g_abs > 0), τ_abs the (1 − ρ) quantile of g_abs, ρ the share
    with g >= τ. The g_abs > 0 guard keeps Gaussians unseen since the last refinement out when τ_abs = 0 (GOF's
    bare >= would select all of them). ``filter3d`` is shared with the method that renders with it (None: no
    filter); ``filter_every`` counts steps like ``refine_every`` and is not scaled.
    """

    prune_opacity: float = 0.05
    filter3d: Filter3D | None = dataclasses.field(default=None, compare=False, repr=False)
    filter_every: int = 100
    iterations: int = REFERENCE_ITERATIONS

    def __post_init__(self):
        super().__post_init__()
        if self.filter_every < 1:
            raise ConfigError(f"AbsGradStrategy needs filter_every >= 1, got {self.filter_every}")

    def scaled(self, total_iterations: int) -> AbsGradStrategy:
        """`DefaultStrategy.scaled` plus ``iterations = total_iterations`` (the filter's end guard)."""
        return dataclasses.replace(super().scaled(total_iterations), iterations=int(total_iterations))

    def step_post_backward(self, gaussians, optimizer, state, step, render_out) -> dict:
        info = super().step_post_backward(gaussians, optimizer, state, step, render_out)
        if (self.filter3d is not None and step > self.refine_stop and step % self.filter_every == 0
                and step < self.iterations - self.filter_every):
            self.filter3d.update(gaussians.means)
        return info

    def _select(self, state: dict) -> tuple[torch.Tensor, torch.Tensor]:
        standard, grads = super()._select(state)
        absgrads = self._mean_absgrad(state)
        threshold = matched_threshold(absgrads, float(standard.sum()) / max(len(standard), 1))
        return standard | ((absgrads.double() >= threshold) & (absgrads > 0)), absgrads

    def _refine(self, gaussians, optimizer, state, step) -> dict:
        info = super()._refine(gaussians, optimizer, state, step)
        if self.filter3d is not None:
            self.filter3d.update(gaussians.means)
        return info

    def _reset(self, gaussians: Gaussians, optimizer) -> None:
        variance = None if self.filter3d is None else self.filter3d.variance
        reset_opacity(gaussians, optimizer, self.reset_value, variance)


def matched_threshold(values: torch.Tensor, ratio: float) -> float:
    """The (1 − ``ratio``) quantile of ``values`` with linear interpolation (``torch.quantile``'s rule,
    without its 16M-element limit), in float64: ``values >= it`` holds for round(ratio·N) of N distinct
    values, and at least for the maximum (docs/methods/gof.md §5.2)."""
    if values.numel() == 0:
        return 0.0
    ordered = torch.sort(values.reshape(-1).to(torch.float64)).values
    pos = (1.0 - ratio) * (len(ordered) - 1)
    lo = math.floor(pos)
    hi = min(lo + 1, len(ordered) - 1)
    return float(ordered[lo] + (pos - lo) * (ordered[hi] - ordered[lo]))
