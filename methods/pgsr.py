"""PGSR, Planar-based Gaussian Splatting (Chen et al. 2024, TVCG), docs/methods/pgsr.md.

Differences from 3DGS (the ``ewa`` kernel, no 3D filter):

- flattened Gaussians: ``min_scale`` pulls the smallest scale of the visible Gaussians to 0 (λ 100 from
  step 0, docs/methods/pgsr.md §4.1);
- unbiased depth: the kernel renders the plane distance D = Σ wᵢdᵢ (dᵢ = −nᵢ·μᵢ, nᵢ the shortest axis facing
  the camera) next to N = Σ wᵢnᵢ; depth = D / (−N·r̃) (`gsbench.methods.pgsr_terms.unbiased_depth`,
  docs/methods/pgsr.md §3);
- losses (docs/methods/pgsr.md §4): 0.8·L1 (on the exposure-compensated image, ``l1_exposure``) + 0.2·D-SSIM +
  100·``min_scale`` + 0.015·``pgsr_normal`` + 0.03·``pgsr_geo`` + 0.15·``pgsr_ncc``, the last three from step 7000;
- multi-view terms: each step one of the reference view's (up to) 8 neighbours (`neighbour_views`: camera
  distance, then angle between viewing directions; angle < 30°, distance in (0.01, 1.5) scene radii) is
  drawn with Python's seeded RNG and rendered by the method itself (``state["pgsr_multiview"]``, built once per
  step and shared by the two terms; docs/methods/pgsr.md §4.3);
- exposure compensation (``exposure_compensation``, on by default; off in the DTU layer as PGSR's DTU
  script): a learnable (a_v, b_v) per image, Ĩ = exp(a_v)·I + b_v, from step 1000, Adam lr 0.001 with
  β = (0.9, 0.99) (docs/methods/pgsr.md §4.5);
- densification: `PGSRStrategy`, 3DGS clone/split with PGSR's extra abs-gradient split and percent_dense 0.001
  (docs/methods/pgsr.md §5);
- mesh: TSDF of the unbiased depth (``mesh.depth: unbiased``), optionally without pixels whose depth normal is
  more than ``tsdf_max_view_angle`` degrees from the viewing ray (TnT: 80, docs/methods/pgsr.md §6).

Not implemented: PGSR's multi-view trim (prune Gaussians observed in fewer than two views every 1000 steps),
virtual cameras (off in PGSR), the NCC on images at twice the training resolution (``ncc_scale`` 0.5): see
docs/methods/pgsr.md §8.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from gsbench.config.run_config import RunConfig
from gsbench.data.camera import Scene
from gsbench.errors import ConfigError
from gsbench.geometry.depth import depth_to_normal, pixel_rays
from gsbench.losses.terms import Batch
from gsbench.methods import pgsr_terms
from gsbench.methods.base import DEPTH_OUTPUTS, GSConfig, Method, MethodInfo
from gsbench.methods.multiview import NeighbourViews, check_multiview_params
from gsbench.raster.types import RenderOutput
from gsbench.training.strategies.absgrad import AbsGradStatistics
from gsbench.training.strategies.base import Strategy
from gsbench.training.trainer import scale_step


@dataclass
class PGSRConfig(GSConfig):
    """PGSR's hyper-parameters (arguments/__init__.py of zju3dv/PGSR, docs/methods/pgsr.md §7): the 3DGS values
    except percent_dense 0.001, plus the abs-gradient split, the multi-view settings and exposure compensation."""

    percent_dense: float = 0.001
    abs_grad_threshold: float = 0.0008  # TnT script: 0.00015
    abs_split_radius: float = 20.0  # px: the abs-gradient split needs a max screen radius above this
    multi_view_num: int = 8
    multi_view_max_angle: float = 30.0  # degrees between viewing directions
    multi_view_min_dis: float = 0.01  # camera distances, in scene radii
    multi_view_max_dis: float = 1.5
    multi_view_patch_half: int = 3  # 7x7 patches
    multi_view_sample_num: int = 102400
    multi_view_pixel_noise_th: float = 1.0  # px
    exposure_compensation: bool = True
    exposure_from: int = 1000  # step (of 30 000) after which the compensated image is used
    exposure_lr: float = 0.001
    tsdf_max_view_angle: float = 0.0  # degrees; 0 = no filter (PGSR --use_depth_filter: 80)


@dataclass(frozen=True)
class PGSRStrategy(AbsGradStatistics):
    """PGSR's densification (docs/methods/pgsr.md §5): `DefaultStrategy` (3DGS) with clones sampled at μ + R(s ⊙ ε)
    and, besides g >= ``grad_threshold``, a split of the Gaussians with s_max > percent_dense·extent, a max
    screen radius > ``abs_split_radius`` px and g_abs >= ``abs_grad_threshold``, g_abs the mean NDC
    abs-gradient (`AbsGradStatistics`)."""

    abs_grad_threshold: float = 0.0008
    abs_split_radius: float = 20.0

    def _refine(self, gaussians, optimizer, state: dict, step: int) -> dict:
        state["_big"] = gaussians.scales.detach().max(-1).values > self.percent_dense * self.scene_extent
        try:
            return super()._refine(gaussians, optimizer, state, step)
        finally:
            state.pop("_big", None)

    def _select(self, state: dict) -> tuple[torch.Tensor, torch.Tensor]:
        standard, grads = super()._select(state)
        absgrads = self._mean_absgrad(state)
        extra = (absgrads >= self.abs_grad_threshold) & (state["radii"] > self.abs_split_radius) & state["_big"]
        return standard | extra, torch.maximum(grads, absgrads)


class PGSR(NeighbourViews, Method):
    """PGSR (module docstring)."""

    name = "pgsr"
    Config = PGSRConfig
    INFO = MethodInfo(primitive="3d", kernel="ewa", outputs=("rgb", "alpha", "normal", "plane_distance"))
    MESH_DEPTHS = ("unbiased", *DEPTH_OUTPUTS)
    NEIGHBOUR_OUTPUTS = ("plane_distance", "normal")

    def __init__(self):
        super().__init__()
        self.init_neighbours()
        self.step = 0
        self.scale = 1.0

    # ---- configuration ------------------------------------------------------------------------
    def check_params(self) -> None:
        super().check_params()
        p, cfg = self.params, self.cfg
        if p.exposure_compensation and cfg.train.optimizer != "adam":
            raise ConfigError(f"method.exposure_compensation needs train.optimizer=adam (the per-image exposure is "
                              f"one more Adam group; {cfg.train.optimizer} steps only visible Gaussian rows); "
                              "set method.exposure_compensation=false or train.optimizer=adam")
        check_multiview_params(p, "docs/methods/pgsr.md §7")
        for key, ok in (("multi_view_sample_num", p.multi_view_sample_num >= 1),
                        ("tsdf_max_view_angle", 0 <= p.tsdf_max_view_angle < 90)):
            if not ok:
                raise ConfigError(f"method.{key} is out of range (got {getattr(p, key)}); see docs/methods/pgsr.md §7")

    def setup(self, scene: Scene, cfg: RunConfig) -> None:
        self.new_exposure(scene)
        super().setup(scene, cfg)
        self.setup_neighbours(scene)

    def make_optimizer(self, gaussians):
        optimizer = super().make_optimizer(gaussians)
        if self.params.exposure_compensation:
            optimizer.add_param_group({"params": [self.exposure], "name": "exposure", "lr": self.params.exposure_lr,
                                       "betas": (0.9, 0.99), "eps": 1e-8})
        return optimizer

    def strategy(self) -> Strategy:
        return PGSRStrategy(**self.densify_settings(PGSRStrategy))

    def update_schedules(self, step: int, scale: float) -> None:
        super().update_schedules(step, scale)
        self.step, self.scale = step, scale

    # ---- what the loss terms read -------------------------------------------------------------
    def loss_state(self) -> dict:
        return {"gaussians": self.gaussians, "exposure": self._exposure_of, "pgsr_multiview": self._multiview}

    def _exposure_of(self, batch: Batch):
        """(a_v, b_v) of the batch's view when exposure compensation is on and past its start, else None."""
        p = self.params
        if not p.exposure_compensation or self.step <= scale_step(p.exposure_from, self.scale):
            return None
        view = batch.view
        return None if view is None else (self.exposure[view, 0], self.exposure[view, 1])

    def planes(self, render: RenderOutput, camera) -> tuple[torch.Tensor, torch.Tensor]:
        """The rendered plane distance and normal (docs/methods/pgsr.md §3.1)."""
        return render.plane_distance, render.normal

    def ncc_sample_cap(self) -> int:
        return self.params.multi_view_sample_num

    # ---- mesh ---------------------------------------------------------------------------------
    def mesh_depth(self, camera, cfg: RunConfig) -> tuple[torch.Tensor, RenderOutput]:
        """``mesh.depth`` for the TSDF (``unbiased``: D / (−N·r̃), docs/methods/pgsr.md §6); with
        ``tsdf_max_view_angle`` > 0, pixels whose depth normal is farther than that from the viewing ray are
        dropped (PGSR ``--use_depth_filter``)."""
        if cfg.mesh.depth == "unbiased":
            out = self.render(camera, {"plane_distance", "normal", "alpha", "rgb"})
            depth = pgsr_terms.render_depth(out, camera)
        else:
            depth, out = super().mesh_depth(camera, cfg)
        return self._view_angle_filter(depth, camera), out

    def _view_angle_filter(self, depth: torch.Tensor, camera) -> torch.Tensor:
        limit = self.params.tsdf_max_view_angle
        if limit <= 0:
            return depth
        normal = depth_to_normal(depth, camera)
        rays = torch.nn.functional.normalize(pixel_rays(camera, depth.dtype), dim=-1)
        cos = (normal * rays).sum(-1).abs()
        return torch.where(cos < math.cos(math.radians(limit)), torch.zeros_like(depth), depth)
