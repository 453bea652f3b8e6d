"""The method interface: a method declares data (config, kernel, outputs, terms), the Trainer runs the loop.

`Method` implements everything the 3DGS family shares (docs/methods/3dgs.md, docs/design.md §3.1
"Method"); a subclass sets ``Config`` (its paper defaults) and ``INFO`` and overrides what differs.

- ``setup(scene, cfg)``: Gaussians from ``scene.points`` (SfM, all of them unless ``max_init_points``)
  or, without points (DTU IDR layout), ``random_init_points`` random points (3DGS uses 100 000 random
  points in a sphere for Blender scenes); never more than ``train.max_gaussians``. Where they go is
  ``random_init_region``:

  - ``visual_hull`` (default), when the scene has loaded masks: model only what the scene needs.
    Gaussians outside the masks' visual hull (`gsbench.data.visual_hull`) can only model what the
    masks exclude, so the points are the sphere's candidates inside the hull of the *training*
    views' masks (held-out views' masks are never used; ``min_views=1``, ``dilate_px=1`` so the
    silhouette keeps its points). Candidates are drawn exactly as the sphere init draws them (same
    seeded generator, batches of n = ``random_init_points`` capped by ``train.max_gaussians``, random
    colours), so the count is chosen from the hull's volume: the first batch's survivors, i.e. the
    sphere init's density restricted to the hull. Below a floor of min(1000, n) further batches are
    drawn (at most 50) until the floor is reached; never more than n. An empty hull is a `DataError`.
  - ``sphere``, and any scene without masks: ``random_init_points`` uniform in the scene sphere
    (`Scene.sphere`, `Gaussians.random_in_sphere`), the initialisation before the hull rule, bit for bit.
  Adam (``train.optimizer``, `gsbench.training.optim`) with eps 1e-15 and one group per parameter,
  ``group["name"]`` = `Gaussians.params` key (docs/methods/3dgs.md §5.1): means ``position_lr_init·extent``, sh_dc
  ``feature_lr``, sh_rest ``feature_lr/20``, opacity ``opacity_lr``, log-scales ``scaling_lr``,
  quaternions ``rotation_lr``.
- ``extent`` is 3DGS ``cameras_extent``: 1.1 × the largest distance of a training camera centre from
  their mean (docs/methods/3dgs.md §1.3); it scales the position lr and the densification size tests.
- Schedules (`update_schedules`, called by the Trainer every step with the preset's schedule
  ``scale`` = iterations / 30000, `gsbench.training.trainer.scale_step`): position lr
  ``exp((1−t) ln lr0 + t ln lr1)`` with t = min(step / (position_lr_max_steps·scale), 1) (docs/methods/3dgs.md §5.1, no
  delay); SH degree ``min(raster.sh_degree, step // (sh_interval·scale))`` (docs/methods/3dgs.md §2.4: +1 every 1000 steps).
- ``render``: the method's kernel on `Gaussians.raster_input` with the method's `filter3d` variance
  (None here; GOF/RaDe-GS return the Mip-Splatting 3D filter) and `raster_settings`. ``render_image``: the
  colour the held-out image metrics score (``render``'s rgb here; RT2DGS's light traced at every pixel).
- ``extract_mesh``: ``mesh.extractor`` must be in ``MESH_EXTRACTORS`` (``tsdf`` here). ``tsdf``: TSDF
  fusion (`gsbench.mesh.tsdf.tsdf_fusion`, docs/methods/3dgs.md §6; docs/methods/2dgs.md §6) of the depth named by ``mesh.depth``
  (``expected`` → the ``depth`` output, ``median`` → ``median_depth``) rendered from every training
  camera, alpha < 0.5 and (with ``data.use_masks``) pixels outside the mask dropped; TSDF lengths are
  relative to the scene radius; ``mesh.num_clusters`` largest components are kept. ``tets`` (GOF):
  `gsbench.mesh.tets.tetra_mesh` of the raster input over the training cameras at ``mesh.level`` with
  ``mesh.bisection_steps`` (docs/methods/gof.md §7).
- ``state_dict`` / ``load_state_dict``: parameters, Adam state (moments and step counts) and the
  active SH degree, enough for a bit-exact resume (the Trainer adds strategy state and RNGs) and for a
  finished run loaded back to render as at its last step.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from gsbench.atomic import atomic_path
from gsbench.config.run_config import RunConfig
from gsbench.data.camera import Scene
from gsbench.data.visual_hull import inside_visual_hull
from gsbench.errors import ConfigError, DataError
from gsbench.losses.terms import active_terms
from gsbench.mesh.cleanup import canonical_order
from gsbench.mesh.tets import MAX_POINTS, tetra_mesh
from gsbench.mesh.tsdf import tsdf_fusion
from gsbench.raster import RasterGaussians, RasterSettings, RenderOutput, rasterize
from gsbench.training.gaussians import Gaussians
from gsbench.training.optim import make_adam
from gsbench.training.strategies.base import Strategy
from gsbench.training.strategies.default import DefaultStrategy
from gsbench.training.trainer import scale_step

ADAM_EPS = 1e-15  # docs/methods/3dgs.md §5.1, §7
DEPTH_OUTPUTS = {"expected": "depth", "median": "median_depth"}  # mesh.depth -> render output
INIT_REGIONS = ("visual_hull", "sphere")  # method.random_init_region
HULL_INIT_FLOOR = 1000  # fewest random points kept in a visual hull (min with random_init_points)
HULL_INIT_MAX_BATCHES = 50  # candidate batches drawn at most to reach that floor
TETRA_BYTES_PER_POINT = 2800  # peak RSS of the Delaunay tetrahedralisation per point (gsbench.mesh.tets, measured)


@dataclass(frozen=True)
class MethodInfo:
    """What a method's implementation is: its primitive (``3d``|``2d``), its rasterizer kernel and the render
    outputs it may request. Its default choices (loss terms and weights, mesh extractor and depth) are data, in
    its own ``configs/methods/<method>.yaml``."""

    primitive: str
    kernel: str
    outputs: tuple[str, ...]


@dataclass
class GSConfig:
    """3DGS 2023 hyper-parameters (docs/methods/3dgs.md §2, §5); step-valued fields are for a 30 000-step run and are
    scaled by the Trainer to the configured iterations."""

    position_lr_init: float = 0.00016
    position_lr_final: float = 0.0000016
    position_lr_max_steps: int = 30000
    feature_lr: float = 0.0025
    feature_rest_divisor: float = 20.0
    opacity_lr: float = 0.05
    scaling_lr: float = 0.005
    rotation_lr: float = 0.001
    sh_interval: int = 1000
    init_opacity: float = 0.1
    random_init_points: int = 100_000
    random_init_region: str = "visual_hull"
    max_init_points: int = 0
    # densification (docs/methods/3dgs.md §5.3), under `DefaultStrategy`'s names and with its 3DGS defaults
    grad_threshold: float = DefaultStrategy.grad_threshold
    percent_dense: float = DefaultStrategy.percent_dense
    prune_opacity: float = DefaultStrategy.prune_opacity
    refine_start: int = DefaultStrategy.refine_start
    refine_stop: int = DefaultStrategy.refine_stop
    refine_every: int = DefaultStrategy.refine_every
    reset_every: int = DefaultStrategy.reset_every
    reset_value: float = DefaultStrategy.reset_value
    prune_screen_size: bool = DefaultStrategy.prune_screen_size


def cameras_extent(cameras) -> float:
    """3DGS ``getNerfppNorm`` radius: 1.1 × max distance of a camera centre from the centres' mean (docs/methods/3dgs.md §1.3)."""
    centres = np.stack([c.center for c in cameras])
    return float(1.1 * np.linalg.norm(centres - centres.mean(0), axis=1).max())


def expon_lr(t: float, lr0: float, lr1: float) -> float:
    """log-linear interpolation exp((1−t) ln lr0 + t ln lr1), t clamped to [0, 1] (docs/methods/3dgs.md §5.1)."""
    t = min(max(t, 0.0), 1.0)
    return math.exp((1 - t) * math.log(lr0) + t * math.log(lr1))


def _export_atomic(mesh, out_path: Path) -> None:
    """Export a trimesh in `canonical_order` atomically (`gsbench.atomic`; the format from the suffix)."""
    with atomic_path(out_path, keep_suffix=True) as tmp:
        canonical_order(mesh).export(tmp)


class Method:
    """Base class of the 3DGS-family methods (see the module docstring)."""

    name = ""
    Config = GSConfig
    INFO: MethodInfo
    MESH_EXTRACTORS: tuple[str, ...] = ("tsdf",)
    MESH_DEPTHS: tuple[str, ...] = tuple(DEPTH_OUTPUTS)  # accepted mesh.depth values (PGSR adds "unbiased")

    def __init__(self):
        self.gaussians: Gaussians | None = None
        self.optimizer: torch.optim.Optimizer | None = None
        self.sh_degree = 0
        self.extent = 1.0
        self.scene_radius = 1.0

    @classmethod
    def info(cls) -> MethodInfo:
        return cls.INFO

    # ---- setup --------------------------------------------------------------------------------
    def configure(self, cfg: RunConfig) -> None:
        """Bind ``cfg`` without a scene: the method's parameters (its ``Config``) and background, checked by
        `check_params`. `setup` starts here; `check_config` stops here."""
        self.cfg = cfg
        self.params = self.Config(**{k: v for k, v in cfg.method.items() if k != "name"})
        self.background = (1.0, 1.0, 1.0) if cfg.data.white_background else (0.0, 0.0, 0.0)
        self.check_params()

    def check_params(self) -> None:
        """ConfigError for a method, mesh or raster setting out of range (what needs no scene); methods
        with parameters of their own extend it."""
        cfg, p = self.cfg, self.params
        if cfg.mesh.depth not in self.MESH_DEPTHS:
            raise ConfigError(f"mesh.depth must be one of {sorted(self.MESH_DEPTHS)}, got '{cfg.mesh.depth}'")
        self.check_extractor(cfg)
        if p.random_init_region not in INIT_REGIONS:
            raise ConfigError(f"method.random_init_region must be one of {', '.join(INIT_REGIONS)}, "
                              f"got '{p.random_init_region}'")
        if cfg.raster.surfel_filter < 0:
            raise ConfigError(f"raster.surfel_filter must be >= 0 (0 switches the filter off), got "
                              f"{cfg.raster.surfel_filter}")

    def check_extractor(self, cfg: RunConfig) -> None:
        """ConfigError unless ``cfg.mesh.extractor`` is one of the method's `MESH_EXTRACTORS`."""
        if cfg.mesh.extractor not in self.MESH_EXTRACTORS:
            raise ConfigError(f"method '{self.name}' supports mesh.extractor "
                              f"{' or '.join(repr(e) for e in self.MESH_EXTRACTORS)}, got '{cfg.mesh.extractor}'")

    @classmethod
    def check_config(cls, cfg: RunConfig) -> None:
        """Every check of ``cfg`` this method can make without a scene: `check_params`, and each configured
        loss term's name and the parameters the method binds to it (`gsbench.losses.terms.active_terms`)."""
        method = cls()
        method.configure(cfg)
        active_terms(cfg.losses, 0, method.term_params())

    @classmethod
    def gaussian_budget(cls, cfg: RunConfig) -> int:
        """The Gaussian count a memory estimate assumes: ``train.max_gaussians``, else (no cap) the random
        initialisation's ``method.random_init_points``."""
        if cfg.train.max_gaussians > 0:
            return cfg.train.max_gaussians
        return cls.Config(**{k: v for k, v in cfg.method.items() if k != "name"}).random_init_points

    @classmethod
    def memory_estimate(cls, cfg: RunConfig) -> dict[str, int]:
        """Bytes the run will need at its largest, by item, from the configuration alone (`memory_check`):

        - the Gaussians at the budget N = ``train.max_gaussians`` (else ``method.random_init_points``): P float32
          parameters each (means 3, log-scales 3, quaternion 4, opacity 1, SH 3(d+1)² at ``raster.sh_degree`` d),
          held 4 times (values, gradients, Adam's two moments), plus the projection payload and its gradient
          (24 float64 each at most) and the densification statistics (8 float32);
        - one render's buffers at the largest trained image (``data.max_size``, long x short side): 16 float64
          maps and their gradients per pixel.
        - with ``mesh.extractor: tets``, the Delaunay tetrahedralisation of 9 points per Gaussian (at most
          `gsbench.mesh.tets.MAX_POINTS`), measured at 2.8 kB per point (`gsbench.mesh.tets`).
        The scene's images are not counted (their number is not known before the scene is read); methods add
        their own items (IBGS's kNN tables)."""
        n = cls.gaussian_budget(cfg)
        params = 11 + 3 * (cfg.raster.sh_degree + 1) ** 2
        pixels = cfg.data.max_size[0] * cfg.data.max_size[1] if len(cfg.data.max_size) == 2 else 0
        items = {"Gaussians": n * (4 * params * 4 + 2 * 24 * 8 + 8 * 4), "render buffers": pixels * 16 * 8 * 2}
        if cfg.mesh.extractor == "tets":
            items["tetrahedra"] = min(9 * n, MAX_POINTS) * TETRA_BYTES_PER_POINT
        return items

    def setup(self, scene: Scene, cfg: RunConfig) -> None:
        """Create the Gaussians and the optimizer for ``scene`` under the resolved ``cfg``; the scene carries the
        run's view split (`gsbench.runs.runner.load_run_scene`), a ConfigError when it is not ``cfg``'s."""
        self.configure(cfg)
        if scene.holdout_every != cfg.data.holdout_every:
            raise ConfigError(f"scene '{scene.name}' was loaded with the view split holdout_every={scene.holdout_every}, "
                              f"the run's data.holdout_every is {cfg.data.holdout_every}; fix: load it with "
                              "gsbench.runs.runner.load_run_scene(cfg) or load_scene(..., holdout_every=...)")
        self.scene_radius = scene.radius
        views = scene.train_views
        self.extent = cameras_extent([scene.cameras[i] for i in views])
        self.gaussians = self.initial_gaussians(scene, cfg)
        self.optimizer = self.make_optimizer(self.gaussians)
        self.sh_degree = 0

    def initial_gaussians(self, scene: Scene, cfg: RunConfig) -> Gaussians:
        """SfM points (seeded subsample to the caps) or random points in the masks' visual hull or the
        scene sphere (``random_init_region``, module docstring)."""
        p, dims = self.params, 2 if self.info().primitive == "2d" else 3
        rng = np.random.default_rng(cfg.seed)
        if scene.points is not None and len(scene.points):
            points, colors = np.asarray(scene.points), scene.colors
            cap = min(x for x in (p.max_init_points, cfg.train.max_gaussians, len(points)) if x > 0)
            if cap < len(points):
                keep = np.sort(rng.choice(len(points), cap, replace=False))
                points, colors = points[keep], None if colors is None else np.asarray(colors)[keep]
            return Gaussians.from_points(points, colors, dims=dims, max_sh_degree=cfg.raster.sh_degree,
                                         init_opacity=p.init_opacity, seed=cfg.seed)
        n = p.random_init_points if cfg.train.max_gaussians <= 0 else min(p.random_init_points, cfg.train.max_gaussians)
        if n <= 0:
            raise ConfigError(f"scene '{scene.name}' has no SfM points, so method.random_init_points must be > 0")
        if p.random_init_region == "visual_hull" and scene.masks is not None:
            points, colors = self._points_in_visual_hull(scene, cfg, n)
            g = Gaussians.from_points(points, colors, dims=dims, max_sh_degree=cfg.raster.sh_degree, seed=cfg.seed)
        else:
            g = Gaussians.random_in_sphere(n, scene.sphere, dims=dims, max_sh_degree=cfg.raster.sh_degree,
                                           seed=cfg.seed)
        g.params["opacity_logits"].data.fill_(math.log(p.init_opacity / (1 - p.init_opacity)))
        return g

    @staticmethod
    def _points_in_visual_hull(scene: Scene, cfg: RunConfig, n: int) -> tuple[np.ndarray, np.ndarray]:
        """(points, colours) of the random init inside the training views' visual hull (module docstring):
        batches of ``n`` candidates drawn as `Gaussians.random_in_sphere` draws them, the first batch's
        survivors kept, more batches only to reach min(1000, n)."""
        views = scene.train_views
        cameras, masks = [scene.cameras[i] for i in views], [scene.masks[i] for i in views]
        floor = min(HULL_INIT_FLOOR, n)
        rng = np.random.default_rng(cfg.seed)
        points, colors, kept = [], [], 0
        for _ in range(HULL_INIT_MAX_BATCHES):
            direction = rng.normal(size=(n, 3))
            direction /= np.linalg.norm(direction, axis=1, keepdims=True)
            candidates = direction * scene.sphere * rng.uniform(0, 1, size=(n, 1)) ** (1 / 3)
            candidate_colors = rng.uniform(0, 1, size=(n, 3))
            inside = inside_visual_hull(candidates, cameras, masks, dilate_px=1, min_views=1)
            points.append(candidates[inside])
            colors.append(candidate_colors[inside])
            kept += int(inside.sum())
            if kept >= floor:
                break
        if kept == 0:
            raise DataError(f"scene '{scene.name}': the visual hull of its {len(views)} training views' masks is "
                            f"empty (none of {HULL_INIT_MAX_BATCHES} x {n} random points in the scene sphere is seen by a "
                            "training view and inside the mask of every view that sees it); fix: check the masks "
                            "(the object's pixels set, not all empty) and that the cameras see the scene sphere, "
                            "or set method.random_init_region=sphere")
        size = kept if len(points) == 1 else min(kept, floor)  # first batch: its density; more: the floor
        return np.concatenate(points)[:size], np.concatenate(colors)[:size]

    def learning_rates(self) -> dict[str, float]:
        """Initial lr per parameter group (docs/methods/3dgs.md §5.1)."""
        p = self.params
        return {"means": p.position_lr_init * self.extent, "log_scales": p.scaling_lr, "quats": p.rotation_lr,
                "opacity_logits": p.opacity_lr, "sh_dc": p.feature_lr, "sh_rest": p.feature_lr / p.feature_rest_divisor}

    def make_optimizer(self, gaussians: Gaussians) -> torch.optim.Optimizer:
        lrs = self.learning_rates()
        groups = [{"params": [param], "name": name, "lr": lrs[name]} for name, param in gaussians.params.items()
                  if param.requires_grad]
        return make_adam(groups, self.cfg.train.optimizer, ADAM_EPS)  # train.optimizer, gsbench/training/optim.py

    # ---- what the Trainer asks for ------------------------------------------------------------
    def strategy(self) -> Strategy:
        """3DGS densification (docs/methods/3dgs.md §5.3) at the paper's 30k-step schedule; the Trainer scales it."""
        return DefaultStrategy(**self.densify_settings())

    def densify_settings(self, strategy=DefaultStrategy) -> dict:
        """The ``strategy`` fields the method's ``Config`` sets, under the strategy's own names (a method declares
        its densification once, in its ``Config``), and the run's: background, scene extent, Gaussian budget."""
        names = {f.name for f in dataclasses.fields(strategy)}
        own = {k: v for k, v in dataclasses.asdict(self.params).items() if k in names}
        return {**own, "white_background": self.cfg.data.white_background, "scene_extent": self.extent,
                "max_gaussians": self.cfg.train.max_gaussians}

    def term_params(self) -> dict[str, dict]:
        """Parameters bound to registered terms (`gsbench.losses.terms.active_terms` ``params``)."""
        return {}

    def loss_state(self) -> dict:
        """The ``state`` argument of the loss terms."""
        return {"gaussians": self.gaussians}

    def update_schedules(self, step: int, scale: float) -> None:
        """Position lr decay and SH degree for ``step`` (module docstring); ``scale`` = iterations/30000."""
        p = self.params
        t = step / scale_step(p.position_lr_max_steps, scale)
        lr = expon_lr(t, p.position_lr_init * self.extent, p.position_lr_final * self.extent)
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = lr
        self.sh_degree = min(self.cfg.raster.sh_degree, step // scale_step(p.sh_interval, scale))

    def training_phases(self) -> dict[str, float]:
        """Seconds of training spent in named method-specific phases (none here; IBGS: kNN, eigen)."""
        return {}

    def filter3d(self) -> torch.Tensor | None:
        """The 3D-filter variance (N,) the rasterizer applies; none for 3DGS/2DGS."""
        return None

    def raster_settings(self) -> RasterSettings:
        """The render settings of the current step (``raster`` config, background, active SH degree)."""
        r = self.cfg.raster
        return RasterSettings(sh_degree=self.sh_degree, background=self.background, near_plane=r.near_plane,
                              far_plane=r.far_plane, scene_radius=self.scene_radius, antialias2d=r.antialias2d,
                              eps2d=None if r.eps2d < 0 else r.eps2d, surfel_filter=r.surfel_filter)

    def raster_input(self) -> RasterGaussians:
        """The activated Gaussians the kernel renders (active SH degree, the method's 3D filter)."""
        return self.gaussians.raster_input(self.filter3d())

    def render(self, camera, outputs) -> RenderOutput:
        """Rasterize the current Gaussians with the method's kernel; only ``outputs`` are computed."""
        return rasterize(self.raster_input(), camera, kernel=self.info().kernel, outputs=tuple(sorted(outputs)),
                         settings=self.raster_settings())

    def render_image(self, camera) -> torch.Tensor:
        """The colour image (H, W, 3) the held-out image metrics score (module docstring)."""
        return self.render(camera, {"rgb"}).rgb

    # ---- a second stage -------------------------------------------------------------------------
    def second_stage_config(self, cfg: RunConfig) -> RunConfig | None:
        """The run config of a second model trained from this one before meshing (SuGaR's refinement), or None."""
        return None

    def second_stage(self, scene: Scene, cfg: RunConfig, second_cfg: RunConfig) -> "Method":
        """The second model, built from this trained one (`second_stage_config` is not None)."""
        raise NotImplementedError(f"method '{self.name}' has no second stage")

    def describe(self) -> dict:
        """What a second stage reports into the record's inputs (sizes)."""
        return {}

    # ---- mesh ---------------------------------------------------------------------------------
    @torch.no_grad()
    def extract_mesh(self, scene: Scene, cfg: RunConfig, out_path) -> dict:
        """Mesh the trained Gaussians with ``mesh.extractor`` into ``out_path`` (.ply); returns its size."""
        self.check_extractor(cfg)
        views = scene.train_views
        if cfg.mesh.extractor == "tets":
            mesh = tetra_mesh(self.raster_input(), [scene.cameras[i] for i in views], self.raster_settings(),
                              kernel=self.info().kernel, level=cfg.mesh.level, bisection_steps=cfg.mesh.bisection_steps)
        else:
            mesh = self._tsdf_mesh(scene, cfg, views)
        _export_atomic(mesh, Path(out_path))
        return {"vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces))}

    def _tsdf_mesh(self, scene: Scene, cfg: RunConfig, views: list[int]):
        """TSDF fusion of ``mesh.depth`` rendered from the training ``views`` (module docstring)."""
        depths, colors, alphas = [], [], []
        for i in tqdm(views, desc="extract", unit="view", disable=None, leave=False):
            depth, out = self.mesh_depth(scene.cameras[i], cfg)
            depths.append(depth.numpy())
            colors.append(out.rgb.clamp(0, 1).numpy())
            alphas.append(out.alpha.numpy())
        masks = [scene.masks[i] for i in views] if cfg.data.use_masks and scene.masks is not None else None
        return tsdf_fusion(depths, [scene.cameras[i] for i in views], cfg.mesh, scene.radius, colors=colors,
                           alphas=alphas, masks=masks)

    def mesh_depth(self, camera, cfg: RunConfig) -> tuple[torch.Tensor, RenderOutput]:
        """The depth (H, W) the TSDF fuses for ``camera`` (``mesh.depth``) and the render holding its rgb and alpha."""
        key = DEPTH_OUTPUTS[cfg.mesh.depth]
        out = self.render(camera, {key, "alpha", "rgb"})
        return getattr(out, key), out

    # ---- checkpoints --------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"params": {k: v.detach().clone() for k, v in self.gaussians.params.items()},
                "learned": sorted(k for k, v in self.gaussians.params.items() if v.requires_grad),
                "max_sh_degree": self.gaussians.max_sh_degree, "optimizer": self.optimizer.state_dict(),
                "sh_degree": self.sh_degree}

    def load_state_dict(self, state: dict) -> None:
        """Replace Gaussians and optimizer by the checkpointed ones (after `setup`)."""
        if set(state["params"]) != set(self.gaussians.params):
            raise ConfigError(f"checkpoint of method '{self.name}' holds parameters {sorted(state['params'])}, "
                              f"expected {sorted(self.gaussians.params)}; was it written by another method?")
        self.gaussians = Gaussians(**{k: v.clone() for k, v in state["params"].items()},
                                   max_sh_degree=state["max_sh_degree"])
        for name in state.get("learned", ()):  # a method's own learned per-Gaussian rows (RT2DGS's transparency)
            self.gaussians.params[name].requires_grad_(True)
        self.optimizer = self.make_optimizer(self.gaussians)
        self.optimizer.load_state_dict(state["optimizer"])
        self.sh_degree = int(state["sh_degree"])
