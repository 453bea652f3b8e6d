"""SuGaR's refinement stage (docs/methods/sugar.md §6): the coarse Poisson mesh with Gaussians bound to its
triangles (`gsbench.methods.sugar_binding`), vertices and Gaussians optimised jointly; the refined mesh is the
output.

From SuGaR's public code (``sugar_trainers/refine.py``, ``sugar_scene/sugar_model.py``,
``sugar_scene/sugar_optimizer.py``):

- n Gaussians per triangle (``refine_gaussians_per_triangle``, the scripts' 1; 6 for the low-poly mesh);
  colour SH DC from the mesh's vertex colours at the barycentric points (grey when the mesh has none),
  higher SH 0, opacity 0.1, in-plane rotation (1, 0), thickness the cameras' extent / 10⁶;
- Adam (ε 1e-15): vertices lr 0.00016·S decaying log-linearly to 0.0000016·S over 30 000 of SuGaR's steps
  (S = 10 x the cameras' extent / √(vertices)), SH DC 0.0025, SH rest 0.000125, opacity 0.05, scales 0.005,
  rotation 0.001; SH degree +1 every 1 000 steps from 0;
- L = 0.8 L1 + 0.2 D-SSIM + 0.1 mesh normal consistency (pytorch3d's: mean over pairs of faces sharing an
  edge of 1 − cos of their normals); no densification, no pruning;
- 2 000 / 7 000 / 15 000 steps (short / medium / long); here scaled as every schedule: SuGaR's 15 000-step
  coarse run is ``train.iterations``, so a refinement of k SuGaR steps runs k x iterations / 15 000 steps, and
  its step-valued settings scale with it.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import trimesh

from gsbench.errors import ConfigError
from gsbench.losses.terms import Batch, loss_term, method_state
from gsbench.methods.base import ADAM_EPS, Method, MethodInfo, _export_atomic
from gsbench.methods.sugar_binding import barycentric, bound_gaussians, initial_log_scales, usable_faces
from gsbench.raster.sh import C0 as SH_C0
from gsbench.raster.types import RasterGaussians
from gsbench.training.gaussians import check_finite_params
from gsbench.training.optim import make_adam
from gsbench.training.strategies.base import Strategy

REFINEMENT_STEPS = {"short": 2000, "medium": 7000, "long": 15000}  # SuGaR's refinement_time presets
SUGAR_COARSE_STEPS = 15000  # SuGaR's coarse run, which train.iterations stands for
SUGAR_LR_STEPS = 30000  # the vertices' lr decay length in SuGaR's refinement steps
SH_EVERY = 1000  # SuGaR's refinement: SH degree + 1 every this many steps
MESH_PARTS = 2  # the coarse mesh is a foreground and a background Poisson mesh, each decimated to the target
PARAMETERS = ("vertices", "log_scales", "rotation", "opacity_logits", "sh_dc", "sh_rest")


class BoundGaussians(torch.nn.Module):
    """The refinement's parameters: mesh ``vertices`` (V, 3) and, per bound Gaussian (F·n rows), log-scales (2),
    complex rotation (2), opacity logit (1), SH DC (1, 3) and rest (K − 1, 3); ``faces`` (F, 3) fixed."""

    def __init__(self, faces: torch.Tensor, per_triangle: int, thickness: float, max_sh_degree: int, **params):
        super().__init__()
        self.register_buffer("faces", faces)
        self.per_triangle, self.thickness, self.max_sh_degree = int(per_triangle), float(thickness), int(max_sh_degree)
        self.params = torch.nn.ParameterDict({k: torch.nn.Parameter(params[k]) for k in PARAMETERS})

    def __len__(self) -> int:
        return int(self.params["log_scales"].shape[0])

    def check_finite(self) -> None:
        check_finite_params(self.params)

    def raster_input(self, filter3d=None) -> RasterGaussians:
        p = self.params
        means, scales, quats = bound_gaussians(p["vertices"], self.faces, self.per_triangle, p["log_scales"],
                                               p["rotation"], self.thickness)
        return RasterGaussians(means=means, quats=quats, scales=scales, opacities=torch.sigmoid(p["opacity_logits"][:, 0]),
                               sh=p["sh_dc"], sh_rest=p["sh_rest"] if p["sh_rest"].shape[1] else None)


class SugarRefinement(Method):
    """The refinement stage of a trained SuGaR coarse model (module docstring); built by `from_coarse`."""

    name = "sugar"
    INFO = MethodInfo(primitive="3d", kernel="ewa", outputs=("rgb", "alpha", "depth", "median_depth"))
    MESH_EXTRACTORS = ("poisson", "tsdf")

    @classmethod
    def from_coarse(cls, coarse, mesh: trimesh.Trimesh, cfg) -> "SugarRefinement":
        """Bind Gaussians to ``mesh`` (the coarse Poisson mesh, decimated) of the trained ``coarse`` SuGaR;
        ``cfg`` is the refinement's run config (`refinement_config`)."""
        self = cls()
        self.cfg, self.params, self.background = cfg, coarse.params, coarse.background  # SuGaR's own Config
        p = self.params
        self.scene_radius, self.extent = coarse.scene_radius, coarse.extent
        vertices, faces = bound_mesh(mesh)
        n = p.refine_gaussians_per_triangle
        coords, _ = barycentric(n, torch.float32)
        colours = mesh.visual.vertex_colors[:, :3] / 255.0 if mesh.visual.kind == "vertex" else np.full((len(vertices), 3), 0.5)
        colour = torch.einsum("gk,fkc->fgc", coords, torch.as_tensor(colours, dtype=torch.float32)[faces]).reshape(-1, 3)
        rows = len(faces) * n
        rest = (cfg.raster.sh_degree + 1) ** 2 - 1
        self.gaussians = BoundGaussians(
            faces, n, thickness=self.extent / 1e6, max_sh_degree=cfg.raster.sh_degree, vertices=vertices,
            log_scales=initial_log_scales(vertices.double(), faces, n).float(),
            rotation=torch.tensor([[1.0, 0.0]]).repeat(rows, 1), opacity_logits=torch.full((rows, 1), math.log(0.1 / 0.9)),
            sh_dc=((colour - 0.5) / SH_C0)[:, None, :], sh_rest=torch.zeros(rows, rest, 3))
        self._face_pairs = face_pairs(faces.numpy())
        self.optimizer = self.make_optimizer(self.gaussians)
        self.sh_degree = 0
        return self

    def strategy(self) -> Strategy:
        return Strategy()  # no densification, no pruning

    def describe(self) -> dict:
        """The record's ``inputs.second_stage``: the refinement, the coarse mesh's size and the Gaussians bound."""
        g = self.gaussians
        return {"refinement": self.params.refinement, "steps": self.cfg.train.iterations,
                "coarse_mesh": {"vertices": int(len(g.params["vertices"])), "faces": int(len(g.faces))},
                "gaussians_per_triangle": g.per_triangle, "bound_gaussians": len(g)}

    def vertex_lr_scale(self) -> float:
        """S = 10 x the cameras' extent / √(vertices) (SuGaR's spatial_lr_scale in refinement)."""
        return 10.0 * self.extent / math.sqrt(len(self.gaussians.params["vertices"]))

    def make_optimizer(self, gaussians) -> torch.optim.Optimizer:
        lrs = {"vertices": 0.00016 * self.vertex_lr_scale(), "log_scales": 0.005, "rotation": 0.001, "opacity_logits": 0.05,
               "sh_dc": 0.0025, "sh_rest": 0.0025 / 20}
        groups = [{"params": [param], "name": name, "lr": lrs[name]} for name, param in gaussians.params.items()]
        return make_adam(groups, "adam", ADAM_EPS)  # SuGaR refine: Adam, eps 1e-15, as 3DGS

    def update_schedules(self, step: int, scale: float) -> None:
        """The vertices' log-linear lr decay and the SH degree, in SuGaR's refinement steps (module docstring)."""
        sugar_step = step * self._sugar_steps_per_step()
        t = min(sugar_step / SUGAR_LR_STEPS, 1.0)
        s = self.vertex_lr_scale()
        lr = math.exp((1 - t) * math.log(0.00016 * s) + t * math.log(0.0000016 * s))
        for group in self.optimizer.param_groups:
            if group["name"] == "vertices":
                group["lr"] = lr
        self.sh_degree = min(self.cfg.raster.sh_degree, int(sugar_step // SH_EVERY))

    def _sugar_steps_per_step(self) -> float:
        return REFINEMENT_STEPS[self.params.refinement] / max(self.cfg.train.iterations, 1)

    def loss_state(self) -> dict:
        return {"gaussians": self.gaussians, "refinement": self}

    @torch.no_grad()
    def extract_mesh(self, scene, cfg, out_path) -> dict:
        """The refined mesh: the coarse mesh's faces on the optimised vertices."""
        g = self.gaussians
        mesh = trimesh.Trimesh(g.params["vertices"].detach().double().numpy(), g.faces.numpy(), process=False)
        _export_atomic(mesh, Path(out_path))
        return {"vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces)), "bound_gaussians": len(g)}

    def state_dict(self) -> dict:
        return {"params": {k: v.detach().clone() for k, v in self.gaussians.params.items()},
                "optimizer": self.optimizer.state_dict(), "sh_degree": self.sh_degree}

    def load_state_dict(self, state: dict) -> None:
        for name, value in state["params"].items():
            self.gaussians.params[name] = torch.nn.Parameter(value.clone())
        self.optimizer = self.make_optimizer(self.gaussians)
        self.optimizer.load_state_dict(state["optimizer"])
        self.sh_degree = int(state["sh_degree"])


def refinement_config(cfg):
    """The refinement's run config: ``train.iterations`` = SuGaR's steps of ``method.refinement`` scaled by
    iterations / 15 000, the refinement's losses (module docstring); everything else the coarse run's."""
    steps = REFINEMENT_STEPS[cfg.method["refinement"]]
    iterations = max(1, round(steps * cfg.train.iterations / SUGAR_COARSE_STEPS))
    losses = {"l1": {"weight": 0.8, "start": 0, "end": -1}, "dssim": {"weight": 0.2, "start": 0, "end": -1},
              "mesh_normal_consistency": {"weight": 0.1, "start": 0, "end": -1}}
    return dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, iterations=iterations), losses=losses)


def bound_mesh(mesh: trimesh.Trimesh) -> tuple[torch.Tensor, torch.Tensor]:
    """The mesh the refinement binds Gaussians to and starts its vertices from: (vertices (V, 3) float32, every one
    kept; faces (F, 3) int64, the usable ones, `usable_faces`)."""
    vertices = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32)
    faces = torch.as_tensor(np.asarray(mesh.faces), dtype=torch.int64)
    return vertices, faces[usable_faces(vertices.double(), faces)]


def face_pairs(faces: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """The pairs of faces that pytorch3d's ``mesh_normal_consistency`` compares: for every edge, every pair among
    the faces that have it (one pair on a manifold edge, k(k − 1)/2 on an edge of k faces, wherever those faces
    stand in ``faces``), in the order of the edges (sorted vertex pairs). Returns (pairs (P, 2) int64, signs (P,)):
    s = +1 when the pair's faces run along their edge in opposite directions (consistently wound), −1 when in the
    same one (`mesh_normal_consistency`)."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = np.sort(directed, axis=1)
    owner = np.tile(np.arange(len(faces)), 3)
    order = np.lexsort((edges[:, 1], edges[:, 0]))
    edges, owner, forward = edges[order], owner[order], (directed[:, 0] < directed[:, 1])[order]
    first = np.flatnonzero(np.r_[True, np.any(edges[1:] != edges[:-1], axis=1)])  # each edge's first entry
    count = np.diff(np.r_[first, len(edges)])
    entries = [np.zeros((0, 2), np.int64)]
    for k in np.unique(count[count > 1]):
        i, j = np.triu_indices(k, 1)
        starts = first[count == k][:, None]
        entries.append(np.stack([(starts + i).ravel(), (starts + j).ravel()], 1))
    entries = np.concatenate(entries)
    entries = entries[np.lexsort((entries[:, 1], entries[:, 0]))]
    signs = np.where(forward[entries[:, 0]] != forward[entries[:, 1]], 1.0, -1.0)
    return torch.from_numpy(owner[entries].astype(np.int64)), torch.from_numpy(signs.astype(np.float32))


def mesh_normal_consistency(vertices: torch.Tensor, faces: torch.Tensor, pairs: torch.Tensor,
                            signs: torch.Tensor) -> torch.Tensor:
    """pytorch3d's mesh normal consistency: the mean over ``pairs`` (`face_pairs`) of 1 − cos(n₀, n₁), with, for faces
    f₀ and f₁ on the edge e = (v₀, v₁) and a, b their vertices off it, n₀ = e × (a − v₀) and n₁ = −e × (b − v₀): 0 for
    coplanar faces on either side of e, 2 for faces folded flat onto each other, whatever their winding.
    Computed as 1 − s·cos(N₀, N₁) with N the faces' own normals (v₁ − v₀) × (v₂ − v₀) and s the pair's sign (e × (a − v₀)
    is ±N₀, + when f₀ runs along e from v₀ to v₁); 0 without pairs."""
    v = vertices[faces]
    normal = F.normalize(torch.linalg.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), dim=-1)
    if len(pairs) == 0:
        return v.sum() * 0
    return (1 - signs.to(normal.dtype) * (normal[pairs[:, 0]] * normal[pairs[:, 1]]).sum(-1)).mean()


def mesh_normal_consistency_term(render, batch: Batch, state: dict) -> torch.Tensor:
    """L_nc: `mesh_normal_consistency` of the refinement's mesh (SuGaR refinement, weight 0.1)."""
    method = method_state(state, "refinement", "mesh_normal_consistency")
    g = method.gaussians
    return mesh_normal_consistency(g.params["vertices"], g.faces, *method._face_pairs)


MESH_NORMAL_CONSISTENCY = loss_term("mesh_normal_consistency", mesh_normal_consistency_term)


def check_refinement(params, cfg) -> None:
    """ConfigError for an unknown refinement or Gaussians per triangle, or a binding the budget cannot hold:
    ``refine_triangles`` x n > ``train.max_gaussians`` (before any training)."""
    if params.refinement not in ("none", "decimated", *REFINEMENT_STEPS):
        raise ConfigError(f"method.refinement must be none, decimated, short, medium or long, got {params.refinement!r}")
    if params.refinement == "none":
        return
    if params.refine_triangles < 1:
        raise ConfigError(f"method.refine_triangles must be >= 1, got {params.refine_triangles}")
    if params.refinement == "decimated":
        return  # no Gaussians bound
    barycentric(params.refine_gaussians_per_triangle)
    n = params.refine_gaussians_per_triangle
    wanted = MESH_PARTS * params.refine_triangles * n
    if cfg.train.max_gaussians > 0 and wanted > cfg.train.max_gaussians:
        raise ConfigError(f"SuGaR refinement could bind {MESH_PARTS} x {params.refine_triangles} triangles x {n} = "
                          f"{wanted} Gaussians (the foreground and background meshes are each decimated to "
                          f"method.refine_triangles), over the run's budget train.max_gaussians = "
                          f"{cfg.train.max_gaussians}; fix: method.refine_triangles <= "
                          f"{cfg.train.max_gaussians // (MESH_PARTS * n)}, or raise the budget")
