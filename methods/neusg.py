"""NeuSG (Chen, Li, Wang, Lee 2023, arXiv 2312.00846): 3D Gaussians and a NeuS signed distance field trained
together, each guiding the other; docs/methods/neusg.md.

- **Gaussian side** (NeuSG eq. 15): 3DGS (``ewa`` kernel, 3DGS densification) with L = L_rgb
  (0.8 L1 + 0.2 D-SSIM) + λ₃ L_s + λ₄ L_align: ``flatten`` L_s = mean min(s₁, s₂, s₃) (λ₃ = 100) pulls each
  Gaussian flat, ``sdf_align`` L_align = mean |1 − |n_wᵀ ∇f̂(μ_i)|| (λ₄ = 1) turns its shortest axis
  n_w = R e_argmin(s) towards the SDF's normal (∇f̂ = ∇f/|∇f|, held fixed: the term moves the Gaussians).
- **SDF side** (NeuSG eq. 14): the implicit scene of `gsbench.methods.neusg_field` (SDF, colour, background,
  NeuS s) with L = ``neus_rgb`` (L1 of the NeuS colour of ``rays`` random pixels of the step's view) +
  λ₁ ``eikonal`` (mean (|∇f| − 1)² at the NeuS samples, λ₁ = 0.1) + λ₂ ``sdf_points``
  (mean |f(μ_i)| over Gaussian centres, held fixed: the term moves the SDF's zero level set, λ₂ = 1).
- Each step computes both objectives (their gradients do not mix: the cross terms hold the other side
  fixed), so L = eq. 14 + eq. 15 is one backward; the NeuS batch is computed once per step by the first
  term that asks for it (`NeuSG.rays`).
- Mesh (``mesh.extractor: sdf``, NeuSG's output): marching cubes (scikit-image) of f at 0 on a grid of
  the cube around the SDF's sphere (``method.sdf_region``, `sdf_region`) with the TSDF's voxel
  (``mesh.voxel_size`` x the scene radius; the record states the grid and the region), the ``mesh.num_clusters`` largest components kept; ``tsdf`` of the Gaussians' expected depth
  stays available for comparison.
- The field's Adam groups (``field.*``) sit beside the Gaussians' in one optimizer (the densification
  strategy touches only the Gaussians' groups); lr: linear warm-up over ``field_warmup`` steps, then
  cosine decay to ``field_lr_final_ratio`` x ``field_lr`` (Neuralangelo's warm-up; docs/methods/neusg.md §3).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from skimage.measure import marching_cubes

from gsbench.config.run_config import RunConfig
from gsbench.data.camera import Scene
from gsbench.errors import ConfigError, import_open3d
from gsbench.geometry.depth import world_rays
from gsbench.losses.terms import Batch, loss_term, method_state
from gsbench.mesh import MeshError
from gsbench.mesh.cleanup import canonical_order, keep_largest_clusters, to_trimesh
from gsbench.methods.base import ADAM_EPS, GSConfig, Method, MethodInfo, _export_atomic
from gsbench.methods.neusg_field import ENCODINGS, HASH_INITIAL_LEVELS, ImplicitScene, RayBatch, level_resolutions
from gsbench.raster.reference_projection import quat_to_rotmat
from gsbench.training.optim import make_adam
from gsbench.training.trainer import scale_step

SDF_REGIONS = ("scene", "cameras", "sfm_points")  # method.sdf_region (`sdf_region`)
SFM_BOUND_STDS = 3.0  # `sdf_region` sfm_points: the radius in standard deviations of the SfM points (Neuralangelo)
MESH_CHUNK = 1 << 18  # field evaluations per batch when meshing
COARSE = 4  # fine cells per coarse cell side of the meshing grid (`sdf_volume`)


@dataclass
class NeuSGConfig(GSConfig):
    """3DGS defaults plus the implicit side (docs/methods/neusg.md §3, §5: which values are NeuSG's,
    NeuS's or Neuralangelo's, and which are this benchmark's budget). ``encoding``: the SDF's grid, ``dense``
    (`gsbench.methods.neusg_field.MultiGrid`) or ``hash`` (`HashGrid`, 2^``hash_table_log2`` rows a level); the
    hash grid's coarse-to-fine schedule adds a level every ``grid_level_step`` steps after ``grid_active_start``
    (steps of a 30 000-step run, scaled like every schedule; Neuralangelo's 5 000 of 500 000 is 300 of 30 000;
    0 = every level from the start). The three hash keys are read by the hash encoding only."""

    rays: int = 128
    coarse_samples: int = 32
    fine_samples: int = 16
    background_samples: int = 8
    grid_levels: int = 5
    grid_min_res: int = 16
    grid_max_res: int = 128
    grid_features: int = 2
    encoding: str = "dense"
    hash_table_log2: int = 19
    grid_active_start: int = 0
    grid_level_step: int = 300
    background_max_res: int = 64
    field_lr: float = 0.01
    field_lr_final_ratio: float = 0.05
    field_warmup: int = 5000
    point_batch: int = 4096
    point_min_opacity: float = 0.5
    sdf_region: str = "scene"


class NeuSG(Method):
    """Gaussians and a NeuS SDF trained together (module docstring)."""

    name = "neusg"
    Config = NeuSGConfig
    INFO = MethodInfo(primitive="3d", kernel="ewa", outputs=("rgb", "alpha", "depth"))
    MESH_EXTRACTORS = ("sdf", "tsdf")

    def __init__(self):
        super().__init__()
        self.field: ImplicitScene | None = None
        self._rays: tuple[tuple, RayBatch] | None = None

    def check_params(self) -> None:
        super().check_params()
        p = self.params
        for name in ("rays", "coarse_samples", "background_samples", "grid_levels", "grid_min_res", "grid_features",
                     "point_batch"):
            if getattr(p, name) < 1:
                raise ConfigError(f"method.{name} must be >= 1, got {getattr(p, name)}")
        if p.fine_samples < 0 or p.grid_max_res < p.grid_min_res:
            raise ConfigError(f"method.fine_samples must be >= 0 and method.grid_max_res >= grid_min_res, got "
                              f"{p.fine_samples}, {p.grid_max_res} < {p.grid_min_res}")
        if p.encoding not in ENCODINGS:
            raise ConfigError(f"method.encoding must be one of {', '.join(ENCODINGS)}, got {p.encoding!r}")
        if not 1 <= p.hash_table_log2 <= 31 or p.grid_active_start < 0 or p.grid_level_step < 0:
            raise ConfigError(f"method.hash_table_log2 must be in [1, 31] and method.grid_active_start, "
                              f"grid_level_step >= 0, got {p.hash_table_log2}, {p.grid_active_start}, "
                              f"{p.grid_level_step}")
        defaults = NeuSGConfig()
        if p.encoding == "dense":
            for name in ("hash_table_log2", "grid_active_start", "grid_level_step"):
                if getattr(p, name) != getattr(defaults, name):
                    raise ConfigError(f"method.{name} is read by the hash encoding only; fix: method.encoding=hash, "
                                      f"or leave method.{name} at {getattr(defaults, name)}")
        if p.sdf_region not in SDF_REGIONS:
            raise ConfigError(f"method.sdf_region must be one of {SDF_REGIONS}, got {p.sdf_region!r}")
        if self.cfg.train.optimizer == "visible_adam":
            raise ConfigError("neusg: train.optimizer visible_adam updates only the rows a view sees; the SDF's grids "
                              "have no such rows; fix: train.optimizer adam")

    @classmethod
    def memory_estimate(cls, cfg: RunConfig) -> dict[str, int]:
        """The base estimate plus the field's grids (float32, 4 copies: values, gradient, Adam moments; a hash level
        holds at most 2^T of its vertices) and one step's NeuS samples (5 evaluations each, ~200 float32 of
        activations and gradients)."""
        items = super().memory_estimate(cfg)
        p = cls.Config(**{k: v for k, v in cfg.method.items() if k != "name"})
        rows = 1 << p.hash_table_log2 if p.encoding == "hash" else math.inf
        resolutions = level_resolutions(p.grid_levels, p.grid_min_res, p.grid_max_res)
        vertices = sum(min((n + 1) ** 3, rows) for n in resolutions)
        items["SDF grids"] = 4 * 4 * p.grid_features * vertices
        items["NeuS samples"] = p.rays * (p.coarse_samples + p.fine_samples) * 5 * 200 * 4
        return items

    def setup(self, scene: Scene, cfg: RunConfig) -> None:
        self.configure(cfg)
        p = self.params
        centre, radius = sdf_region(scene, p.sdf_region)
        self.field = ImplicitScene(radius, cfg.seed, centre=centre, levels=p.grid_levels, min_res=p.grid_min_res,
                                   max_res=p.grid_max_res, features=p.grid_features,
                                   background_max_res=p.background_max_res, encoding=p.encoding,
                                   table_log2=p.hash_table_log2)
        super().setup(scene, cfg)

    def make_optimizer(self, gaussians) -> torch.optim.Optimizer:
        lrs = self.learning_rates()
        groups = [{"params": [param], "name": name, "lr": lrs[name]} for name, param in gaussians.params.items()
                  if param.requires_grad]
        groups += [{"params": [param], "name": f"field.{name}", "lr": self.params.field_lr}
                   for name, param in self.field.named_parameters()]
        return make_adam(groups, self.cfg.train.optimizer, ADAM_EPS)

    def update_schedules(self, step: int, scale: float) -> None:
        """The 3DGS schedules, the field's lr (linear warm-up, then cosine to ``field_lr_final_ratio``) and the hash
        grid's active levels (`active_levels`)."""
        super().update_schedules(step, scale)
        p = self.params
        if p.encoding == "hash":
            self.field.sdf.grid.set_active(active_levels(step, scale_step(p.grid_active_start, scale),
                                                         scale_step(p.grid_level_step, scale), p.grid_levels))
        warmup, total = scale_step(p.field_warmup, scale), max(self.cfg.train.iterations, 1)
        if step < warmup:
            factor = step / warmup
        else:
            progress = min((step - warmup) / max(total - warmup, 1), 1.0)
            factor = p.field_lr_final_ratio + (1 - p.field_lr_final_ratio) * 0.5 * (1 + math.cos(math.pi * progress))
        for group in self.optimizer.param_groups:
            if group["name"].startswith("field."):
                group["lr"] = p.field_lr * factor

    # ---- the terms ------------------------------------------------------------------------------
    def loss_state(self) -> dict:
        return {"gaussians": self.gaussians, "neusg": self}

    def rays(self, batch: Batch) -> tuple[RayBatch, torch.Tensor]:
        """(the NeuS render of ``rays`` random pixels of the batch's view, their GT colours), once per step:
        pixels drawn from torch's global generator (checkpointed, so a resume is bit-exact)."""
        key = (batch.step, batch.view)
        if self._rays is None or self._rays[0] != key:
            camera, p = batch.camera, self.params
            pixels = torch.randint(0, camera.width * camera.height, (p.rays,))
            rays = torch.from_numpy(world_rays(camera, pixels.numpy())).float()
            directions = F.normalize(rays[:, 3:], dim=-1)
            out = self.field.render_rays(rays[:, :3], directions, p.coarse_samples, p.fine_samples,
                                         p.background_samples, None)
            self._rays = (key, (out, batch.image.reshape(-1, 3)[pixels]))
        return self._rays[1]

    def centre_sample(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(indices, means) of up to ``point_batch`` Gaussians with opacity ≥ ``point_min_opacity`` inside the
        field's sphere, drawn from torch's global generator; empty when none qualifies."""
        g, p = self.gaussians, self.params
        means = g.means.detach()
        ok = (g.opacities.detach() >= p.point_min_opacity) & (self.field.local(means).norm(dim=-1) < self.field.radius)
        index = ok.nonzero().squeeze(1)
        if len(index) > p.point_batch:
            index = index[torch.randperm(len(index))[:p.point_batch]]
        return index, means[index]

    # ---- mesh ---------------------------------------------------------------------------------
    @torch.no_grad()
    def extract_mesh(self, scene: Scene, cfg: RunConfig, out_path) -> dict:
        """``sdf``: marching cubes of f = 0 (module docstring); ``tsdf``: the base class's."""
        self.check_extractor(cfg)
        if cfg.mesh.extractor != "sdf":
            return super().extract_mesh(scene, cfg, out_path)
        voxel = cfg.mesh.voxel_size * (1.0 if cfg.mesh.absolute else scene.radius)  # the TSDF's voxel
        mesh, grid = sdf_mesh(lambda x: self.field.sdf(x)[0], self.field.radius, voxel)
        mesh.translate(self.field.centre.double().numpy())
        mesh = canonical_order(to_trimesh(keep_largest_clusters(mesh, cfg.mesh.num_clusters)))
        _export_atomic(mesh, Path(out_path))
        region = {"centre": [round(float(c), 6) for c in self.field.centre], "radius": round(self.field.radius, 6)}
        return {"vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces)), "sdf_grid": grid,
                "sdf_region": region}

    # ---- checkpoints --------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {**super().state_dict(), "field": {k: v.detach().clone() for k, v in self.field.state_dict().items()}}

    def load_state_dict(self, state: dict) -> None:
        self.field.load_state_dict(state["field"])
        super().load_state_dict(state)


def active_levels(step: int, start: int, level_step: int, levels: int) -> int:
    """Neuralangelo's coarse-to-fine count of active levels at ``step`` (its ``set_active_levels``):
    min(L, max(`HASH_INITIAL_LEVELS`, ⌊(step − start) / level_step⌋)); every level when ``level_step`` is 0."""
    if level_step <= 0:
        return levels
    return min(levels, max(HASH_INITIAL_LEVELS, (step - start) // level_step))


def sdf_region(scene: Scene, region: str) -> tuple[np.ndarray, float]:
    """(centre, radius) of the SDF's sphere in the training frame (docs/methods/neusg.md §5.6), from what a capture
    offers, never its ground truth: ``scene``, the training frame's scene sphere (DTU's unit sphere, as IDR and
    Neuralangelo bound DTU; on TnT the cameras' extent); ``cameras`` and ``sfm_points``, the two automatic bounds
    of Neuralangelo's ``convert_data_to_json.py`` for a COLMAP capture (`bound_by_cameras`,
    `bound_by_sfm_points`). The training frame is the COLMAP frame shifted (and on DTU scaled), so each sphere is
    the one found there. A scene without SfM points is a ConfigError
    naming the fix."""
    if region == "scene":
        return np.zeros(3), float(scene.sphere)
    if region == "cameras":
        return bound_by_cameras(scene.cameras)
    if region == "sfm_points":
        if scene.points is None or len(scene.points) == 0:
            raise ConfigError(f"scene '{scene.name}' has no SfM points, so method.sdf_region=sfm_points has nothing to "
                              "bound; fix: method.sdf_region=cameras or scene")
        return bound_by_sfm_points(np.asarray(scene.points, dtype=np.float64))
    raise ConfigError(f"method.sdf_region must be one of {SDF_REGIONS}, got {region!r}")


def bound_by_cameras(cameras) -> tuple[np.ndarray, float]:
    """Neuralangelo's ``bound_by_pose`` (its "object" scenes): centre = the mean over all ordered pairs of cameras
    (i, j), i = j included, of the midpoint of the closest points of their optical axes (least squares, minimum
    norm for parallel axes: a camera with itself gives its own centre); radius = the cameras' mean distance from
    that centre. Deviation: Neuralangelo takes the mean distance from the COLMAP frame's origin, which depends on
    where COLMAP put it."""
    origins = np.array([cam.center for cam in cameras], dtype=np.float64)
    axes = np.array([cam.R[2] for cam in cameras], dtype=np.float64)  # camera z, world frame (OpenCV: forward)
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    total = np.zeros(3)
    for origin, axis in zip(origins, axes):  # camera i against every camera j: t_i d_i - t_j d_j = o_j - o_i
        system = np.stack([np.broadcast_to(axis, axes.shape), -axes], axis=-1)
        steps = np.linalg.pinv(system, rcond=3 * np.finfo(np.float64).eps) @ (origins - origin)[..., None]
        total += (origin + axis * steps[:, 0] + origins + axes * steps[:, 1]).sum(axis=0)
    centre = total / (2 * len(cameras) ** 2)
    return centre, float(np.linalg.norm(origins - centre, axis=1).mean())


def bound_by_sfm_points(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Neuralangelo's ``bound_by_points`` (its "outdoor" and "indoor" scenes): centre = the SfM points' mean,
    radius = `SFM_BOUND_STDS` x their largest per-axis standard deviation."""
    return points.mean(axis=0), SFM_BOUND_STDS * float(points.std(axis=0).max())


def evaluate(sdf_fn, points: np.ndarray) -> np.ndarray:
    """``sdf_fn`` (torch (N,3) -> (N,)) at ``points`` (N,3), in batches of `MESH_CHUNK`."""
    chunks = [sdf_fn(torch.from_numpy(chunk).float()).numpy() for chunk in np.array_split(points, max(1, len(points) // MESH_CHUNK))]
    return np.concatenate(chunks) if chunks else np.zeros(0, np.float32)


def sdf_volume(sdf_fn, radius: float, voxel: float) -> tuple[np.ndarray, float]:
    """f on the grid of the cube [−R, R]³ with ``COARSE``·k + 1 vertices a side, spacing about ``voxel``
    (values, spacing). Evaluated exactly in the coarse cells (``COARSE`` fine cells a side) whose corners
    change sign or come within λ · (a coarse cell's diagonal) of 0, λ = max(1, the cell's `coarse_slope`);
    elsewhere the trilinear interpolation of the coarse values, which has the same sign and no zero crossing
    there: a zero inside a cell puts every corner within max |∇f| · diagonal of 0 (the cell's), and λ is that slope
    as the coarse grid measures it around the cell (|∇f| ≈ 1 under the Eikonal term; a trained field can be
    steeper: tests/test_neusg_terms.py)."""
    cells = max(1, int(math.ceil(2 * radius / voxel / COARSE)))
    n = COARSE * cells + 1
    spacing = 2 * radius / (n - 1)
    coarse_axis = -radius + spacing * COARSE * np.arange(cells + 1)
    grid = np.stack(np.meshgrid(coarse_axis, coarse_axis, coarse_axis, indexing="ij"), -1).reshape(-1, 3)
    coarse = evaluate(sdf_fn, grid).reshape(cells + 1, cells + 1, cells + 1)
    values = torch.nn.functional.interpolate(torch.from_numpy(coarse)[None, None], size=(n, n, n), mode="trilinear",
                                             align_corners=True)[0, 0].numpy()
    corners = np.stack([coarse[i:i + cells, j:j + cells, k:k + cells] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    margin = np.maximum(1.0, coarse_slope(coarse, COARSE * spacing)) * COARSE * spacing * math.sqrt(3)
    near = (np.abs(corners).min(0) < margin) | (corners.min(0) < 0) & (corners.max(0) > 0)
    active = np.argwhere(near)
    if len(active):
        offsets = np.stack(np.meshgrid(*(np.arange(COARSE + 1),) * 3, indexing="ij"), -1).reshape(-1, 3)
        vertices = np.unique((active[:, None] * COARSE + offsets[None]).reshape(-1, 3), axis=0)
        values[tuple(vertices.T)] = evaluate(sdf_fn, -radius + spacing * vertices.astype(np.float64))
    return values, spacing


def coarse_slope(values: np.ndarray, spacing: float) -> np.ndarray:
    """Per cell of the grid of ``values`` (k+1 vertices a side, k³ cells), the largest |Δf| / ``spacing`` over the
    grid edges that touch one of its corners (its own 12 and the 24 that leave it): the field's slope as the grid
    measures it around the cell (a lower bound of the local max |∇f|; the edges that leave the cell see the flanks
    of a thin feature whose cell's corners are all equal)."""
    vertex = np.zeros_like(values)
    for axis in range(3):
        edge = np.abs(np.diff(values, axis=axis)) / spacing
        before = [(0, 0)] * 3
        before[axis] = (1, 0)
        after = [(0, 0)] * 3
        after[axis] = (0, 1)
        vertex = np.maximum(vertex, np.maximum(np.pad(edge, before), np.pad(edge, after)))
    k = values.shape[0] - 1
    return np.max([vertex[i:i + k, j:j + k, l:l + k] for i in (0, 1) for j in (0, 1) for l in (0, 1)], axis=0)


def sdf_mesh(sdf_fn, radius: float, voxel: float):
    """Marching cubes of ``sdf_fn``'s zero level set on the cube [−R, R]³ (`sdf_volume`): (open3d mesh, grid
    vertices a side); an SDF with no zero crossing there, or not finite, is a `MeshError`."""
    o3d = import_open3d()
    values, spacing = sdf_volume(sdf_fn, radius, voxel)
    n = values.shape[0]
    if not np.all(np.isfinite(values)):
        raise MeshError(f"the SDF is not finite at {int((~np.isfinite(values)).sum())} of {values.size} grid points")
    if values.min() >= 0 or values.max() <= 0:
        raise MeshError(f"the SDF has no zero level set in its region's cube (values {values.min():.4g} to "
                        f"{values.max():.4g} on a {n}³ grid): nothing to mesh; the SDF did not converge to a surface "
                        "(check neus_rgb and sdf_points) or the object lies outside the SDF's sphere (method.sdf_region)")
    vertices, faces, _, _ = marching_cubes(values, level=0.0, spacing=(spacing,) * 3)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices - radius),
                                     o3d.utility.Vector3iVector(faces.astype(np.int32)))
    return mesh, n


def neus_rgb_term(render, batch: Batch, state: dict) -> torch.Tensor:
    """L_rgb of the SDF (NeuSG eq. 14, NeuS): mean |C_NeuS − C_gt| over the step's sampled pixels and channels."""
    out, target = method_state(state, "neusg", "neus_rgb").rays(batch)
    return (out.colour - target).abs().mean()


def eikonal_term(render, batch: Batch, state: dict) -> torch.Tensor:
    """L_eik = mean (|∇f(x)| − 1)² over the NeuS samples inside the sphere (NeuSG eq. 14); 0 without samples."""
    grad = method_state(state, "neusg", "eikonal").rays(batch)[0].gradients
    if grad.shape[0] == 0:
        return grad.sum()
    return ((grad.norm(dim=-1) - 1) ** 2).mean()


def sdf_points_term(render, batch: Batch, state: dict) -> torch.Tensor:
    """L_pt = mean |f(μ_i)| over a sample of Gaussian centres (NeuSG eq. 14; centres held fixed); 0 if none."""
    method = method_state(state, "neusg", "sdf_points")
    _, means = method.centre_sample()
    if len(means) == 0:
        return method.field.variance * 0
    return method.field.sdf(method.field.local(means))[0].abs().mean()


def sdf_align_term(render, batch: Batch, state: dict) -> torch.Tensor:
    """L_align = mean |1 − |n_wᵀ ∇f̂(μ_i)|| over a sample of Gaussians, n_w the rotation column of the smallest
    scale, ∇f̂ the SDF's unit normal held fixed (NeuSG eq. 15); 0 if none."""
    method = method_state(state, "neusg", "sdf_align")
    g = method.gaussians
    index, means = method.centre_sample()
    if len(index) == 0:
        return g.params["quats"].sum() * 0
    with torch.no_grad():
        normal = F.normalize(method.field.sdf.with_gradient(method.field.local(means))[1], dim=-1)
    rot = quat_to_rotmat(F.normalize(g.params["quats"][index], dim=-1))
    shortest = g.params["log_scales"][index].detach().argmin(dim=-1)
    axis = torch.gather(rot, 2, shortest[:, None, None].expand(-1, 3, 1)).squeeze(-1)
    return (1 - (axis * normal).sum(-1).abs()).abs().mean()


NEUS_RGB = loss_term("neus_rgb", neus_rgb_term)
EIKONAL = loss_term("eikonal", eikonal_term)
SDF_POINTS = loss_term("sdf_points", sdf_points_term)
SDF_ALIGN = loss_term("sdf_align", sdf_align_term)
