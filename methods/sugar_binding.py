"""SuGaR's refinement: Gaussians bound to the triangles of the coarse mesh (docs/methods/sugar.md §6).

Read from the public code (Anttwo/SuGaR, ``sugar_scene/sugar_model.py``, class ``SuGaR`` in its bound mode):

- each triangle (v₀, v₁, v₂) carries n Gaussians at fixed barycentric coordinates b (`BARYCENTRIC`); a
  Gaussian's centre is μ = Σ_k b_k v_k, so it moves with the vertices, which are the learned parameters;
- its frame: the face normal n = normalize((v₁ − v₀) × (v₂ − v₀)), the in-plane base e₁ = normalize(v₀ − v₁),
  e₂ = normalize(n × e₁); its in-plane rotation is a complex number z = (a, b), normalised, giving the axes
  r₁ = a e₁ + b e₂, r₂ = −b e₁ + a e₂ (a rotation by arg z about n); the rotation matrix has columns
  [n, r₁, r₂] (`bound_frames`);
- its scales are [t, exp(σ₁), exp(σ₂)] with the thin axis along n: t a fixed thickness (SuGaR:
  the cameras' extent / 10⁶), σ learned, initially log(r · shortest edge) with r the factor of `BARYCENTRIC`.

`bound_gaussians` turns (vertices, faces, per-Gaussian parameters) into the rasterizer's Gaussians,
differentiably (the quaternion by `gsbench.geometry.rotations.rotmat_to_quat`).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from gsbench.errors import ConfigError
from gsbench.geometry.rotations import rotmat_to_quat
from gsbench.mesh import MeshError

# n Gaussians per triangle -> (barycentric coordinates (n, 3), radius factor r) (sugar_model.py, SuGaR.__init__)
BARYCENTRIC = {
    1: ([[1 / 3, 1 / 3, 1 / 3]], 1 / (2 * math.sqrt(3))),
    3: ([[1 / 2, 1 / 4, 1 / 4], [1 / 4, 1 / 2, 1 / 4], [1 / 4, 1 / 4, 1 / 2]], 1 / (2 * (math.sqrt(3) + 1))),
    4: ([[1 / 3, 1 / 3, 1 / 3], [2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]], 1 / (4 * math.sqrt(3))),
    6: ([[2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3],
         [1 / 6, 5 / 12, 5 / 12], [5 / 12, 1 / 6, 5 / 12], [5 / 12, 5 / 12, 1 / 6]], 1 / (4 + 2 * math.sqrt(3))),
}
MIN_SCALE = 1e-7  # SuGaR's floor of the initial in-plane scale
DEGENERATE = 1e-12  # relative: a face whose |cross| is below this x its longest edge² has no plane


def barycentric(per_triangle: int, dtype=torch.float64) -> tuple[torch.Tensor, float]:
    """(coordinates (n, 3), radius factor) of ``per_triangle`` Gaussians per triangle (`BARYCENTRIC`)."""
    if per_triangle not in BARYCENTRIC:
        raise ConfigError(f"method.refine_gaussians_per_triangle must be one of {sorted(BARYCENTRIC)} (SuGaR's placements), "
                          f"got {per_triangle}")
    coords, factor = BARYCENTRIC[per_triangle]
    return torch.tensor(coords, dtype=dtype), factor


def usable_faces(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(F,) bool: the faces with a plane (not zero-area, not degenerate to float precision: |(v₁ − v₀) × (v₂ − v₀)|
    > 1e-12 x the longest edge²) and finite vertices. An empty mesh, or one with no usable face, is a
    MeshError (the coarse mesh has nothing to bind Gaussians to)."""
    if len(faces) == 0:
        raise MeshError("SuGaR refinement: the coarse mesh is empty; nothing to bind Gaussians to (the coarse stage "
                        "found no surface: check its Poisson mesh, or train longer)")
    v = vertices[faces]
    cross = torch.linalg.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]).norm(dim=-1)
    longest = torch.stack([(v[:, 1] - v[:, 0]).norm(dim=-1), (v[:, 2] - v[:, 1]).norm(dim=-1),
                           (v[:, 0] - v[:, 2]).norm(dim=-1)], -1).max(-1).values
    ok = torch.isfinite(v).all(-1).all(-1) & (cross > DEGENERATE * longest**2)
    if not bool(ok.any()):
        raise MeshError(f"SuGaR refinement: none of the coarse mesh's {len(faces)} faces has a plane (all zero-area or "
                        "non-finite); nothing to bind Gaussians to")
    return ok


def initial_log_scales(vertices: torch.Tensor, faces: torch.Tensor, per_triangle: int) -> torch.Tensor:
    """(F·n, 2) log of SuGaR's initial in-plane scales: r x the face's shortest edge (at least `MIN_SCALE`)."""
    _, factor = barycentric(per_triangle, vertices.dtype)
    v = vertices[faces]
    shortest = torch.stack([(v[:, 1] - v[:, 0]).norm(dim=-1), (v[:, 2] - v[:, 1]).norm(dim=-1),
                            (v[:, 0] - v[:, 2]).norm(dim=-1)], -1).min(-1).values
    scale = (factor * shortest).clamp_min(MIN_SCALE)
    return torch.log(scale).repeat_interleave(per_triangle)[:, None].expand(-1, 2).clone()


def bound_frames(vertices: torch.Tensor, faces: torch.Tensor, rotation: torch.Tensor, per_triangle: int) -> torch.Tensor:
    """(F·n, 3, 3) rotation matrices, columns [n, r₁, r₂] (module docstring); ``rotation`` (F·n, 2) the complex
    numbers (a, b), normalised here."""
    v = vertices[faces]
    normal = F.normalize(torch.linalg.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), dim=-1)
    e1 = F.normalize(v[:, 0] - v[:, 1], dim=-1)
    e2 = F.normalize(torch.linalg.cross(normal, e1), dim=-1)
    normal, e1, e2 = (x.repeat_interleave(per_triangle, 0) for x in (normal, e1, e2))
    z = F.normalize(rotation, dim=-1)
    a, b = z[:, :1], z[:, 1:]
    return torch.stack([normal, a * e1 + b * e2, -b * e1 + a * e2], -1)


def bound_gaussians(vertices: torch.Tensor, faces: torch.Tensor, per_triangle: int, log_scales: torch.Tensor,
                    rotation: torch.Tensor, thickness: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(means (F·n, 3), scales (F·n, 3), quaternions (F·n, 4)) of the Gaussians bound to ``faces`` of ``vertices``
    (module docstring), in the order face-major (a face's n Gaussians together)."""
    coords, _ = barycentric(per_triangle, vertices.dtype)
    means = torch.einsum("gk,fkc->fgc", coords, vertices[faces]).reshape(-1, 3)
    scales = torch.cat([torch.full_like(log_scales[:, :1], thickness), torch.exp(log_scales)], -1)
    frames = bound_frames(vertices, faces, rotation, per_triangle)
    quats = rotmat_to_quat(frames.double()).to(vertices.dtype)
    return means, scales, quats
