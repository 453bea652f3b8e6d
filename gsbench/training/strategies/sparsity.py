"""IBGS densification: GOF's abs-gradient clone/split/prune (taken to be the paper's Eq. 2 [ASSUMED]) plus
sparsity-aware densification, SADC (its form [ASSUMED], switchable), as docs/methods/ibgs.md §6 states them.

SADC: with d̄_i = mean_j ‖μ_j − μ_i‖ over the neighbours and m = median_i d̄_i, Gaussian i is sparse if
d̄_i > ``sparsity``·m or it is large enough to split; each sparse i and neighbour j with ‖μ_j − μ_i‖ >
``min_gap``·m add one Gaussian at their midpoint projected onto i's local plane. The strategy shares the
method's `gsbench.geometry.neighbours.NeighbourIndex` and orients offsets with the IBGS rotation ΔR·V.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass

import torch

from gsbench.geometry.local_geometry import local_geometry, neighbourhood_points
from gsbench.geometry.neighbours import NeighbourIndex
from gsbench.geometry.rotations import quat_multiply, rotmat_to_quat
from gsbench.training.gaussians import Gaussians
from gsbench.training.strategies.absgrad import AbsGradStrategy
from gsbench.training.strategies.base import append_params


def ibgs_orientations(rows: Mapping[str, torch.Tensor]) -> torch.Tensor:
    """Quaternions of the IBGS rotation V' = ΔR·V for parameter ``rows`` holding ``quats`` (ΔR) and the
    reference ``frame`` V (N,3,3)."""
    delta = torch.nn.functional.normalize(rows["quats"], dim=-1)
    return quat_multiply(delta, rotmat_to_quat(rows["frame"].to(delta.dtype)))


@dataclass(frozen=True)
class SparsityAwareStrategy(AbsGradStrategy):
    """`AbsGradStrategy` + kNN refresh + SADC (module docstring)."""

    neighbours: NeighbourIndex | None = dataclasses.field(default=None, compare=False, repr=False)
    sadc: bool = True
    sparsity: float = 2.0
    min_gap: float = 1.5
    knn_include_self: bool = True
    scene_radius: float = 1.0

    @staticmethod
    def _orientations(rows: Mapping[str, torch.Tensor]) -> torch.Tensor:
        return ibgs_orientations(rows)

    def _refine(self, gaussians, optimizer, state, step) -> dict:
        info = super()._refine(gaussians, optimizer, state, step)
        self.neighbours.refresh(gaussians.means)
        added = 0
        if self.sadc:
            added, cut = self._densify_sparse(gaussians, optimizer)
            info["budget_cut"] += cut
            if added:
                state.update(self.init_state(len(gaussians)))
                if self.filter3d is not None:
                    self.filter3d.update(gaussians.means)
                self.neighbours.refresh(gaussians.means)
        return {**info, "sadc": added}

    @torch.no_grad()
    def _densify_sparse(self, gaussians: Gaussians, optimizer) -> tuple[int, int]:
        """Append SADC Gaussians (docs/methods/ibgs.md §6.3); returns how many, and how many pairs the
        budget left out."""
        n = len(gaussians)
        index = self.neighbours.check(n)
        if n < 3 or index.shape[1] == 0:
            return 0, 0
        means = gaussians.means.detach()
        gaps = (means[index] - means[:, None]).norm(dim=-1)  # (N, K)
        spacing = gaps.mean(1)
        typical = float(spacing.median())
        large = gaussians.scales.detach().max(-1).values > self.percent_dense * self.scene_extent
        sparse = (spacing > self.sparsity * typical) | large
        wide = sparse[:, None] & (gaps > self.min_gap * typical)
        i, k = torch.nonzero(wide, as_tuple=True)
        j = index[i, k]
        # (i, j) and (j, i) count once; the sparse Gaussian comes first (its plane takes the new one),
        # the lower index when both are sparse
        swap = sparse[j] & (j < i)
        pairs = torch.unique(torch.stack([torch.where(swap, j, i), torch.where(swap, i, j)], 1), dim=0)
        if len(pairs) == 0:
            return 0, 0
        kept = self._fit_budget(pairs, means, n)
        append_params(gaussians, optimizer, self._midpoint_rows(gaussians, kept))
        return len(kept), len(pairs) - len(kept)

    def _fit_budget(self, pairs: torch.Tensor, means: torch.Tensor, n: int) -> torch.Tensor:
        """The pairs that fit ``max_gaussians`` (0 = no budget), widest gaps first."""
        if self.max_gaussians <= 0 or len(pairs) <= self.max_gaussians - n:
            return pairs
        room = max(0, self.max_gaussians - n)
        width = (means[pairs[:, 0]] - means[pairs[:, 1]]).norm(dim=-1)
        return pairs[torch.argsort(width, descending=True, stable=True)[:room]]

    def _midpoint_rows(self, gaussians: Gaussians, pairs: torch.Tensor) -> dict:
        """Parameter rows of the new Gaussians between ``pairs`` (P,2), projected on the first one's plane."""
        params = {k: v.detach() for k, v in gaussians.params.items()}
        a, b = pairs[:, 0], pairs[:, 1]
        index = self.neighbours.index
        normal = local_geometry(params["means"], index, self.scene_radius, self.knn_include_self).normals[a]
        normal = normal.to(params["means"].dtype)
        centre = neighbourhood_points(params["means"][a], params["means"][index[a]], self.knn_include_self).mean(1)
        mid = (params["means"][a] + params["means"][b]) / 2
        mid = mid - ((mid - centre) * normal).sum(-1, keepdim=True) * normal
        rows = {k: v[a].clone() for k, v in params.items()}
        rows["means"] = mid
        rows["sh_dc"] = (params["sh_dc"][a] + params["sh_dc"][b]) / 2
        rows["sh_rest"] = (params["sh_rest"][a] + params["sh_rest"][b]) / 2
        opacity = (torch.sigmoid(params["opacity_logits"][a]) + torch.sigmoid(params["opacity_logits"][b])) / 2
        rows["opacity_logits"] = torch.logit(opacity.clamp(1e-6, 1 - 1e-6))
        rows["quats"] = torch.zeros_like(rows["quats"])
        rows["quats"][:, 0] = 1.0
        rows["log_scales"] = rows["log_scales"] - math.log(2.0) * self._in_plane(rows["frame"], normal,
                                                                                  rows["log_scales"].shape[1])
        return rows

    @staticmethod
    def _in_plane(frame: torch.Tensor, normal: torch.Tensor, dims: int) -> torch.Tensor:
        """(P, dims) 1 for the scale axes in the local plane, 0 for the one along ``normal`` (3D only)."""
        if dims == 2:
            return torch.ones(len(frame), 2, dtype=frame.dtype)
        along = (frame * normal[:, :, None].to(frame.dtype)).sum(1).abs().argmax(-1)
        return 1.0 - torch.nn.functional.one_hot(along, 3).to(frame.dtype)
