"""3DGS 2023 densification: clone, split, prune and opacity reset (docs/methods/3dgs.md §5.3)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass

import torch

from gsbench.errors import ConfigError
from gsbench.raster.types import RenderOutput
from gsbench.training.gaussians import Gaussians
from gsbench.training.strategies.base import (
    REFERENCE_ITERATIONS,
    Strategy,
    _sample_offsets,
    append_params,
    keep_params,
    reset_opacity,
)


@dataclass(frozen=True)
class DefaultStrategy(Strategy):
    """3DGS 2023 clone/split/prune and opacity reset, as docs/methods/3dgs.md §5.3 states it (2DGS splits
    in the surfel plane, docs/methods/2dgs.md §5). Beyond the paper's:

    - ``prune_grace``: no low-opacity prune within that many steps after a periodic opacity reset (the
      white-background reset at ``refine_start`` gets none; 0, the paper's behaviour, prunes every time);
    - ``prune_world_size`` false (GGGS): prune by opacity only;
    - ``max_gaussians`` > 0: clone (+1) and split (+``split_n`` − 1) candidates by decreasing g while they fit
      (counted before pruning); those left out are the info's ``budget_cut`` (docs/training.md §6).

    ``scene_extent`` is 3DGS ``cameras_extent``, in the scene's units. Split sampling uses torch's global RNG.
    """

    grad_threshold: float = 0.0002
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    refine_start: int = 500
    refine_stop: int = 15000
    refine_every: int = 100
    reset_every: int = 3000
    reset_value: float = 0.01
    screen_size: float = 20.0
    big_world: float = 0.1
    prune_screen_size: bool = False
    prune_world_size: bool = True
    split_n: int = 2
    prune_grace: int = 0
    white_background: bool = False
    scene_extent: float = 1.0
    max_gaussians: int = 0

    def __post_init__(self):
        if self.refine_every < 1 or self.reset_every < 1 or self.split_n < 2:
            raise ConfigError(f"strategy needs refine_every >= 1, reset_every >= 1 and split_n >= 2; got "
                              f"{self.refine_every}, {self.reset_every}, {self.split_n}")

    def scaled(self, total_iterations: int) -> DefaultStrategy:
        """The step-based fields scaled by ``total_iterations`` / 30000 (rounded, at least 1)."""
        f = total_iterations / REFERENCE_ITERATIONS
        fields = ("refine_start", "refine_stop", "refine_every", "reset_every")
        return dataclasses.replace(self, **{k: max(1, round(getattr(self, k) * f)) for k in fields})

    def init_state(self, n: int) -> dict:
        return {"grad2d": torch.zeros(n), "count": torch.zeros(n), "radii": torch.zeros(n)}

    def step_post_backward(self, gaussians, optimizer, state, step, render_out) -> dict:
        info = super().step_post_backward(gaussians, optimizer, state, step, render_out)
        if step >= self.refine_stop:
            return info
        self._accumulate(state, render_out)
        if step > self.refine_start and step % self.refine_every == 0:
            info.update(self._refine(gaussians, optimizer, state, step))
        if step % self.reset_every == 0 or (self.white_background and step == self.refine_start):
            self._reset(gaussians, optimizer)
            info["reset"] = True
        return info

    # ---- internals ------------------------------------------------------------------------------
    def _accumulate(self, state: dict, out: RenderOutput) -> torch.Tensor:
        """Add this render's statistics; returns the visible mask."""
        grad, _ = out.densify_grads()
        radii = out.radii.detach().to(state["radii"].dtype)
        visible = out.visible if out.visible is not None else radii > 0
        # masked elementwise updates rather than boolean indexing: the same values (adding 0 is exact),
        # without a nonzero() and a gather/scatter per statistic on every step
        norm = grad.detach().norm(dim=-1).to(state["grad2d"].dtype)
        state["grad2d"].add_(torch.where(visible, norm, torch.zeros((), dtype=norm.dtype)))
        state["count"].add_(visible.to(state["count"].dtype))
        torch.where(visible, torch.maximum(state["radii"], radii), state["radii"], out=state["radii"])
        return visible

    def _select(self, state: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """(densify candidates (N,) bool, budget priority (N,)): g >= ``grad_threshold``, by g."""
        grads = torch.nan_to_num(state["grad2d"] / state["count"], nan=0.0, posinf=0.0)
        return grads >= self.grad_threshold, grads

    @staticmethod
    def _clones(gaussians: Gaussians, clone: torch.Tensor) -> dict:
        """New rows for the (N,) bool ``clone``: identical copies (3DGS)."""
        return {k: v.detach()[clone] for k, v in gaussians.params.items()}

    def _reset(self, gaussians: Gaussians, optimizer) -> None:
        reset_opacity(gaussians, optimizer, self.reset_value)

    @staticmethod
    def _orientations(rows: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """The quaternions (N,4) that orient the Gaussians of parameter ``rows`` (the ``quats`` group;
        IBGS composes them with its reference frame, `gsbench.training.strategies.sparsity`)."""
        return rows["quats"]

    def _select_budget(self, n: int, priority: torch.Tensor, clone: torch.Tensor, split: torch.Tensor):
        """Restrict clone/split to the highest-``priority`` candidates whose added rows fit the budget;
        returns the kept clone and split masks and how many candidates the budget left out."""
        if self.max_gaussians <= 0:
            return clone, split, 0
        room = max(0, self.max_gaussians - n)
        cost = clone.long() + split.long() * (self.split_n - 1)
        if int(cost.sum()) <= room:
            return clone, split, 0
        candidates = torch.nonzero(cost > 0).flatten()
        order = candidates[torch.argsort(priority[candidates], descending=True, stable=True)]
        take = order[torch.cumsum(cost[order], 0) <= room]
        chosen = torch.zeros(n, dtype=torch.bool)
        chosen[take] = True
        return clone & chosen, split & chosen, len(candidates) - len(take)

    def _split_children(self, gaussians: Gaussians, split: torch.Tensor) -> dict:
        n = self.split_n
        params = {k: v.detach()[split] for k, v in gaussians.params.items()}
        children = {k: v.repeat((n,) + (1,) * (v.dim() - 1)) for k, v in params.items()}
        children["means"] = children["means"] + _sample_offsets(children, self._orientations(children))
        children["log_scales"] = children["log_scales"] - math.log(0.8 * n)
        return children

    def _refine(self, gaussians: Gaussians, optimizer, state: dict, step: int) -> dict:
        n = len(gaussians)
        extent = self.scene_extent
        selected, priority = self._select(state)
        small = gaussians.scales.detach().max(-1).values <= self.percent_dense * extent
        clone, split, cut = self._select_budget(n, priority, selected & small, selected & ~small)

        clones = self._clones(gaussians, clone)
        children = self._split_children(gaussians, split)
        append_params(gaussians, optimizer, {k: torch.cat([clones[k], children[k]]) for k in clones})
        added = len(gaussians) - n

        radii = torch.cat([state["radii"], torch.zeros(added)])
        prune = gaussians.opacities.detach() < self.prune_opacity
        if step >= self.reset_every and step % self.reset_every < self.prune_grace:
            prune[:] = False  # opacities reset moments ago have not had time to recover
        if step > self.reset_every and self.prune_world_size:
            prune |= gaussians.scales.detach().max(-1).values > self.big_world * extent
            if self.prune_screen_size:
                prune |= radii > self.screen_size
        parents = torch.cat([split, torch.zeros(added, dtype=torch.bool)])
        keep = ~(prune | parents)
        keep_params(gaussians, optimizer, keep)
        state.update(self.init_state(len(gaussians)))
        return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": int((prune & ~parents).sum()),
                "budget_cut": cut}
