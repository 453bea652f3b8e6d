"""GGGS, Geometry-Grounded Gaussian Splatting (Zhang, Jiang, Li, Shen, Tan 2026), docs/methods/gggs.md.

Differences from 3DGS, after the authors' code (HKUST-SAIL, f727413; docs/methods/gggs.md §3):

- ``rade`` kernel (RaDe-GS's depth plane, same authors' group) with the Mip-Splatting 3D filter and no 2D dilation,
  plus the ``solid_depth`` output: the depth where the Gaussians' transmittance as stochastic solids crosses ½
  (docs/rasterizer.md §9a), searched in [init ± ``solid_search_range``·scene radius] (5 rounds of 8 cells);
- losses (docs/methods/gggs.md §3): 0.8·L1 of the exposure-compensated render (PGSR's per-image exp(a)·I + b,
  from step 0, no SSIM gate) + 0.2·D-SSIM of the raw render, and from step 7000 0.05·``gggs_normal`` +
  0.02·``gggs_geo`` + 0.6·``gggs_ncc`` (`gsbench.methods.gggs_terms`): the depth–normal consistency of the
  solid depth and PGSR's multi-view geometric and NCC terms on the solid depth and the rendered normal, one of
  the (up to) 8 PGSR neighbours per step;
- colour learning rates 0.0013 (DC) and 0.00011 (rest); initial scales at most 0.05 × the distance to the
  nearest training camera;
- densification: GOF's (`AbsGradStrategy`: abs-gradient quantile split, sampled clones, 3D filter
  recomputed), pruning by opacity < 0.05 only (no world- or screen-size pruning);
- mesh: TSDF of the solid depth (``mesh.depth: solid``), the largest cluster kept (DTU voxel and truncation
  in ``configs/methods/gggs.dtu.yaml``);
- ``surface_depth`` (docs/methods/gggs.md §3.5): ``solid`` (the paper's); ``median`` puts the median depth in place
  of the solid depth in the three geometric terms and the multi-view planes
  (`gsbench.methods.gggs_terms.surface_depth`), so no solid pass runs; the ablation meshes it with
  ``mesh.depth: median``.

Not implemented (docs/methods/gggs.md §5): the neighbour's depth is read from its rendered solid-depth map
(bilinear, as PGSR's plane) rather than by a query along the warped ray; TnT's marching tetrahedra on the
stochastic-solid field (TSDF on TnT too); the spherical-Gaussian colour (off in the DTU and TnT scripts).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from gsbench.config.run_config import RunConfig
from gsbench.data.camera import Scene
from gsbench.errors import ConfigError
from gsbench.geometry.depth import pixel_rays
from gsbench.losses.terms import Batch
from gsbench.methods.base import ADAM_EPS, DEPTH_OUTPUTS, MethodInfo
from gsbench.methods.filtered import FilteredConfig, FilteredMethod
from gsbench.methods.gggs_terms import SURFACE_OUTPUTS, surface_depth
from gsbench.methods.multiview import NeighbourViews, check_multiview_params
from gsbench.raster import RasterSettings
from gsbench.raster.types import RenderOutput
from gsbench.training.gaussians import Gaussians


@dataclass
class GGGSConfig(FilteredConfig):
    """GGGS's hyper-parameters (arguments/__init__.py of the authors' code, docs/methods/gggs.md §3)."""

    feature_lr: float = 0.0013
    feature_rest_divisor: float = 0.0013 / 0.00011  # sh_rest lr 0.00011
    prune_world_size: bool = False
    init_scale_camera_share: float = 0.05  # initial scale <= this × distance to the nearest training camera
    solid_search_range: float = 0.4  # × scene radius (1): the authors' 0.4 in IDR's units on DTU, COLMAP's on TnT
    solid_rounds: int = 5
    multi_view_num: int = 8
    multi_view_max_angle: float = 30.0  # degrees between viewing directions
    multi_view_min_dis: float = 0.01  # camera distances, in scene radii
    multi_view_max_dis: float = 1.5
    multi_view_patch_half: int = 3  # 7x7 samples ...
    multi_view_patch_step: float = 0.5  # ... half a pixel apart
    multi_view_pixel_noise_th: float = 1.0  # px
    exposure_lr: float = 0.001
    surface_depth: str = "solid"  # the depth D of the geometric terms: solid, or median (docs/methods/gggs.md §3.5)


def depth_planes(depth: torch.Tensor, normal: torch.Tensor, camera) -> tuple[torch.Tensor, torch.Tensor]:
    """(plane distance (H, W), unit normal (H, W, 3)) of the plane through each pixel's depth point D·r with the
    direction of the rendered ``normal``: d = −D (n̂·r), so n̂·X = −d on it (PGSR's plane convention, 0 where
    D = 0)."""
    unit = torch.nn.functional.normalize(normal, dim=-1)
    rays = pixel_rays(camera, depth.dtype)
    return -depth * (unit * rays).sum(-1), unit


class GGGS(NeighbourViews, FilteredMethod):
    """Geometry-Grounded Gaussian Splatting (module docstring)."""

    name = "gggs"
    Config = GGGSConfig
    INFO = MethodInfo(primitive="3d", kernel="rade", outputs=("rgb", "alpha", "normal", "solid_depth", "median_depth"))
    MESH_DEPTHS = ("solid", *DEPTH_OUTPUTS)
    NEIGHBOUR_OUTPUTS = ("solid_depth", "normal")

    def __init__(self):
        super().__init__()
        self.init_neighbours()

    # ---- configuration ------------------------------------------------------------------------
    def check_params(self) -> None:
        super().check_params()
        p, cfg = self.params, self.cfg
        if cfg.train.optimizer != "adam":
            raise ConfigError(f"method gggs trains a per-image exposure as one more Adam group; train.optimizer "
                              f"{cfg.train.optimizer} steps only visible Gaussian rows: set train.optimizer=adam")
        check_multiview_params(p, "docs/methods/gggs.md §3")
        if p.surface_depth not in SURFACE_OUTPUTS:
            raise ConfigError(f"method.surface_depth must be one of {', '.join(SURFACE_OUTPUTS)}, got "
                              f"'{p.surface_depth}'; see docs/methods/gggs.md §3.5")
        checks = [("solid_search_range", p.solid_search_range > 0), ("solid_rounds", 1 <= p.solid_rounds <= 12),
                  ("init_scale_camera_share", p.init_scale_camera_share > 0),
                  ("multi_view_patch_step", p.multi_view_patch_step > 0)]
        for key, ok in checks:
            if not ok:
                raise ConfigError(f"method.{key} is out of range (got {getattr(p, key)}); see docs/methods/gggs.md §3")

    def setup(self, scene: Scene, cfg: RunConfig) -> None:
        self.new_exposure(scene)
        super().setup(scene, cfg)
        self.setup_neighbours(scene)
        self.NEIGHBOUR_OUTPUTS = (*SURFACE_OUTPUTS[self.params.surface_depth], "normal")  # what `planes` reads

    def initial_gaussians(self, scene: Scene, cfg: RunConfig) -> Gaussians:
        """The base initialisation with each scale at most ``init_scale_camera_share`` × the distance from the
        centre to the nearest training camera (GGGS scene/__init__.py)."""
        g = super().initial_gaussians(scene, cfg)
        centres = torch.as_tensor(np.stack([scene.cameras[i].center for i in scene.train_views]), dtype=torch.float64)
        means = g.params["means"].detach().to(torch.float64)
        nearest = torch.cdist(means, centres).min(1).values.clamp_min(1e-12)
        limit = torch.log(self.params.init_scale_camera_share * nearest).to(g.params["log_scales"].dtype)
        g.params["log_scales"].data = torch.minimum(g.params["log_scales"].data, limit[:, None])
        return g

    def make_optimizer(self, gaussians):
        optimizer = super().make_optimizer(gaussians)
        optimizer.add_param_group({"params": [self.exposure], "name": "exposure", "lr": self.params.exposure_lr,
                                   "eps": ADAM_EPS})  # Adam's default betas: GGGS's "beta" key is ignored by torch
        return optimizer

    def raster_settings(self) -> RasterSettings:
        """The base settings with the solid-depth search (module docstring)."""
        p = self.params
        return dataclasses.replace(super().raster_settings(), solid_rounds=p.solid_rounds,
                                   solid_search_range=p.solid_search_range * self.scene_radius)

    def term_params(self) -> dict[str, dict]:
        """The L1 on the exposure-compensated render without PGSR's SSIM gate; the geometric terms' depth when it is
        not the solid one (their default, so a solid run's record lists no parameter for them)."""
        params = {"l1_exposure": {"ssim_gate": False}}
        if self.params.surface_depth != "solid":
            params |= {term: {"depth": self.params.surface_depth} for term in ("gggs_normal", "gggs_geo", "gggs_ncc")}
        return {k: v for k, v in params.items() if k in self.cfg.losses}

    # ---- what the loss terms read -------------------------------------------------------------
    def loss_state(self) -> dict:
        return {"gaussians": self.gaussians, "exposure": self._exposure_of, "pgsr_multiview": self._multiview}

    def _exposure_of(self, batch: Batch):
        view = batch.view
        return None if view is None else (self.exposure[view, 0], self.exposure[view, 1])

    def planes(self, render: RenderOutput, camera) -> tuple[torch.Tensor, torch.Tensor]:
        """The planes through the surface-depth points with the rendered normals (`depth_planes`)."""
        return depth_planes(surface_depth(render, self.params.surface_depth), render.normal, camera)

    def patch_step(self) -> float:
        return self.params.multi_view_patch_step

    # ---- mesh ---------------------------------------------------------------------------------
    def mesh_depth(self, camera, cfg: RunConfig) -> tuple[torch.Tensor, RenderOutput]:
        """``mesh.depth`` for the TSDF; ``solid``: the stochastic-solid depth with the training search (GGGS's
        mesh_extract.py renders with the same ±0.4, 5 rounds)."""
        if cfg.mesh.depth != "solid":
            return super().mesh_depth(camera, cfg)
        out = self.render(camera, {"solid_depth", "alpha", "rgb"})
        return out.solid_depth, out
