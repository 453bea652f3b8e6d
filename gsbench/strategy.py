"""Densification strategies with external state (gsplat-style; DESIGN.md "Strategy").

A strategy keeps no tensors itself: `Strategy.init_state` returns a plain dict of tensors the caller
checkpoints, and the caller runs, per training step (``step`` = 1-based iteration, as 3DGS
``train.py`` counts them)::

    out = method.render(...);  strategy.step_pre_backward(out)
    loss.backward();           strategy.step_post_backward(gaussians, optimizer, state, step, out)
    optimizer.step()

`DefaultStrategy` is 3DGS 2023 (methods-3dgs-2dgs-sugar.md §1.8); `NoStrategy` does nothing
(SuGaR coarse/refinement). Densify and prune keep the Adam state in step with the rows of every
parameter group (`append_params`, `keep_params`): new rows get zero moments, removed rows drop
theirs. Replaced parameters have no ``.grad``, so the Adam step right after a densification skips
them — faithful to 3DGS (§1.8 item 6).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass

import torch

from gsbench.errors import ConfigError
from gsbench.gaussians import Gaussians
from gsbench.raster.reference import quat_to_rotmat
from gsbench.raster.types import RenderOutput

REFERENCE_ITERATIONS = 30000  # the 3DGS schedule the step-based defaults belong to


# ---- optimizer-aware parameter surgery ----------------------------------------------------------


def _group(optimizer: torch.optim.Optimizer, name: str) -> dict | None:
    for group in optimizer.param_groups:
        if group.get("name") == name:
            if len(group["params"]) != 1:
                raise ConfigError(f"optimizer group '{name}' holds {len(group['params'])} tensors; the strategy "
                                  "needs one parameter per group, named as in Gaussians.params")
            return group
    return None


def _swap(gaussians: Gaussians, optimizer: torch.optim.Optimizer, name: str, value: torch.Tensor,
          moments) -> None:
    """Replace parameter ``name`` by ``value``; ``moments(old_moment) -> new_moment`` maps the Adam state."""
    old = gaussians.params[name]
    new = torch.nn.Parameter(value.detach().contiguous(), requires_grad=old.requires_grad)
    gaussians.params[name] = new
    group = _group(optimizer, name)
    if group is None:
        return
    group["params"][0] = new
    state = optimizer.state.pop(old, None)
    if state:
        optimizer.state[new] = {k: moments(v) if k in ("exp_avg", "exp_avg_sq") else v for k, v in state.items()}


def append_params(gaussians: Gaussians, optimizer: torch.optim.Optimizer, new: Mapping[str, torch.Tensor]) -> None:
    """Append rows ``new[name]`` to every parameter; their Adam moments start at zero."""
    for name, param in list(gaussians.params.items()):
        rows = new[name].to(param.dtype)

        def grow(m, rows=rows):
            return torch.cat([m, torch.zeros((len(rows),) + m.shape[1:], dtype=m.dtype)])

        _swap(gaussians, optimizer, name, torch.cat([param.detach(), rows]), grow)


def keep_params(gaussians: Gaussians, optimizer: torch.optim.Optimizer, keep: torch.Tensor) -> None:
    """Keep the rows where the (N,) bool ``keep`` is true, in parameters and Adam moments."""
    for name, param in list(gaussians.params.items()):
        _swap(gaussians, optimizer, name, param.detach()[keep], lambda m: m[keep])


def reset_opacity(gaussians: Gaussians, optimizer: torch.optim.Optimizer, value: float) -> None:
    """o ← min(o, value) stored as a logit, and zero that group's Adam moments (3DGS ``reset_opacity``)."""
    o = torch.clamp(gaussians.opacities.detach(), max=value)
    _swap(gaussians, optimizer, "opacity_logits", torch.logit(o), torch.zeros_like)


# ---- strategies ---------------------------------------------------------------------------------


class Strategy:
    """Interface: state dict in, Gaussians/optimizer modified in place, a small info dict out."""

    def init_state(self, n: int) -> dict:
        return {}

    def step_pre_backward(self, render_out: RenderOutput) -> None:
        """Make sure ``render_out.means2d.grad`` is filled by the coming backward."""
        m = render_out.means2d
        if m is not None and m.requires_grad and not m.is_leaf:
            m.retain_grad()

    def step_post_backward(self, gaussians: Gaussians, optimizer: torch.optim.Optimizer, state: dict, step: int,
                           render_out: RenderOutput) -> dict:
        return {"cloned": 0, "split": 0, "pruned": 0, "reset": False}


class NoStrategy(Strategy):
    """No densification, pruning or opacity reset (SuGaR coarse and refinement stages, §3.2/§3.4)."""


@dataclass(frozen=True)
class DefaultStrategy(Strategy):
    """3DGS 2023 clone/split/prune/opacity reset (methods-3dgs-2dgs-sugar.md §1.8, §2.8).

    While ``step < refine_stop``: accumulate, for visible Gaussians (radii > 0), ‖∂L/∂μ_ndc‖ and a
    count, and the max screen radius. When ``step > refine_start`` and ``step % refine_every == 0``:
    with g = accum / count (0 where never seen) and s_max the largest scale,

    - clone  where g >= ``grad_threshold`` and s_max <= ``percent_dense``·extent (identical copy);
    - split  where g >= ``grad_threshold`` and s_max >  ``percent_dense``·extent: ``split_n`` children
      at μ + R (s ⊙ ε), ε ~ N(0, I) (in-plane only for 2D surfels), scale s / (0.8·split_n); the
      parent is removed. Both use the pre-densification g, so fresh clones are never split;
    - prune  where o < ``prune_opacity``, and when ``step > reset_every`` also s_max >
      ``big_world``·extent and, only with ``prune_screen_size``, max radius > ``screen_size`` px.
      3DGS 2023 resets the radii during clone/split, so its screen test never fires (issues
      #123/#643; gsplat disables it too): ``prune_screen_size = False`` is that faithful behaviour;
    - then the statistics restart at zero.

    When ``step % reset_every == 0`` (and at ``step == refine_start`` with ``white_background``):
    o ← min(o, ``reset_value``) and that group's Adam moments are zeroed.

    ``max_gaussians`` > 0 is a budget: if clone (+1 each) and split (+split_n − 1 each) would exceed
    it, the highest-g candidates are taken while they fit (counted before pruning). ``scene_extent``
    is 3DGS ``cameras_extent`` in the scene's units. Split sampling uses torch's global RNG.
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
    split_n: int = 2
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
            reset_opacity(gaussians, optimizer, self.reset_value)
            info["reset"] = True
        return info

    # ---- internals ------------------------------------------------------------------------------
    @staticmethod
    def _accumulate(state: dict, out: RenderOutput) -> None:
        grad, _ = out.densify_grads()
        radii = out.radii.detach().to(state["radii"].dtype)
        visible = out.visible if out.visible is not None else radii > 0
        state["grad2d"][visible] += grad.detach().norm(dim=-1).to(state["grad2d"].dtype)[visible]
        state["count"][visible] += 1
        state["radii"][visible] = torch.maximum(state["radii"][visible], radii[visible])

    def _select_budget(self, n: int, grads: torch.Tensor, clone: torch.Tensor, split: torch.Tensor):
        """Restrict clone/split to the highest-gradient candidates whose added rows fit the budget."""
        if self.max_gaussians <= 0:
            return clone, split
        room = max(0, self.max_gaussians - n)
        cost = clone.long() + split.long() * (self.split_n - 1)
        if int(cost.sum()) <= room:
            return clone, split
        candidates = torch.nonzero(cost > 0).flatten()
        order = candidates[torch.argsort(grads[candidates], descending=True, stable=True)]
        take = order[torch.cumsum(cost[order], 0) <= room]
        chosen = torch.zeros(n, dtype=torch.bool)
        chosen[take] = True
        return clone & chosen, split & chosen

    def _split_children(self, gaussians: Gaussians, split: torch.Tensor) -> dict:
        n = self.split_n
        params = {k: v.detach()[split] for k, v in gaussians.params.items()}
        scales = torch.exp(params["log_scales"]).repeat(n, 1)
        std = torch.cat([scales, torch.zeros(len(scales), 3 - scales.shape[1], dtype=scales.dtype)], -1)
        offsets = torch.normal(torch.zeros_like(std), std)
        rot = quat_to_rotmat(params["quats"]).repeat(n, 1, 1)
        children = {k: v.repeat((n,) + (1,) * (v.dim() - 1)) for k, v in params.items()}
        children["means"] = children["means"] + torch.einsum("nij,nj->ni", rot, offsets)
        children["log_scales"] = children["log_scales"] - math.log(0.8 * n)
        return children

    def _refine(self, gaussians: Gaussians, optimizer, state: dict, step: int) -> dict:
        n = len(gaussians)
        extent = self.scene_extent
        grads = torch.nan_to_num(state["grad2d"] / state["count"], nan=0.0, posinf=0.0)
        big_grad = grads >= self.grad_threshold
        small = gaussians.scales.detach().max(-1).values <= self.percent_dense * extent
        clone, split = self._select_budget(n, grads, big_grad & small, big_grad & ~small)

        clones = {k: v.detach()[clone] for k, v in gaussians.params.items()}
        children = self._split_children(gaussians, split)
        append_params(gaussians, optimizer, {k: torch.cat([clones[k], children[k]]) for k in clones})
        added = len(gaussians) - n

        radii = torch.cat([state["radii"], torch.zeros(added)])
        prune = gaussians.opacities.detach() < self.prune_opacity
        if step > self.reset_every:
            prune |= gaussians.scales.detach().max(-1).values > self.big_world * extent
            if self.prune_screen_size:
                prune |= radii > self.screen_size
        parents = torch.cat([split, torch.zeros(added, dtype=torch.bool)])
        keep = ~(prune | parents)
        keep_params(gaussians, optimizer, keep)
        state.update(self.init_state(len(gaussians)))
        return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": int((prune & ~parents).sum())}
