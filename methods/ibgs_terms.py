"""IBGS loss terms ``eigval`` and ``eigvec`` (docs/methods/ibgs.md §5.2, §5.3, §5),
declared in configs/loss_terms/.

Both read ``state["local_geometry"]`` (a `gsbench.geometry.local_geometry.LocalGeometry` of this step) and
``state["scene_radius"]``; Gaussians whose neighbourhood is a single point (``valid`` false) are skipped.

- ``eigval`` (Eq. 8, confirmed): L = mean_i λ3,i / radius². λ3 has units of length², so dividing by
  the scene radius² makes the weight scale-free (docs/methods/ibgs.md §5.2). Its gradient needs no eigenvector
  derivative: ∂λ3/∂p = (2/n)(v3·(p − μ̄))v3 for every p in the neighbourhood, which pulls the points
  onto their best-fit plane; it is stable for repeated eigenvalues (a valid subgradient).
- ``eigvec`` (Eq. 9, form [ASSUMED]): L = mean over i and j ∈ N(i) of γ_i (1 − |v3,i · v3,j|), with
  γ_i = (λ2 − λ3)/λ1 the detached planarity (Eq. 10), pairs with γ_i < ``min_planarity`` (1e-3)
  masked (docs/methods/ibgs.md §5.3). |·| makes it invariant to eigenvector signs. The mean over j (the spec writes a
  sum) keeps the weight comparable across K. v3's gradient comes through the gap-regularised
  eigen backward (`gsbench.geometry.eigen3`).
"""

from __future__ import annotations

import torch

from gsbench.errors import ConfigError
from gsbench.geometry.local_geometry import LocalGeometry
from gsbench.geometry.neighbours import rows
from gsbench.losses.terms import Batch, loss_term
from gsbench.raster.types import RenderOutput


def _geometry(state: dict, term: str) -> tuple[LocalGeometry, float]:
    if "local_geometry" not in state:
        raise ConfigError(f"loss term '{term}' needs the IBGS neighbourhood eigen-decomposition; only the IBGS "
                          f"methods (ibgs, ibgs-gof, ibgs-2dgs) provide it, so remove losses.{term} for this method")
    return state["local_geometry"], float(state["scene_radius"])


def eigval_term(render: RenderOutput, batch: Batch, state: dict) -> torch.Tensor:
    """L_eigval = mean_i λ3,i / radius² over valid neighbourhoods (module docstring); 0 if none."""
    geometry, radius = _geometry(state, "eigval")
    lam3 = geometry.eigenvalues[:, 2][geometry.valid]
    if lam3.numel() == 0:
        return geometry.eigenvalues.sum() * 0.0
    return (lam3.mean() / radius**2).float()


def eigvec_term(render: RenderOutput, batch: Batch, state: dict, min_planarity: float = 1e-3) -> torch.Tensor:
    """L_eigvec = mean_{i, j∈N(i)} γ_i (1 − |v3,i·v3,j|) (module docstring); 0 without neighbours."""
    geometry, _ = _geometry(state, "eigvec")
    index = geometry.index
    if index.numel() == 0:
        return geometry.eigenvalues.sum() * 0.0
    normals = geometry.normals
    # v3,i·v3,j summed component by component on (N, K) maps: a broadcast multiply with a sum over the last
    # axis of 3 (or a batched matmul) costs several times more on the CPU, forward and backward
    similarity = sum(rows(normals[:, c].contiguous(), index) * normals[:, c, None] for c in range(3)).abs()
    gamma = geometry.planarity()
    weight = gamma * (gamma >= min_planarity) * geometry.valid
    weight = weight[:, None] * rows(geometry.valid, index)
    return (weight * (1.0 - similarity)).mean().float()


EIGVAL = loss_term("eigval", eigval_term)
EIGVEC = loss_term("eigvec", eigvec_term, params={"min_planarity": 1e-3})
