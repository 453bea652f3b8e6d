"""SuGaR's coarse-stage regularisers as loss terms (docs/methods/sugar.md §3, §5), declared in configs/loss_terms/:

- ``sugar_sdf``  — SuGaR's "SDF estimation" loss (``estimation_factor`` 0.2), parameter ``mode``:
  ``density`` (``coarse_density.py``, the default) or ``sdf`` (``coarse_sdf.py``);
- ``sugar_normal`` — SuGaR's "better normal" loss (``normal_factor`` 0.2).

Both read ``state["gaussians"]`` and, when the method keeps one, ``state["knn"]``: the (N, K) indices
of every Gaussian's K nearest centres, itself included (SuGaR K = 16, refreshed on SuGaR's schedule by
`gsbench.methods.sugar`); without it the kNN of the current centres is computed (`knn_indices`).
Surfels (two scales) are treated as 3D Gaussians whose third scale is 0 (then clamped, below).

**Samples** (drawn once per step and shared by the two terms through ``state["sugar_samples"]``):
``num_samples`` Gaussians g chosen uniformly with replacement among the visible ones (radii > 0; in
``sdf`` mode also "close to the surface": |D(π(μ)) − z(μ)| < 2·σ_view, σ_view = ‖s ⊙ (Rᵀ v̂)‖ with v̂
the unit direction from μ to the camera), and x = μ_g + R_g (1.5·s_g ⊙ ε), ε ~ N(0, I) from torch's
global RNG; x carries gradients to μ_g, R_g, s_g.

**Density at x** over the neighbours j of g: d(x) = Σ_j κ·o_j·exp(−½‖diag(1/s_j) R_jᵀ (x − μ_j)‖²),
the squared norm clamped to [0, 1e8] and s_j to >= 1e-8 (docs/methods/sugar.md §3.5, §5); κ = 1 in ``density`` mode, 1/K in
``sdf`` mode. β(x) = mean_j min(s_j). n_g = the axis of g's smallest scale.

- ``density`` mode: f̂ = ⟨x − μ_g, n_g⟩, target d* = exp(−½ f̂²/β²) (exponent clamped at 1e8 like the
  Mahalanobis term), loss = mean |d(x) − d*(x)|. d is the raw sum: SuGaR's ``get_field_values`` stores
  ``fields['density']`` before its d >= 1 normalisation.
- ``sdf`` mode: d̄ = d / max(stopgrad(d), 1) (value 1, gradient 1/d where d >= 1); ideal SDF
  f = β·sqrt(max(−2·log(max(d̄, 1e-16)), 1e-12)); f̂ = D(π(x)) − z(x) on the rendered depth map
  D = Σ wᵢzᵢ + T·z_max (our expected depth × alpha, plus the farthest centre depth as background, as
  SuGaR renders it; bilinear, border padding), only for samples with z > ``near``; loss =
  mean(min(|f − |f̂|| / (extent/10), 10·extent)). The 1e-12 floor under the square root is ours: at
  d̄ = 1 the square root's derivative is infinite and SuGaR's gradient would be too.

**Normal loss**: neighbours' normals n_j flipped to agree with n_g (sign detached); weights
w_j = stopgrad(κ·o_j·G_j(x)) · stopgrad|⟨x − μ_j, n_j⟩| / max(stopgrad min(s_j), 1e-6)², normalised
ŵ_j = w_j / max(Σ_k w_k, 1e-6); loss = mean ‖n_g − Σ_j ŵ_j n_j‖². The weights carry no gradient, the
normals do (SuGaR ``sdf_better_normal_gradient_through_normal_only``).

With no visible (or, in ``sdf`` mode, no close-to-surface / in-front) sample a term is 0.

**Implementation**: the per-pair work, the M×K neighbour terms o_j·G_j(x) and the normal loss's
Σ_j ŵ_j n_j, runs in the fused C++/OpenMP kernels of `gsbench.methods.sugar_field` (``neighbour_field``,
``neighbour_normals``: float64 arithmetic, gradients bitwise the same for any thread count);
``GSBENCH_SUGAR_FIELD=reference`` selects its PyTorch reference, the same formulas with autograd. Rows of
per-Gaussian tensors are gathered with ``index_select`` (`rows`), whose backward (an index_add) is much
cheaper on the CPU than advanced indexing's index_put.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from gsbench.errors import ConfigError
from gsbench.geometry.neighbours import nearest_other, rows
from gsbench.losses.terms import Batch, loss_term
from gsbench.methods.sugar_field import neighbour_field, neighbour_normals
from gsbench.raster.payload import quat_to_rotmat
from gsbench.raster.types import RenderOutput

MODES = ("density", "sdf")
KNN_K = 16  # SuGaR regularity_knn, itself included (docs/methods/sugar.md §3.3)
NUM_SAMPLES = 10_000  # samples per step (SuGaR: 1 000 000; why fewer: gsbench.methods.sugar)
SAMPLE_SCALE = 1.5  # sdf_sampling_scale_factor (docs/methods/sugar.md §3.4)
SURFACE_SIGMAS = 2.0  # close_gaussian_threshold, sdf mode (docs/methods/sugar.md §3.4)
MAHALANOBIS_MAX = 1e8  # docs/methods/sugar.md §5
SCALE_MIN = 1e-8  # docs/methods/sugar.md §5: 1/s with s >= 1e-8
DENSITY_MIN = 1e-16  # docs/methods/sugar.md §5: log(max(d, 1e-16))
SQRT_MIN = 1e-12  # ours: sqrt(max(−2 log d̄, 1e-12)) keeps the SDF gradient finite at d̄ = 1
NORMAL_SCALE_MIN = 1e-6  # docs/methods/sugar.md §5: min-scale clamp in the normal weights
WEIGHT_SUM_MIN = 1e-6  # docs/methods/sugar.md §5: weight-sum clamp in the normal weights
SDF_NORMALISER = 10.0  # |f − |f̂|| / (extent / 10), clamped at 10·extent (docs/methods/sugar.md §3.7)


def knn_indices(means: torch.Tensor, k: int = KNN_K) -> torch.Tensor:
    """(N, min(k, N)) int64 indices of each centre's nearest centres, itself first, as SuGaR's pytorch3d
    ``knn_points`` of the points against themselves (`gsbench.geometry.neighbours.nearest_other` for the others)."""
    points = means.detach().cpu().numpy().astype(np.float64)
    if int(k) < 1 or len(points) == 0:
        return torch.zeros((len(points), 0), dtype=torch.int64)
    others = nearest_other(points, int(k) - 1)
    return torch.as_tensor(np.concatenate([np.arange(len(points))[:, None], others], 1), dtype=torch.int64)


def check_mode(mode: str) -> str:
    """``mode`` if it is ``density`` or ``sdf``, else a ConfigError naming ``method.regularizer``."""
    if mode not in MODES:
        raise ConfigError(f"SuGaR regulariser mode must be one of {MODES} (method.regularizer), got {mode!r}")
    return mode


def check_samples(num_samples) -> int:
    """``num_samples`` as an int >= 1, else a ConfigError naming ``method.num_samples``."""
    if int(num_samples) < 1:
        raise ConfigError(f"SuGaR needs num_samples >= 1 (method.num_samples), got {num_samples}")
    return int(num_samples)


@dataclass
class GaussianFrames:
    """Activated parameters the field needs: means (N,3), rotations R (N,3,3), scales s (N,3) clamped
    at >= 1e-8, opacities (N,), normals n (N,3) = the smallest-scale axis."""

    means: torch.Tensor
    rotations: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    normals: torch.Tensor

    @classmethod
    def of(cls, gaussians) -> GaussianFrames:
        scales = gaussians.scales
        if scales.shape[1] == 2:  # a surfel: a 3D Gaussian with zero thickness
            scales = torch.cat([scales, torch.zeros_like(scales[:, :1])], 1)
        scales = scales.clamp(min=SCALE_MIN)
        rotations = quat_to_rotmat(gaussians.quats)
        axis = scales.detach().argmin(-1)
        normals = rotations.gather(2, axis[:, None, None].expand(-1, 3, 1)).squeeze(-1)
        return cls(gaussians.means, rotations, scales, gaussians.opacities, normals)

    def view_sigma(self, ids: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
        """‖s ⊙ (Rᵀ v)‖: the standard deviation of Gaussians ``ids`` along unit ``directions`` (…,3)."""
        local = torch.einsum("...ji,...j->...i", self.rotations[ids], directions)
        return (self.scales[ids] * local).norm(dim=-1)

    def min_scales(self) -> torch.Tensor:
        """(N,) the smallest scale of every Gaussian."""
        return self.scales.min(-1).values


@dataclass
class SampleField:
    """Samples x (M,3) drawn in Gaussians g (M,), their neighbours idx = kNN[g] (M,K) and the neighbour
    terms o_j·G_j(x) (M,K) (module docstring, without κ; `gsbench.methods.sugar_field.neighbour_field`)."""

    frames: GaussianFrames
    points: torch.Tensor
    source: torch.Tensor
    neighbours: torch.Tensor
    contributions: torch.Tensor

    @classmethod
    def at(cls, frames: GaussianFrames, points: torch.Tensor, source: torch.Tensor, knn: torch.Tensor) -> SampleField:
        idx = rows(knn, source)
        contributions = neighbour_field(points, frames.means, frames.rotations, frames.scales, frames.opacities, idx,
                                        MAHALANOBIS_MAX)
        return cls(frames, points, source, idx, contributions)

    def beta(self) -> torch.Tensor:
        """β (M,) = mean over the neighbours of their smallest scale (``beta_mode = 'average'``)."""
        return rows(self.frames.min_scales(), self.neighbours).mean(-1)


def _gaussians(state: Mapping, term: str):
    if "gaussians" not in state:
        raise ConfigError(f"loss term '{term}' needs the Gaussians in state['gaussians']; this method does not "
                          f"provide them, so remove losses.{term} or set its weight to 0")
    return state["gaussians"]


def _knn(state: Mapping, n: int) -> torch.Tensor:
    """The method's kNN (``state['knn']``), or the current centres' when it keeps none."""
    knn = state.get("knn")
    if knn is None:
        return knn_indices(state["gaussians"].means)
    if knn.shape[0] != n:
        raise ConfigError(f"state['knn'] has {knn.shape[0]} rows for {n} Gaussians; the method must refresh its "
                          "kNN after every change of the Gaussian count")
    return knn


def camera_points(camera, points: torch.Tensor) -> torch.Tensor:
    """``points`` (M,3) in the camera frame, x_c = R x + t."""
    R = torch.as_tensor(camera.R, dtype=points.dtype)
    t = torch.as_tensor(camera.t, dtype=points.dtype)
    return points @ R.T + t


def depth_map(render: RenderOutput, camera, means: torch.Tensor) -> torch.Tensor:
    """SuGaR's sdf-mode depth D = Σ wᵢzᵢ + T·z_max (H,W): expected depth × alpha plus the farthest centre
    camera depth (detached) as background; differentiable through ``depth`` and ``alpha``."""
    z_max = camera_points(camera, means.detach())[:, 2].max()
    return render.depth * render.alpha + (1.0 - render.alpha) * z_max


def sample_depth(depth: torch.Tensor, camera, cam_points: torch.Tensor) -> torch.Tensor:
    """D (M,) at the projections of camera-frame ``cam_points`` with z > 0, bilinear, border padding.

    Pixel (i, j) is centred at (i + 0.5, j + 0.5) (`gsbench.data.camera`), which is ``grid_sample``'s
    ``align_corners=False`` convention with x_norm = 2u/W − 1.
    """
    z = cam_points[:, 2]
    u = camera.fx * cam_points[:, 0] / z + camera.cx
    v = camera.fy * cam_points[:, 1] / z + camera.cy
    grid = torch.stack([2.0 * u / camera.width - 1.0, 2.0 * v / camera.height - 1.0], -1).to(depth.dtype)
    values = F.grid_sample(depth[None, None], grid[None, :, None, :], mode="bilinear", padding_mode="border",
                           align_corners=False)
    return values[0, 0, :, 0]


def _sampling_mask(render: RenderOutput, batch: Batch, frames: GaussianFrames, mode: str) -> torch.Tensor:
    """Visible Gaussians; in ``sdf`` mode only those within 2·σ_view of the rendered depth (no gradient)."""
    n = frames.means.shape[0]
    visible = render.visible if render.visible is not None else torch.ones(n, dtype=torch.bool)
    if mode == "density":
        return visible
    with torch.no_grad():
        means = frames.means.detach()
        to_camera = F.normalize(torch.as_tensor(batch.camera.center, dtype=means.dtype) - means, dim=-1)
        sigma = frames.view_sigma(torch.arange(n), to_camera)
        cam = camera_points(batch.camera, means)
        close = torch.zeros(n, dtype=torch.bool)
        front = cam[:, 2] > 0
        map_z = sample_depth(depth_map(render, batch.camera, means).detach(), batch.camera, cam[front])
        close[front] = (map_z - cam[front, 2]).abs() < SURFACE_SIGMAS * sigma[front]
        return visible & close


def draw_samples(frames: GaussianFrames, mask: torch.Tensor, num_samples: int):
    """(x (M,3), g (M,)): g uniform with replacement among ``mask``; x = μ_g + R_g (1.5·s_g ⊙ ε)."""
    candidates = torch.nonzero(mask).flatten()
    if candidates.numel() == 0:
        return None
    source = candidates[torch.randint(len(candidates), (num_samples,))]
    eps = torch.randn(num_samples, 3, dtype=frames.means.dtype)
    scaled = SAMPLE_SCALE * rows(frames.scales, source) * eps
    offsets = torch.einsum("mij,mj->mi", rows(frames.rotations, source), scaled)
    return rows(frames.means, source) + offsets, source


def step_samples(render: RenderOutput, batch: Batch, state: dict, mode: str, num_samples: int,
                 term: str) -> SampleField | None:
    """This step's `SampleField`, drawn by the first SuGaR term that asks and kept in ``state``."""
    key = (mode, num_samples)
    cached = state.get("sugar_samples")
    if cached is not None and cached[0] is render and cached[1] == key:
        return cached[2]
    gaussians = _gaussians(state, term)
    frames = GaussianFrames.of(gaussians)
    drawn = draw_samples(frames, _sampling_mask(render, batch, frames, mode), num_samples)
    field = None if drawn is None else SampleField.at(frames, *drawn, _knn(state, len(gaussians)))
    state["sugar_samples"] = (render, key, field)
    return field


def _zero(state: Mapping) -> torch.Tensor:
    """A 0 that is part of the graph (a term without samples)."""
    return state["gaussians"].means[:0].sum()


def density_factor(mode: str, k: int) -> float:
    """κ: 1 in ``density`` mode, 1/K in ``sdf`` mode (SuGaR: "should be equal to 1 / regularity_knn")."""
    return 1.0 if check_mode(mode) == "density" else 1.0 / k


def density_loss(field: SampleField) -> torch.Tensor:
    """``density`` mode: mean |d(x) − exp(−½ f̂²/β²)|, f̂ = ⟨x − μ_g, n_g⟩, κ = 1 (module docstring)."""
    frames = field.frames
    estimate = ((field.points - rows(frames.means, field.source)) * rows(frames.normals, field.source)).sum(-1)
    exponent = (estimate**2 / field.beta() ** 2).clamp(max=MAHALANOBIS_MAX)
    return (field.contributions.sum(-1) - torch.exp(-0.5 * exponent)).abs().mean()


def sdf_loss(field: SampleField, depth: torch.Tensor, camera, extent: float, near: float) -> torch.Tensor | None:
    """``sdf`` mode: mean(min(|f − |D(π(x)) − z(x)|| / (extent/10), 10·extent)) over the samples with
    z > ``near`` (module docstring); None when there is none. ``depth`` is D (`depth_map`)."""
    density = field.contributions.sum(-1) * density_factor("sdf", field.neighbours.shape[1])
    density = density / density.detach().clamp(min=1.0)
    sdf = field.beta() * torch.sqrt((-2.0 * torch.log(density.clamp(min=DENSITY_MIN))).clamp(min=SQRT_MIN))
    cam = camera_points(camera, field.points)
    front = cam[:, 2] > max(float(near), 0.0)
    if not bool(front.any()):
        return None
    estimate = sample_depth(depth, camera, cam[front]) - cam[front, 2]
    error = (sdf[front] - estimate.abs()).abs() / (extent / SDF_NORMALISER)
    return error.clamp(max=SDF_NORMALISER * extent).mean()


def normal_loss(field: SampleField, kappa: float) -> torch.Tensor:
    """mean ‖n_g − Σ_j ŵ_j n_j‖² with SuGaR's detached weights ŵ (module docstring, "Normal loss")."""
    frames = field.frames
    average = neighbour_normals(frames.normals, field.points, frames.means, frames.min_scales(), field.contributions,
                                field.source, field.neighbours, kappa, NORMAL_SCALE_MIN, WEIGHT_SUM_MIN)
    return ((rows(frames.normals, field.source) - average) ** 2).sum(-1).mean()


def sdf_term(render: RenderOutput, batch: Batch, state: dict, mode: str = "density", num_samples: int = NUM_SAMPLES,
             extent: float = 1.0, near: float = 0.0) -> torch.Tensor:
    """SuGaR SDF-estimation loss: `density_loss` (``density``) or `sdf_loss` (``sdf``) on this step's samples.

    ``extent``: 3DGS ``cameras_extent`` (the sdf-mode normaliser); ``near``: the znear of the sdf-mode
    sample filter, in scene units.
    """
    field = step_samples(render, batch, state, check_mode(mode), check_samples(num_samples), "sugar_sdf")
    if field is None:
        return _zero(state)
    if mode == "density":
        return density_loss(field)
    loss = sdf_loss(field, depth_map(render, batch.camera, field.frames.means), batch.camera, extent, near)
    return _zero(state) if loss is None else loss


def normal_term(render: RenderOutput, batch: Batch, state: dict, mode: str = "density",
                num_samples: int = NUM_SAMPLES) -> torch.Tensor:
    """SuGaR "better normal" loss (`normal_loss`) on this step's samples."""
    field = step_samples(render, batch, state, check_mode(mode), check_samples(num_samples), "sugar_normal")
    if field is None:
        return _zero(state)
    return normal_loss(field, density_factor(mode, field.neighbours.shape[1]))


def _sdf_requires(params: Mapping) -> frozenset:
    return frozenset({"depth", "alpha"} if check_mode(params["mode"]) == "sdf" else ())


SUGAR_SDF = loss_term("sugar_sdf", sdf_term, params={"mode": "density", "num_samples": NUM_SAMPLES, "extent": 1.0, "near": 0.0},
                      requires_fn=_sdf_requires)
SUGAR_NORMAL = loss_term("sugar_normal", normal_term, params={"mode": "density", "num_samples": NUM_SAMPLES})
