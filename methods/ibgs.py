"""IBGS, "Injecting Inductive Bias to 3D Gaussian Splatting for Geometrically Accurate Radiance Fields"
(ICLR 2025 submission), docs/methods/ibgs.md. What the authors confirmed docs/methods/ibgs.md §1.2; the rest
is the reconstruction of docs/methods/ibgs.md §10, every assumption a config field.

`IBGSMixin` adds to a base method (its kernel, losses, filter and mesh):

- orientation from the neighbourhood (docs/methods/ibgs.md §4.1, §2, §3, §4): a `gsbench.geometry.neighbours.NeighbourIndex`
  of the ``knn_k`` nearest other means (default 5), refreshed every ``knn_refresh_every`` steps (100,
  like the refinement interval not scaled with the run length) and after every densify/prune; every
  step the local covariance of the neighbour means and its eigenvectors V (`gsbench.geometry.local_geometry`,
  gap-regularised float64 eigen-solver), kept continuous in sign and order against the previous
  step's frame (stored per Gaussian as the state tensor ``frame``, densified and checkpointed with
  the rows; ``match_frames``); the rendered rotation is V' = ΔR·V with the learnable residual ΔR
  stored in the ``quats`` group (a unit quaternion initialised at identity, 3DGS rotation lr, docs/methods/ibgs.md §4.1
  step 4), det V' = +1. V is detached inside the covariance (``attach_eigenvectors`` false, docs/methods/ibgs.md §4.3);
  true lets the rendering gradient reach the neighbour means through V. Scales stay free; scale axis
  k follows frame column k (v3, the normal, is the third axis at init; surfels keep it there);
- losses ``eigval`` and ``eigvec`` (`gsbench.methods.ibgs_terms`), weights in the method yaml;
- densification: `gsbench.training.strategies.sparsity.SparsityAwareStrategy` — the abs-gradient criterion plus SADC
  (``sadc``, ``sparsity``, ``min_gap``).

Registered variants, one per kernel (the authors' RaDe-GS, GOF and 2DGS variants, docs/methods/ibgs.md §1.3, §11.2): ``ibgs``
(RaDe-GS v1 on ``rade``: λ_d 100, L_n, TSDF of the median depth), ``ibgs-gof`` (GOF on ``raymax``) and
``ibgs-2dgs`` (2DGS on ``surfel``). Each variant's yaml ``extends`` its base method's, so it keeps the
base's losses, schedule and per-dataset settings and adds only the IBGS terms.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

from gsbench.config.run_config import RunConfig
from gsbench.data.camera import Scene
from gsbench.errors import ConfigError
from gsbench.geometry.local_geometry import LocalGeometry, apply_alignment, frame_alignment, local_geometry
from gsbench.geometry.neighbours import NeighbourIndex
from gsbench.geometry.rotations import quat_multiply, rotmat_to_quat
from gsbench.methods.gof import GOF, GOFConfig
from gsbench.methods.gs2d import GS2D, GS2DConfig
from gsbench.methods.radegs import RaDeGS, RaDeGSConfig
from gsbench.phase_timer import PhaseTimer
from gsbench.raster import RasterGaussians
from gsbench.training.strategies.base import Strategy
from gsbench.training.strategies.sparsity import SparsityAwareStrategy


@dataclass
class IBGSFields:
    """The IBGS hyper-parameters added to the base method's config (module docstring, docs/methods/ibgs.md §1.4)."""

    knn_k: int = 5
    knn_refresh_every: int = 100
    knn_include_self: bool = True
    attach_eigenvectors: bool = False
    match_frames: bool = True
    eigen_gap_eps: float = 1e-3
    sadc: bool = True
    sparsity: float = 2.0
    min_gap: float = 1.5


class IBGSMixin:
    """IBGS parameterisation, losses and densification on top of a base method (module docstring)."""

    def check_params(self) -> None:
        """The base checks, the neighbourhood size and its refresh interval."""
        super().check_params()
        p = self.params
        if p.knn_k < 1:
            raise ConfigError(f"method.knn_k must be >= 1 neighbour, got {p.knn_k}")
        if p.knn_refresh_every < 1:
            raise ConfigError(f"method.knn_refresh_every must be >= 1 step, got {p.knn_refresh_every}")

    @classmethod
    def memory_estimate(cls, cfg: RunConfig) -> dict[str, int]:
        """The base method's items and the kNN tables for N Gaussians and K = ``method.knn_k``: the query's
        distances and indices (16 NK bytes) and the neighbourhood covariance's gathered neighbours, forward and
        backward, in float64 (56 NK bytes)."""
        return {**super().memory_estimate(cfg), "kNN tables": 72 * cls.gaussian_budget(cfg) * int(cfg.method["knn_k"])}

    def setup(self, scene: Scene, cfg: RunConfig) -> None:
        super().setup(scene, cfg)
        p = self.params
        g = self.gaussians
        g.params["quats"].data.zero_()
        g.params["quats"].data[:, 0] = 1.0  # ΔR = I
        self.neighbours = NeighbourIndex(p.knn_k)
        self.neighbours.refresh(g.means)
        self.timer = PhaseTimer()
        with torch.no_grad():
            g.add_state("frame", self._local_geometry().eigenvectors.detach().float())
        self._geometry: LocalGeometry | None = None

    def _local_geometry(self) -> LocalGeometry:
        p = self.params
        return local_geometry(self.gaussians.means, self.neighbours.check(len(self.gaussians)), self.scene_radius,
                              p.knn_include_self, p.eigen_gap_eps, timer=self.timer if torch.is_grad_enabled() else None)

    def update_schedules(self, step: int, scale: float) -> None:
        """The base schedules, and the periodic kNN refresh (every ``knn_refresh_every`` steps)."""
        super().update_schedules(step, scale)
        if step % self.params.knn_refresh_every == 0:
            self.neighbours.refresh(self.gaussians.means)

    def raster_input(self) -> RasterGaussians:
        """The base raster input with the rotation V' = ΔR·V of this step's neighbourhoods."""
        geometry = self._geometry = self._local_geometry()
        frame = self.gaussians.params["frame"]
        vectors = geometry.eigenvectors if self.params.attach_eigenvectors else geometry.eigenvectors.detach()
        if self.params.match_frames:
            perm, signs = frame_alignment(vectors.detach(), frame, surfel=self.info().primitive == "2d")
            vectors = apply_alignment(vectors, perm, signs)
        frame.data.copy_(vectors.detach().to(frame.dtype))
        rotation = quat_multiply(self.gaussians.quats, rotmat_to_quat(vectors).to(self.gaussians.quats.dtype))
        return dataclasses.replace(super().raster_input(), quats=rotation)

    def loss_state(self) -> dict:
        if self._geometry is None:
            self._geometry = self._local_geometry()
        return {**super().loss_state(), "local_geometry": self._geometry, "scene_radius": self.scene_radius}

    def strategy(self) -> Strategy:
        """Abs-gradient densification + SADC, sharing the kNN index (and the 3D filter, if any)."""
        return SparsityAwareStrategy(**self.densify_settings(SparsityAwareStrategy),
                                     filter3d=getattr(self, "filter", None), neighbours=self.neighbours,
                                     scene_radius=self.scene_radius)

    def training_phases(self) -> dict[str, float]:
        """Seconds in kNN refreshes (``knn``) and in the neighbourhood covariance + eigen-decomposition,
        forward and backward (``local_geometry``) — the costs the authors measured (docs/methods/ibgs.md §11.3)."""
        return {"knn": self.neighbours.seconds, **self.timer.seconds}

    def state_dict(self) -> dict:
        return {**super().state_dict(), "neighbours": self.neighbours.state_dict(), "timer": self.timer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self.neighbours.load_state_dict(state["neighbours"])
        self.timer.load_state_dict(state["timer"])
        self._geometry = None


@dataclass
class IBGSConfig(RaDeGSConfig, IBGSFields):
    """RaDe-GS's hyper-parameters plus `IBGSFields`."""


@dataclass
class IBGSGOFConfig(GOFConfig, IBGSFields):
    """GOF's hyper-parameters plus `IBGSFields`."""


@dataclass
class IBGS2DGSConfig(GS2DConfig, IBGSFields):
    """2DGS's hyper-parameters plus `IBGSFields`."""


class IBGS(IBGSMixin, RaDeGS):
    """IBGS on RaDe-GS v1 (the paper's method)."""

    name = "ibgs"
    Config = IBGSConfig


class IBGSGOF(IBGSMixin, GOF):
    """The IBGS additions on GOF (docs/methods/ibgs.md §11.2)."""

    name = "ibgs-gof"
    Config = IBGSGOFConfig


class IBGS2DGS(IBGSMixin, GS2D):
    """The IBGS additions on 2DGS (docs/methods/ibgs.md §11.2)."""

    name = "ibgs-2dgs"
    Config = IBGS2DGSConfig
