"""Arbitrary rays through 2D Gaussian surfels: the dense PyTorch reference of the ray tracer the
transparent-object method bends rays with (docs/methods/rt2dgs.md §3). Every (ray, surfel) pair is an (R, N)
tensor, as `gsbench.raster.reference` does for pixels; autograd gives the gradients.

For a ray x(t) = a + t d (|d| = 1) and a surfel (centre μ, axes t_u, t_v, t_w, scales s_u, s_v, opacity o):
t_i = ((μ − a)·t_w)/(d·t_w), skipped if |d·t_w| < 1e-12 or t_i <= ``near``; ρ = u² + v² with u = (x(t_i) − μ)·t_u
/ s_u, v likewise, skipped beyond ρ > 9; α_i = min(0.99, o·exp(−ρ/2)), skipped below 1/255; w_i = α_i Π_{j before
i} (1 − α_j) front to back in t (ties in index order); the pair's normal is −sign(d·t_w) t_w. Unlike the
rasterizer: no screen-space low-pass term (there is no pixel) and no early stop at transmittance 1e-4.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from gsbench.errors import import_open3d
from gsbench.raster.reference_projection import ALPHA_MAX, ALPHA_MIN, quat_to_rotmat

SURFEL_CUTOFF_SQ = 9.0  # ρ beyond which a pair is skipped (3σ, the rasterizer's surfel box)
PARALLEL = 1e-12  # |d·t_w| below which the ray runs in the surfel's plane
GROW = 1.01  # the candidate squares are this much larger than 3σ (float32 casting, the shifts below)
SHIFT_STEP, SHIFT_LEVELS = 2e-6, 1024  # square i lies (i mod 1024 + 1) x 2e-6 off its surfel's plane


@dataclass
class SurfelTrace:
    """What rays see through the surfels: ``features`` (R, F) = Σ w_i f_i, ``alpha`` (R,) = Σ w_i,
    ``depth`` (R,) = Σ w_i t_i (not divided by alpha), ``normal`` (R, 3) = Σ w_i n_i (facing the ray),
    and the pairs, sorted by ray then t: ``ray``, ``surfel`` (P,) int64, their ``weights`` (P,, 0 for skipped
    pairs), hit parameters ``t`` (P,) and facing normals ``pair_normal`` (P, 3)."""

    features: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    normal: torch.Tensor
    ray: torch.Tensor
    surfel: torch.Tensor
    weights: torch.Tensor
    t: torch.Tensor
    pair_normal: torch.Tensor


def surfel_axes(quats: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) rotations of the surfels, columns t_u, t_v, t_w (the normal)."""
    return quat_to_rotmat(torch.nn.functional.normalize(quats, dim=-1))


def pair_hits(origins: torch.Tensor, directions: torch.Tensor, means: torch.Tensor, axes: torch.Tensor,
              scales: torch.Tensor, opacities: torch.Tensor, near: float = 0.0):
    """(t, alpha, normal, ok) of aligned pairs: ray k of ``origins``/``directions`` (P, 3) with surfel k of
    the other arguments (P, ...) (module docstring); ``directions`` unit; ``axes`` (P, 3, 3) `surfel_axes`;
    ``scales`` (P, 2) or (P, 3)."""
    tu, tv, tw = axes[..., 0], axes[..., 1], axes[..., 2]
    d_dot_w = (directions * tw).sum(-1)
    offset = means - origins  # μ − a
    ok = d_dot_w.abs() >= PARALLEL
    t = (offset * tw).sum(-1) / torch.where(ok, d_dot_w, torch.ones_like(d_dot_w))
    ok = ok & (t > near)
    local = directions * t[:, None] - offset  # x(t) − μ
    u = (local * tu).sum(-1) / scales[:, 0]
    v = (local * tv).sum(-1) / scales[:, 1]
    rho = u * u + v * v
    ok = ok & (rho <= SURFEL_CUTOFF_SQ)
    alpha = torch.clamp(opacities * torch.exp(-0.5 * torch.where(ok, rho, torch.zeros_like(rho))), max=ALPHA_MAX)
    ok = ok & (alpha >= ALPHA_MIN)
    normal = -torch.sign(d_dot_w).detach()[:, None] * tw
    return t, torch.where(ok, alpha, torch.zeros_like(alpha)), normal, ok


def trace_pairs(origins: torch.Tensor, directions: torch.Tensor, means: torch.Tensor, quats: torch.Tensor,
                scales: torch.Tensor, opacities: torch.Tensor, features: torch.Tensor, ray: torch.Tensor,
                surfel: torch.Tensor, near: float = 0.0) -> SurfelTrace:
    """Blend ``features`` (N, F) along each of the R rays over the candidate pairs (``ray``, ``surfel``) (P,):
    every pair that can contribute must be listed once (module docstring); the others are skipped. Pairs
    are blended front to back per ray: the transmittance before a pair is exp of the sum of log(1 − α) of
    the ray's earlier pairs (α ≤ 0.99, so the logarithm is finite), accumulated in float64."""
    t, alpha, normal, ok = pair_hits(origins[ray], directions[ray], means[surfel], surfel_axes(quats)[surfel],
                                     scales[surfel], opacities[surfel], near)
    key = torch.where(ok, t, torch.full_like(t, float("inf"))).detach().double()
    order = torch.from_numpy(np.lexsort((surfel.numpy(), key.numpy(), ray.numpy())))  # by ray, then t, then index
    ray, surfel, t, alpha, normal, ok = ray[order], surfel[order], t[order], alpha[order], normal[order], ok[order]
    log_through = torch.log1p(-alpha.double())
    running = torch.cumsum(log_through, 0) - log_through  # exclusive, over all pairs
    first = torch.ones_like(ray, dtype=torch.bool)
    first[1:] = ray[1:] != ray[:-1]
    start = torch.cummax(torch.where(first, torch.arange(len(ray)), torch.zeros_like(ray)), 0).values
    weights = (alpha.double() * torch.exp(running - running[start])).to(alpha.dtype)
    rays = len(origins)
    zero = torch.zeros(rays, dtype=alpha.dtype)
    return SurfelTrace(
        features=torch.zeros(rays, features.shape[1], dtype=features.dtype).index_add(0, ray, weights[:, None] * features[surfel]),
        alpha=zero.index_add(0, ray, weights),
        depth=zero.index_add(0, ray, weights * torch.where(ok, t, torch.zeros_like(t))),
        normal=torch.zeros(rays, 3, dtype=alpha.dtype).index_add(0, ray, weights[:, None] * normal),
        ray=ray, surfel=surfel, weights=weights, t=torch.where(ok, t, torch.zeros_like(t)), pair_normal=normal)


def trace(origins: torch.Tensor, directions: torch.Tensor, means: torch.Tensor, quats: torch.Tensor,
          scales: torch.Tensor, opacities: torch.Tensor, features: torch.Tensor, near: float = 0.0) -> SurfelTrace:
    """The dense reference: `trace_pairs` over every (ray, surfel) pair."""
    ray, surfel = torch.meshgrid(torch.arange(len(origins)), torch.arange(len(means)), indexing="ij")
    return trace_pairs(origins, directions, means, quats, scales, opacities, features, ray.reshape(-1), surfel.reshape(-1), near)


class CandidateIndex:
    """Open3D's ray-casting BVH (Embree) of the surfels' 3σ squares (two triangles each), built once and
    queried by `pairs` for any number of ray batches."""

    def __init__(self, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor):
        self.count = len(means)
        if self.count == 0:
            return
        o3d = import_open3d()
        self._o3d = o3d
        with torch.no_grad():
            rot = surfel_axes(quats.detach()).double()
            half_u = 3 * scales.detach()[:, :1].double() * rot[..., 0] * GROW
            half_v = 3 * scales.detach()[:, 1:2].double() * rot[..., 1] * GROW
            # open3d lists one hit per distance along a ray (coplanar squares, e.g. a wall tiled by surfels,
            # would give one candidate): each square is shifted off its plane by its own few micrometres
            shift = ((torch.arange(self.count) % SHIFT_LEVELS + 1) * SHIFT_STEP).double()[:, None] * rot[..., 2]
            centre = means.detach().double() + shift
            corners = torch.stack([centre - half_u - half_v, centre + half_u - half_v, centre + half_u + half_v,
                                   centre - half_u + half_v], 1).reshape(-1, 3)
            base = 4 * torch.arange(self.count)
            triangles = torch.stack([torch.stack([base, base + 1, base + 2], 1), torch.stack([base, base + 2, base + 3], 1)],
                                    1).reshape(-1, 3)
            self.scene = o3d.t.geometry.RaycastingScene()
            self.scene.add_triangles(o3d.core.Tensor(corners.float().numpy()),
                                     o3d.core.Tensor(triangles.numpy().astype(np.uint32)))

    def pairs(self, origins: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(ray, surfel) of every pair whose ray crosses the surfel's square, each listed once."""
        if len(origins) == 0 or self.count == 0:  # open3d's list_intersections crashes on zero rays
            empty = torch.zeros(0, dtype=torch.int64)
            return empty, empty
        rays = torch.cat([origins.detach(), directions.detach()], 1).float().numpy()
        hits = self.scene.list_intersections(self._o3d.core.Tensor(rays))
        ray = hits["ray_ids"].numpy().astype(np.int64)
        surfel = hits["primitive_ids"].numpy().astype(np.int64) // 2
        # a ray through a square's diagonal hits both its triangles, one after the other in its list
        fresh = np.ones(len(ray), dtype=bool)
        fresh[1:] = (ray[1:] != ray[:-1]) | (surfel[1:] != surfel[:-1])
        return torch.from_numpy(ray[fresh]), torch.from_numpy(surfel[fresh])


def candidate_pairs(origins: torch.Tensor, directions: torch.Tensor, means: torch.Tensor, quats: torch.Tensor,
                    scales: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(ray, surfel) of every pair whose ray crosses the surfel's 3σ square (the region ρ ≤ 9 lies inside it),
    found by open3d's ray casting (`CandidateIndex`): the pairs `trace_pairs` needs, without the (R, N)
    grid. Each pair is listed once. open3d reports one hit per distance along a ray, so each square is
    shifted along its normal by its own amount (`SHIFT_STEP`); a ray grazing a square could then miss its
    edge by shift / tan(angle), which the 1% margin (`GROW`) covers down to about 0.1° at the largest
    shift for a surfel of scale 0.1."""
    return CandidateIndex(means, quats, scales).pairs(origins, directions)
