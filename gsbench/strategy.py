"""Densification strategies with external state (gsplat-style; docs/design.md §3.3).

A strategy keeps no tensors itself: `Strategy.init_state` returns a plain dict of tensors the caller
checkpoints, and the caller runs, per training step (``step`` = 1-based iteration, as 3DGS
``train.py`` counts them)::

    out = method.render(...);  strategy.step_pre_backward(out)
    loss.backward();           strategy.step_post_backward(gaussians, optimizer, state, step, out)
    optimizer.step()

`DefaultStrategy` is 3DGS 2023 (docs/methods/3dgs.md §5.3); `AbsGradStrategy` is GOF's and
RaDe-GS's (docs/methods/gof.md §5, with the 3D filter of docs/methods/gof.md §2); `NoStrategy` does nothing
(SuGaR coarse/refinement). Densify and prune keep the Adam state in step with the rows of every
parameter group (`append_params`, `keep_params`): new rows get zero moments, removed rows drop
theirs. Replaced parameters have no ``.grad``, so the Adam step right after a densification skips
them — faithful to 3DGS (docs/methods/3dgs.md §5.3).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass

import torch

from gsbench.errors import ConfigError
from gsbench.filter3d import Filter3D, filter_coefficient
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


def reset_opacity(gaussians: Gaussians, optimizer: torch.optim.Optimizer, value: float,
                  filter3d: torch.Tensor | None = None) -> None:
    """o ← min(o, value) stored as a logit, and zero that group's Adam moments (3DGS ``reset_opacity``).

    With a 3D-filter variance ``filter3d`` (N,) the *filtered* opacity is reset (docs/methods/gof.md §2.5): with
    c = `filter_coefficient`, o_eff = o·c ← min(o_eff, value), stored as o = o_eff / c (<= o).
    """
    o = gaussians.opacities.detach()
    if filter3d is None:
        o = torch.clamp(o, max=value)
    else:
        coef = filter_coefficient(gaussians.scales.detach(), filter3d.to(o.dtype))
        o = torch.clamp(o * coef, max=value) / coef
    _swap(gaussians, optimizer, "opacity_logits", torch.logit(o), torch.zeros_like)


def _sample_offsets(rows: Mapping[str, torch.Tensor], quats: torch.Tensor) -> torch.Tensor:
    """R (s ⊙ ε) per row, R the rotation of ``quats`` (N,4), ε ~ N(0, I) from torch's global RNG (in the
    surfel plane for 2D scales)."""
    scales = torch.exp(rows["log_scales"])
    std = torch.cat([scales, torch.zeros(len(scales), 3 - scales.shape[1], dtype=scales.dtype)], -1)
    offsets = torch.normal(torch.zeros_like(std), std)
    return torch.einsum("nij,nj->ni", quat_to_rotmat(quats), offsets)


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
    """No densification, pruning or opacity reset (SuGaR coarse and refinement stages, docs/methods/sugar.md §3.1, §6)."""


@dataclass(frozen=True)
class DefaultStrategy(Strategy):
    """3DGS 2023 clone/split/prune/opacity reset (docs/methods/3dgs.md §5.3; docs/methods/2dgs.md §5).

    While ``step < refine_stop``: accumulate, for visible Gaussians (radii > 0), ‖∂L/∂μ_ndc‖ and a
    count, and the max screen radius. When ``step > refine_start`` and ``step % refine_every == 0``:
    with g = accum / count (0 where never seen) and s_max the largest scale,

    - clone  where g >= ``grad_threshold`` and s_max <= ``percent_dense``·extent (identical copy);
    - split  where g >= ``grad_threshold`` and s_max >  ``percent_dense``·extent: ``split_n`` children
      at μ + R (s ⊙ ε), ε ~ N(0, I) (in-plane only for 2D surfels), scale s / (0.8·split_n); the
      parent is removed. Both use the pre-densification g, so fresh clones are never split;
    - prune  where o < ``prune_opacity`` (not within ``prune_grace`` steps after a periodic opacity
      reset — the white-background reset at ``refine_start`` gets no grace; 0, the paper's
      behaviour, prunes at every refinement), and when ``step > reset_every`` also s_max >
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
        state["grad2d"][visible] += grad.detach().norm(dim=-1).to(state["grad2d"].dtype)[visible]
        state["count"][visible] += 1
        state["radii"][visible] = torch.maximum(state["radii"][visible], radii[visible])
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
        IBGS composes them with its reference frame, `gsbench.sparsity`)."""
        return rows["quats"]

    def _select_budget(self, n: int, priority: torch.Tensor, clone: torch.Tensor, split: torch.Tensor):
        """Restrict clone/split to the highest-``priority`` candidates whose added rows fit the budget."""
        if self.max_gaussians <= 0:
            return clone, split
        room = max(0, self.max_gaussians - n)
        cost = clone.long() + split.long() * (self.split_n - 1)
        if int(cost.sum()) <= room:
            return clone, split
        candidates = torch.nonzero(cost > 0).flatten()
        order = candidates[torch.argsort(priority[candidates], descending=True, stable=True)]
        take = order[torch.cumsum(cost[order], 0) <= room]
        chosen = torch.zeros(n, dtype=torch.bool)
        chosen[take] = True
        return clone & chosen, split & chosen

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
        clone, split = self._select_budget(n, priority, selected & small, selected & ~small)

        clones = self._clones(gaussians, clone)
        children = self._split_children(gaussians, split)
        append_params(gaussians, optimizer, {k: torch.cat([clones[k], children[k]]) for k in clones})
        added = len(gaussians) - n

        radii = torch.cat([state["radii"], torch.zeros(added)])
        prune = gaussians.opacities.detach() < self.prune_opacity
        if step >= self.reset_every and step % self.reset_every < self.prune_grace:
            prune[:] = False  # opacities reset moments ago have not had time to recover
        if step > self.reset_every:
            prune |= gaussians.scales.detach().max(-1).values > self.big_world * extent
            if self.prune_screen_size:
                prune |= radii > self.screen_size
        parents = torch.cat([split, torch.zeros(added, dtype=torch.bool)])
        keep = ~(prune | parents)
        keep_params(gaussians, optimizer, keep)
        state.update(self.init_state(len(gaussians)))
        return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": int((prune & ~parents).sum())}


@dataclass(frozen=True)
class AbsGradStrategy(DefaultStrategy):
    """GOF / RaDe-GS densification (docs/methods/gof.md §5, docs/methods/radegs.md §2.2, docs/methods/radegs.md §2.2) with the 3D filter (docs/methods/gof.md §2.4).

    `DefaultStrategy` (window, interval, pruning, opacity-reset schedule, budget) with these changes:

    - statistics: besides g = mean ‖∂L/∂μ_ndc‖ it averages the abs-gradient
      g_abs = mean Σ_pixels (|∂L_pix/∂m_x| + |∂L_pix/∂m_y|) (`RenderOutput.densify_grads`, NDC units)
      over the same visible renders;
    - selection: with ρ = the fraction of Gaussians with g >= τ (``grad_threshold``), τ_abs = the
      (1 − ρ) quantile of g_abs (linear interpolation, as ``torch.quantile``), so the abs-criterion
      selects as many Gaussians as the standard one; selected = (g >= τ) OR (g_abs >= τ_abs, g_abs > 0).
      The g_abs > 0 guard keeps Gaussians unseen since the last refinement out when τ_abs = 0 (GOF's
      bare >= would select all of them); ρ = 0 still selects the largest g_abs, as in GOF;
    - clone: the copy's centre is sampled at μ + R (s ⊙ ε), ε ~ N(0, I) (split as in 3DGS);
    - budget: candidates are taken by decreasing g_abs (>= g for every Gaussian);
    - 3D filter (``filter3d``, shared with the method that renders with it; None = no filter): recomputed
      after every refinement, before the opacity reset, which resets the *filtered* opacity
      (`reset_opacity` with the variance); and every ``filter_every`` steps after ``refine_stop``
      while ``step < iterations − filter_every`` (GOF ``train.py``). ``filter_every`` is a number of
      steps like ``refine_every`` and is not scaled; `scaled` sets ``iterations`` to the run length.
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

    def init_state(self, n: int) -> dict:
        return {**super().init_state(n), "absgrad": torch.zeros(n)}

    def step_post_backward(self, gaussians, optimizer, state, step, render_out) -> dict:
        info = super().step_post_backward(gaussians, optimizer, state, step, render_out)
        if (self.filter3d is not None and step > self.refine_stop and step % self.filter_every == 0
                and step < self.iterations - self.filter_every):
            self.filter3d.update(gaussians.means)
        return info

    def _accumulate(self, state: dict, out: RenderOutput) -> torch.Tensor:
        visible = super()._accumulate(state, out)
        _, absgrad = out.densify_grads()
        state["absgrad"][visible] += absgrad.detach().to(state["absgrad"].dtype)[visible]
        return visible

    def _select(self, state: dict) -> tuple[torch.Tensor, torch.Tensor]:
        standard, grads = super()._select(state)
        absgrads = torch.nan_to_num(state["absgrad"] / state["count"], nan=0.0, posinf=0.0)
        threshold = matched_threshold(absgrads, float(standard.sum()) / max(len(standard), 1))
        return standard | ((absgrads.double() >= threshold) & (absgrads > 0)), absgrads

    def _clones(self, gaussians: Gaussians, clone: torch.Tensor) -> dict:
        rows = super()._clones(gaussians, clone)
        rows["means"] = rows["means"] + _sample_offsets(rows, self._orientations(rows))
        return rows

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
