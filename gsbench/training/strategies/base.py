"""Densification strategies with external state (gsplat-style, docs/design.md §3.3): the interface and the
optimizer-aware parameter surgery the strategies share.

``step`` is the 1-based iteration, as 3DGS ``train.py`` counts. `append_params` and `keep_params` keep the Adam
state in step with the rows: new rows get zero moments, removed rows drop theirs. A replaced parameter has no
``.grad``, so the Adam step right after a densification skips it, as 3DGS's does (docs/methods/3dgs.md §5.3).
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

from gsbench.errors import ConfigError
from gsbench.geometry.filter3d import filter_coefficient
from gsbench.raster.reference_projection import quat_to_rotmat
from gsbench.raster.types import RenderOutput
from gsbench.training.gaussians import Gaussians

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
    """logit ← min(logit, logit(value / c)) and that group's Adam moments zeroed (3DGS ``reset_opacity``), with
    c = `filter_coefficient` of the 3D-filter variance ``filter3d`` (c = 1 without): the filtered opacity o·c
    is reset. Applied to the logit, a row the reset does not lower keeps it exactly, and a saturated opacity
    gives no +inf or NaN as the authors' round trip through o does (docs/methods/gof.md §2.5).
    """
    logits = gaussians.params["opacity_logits"].detach()
    if filter3d is None:
        ceiling = torch.full_like(logits, value)
    else:
        ceiling = value / filter_coefficient(gaussians.scales.detach(), filter3d.to(logits.dtype))
    # value / c at or above 1 (c <= value) lowers nothing: clamped to 1, its logit is +inf
    ceiling_logit = torch.logit(ceiling.clamp(max=1.0))
    _swap(gaussians, optimizer, "opacity_logits", torch.minimum(logits, ceiling_logit), torch.zeros_like)


def _sample_offsets(rows: Mapping[str, torch.Tensor], quats: torch.Tensor) -> torch.Tensor:
    """R (s ⊙ ε) per row, R the rotation of ``quats`` (N,4), ε ~ N(0, I) from torch's global RNG (in the
    surfel plane for 2D scales)."""
    scales = torch.exp(rows["log_scales"])
    std = torch.cat([scales, torch.zeros(len(scales), 3 - scales.shape[1], dtype=scales.dtype)], -1)
    offsets = torch.normal(torch.zeros_like(std), std)
    return torch.einsum("nij,nj->ni", quat_to_rotmat(quats), offsets)


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
