"""SuGaR coarse stage (Guédon & Lepetit, CVPR 2024), docs/methods/sugar.md.

Pipeline (docs/methods/sugar.md §1.1, §2, §3), one training run on the ``ewa`` (3DGS) kernel:

1. **3DGS warm-up** until step ``warmup_until``: the 2023 3DGS loss 0.8·L1 + 0.2·(1 − SSIM) and its
   densification (`gsbench.training.strategies.default.DefaultStrategy`: clone/split/prune every 100 steps, opacity
   resets), stopped at the end of the warm-up whatever ``refine_stop`` says (SuGaR's 3DGS stops at
   7000 < 15000).
2. **Coarse stage** from step ``warmup_until``: a fresh Adam state (SuGaR builds a new optimizer from
   the 7k checkpoint; the position lr continues along the same log-linear decay), the full SH degree,
   no densification and no opacity reset; the opacity entropy term (``opacity_entropy``, weight 0.1)
   until ``hard_prune_at``.
3. At the start of step ``hard_prune_at``: **hard prune** of the Gaussians with opacity <
   ``hard_prune_opacity`` (0.5), optimizer-aware (`gsbench.training.strategies.base.keep_params`); then the kNN graph
   (``knn_k`` = 16 nearest centres, itself included, scipy cKDTree) is computed, and recomputed every
   ``knn_every`` steps after that. From that step the SDF-estimation regulariser (``sugar_sdf``, weight
   0.2, ``regularizer``: ``density`` by default or ``sdf``) and the normal regulariser (``sugar_normal``,
   weight 0.2) run on ``num_samples`` samples per step (`gsbench.methods.sugar_terms`). SuGaR computes
   the kNN from step 7001 on; before the prune nothing reads it, so it starts at the prune here.
4. **Mesh** (docs/methods/sugar.md §4): ``mesh.extractor: poisson`` — points on the ``mesh.level`` (0.3) set of the
   density field sampled along the rays of every training view, screened Poisson
   (`gsbench.mesh.levelset`). ``tsdf`` is also accepted.

**Schedule.** SuGaR runs 15 000 steps (7000 3DGS + 8000 coarse). Every step-valued setting of gsbench is
for a 30 000-step run and scaled by ``train.iterations / 30000`` (`gsbench.training.trainer`), so SuGaR's step
numbers are doubled here: warm-up 14 000, entropy window 14 000–18 000, prune and regularisers from
18 000, kNN refresh every 1000, and the warm-up's 3DGS schedule (densify from 1000, opacity reset every
6000, position lr decay over 60 000, SH degree +1 every 2000). Any ``train.iterations`` keeps SuGaR's
proportions (7/15 warm-up, entropy to 9/15); ``--set train.iterations=15000`` reproduces SuGaR's step
numbers exactly. The densification interval stays 100 Adam steps (`gsbench.training.trainer.scaled_strategy`).

**Samples per step** (``num_samples``, default 10 000; SuGaR: 1 000 000). The two regularisers cost
≈ 1.8 µs per sample with the fused field kernels (16 neighbours, forward + backward: 18 ms for 10 000
samples on 1 thread, `gsbench bench train --workloads sugar`, AMD EPYC VM; the cost grows linearly with
the sample count, and the kernels' scratch memory by ≈ 0.8 KB per sample). 10 000 is of the order of
one sample per Gaussian at the cpu preset (≈ 10⁴ Gaussians), SuGaR's own ratio (10⁶ samples for ~10⁶
Gaussians). Presets cannot set method fields, so the paper preset uses the same default: SuGaR's 10⁶
over the paper preset's 12 000 regularised steps would add ≈ 6 hours per scene on one thread (by the
linear estimate), hence the deviation; ``--set method.num_samples=1000000`` restores SuGaR's value.

**Refinement** (``method.refinement``: none, short, medium, long; docs/methods/sugar.md §6,
`gsbench.methods.sugar_refine`): after the coarse run, Gaussians bound to the coarse Poisson mesh's
triangles, vertices and Gaussians trained jointly (`second_stage`); the refined mesh is then the evaluated
mesh. ``decimated`` is the control without refinement: the evaluated mesh is the one the refinement would
start from (`refinement_mesh`, decimated alike), the rendered model the coarse one (docs/methods/sugar.md §6.1).
Not reproduced: SuGaR's default ``--eval`` split (docs/methods/sugar.md §6; the benchmark trains every method on
the same views, ``data.holdout_every``), the mesh decimation target being a vertex count (it is a triangle count
here, as Open3D takes it), and the UV texture.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from gsbench.config.run_config import RunConfig
from gsbench.data.camera import Scene
from gsbench.errors import ConfigError, NumericalError
from gsbench.mesh.levelset import levelset_mesh
from gsbench.methods import sugar_terms
from gsbench.methods.base import DEPTH_OUTPUTS, GSConfig, Method, MethodInfo, _export_atomic
from gsbench.methods.sugar_refine import SugarRefinement, bound_mesh, check_refinement, refinement_config
from gsbench.training.strategies.base import Strategy, keep_params
from gsbench.training.strategies.default import DefaultStrategy
from gsbench.training.trainer import scale_step


@dataclass
class SugarConfig(GSConfig):
    """SuGaR coarse-stage hyper-parameters (module docstring); step values for a 30 000-step run, i.e.
    SuGaR's 15 000-step numbers doubled, including the 3DGS warm-up's own schedule (docs/methods/sugar.md §1.2, §1.3)."""

    position_lr_max_steps: int = 60000
    sh_interval: int = 2000
    refine_start: int = 1000
    refine_stop: int = 30000
    reset_every: int = 6000
    warmup_until: int = 14000
    hard_prune_at: int = 18000
    hard_prune_opacity: float = 0.5
    knn_k: int = sugar_terms.KNN_K
    knn_every: int = 1000
    regularizer: str = "density"
    num_samples: int = sugar_terms.NUM_SAMPLES
    # the refinement stage (docs/methods/sugar.md §6), added after the suites' records: at these defaults they are
    # left out of the run id (gsbench.config.run_config.ADDED_AFTER_RECORDS), so the coarse-only runs keep theirs;
    # none | decimated (the control: the refinement's starting mesh, not refined) | short | medium | long
    refinement: str = "none"
    refine_gaussians_per_triangle: int = 1
    refine_triangles: int = 50_000


class SuGaR(Method):
    """SuGaR's coarse stage: 3DGS warm-up, entropy, hard prune, density/normal regularisers, Poisson mesh.

    The mesh (``mesh.extractor: poisson``, configs/methods/sugar.yaml) is the coarse mesh (docs/methods/sugar.md §4),
    with ``refinement`` on the refined one (docs/methods/sugar.md §6), with ``refinement: decimated`` the refinement's
    starting mesh (docs/methods/sugar.md §6.1).
    """

    name = "sugar"
    Config = SugarConfig
    INFO = MethodInfo(primitive="3d", kernel="ewa", outputs=("rgb", "alpha", "depth", "median_depth"))
    MESH_EXTRACTORS = ("poisson", "tsdf")

    def check_params(self) -> None:
        """The base checks, the coarse-stage schedule, the prune threshold, the kNN and the regulariser."""
        super().check_params()
        p = self.params
        if not 0 < p.warmup_until <= p.hard_prune_at:
            raise ConfigError(f"SuGaR needs 0 < method.warmup_until <= method.hard_prune_at, got "
                              f"{p.warmup_until} and {p.hard_prune_at} (steps of a 30 000-step run)")
        if not 0.0 <= p.hard_prune_opacity < 1.0:
            raise ConfigError(f"method.hard_prune_opacity must be in [0, 1), got {p.hard_prune_opacity}")
        if p.knn_k < 1 or p.knn_every < 1:
            raise ConfigError(f"method.knn_k and method.knn_every must be >= 1, got {p.knn_k} and {p.knn_every}")
        sugar_terms.check_mode(p.regularizer)
        sugar_terms.check_samples(p.num_samples)
        check_refinement(p, self.cfg)

    def setup(self, scene: Scene, cfg: RunConfig) -> None:
        super().setup(scene, cfg)
        self.knn: torch.Tensor | None = None

    def strategy(self) -> Strategy:
        """3DGS densification (docs/methods/3dgs.md §5.3) during the warm-up only (docs/methods/sugar.md §3.1: none in
        the coarse stage)."""
        settings = self.densify_settings()
        settings["refine_stop"] = min(self.params.refine_stop, self.params.warmup_until)
        return DefaultStrategy(**settings)

    def term_params(self) -> dict[str, dict]:
        """The regulariser mode and sample count; the sdf mode's extent normaliser and znear (docs/methods/sugar.md §3.7)."""
        p = self.params
        params = {"sugar_sdf": {"mode": p.regularizer, "num_samples": p.num_samples, "extent": self.extent,
                                "near": self.raster_settings().near},
                  "sugar_normal": {"mode": p.regularizer, "num_samples": p.num_samples}}
        return {k: v for k, v in params.items() if k in self.cfg.losses}

    def loss_state(self) -> dict:
        return {"gaussians": self.gaussians, "knn": self.knn}

    def update_schedules(self, step: int, scale: float) -> None:
        """3DGS lr/SH schedules; the coarse-stage switch, the hard prune and the kNN refresh (module docstring)."""
        p = self.params
        coarse_from = scale_step(p.warmup_until, scale)
        prune_at = scale_step(p.hard_prune_at, scale)
        if step == coarse_from:
            self.optimizer.state.clear()  # fresh Adam moments and step counts (docs/methods/sugar.md §3.1)
        super().update_schedules(step, scale)
        if step >= coarse_from:
            self.sh_degree = self.cfg.raster.sh_degree
        if step == prune_at:
            self.hard_prune(step)
        refresh = step == prune_at or (step > prune_at and step % scale_step(p.knn_every, scale) == 0)
        if refresh or (step > prune_at and self.knn is None):  # the latter: a start past the prune (bench train)
            self.knn = sugar_terms.knn_indices(self.gaussians.means, p.knn_k)

    def hard_prune(self, step: int) -> None:
        """Keep the Gaussians with opacity >= ``hard_prune_opacity``, in parameters and Adam state (docs/methods/sugar.md §3.3)."""
        keep = self.gaussians.opacities.detach() >= self.params.hard_prune_opacity
        if not bool(keep.any()):
            raise NumericalError(f"step {step}: the SuGaR hard prune (opacity < {self.params.hard_prune_opacity}) "
                                 f"would remove all {len(self.gaussians)} Gaussians; train longer or lower "
                                 "method.hard_prune_opacity")
        keep_params(self.gaussians, self.optimizer, keep)

    @torch.no_grad()
    def extract_mesh(self, scene: Scene, cfg: RunConfig, out_path) -> dict:
        """``poisson``: SuGaR's level-set points + screened Poisson (docs/methods/sugar.md §4); other extractors as `Method`.
        With ``refinement: decimated``, whatever the extractor (as the refined mesh): the mesh the refinement starts
        from, its vertices and faces as `bound_mesh` gives them (docs/methods/sugar.md §6.1)."""
        if self.params.refinement == "decimated":
            vertices, faces = bound_mesh(self.refinement_mesh(scene, cfg))
            mesh = trimesh.Trimesh(vertices.double().numpy(), faces.numpy(), process=False)
        elif cfg.mesh.extractor != "poisson":
            return super().extract_mesh(scene, cfg, out_path)
        else:
            mesh = self.coarse_mesh(scene, cfg.mesh, cfg.seed)
        _export_atomic(mesh, Path(out_path))
        return {"vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces))}

    @torch.no_grad()
    def coarse_mesh(self, scene: Scene, mesh_cfg, seed: int):
        """SuGaR's coarse Poisson mesh of the trained Gaussians (docs/methods/sugar.md §4)."""
        views = scene.train_views
        cameras = [scene.cameras[i] for i in views]
        masks = [scene.masks[i] for i in views] if self.cfg.data.use_masks and scene.masks is not None else None
        return levelset_mesh(self.raster_input(), cameras, self.raster_settings(), mesh_cfg, kernel=self.info().kernel,
                             depth_output=DEPTH_OUTPUTS[mesh_cfg.depth], centre=np.mean([c.center for c in cameras], 0),
                             extent=self.extent, masks=masks, seed=seed)

    # ---- the refinement (methods/sugar_refine.py) ---------------------------------------------
    def second_stage_config(self, cfg: RunConfig) -> RunConfig | None:
        return None if self.params.refinement in ("none", "decimated") else refinement_config(cfg)

    def second_stage(self, scene: Scene, cfg: RunConfig, second_cfg: RunConfig) -> SugarRefinement:
        """Gaussians bound to `refinement_mesh`."""
        return SugarRefinement.from_coarse(self, self.refinement_mesh(scene, cfg), second_cfg)

    def refinement_mesh(self, scene: Scene, cfg: RunConfig):
        """The coarse Poisson mesh with each part decimated to ``refine_triangles`` triangles (docs/methods/sugar.md §6)."""
        mesh_cfg = dataclasses.replace(cfg.mesh, poisson_triangles=self.params.refine_triangles)
        return self.coarse_mesh(scene, mesh_cfg, cfg.seed)

    def state_dict(self) -> dict:
        return {**super().state_dict(), "knn": None if self.knn is None else self.knn.clone()}

    def load_state_dict(self, state: dict) -> None:
        """`Method.load_state_dict` plus the kNN graph (recomputing it would change a resumed run)."""
        super().load_state_dict(state)
        self.knn = None if state["knn"] is None else state["knn"].clone()
