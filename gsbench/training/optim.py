"""The optimizers a run can choose (``train.optimizer``, docs/training.md §8): ``adam``, `FusedAdam`
(torch's fused Adam, the papers' update), and ``visible_adam``, `VisibleAdam`, which per visible row i,
with the group's global step count t, does

    m_i ← β1 m_i + (1 − β1) g_i,   v_i ← β2 v_i + (1 − β2) g_i²,
    θ_i ← θ_i − lr / (1 − β1ᵗ) · m_i / (√v_i / √(1 − β2ᵗ) + ε)

and nothing for the rows the view does not see (not the papers' update: opt-in, no preset uses it).
"""

from __future__ import annotations

import math

import torch

from gsbench.errors import ConfigError

OPTIMIZERS = ("adam", "visible_adam")


class VisibleAdam(torch.optim.Adam):
    """Adam on visible rows only (the module's formula); set ``visible`` (bool (N,)) before each `step`.

    The state keeps Adam's layout (``step``, ``exp_avg``, ``exp_avg_sq`` per parameter), so
    densification's row surgery (`gsbench.training.strategies`) and checkpoints work unchanged. ``visible`` None:
    the plain Adam step.
    """

    def __init__(self, params, **kwargs):
        super().__init__(params, foreach=False, **kwargs)
        self.visible: torch.Tensor | None = None

    @torch.no_grad()
    def step(self, closure=None):
        if self.visible is None:
            return super().step(closure)
        rows = self.visible.nonzero().squeeze(1)
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            for param in group["params"]:
                if param.grad is None:
                    continue
                state = self.state[param]
                if not state:
                    state["step"] = torch.tensor(0.0)
                    state["exp_avg"] = torch.zeros_like(param)
                    state["exp_avg_sq"] = torch.zeros_like(param)
                state["step"] += 1
                t = float(state["step"])
                grad = param.grad[rows]
                m = state["exp_avg"][rows].mul_(beta1).add_(grad, alpha=1 - beta1)
                v = state["exp_avg_sq"][rows].mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
                state["exp_avg"][rows], state["exp_avg_sq"][rows] = m, v
                denom = (v.sqrt() / math.sqrt(1 - beta2**t)).add_(group["eps"])
                param[rows] = param[rows].addcdiv(m, denom, value=-group["lr"] / (1 - beta1**t))
        return None


class FusedAdam(torch.optim.Adam):
    """`torch.optim.Adam` with ``fused=True`` whose step calls the fused kernel (``torch._fused_adam_``) once per
    parameter group with the arguments torch's own fused step passes (steps incremented first), without that
    step's per-call Python (grouping by device and dtype, state and option checks): at 6 groups of 13k
    Gaussians that Python cost ~0.25 ms, about as much as the update itself. The first step (state not yet
    created), amsgrad, a closure or a group of mixed dtypes take torch's own step."""

    def __init__(self, params, **kwargs):
        super().__init__(params, fused=True, **kwargs)

    def step(self, closure=None):
        calls = []
        for group in self.param_groups:
            params = [p for p in group["params"] if p.grad is not None]
            if not params:
                continue
            states = [self.state[p] for p in params]
            if closure is not None or group["amsgrad"] or not all(states) or len({p.dtype for p in params}) > 1:
                return super().step(closure)
            calls.append((group, params, states))
        with torch.no_grad():
            for group, params, states in calls:
                steps = [state["step"] for state in states]
                torch._foreach_add_(steps, 1)
                beta1, beta2 = group["betas"]
                torch._fused_adam_(params, [p.grad for p in params], [state["exp_avg"] for state in states],
                                   [state["exp_avg_sq"] for state in states], [], steps, amsgrad=False,
                                   lr=group["lr"], beta1=beta1, beta2=beta2, weight_decay=group["weight_decay"],
                                   eps=group["eps"], maximize=group["maximize"], grad_scale=None, found_inf=None)
        return None


def make_adam(groups, kind: str, eps: float) -> torch.optim.Optimizer:
    """The optimizer ``kind`` (`OPTIMIZERS`) over ``groups`` with Adam's ``eps``."""
    if kind == "adam":
        return FusedAdam(groups, lr=0.0, eps=eps)
    if kind == "visible_adam":
        return VisibleAdam(groups, lr=0.0, eps=eps)
    raise ConfigError(f"train.optimizer must be one of {', '.join(OPTIMIZERS)}, got '{kind}'")
