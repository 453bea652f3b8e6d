"""GGGS's loss terms (docs/methods/gggs.md §3), declared in configs/loss_terms/. They read the surface depth D
(`surface_depth`, camera z: the stochastic-solid depth, or with ``depth`` "median" the median depth,
docs/methods/gggs.md §3.5) and the rendered normal N = Σ wᵢnᵢ:

- ``gggs_normal``: mean over all H×W pixels of 1 − n_r·n_d, n_r = N/α (GGGS divides the normal by 1 − T, not
  to unit length; 0 where α = 0), n_d the unit normal of D's central differences (`depth_to_normal`), 0 unless
  D > 0 at the pixel and its four neighbours (GGGS's validity); no image-gradient weight;
- ``gggs_geo`` / ``gggs_ncc``: PGSR's multi-view geometric and photometric terms (`gsbench.methods.pgsr_terms`
  `multiview_geo`, `multiview_ncc`) on the warp the method builds from the planes through D·r with normal
  N/‖N‖ (``state["pgsr_multiview"]``, `gsbench.methods.gggs.GGGS`); GGGS's NCC samples 7×7 points half a pixel
  apart (the method's ``patch_step``).

Each term's parameter ``depth`` ("solid", the default, or "median") is the method's ``surface_depth``
(`gsbench.methods.gggs.GGGS.term_params`); it decides which render outputs the term asks for.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from gsbench.errors import ConfigError
from gsbench.geometry.depth import depth_to_normal
from gsbench.losses.terms import Batch, loss_term
from gsbench.methods.pgsr_terms import multiview_context, multiview_geo, multiview_ncc
from gsbench.raster.types import RasterSettings, RenderOutput

# method.surface_depth -> the render outputs its D is made of
SURFACE_OUTPUTS = {"solid": ("solid_depth",), "median": ("median_depth", "alpha")}
# the solid depth's no-surface rule (GGGS's MIN_TRANSMITTANCE), applied to the median depth too
NO_SURFACE_TRANSMITTANCE = RasterSettings.solid_min_transmittance


def surface_depth(render: RenderOutput, depth: str) -> torch.Tensor:
    """D (H, W), camera z. ``solid``: the stochastic-solid depth, T(t) = ½ searched around the median
    (docs/methods/gggs.md §2). ``median``: the ``median_depth`` output, the depth plane of the last blended Gaussian
    with T > ½ before it (the solid search's initial estimate, RaDe-GS's median), 0 where the final transmittance
    1 − α exceeds `NO_SURFACE_TRANSMITTANCE`, as the solid depth is (docs/methods/gggs.md §3.5); the rule is
    not differentiated."""
    if depth == "solid":
        return render.solid_depth
    if depth == "median":
        surface = (1.0 - render.alpha.detach()) <= NO_SURFACE_TRANSMITTANCE
        return torch.where(surface, render.median_depth, torch.zeros_like(render.median_depth))
    raise ConfigError(f"GGGS surface depth must be one of {', '.join(SURFACE_OUTPUTS)}, got '{depth}'")


def _requires(*always: str):
    """``requires_fn`` of a term that reads D and ``always``."""
    return lambda params: frozenset((*SURFACE_OUTPUTS[params["depth"]], *always))


def depth_validity(depth: torch.Tensor) -> torch.Tensor:
    """(H, W) bool: D > 0 at the pixel and its four neighbours (False on the 1-pixel border)."""
    positive = F.pad((depth > 0).to(torch.float32)[None, None], (1, 1, 1, 1))[0, 0]
    centre = positive[1:-1, 1:-1]
    return (centre * positive[:-2, 1:-1] * positive[2:, 1:-1] * positive[1:-1, :-2] * positive[1:-1, 2:]) > 0


def gggs_normal_term(render: RenderOutput, batch: Batch, state: dict, depth: str = "solid") -> torch.Tensor:
    """L_dn = mean over H×W of (1 − n_r·n_d) where valid, else 0 (module docstring; GGGS train.py)."""
    d = surface_depth(render, depth)
    alpha = render.alpha
    covered = alpha > 0
    n_r = render.normal / torch.where(covered, alpha, torch.ones_like(alpha))[..., None]
    n_r = torch.where(covered[..., None], n_r, torch.zeros_like(n_r))
    n_d = depth_to_normal(d, batch.camera)
    cost = 1.0 - (n_r * n_d).sum(-1)
    return torch.where(depth_validity(d.detach()), cost, torch.zeros_like(cost)).mean()


def gggs_geo_term(render: RenderOutput, batch: Batch, state: dict, depth: str = "solid") -> torch.Tensor:
    """L_geo = `multiview_geo` of the step's warp (module docstring)."""
    zero = surface_depth(render, depth).sum() * 0.0
    return multiview_geo(multiview_context(state, "gggs_geo", render, batch), zero)


def gggs_ncc_term(render: RenderOutput, batch: Batch, state: dict, depth: str = "solid") -> torch.Tensor:
    """L_ncc = `multiview_ncc` of the step's warp (module docstring)."""
    zero = surface_depth(render, depth).sum() * 0.0
    return multiview_ncc(multiview_context(state, "gggs_ncc", render, batch), zero)


GGGS_NORMAL = loss_term("gggs_normal", gggs_normal_term, params={"depth": "solid"},
                        requires_fn=_requires("normal", "alpha"))
GGGS_GEO = loss_term("gggs_geo", gggs_geo_term, params={"depth": "solid"}, requires_fn=_requires("normal"))
GGGS_NCC = loss_term("gggs_ncc", gggs_ncc_term, params={"depth": "solid"}, requires_fn=_requires("normal"))
