"""GGGS's loss terms (docs/methods/gggs.md §3), declared in configs/loss_terms/. They read the
stochastic-solid depth D (the ``solid_depth`` output, camera z) and the rendered normal N = Σ wᵢnᵢ:

- ``gggs_normal``: mean over all H×W pixels of 1 − n_r·n_d, n_r = N/α (GGGS divides the normal by 1 − T, not
  to unit length; 0 where α = 0), n_d the unit normal of D's central differences (`depth_to_normal`), 0 unless
  D > 0 at the pixel and its four neighbours (GGGS's validity); no image-gradient weight;
- ``gggs_geo`` / ``gggs_ncc``: PGSR's multi-view geometric and photometric terms (`gsbench.methods.pgsr_terms`
  `multiview_geo`, `multiview_ncc`) on the warp the method builds from the planes through D·r with normal
  N/‖N‖ (``state["pgsr_multiview"]``, `gsbench.methods.gggs.GGGS`); GGGS's NCC samples 7×7 points half a pixel
  apart (the method's ``patch_step``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from gsbench.geometry.depth import depth_to_normal
from gsbench.losses.terms import Batch, loss_term
from gsbench.methods.pgsr_terms import multiview_context, multiview_geo, multiview_ncc
from gsbench.raster.types import RenderOutput


def depth_validity(depth: torch.Tensor) -> torch.Tensor:
    """(H, W) bool: D > 0 at the pixel and its four neighbours (False on the 1-pixel border)."""
    positive = F.pad((depth > 0).to(torch.float32)[None, None], (1, 1, 1, 1))[0, 0]
    centre = positive[1:-1, 1:-1]
    return (centre * positive[:-2, 1:-1] * positive[2:, 1:-1] * positive[1:-1, :-2] * positive[1:-1, 2:]) > 0


def gggs_normal_term(render: RenderOutput, batch: Batch, state: dict) -> torch.Tensor:
    """L_dn = mean over H×W of (1 − n_r·n_d) where valid, else 0 (module docstring; GGGS train.py)."""
    depth = render.solid_depth
    alpha = render.alpha
    covered = alpha > 0
    n_r = render.normal / torch.where(covered, alpha, torch.ones_like(alpha))[..., None]
    n_r = torch.where(covered[..., None], n_r, torch.zeros_like(n_r))
    n_d = depth_to_normal(depth, batch.camera)
    cost = 1.0 - (n_r * n_d).sum(-1)
    return torch.where(depth_validity(depth.detach()), cost, torch.zeros_like(cost)).mean()


def gggs_geo_term(render: RenderOutput, batch: Batch, state: dict) -> torch.Tensor:
    """L_geo = `multiview_geo` of the step's warp (module docstring)."""
    return multiview_geo(multiview_context(state, "gggs_geo", render, batch), render.solid_depth.sum() * 0.0)


def gggs_ncc_term(render: RenderOutput, batch: Batch, state: dict) -> torch.Tensor:
    """L_ncc = `multiview_ncc` of the step's warp (module docstring)."""
    return multiview_ncc(multiview_context(state, "gggs_ncc", render, batch), render.solid_depth.sum() * 0.0)


GGGS_NORMAL = loss_term("gggs_normal", gggs_normal_term, {"solid_depth", "normal", "alpha"})
GGGS_GEO = loss_term("gggs_geo", gggs_geo_term, {"solid_depth", "normal"})
GGGS_NCC = loss_term("gggs_ncc", gggs_ncc_term, {"solid_depth", "normal"})
