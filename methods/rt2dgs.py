"""Ray-traced 2D Gaussians for transparent objects ("Ray-Tracing Enhanced 2D Gaussian Splatting for Transparent
Object Reconstruction"), docs/methods/rt2dgs.md.

2DGS (`gsbench.methods.gs2d`) plus a transparent interface: each surfel has a learned transparency τ_i in
(0, 1) and the interface one learned index of refraction η (> 1, initial ``ior``). A pixel's colour is

    C = Σ_i w_i (1 − τ_i) c_i + τ̄ L,    τ̄ = Σ_i w_i τ_i,

the first two rasterised (the shared rasterizer, ``surfel`` kernel, colours (1 − τ_i) c_i and τ_i as
degree-0 colours of two passes), L the light the interface lets through and reflects, traced from the
pixel's surface point x = camera + D·ray (D the median depth) with the rendered normal N
(`gsbench.geometry.optics`, rays through the surfels by `gsbench.raster.surfel_rays`):

    L = R₁ E(reflect) + (1 − R₁)(1 − R₂) E(out)

R₁ the Fresnel reflectance entering at x (air to η), the refracted ray traced through the surfels to the
exit interface (its τ-weighted depth and normal), R₂ the reflectance leaving there (η to air; total
internal reflection: 1), E(ray) = Σ_j w_j (1 − τ_j) c_j along a ray (what opaque surfels it meets). Two
interfaces and one reflection: the bounded tree (docs/methods/rt2dgs.md §2). L is traced at up to
``trace_pixels`` pixels per render (a regular sub-grid with a random offset per step, nearest-neighbour
filled between them) whose τ̄ exceeds ``trace_min_transparency``; elsewhere τ̄ L is left out. The held-out
images (``render_image``) trace every such pixel, as the paper's renderer does. With
``transparency_gradient`` "traced" (the default) τ learns only at the traced pixels: the filled ones copy
a neighbour's L, so their dC/dτ = L − c is wrong; "filled" takes it from every pixel. The light
is traced from step ``trace_from`` (7 000 of 30 000, scaled to the run); before it the render is 2DGS's and
τ gets no gradient, so the transparency is not driven to 0 by a traced light computed on the first,
noisy surfaces (docs/methods/rt2dgs.md §8).

Losses (configs/methods/rt2dgs.yaml): 0.8 L1 + 0.2 D-SSIM of C, 2DGS's depth distortion (λ_d = 1000) and
normal consistency (λ_n = 0.2, the paper's value), and ``normal_smoothness`` (λ = 0.3):
L_smooth = mean over neighbour pairs (i, j) of log(2 / (|n_i·n_j| + 1)) / (d_ij + ε), j among the
``smooth_neighbours`` nearest surfels of i. Surfel scales are s = ``min_scale`` x radius + exp(log s)
(the paper's minimum eigenvalue), SH degrees grow as in 3DGS (the paper's progressive SH).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F

from gsbench.errors import ConfigError
from gsbench.geometry.neighbours import NeighbourIndex, rows
from gsbench.geometry.optics import fresnel, reflect, refract
from gsbench.losses.terms import Batch, loss_term, method_state
from gsbench.methods.base import ADAM_EPS, DEPTH_OUTPUTS, MethodInfo
from gsbench.methods.gs2d import GS2D, GS2DConfig
from gsbench.raster import rasterize
from gsbench.raster.reference_projection import eval_sh
from gsbench.raster.sh import C0 as SH_C0
from gsbench.raster.surfel_rays import CandidateIndex, surfel_axes, trace_pairs
from gsbench.raster.types import RasterGaussians, RenderOutput
from gsbench.training.optim import make_adam
from gsbench.training.trainer import scale_step

IOR_MAX = 3.0  # the learned index lives in (1, IOR_MAX): η = 1 + (IOR_MAX − 1) sigmoid(raw)
EXIT_MIN = 0.1  # Σ w τ along the refracted ray below which no exit interface is found (the ray goes on)
TRACE_CHUNK = 4096  # pixels traced at once (each ray's surfel pairs are held at once: memory, not results)
TRANSPARENCY_GRADIENTS = ("traced", "filled")  # docs/methods/rt2dgs.md §4


@dataclass
class RT2DGSConfig(GS2DConfig):
    """2DGS's parameters plus the transparent interface (docs/methods/rt2dgs.md §3: which values the paper
    gives and which are chosen here)."""

    ior: float = 1.5
    learn_ior: bool = True
    ior_lr: float = 0.001
    transparency_init: float = 0.1
    transparency_lr: float = 0.05
    min_scale: float = 0.0005
    trace_pixels: int = 256
    trace_from: int = 7000  # step (of 30 000, scaled) of the first traced light (2DGS's before); past the run: never
    trace_min_transparency: float = 0.02
    transparency_gradient: str = "traced"  # where τ learns: "traced" pixels only, or every "filled" one as well
    smooth_neighbours: int = 8
    smooth_epsilon: float = 0.001
    smooth_refresh: int = 100


def logit(p: float) -> float:
    return math.log(p / (1 - p))


class RT2DGS(GS2D):
    """2DGS with a transparent, refracting interface (module docstring)."""

    name = "rt2dgs"
    Config = RT2DGSConfig
    INFO = MethodInfo(primitive="2d", kernel="surfel",
                      outputs=("rgb", "alpha", "depth", "median_depth", "normal", "distortion"))

    def __init__(self):
        super().__init__()
        self.ior_raw: torch.nn.Parameter | None = None
        self.neighbours: NeighbourIndex | None = None
        self.step = 0
        self.scale = 1.0

    def check_params(self) -> None:
        super().check_params()
        p = self.params
        if not 1.0 < p.ior < IOR_MAX:
            raise ConfigError(f"method.ior must be in (1, {IOR_MAX}), got {p.ior}")
        if not 0.0 < p.transparency_init < 1.0:
            raise ConfigError(f"method.transparency_init must be in (0, 1), got {p.transparency_init}")
        if p.transparency_gradient not in TRANSPARENCY_GRADIENTS:
            raise ConfigError(f"method.transparency_gradient must be one of {', '.join(TRANSPARENCY_GRADIENTS)}, "
                              f"got {p.transparency_gradient!r}")
        if p.trace_from < 0:
            raise ConfigError(f"method.trace_from must be >= 0 (a step of 30 000), got {p.trace_from}")
        for name in ("trace_pixels", "smooth_neighbours", "smooth_refresh"):
            if getattr(p, name) < 1:
                raise ConfigError(f"method.{name} must be >= 1, got {getattr(p, name)}")
        if p.min_scale < 0 or p.smooth_epsilon <= 0:
            raise ConfigError(f"method.min_scale must be >= 0 and method.smooth_epsilon > 0, got {p.min_scale}, "
                              f"{p.smooth_epsilon}")

    def setup(self, scene, cfg) -> None:
        super().setup(scene, cfg)
        p = self.params
        n = len(self.gaussians)
        self.gaussians.params["transparency_logits"] = torch.nn.Parameter(torch.full((n, 1), logit(p.transparency_init)))
        self.ior_raw = torch.nn.Parameter(torch.tensor(logit((p.ior - 1) / (IOR_MAX - 1))), requires_grad=p.learn_ior)
        self.neighbours = NeighbourIndex(p.smooth_neighbours)
        self.optimizer = self.make_optimizer(self.gaussians)

    def make_optimizer(self, gaussians) -> torch.optim.Optimizer:
        lrs = {**self.learning_rates(), "transparency_logits": self.params.transparency_lr}
        groups = [{"params": [param], "name": name, "lr": lrs[name]} for name, param in gaussians.params.items()
                  if param.requires_grad]
        if self.ior_raw is not None and self.ior_raw.requires_grad:
            groups.append({"params": [self.ior_raw], "name": "ior", "lr": self.params.ior_lr})
        return make_adam(groups, self.cfg.train.optimizer, ADAM_EPS)

    # ---- the interface ------------------------------------------------------------------------
    @property
    def ior(self) -> torch.Tensor:
        return 1.0 + (IOR_MAX - 1.0) * torch.sigmoid(self.ior_raw)

    @property
    def transparency(self) -> torch.Tensor:
        return torch.sigmoid(self.gaussians.params["transparency_logits"][:, 0])

    def raster_input(self) -> RasterGaussians:
        """2DGS's activated surfels with the scale floor ``min_scale`` x scene radius added."""
        g = super().raster_input()
        g.scales = g.scales + self.params.min_scale * self.scene_radius
        return g

    def _colours(self, g: RasterGaussians, camera) -> torch.Tensor:
        """Each surfel's colour (N, 3) seen from ``camera``: SH at the active degree + 0.5, clamped at 0
        (what the rasterizer computes per Gaussian)."""
        centre = torch.as_tensor(camera.center, dtype=g.means.dtype)
        dirs = F.normalize(g.means - centre, dim=-1)
        return (eval_sh(g.all_sh(), dirs, self.sh_degree) + 0.5).clamp_min(0.0)

    def tracing(self) -> bool:
        """Whether the light is traced at this step (from ``trace_from``, scaled to the run)."""
        return self.step >= scale_step(self.params.trace_from, self.scale)

    def render(self, camera, outputs) -> RenderOutput:
        """The pixel colour of the module docstring from ``trace_from`` on (2DGS's before it, τ unused), the light
        traced on the training's sub-grid; other outputs are 2DGS's (the surfaces)."""
        return self._render(camera, outputs, every_pixel=False)

    def render_image(self, camera) -> torch.Tensor:
        """The held-out image: `render`'s colour with the light traced at every candidate pixel, as the paper's
        renderer does (the sub-grid and its fill are the training's CPU budget, docs/methods/rt2dgs.md §4)."""
        return self._render(camera, {"rgb"}, every_pixel=True).rgb

    def _render(self, camera, outputs, every_pixel: bool) -> RenderOutput:
        outputs = set(outputs)
        if "rgb" not in outputs or not self.tracing():
            return super().render(camera, outputs)
        g = self.raster_input()
        tau = self.transparency
        only_traced = self.params.transparency_gradient == "traced"
        tau_opaque = tau.detach() if only_traced else tau  # the opaque pass's τ ("traced": no gradient through it)
        colours = self._colours(g, camera)
        settings = self.raster_settings()
        degree0 = lambda c: ((c - 0.5) / SH_C0)[:, None, :]  # noqa: E731  (a colour as a degree-0 SH row)
        opaque = rasterize(RasterGaussians(g.means, g.quats, g.scales, g.opacities, degree0((1 - tau_opaque)[:, None] * colours)),
                           camera, kernel="surfel", outputs=tuple(sorted(outputs | {"median_depth", "normal", "alpha"})),
                           settings=_degree0(settings, settings.background))
        clear = rasterize(RasterGaussians(g.means, g.quats, g.scales, g.opacities, degree0(tau[:, None].expand(-1, 3))),
                          camera, kernel="surfel", outputs=("rgb",), settings=_degree0(settings, (0.0, 0.0, 0.0)))
        tau_map = clear.rgb[..., 0]
        light, traced = self._traced_light(camera, opaque, tau_map, g, tau, colours, every_pixel)
        if not only_traced:
            opaque.rgb = opaque.rgb + tau_map[..., None] * light
            return opaque
        if not bool(traced.any()):
            return opaque
        # τ learns only where L was traced (docs/methods/rt2dgs.md §4): there C gets −Σ w τ c through a pass that
        # carries τ's gradient alone (zero in value), elsewhere the τ̄ L term is held fixed
        shift = rasterize(RasterGaussians(g.means.detach(), g.quats.detach(), g.scales.detach(), g.opacities.detach(),
                                          degree0(tau[:, None] * colours.detach())),
                          camera, kernel="surfel", outputs=("rgb",), settings=_degree0(settings, (0.0, 0.0, 0.0))).rgb
        mask = traced[..., None]
        through = tau_map[..., None] * light
        opaque.rgb = (opaque.rgb - torch.where(mask, shift - shift.detach(), torch.zeros_like(shift))
                      + torch.where(mask, through, through.detach()))
        return opaque

    def mesh_depth(self, camera, cfg):
        """2DGS's depth for the TSDF, its render's colour without the traced light (the TSDF's colours only
        paint the mesh; tracing them would cost every training view's light)."""
        key = DEPTH_OUTPUTS[cfg.mesh.depth]
        out = super().render(camera, {key, "alpha", "rgb"})
        return getattr(out, key), out

    def _traced_light(self, camera, out: RenderOutput, tau_map: torch.Tensor, g: RasterGaussians, tau: torch.Tensor,
                      colours: torch.Tensor, every_pixel: bool) -> torch.Tensor:
        """(L (H, W, 3) at the traced sub-grid, nearest-filled, 0 where τ̄ is below the threshold; the traced
        pixels (H, W) bool). ``every_pixel``: every candidate is traced (stride 1, no fill), ``TRACE_CHUNK`` rays
        at a time."""
        p = self.params
        H, W = tau_map.shape
        light = torch.zeros(H, W, 3, dtype=colours.dtype)
        candidates = (tau_map.detach() > p.trace_min_transparency) & (out.median_depth.detach() > 0)
        count = int(candidates.sum())
        if count == 0:
            return light, torch.zeros(H, W, dtype=torch.bool)
        stride = 1 if every_pixel else max(1, math.ceil(math.sqrt(count / p.trace_pixels)))
        oy, ox = (int(v) for v in torch.randint(0, stride, (2,))) if stride > 1 else (0, 0)
        grid = torch.zeros(H, W, dtype=torch.bool)
        grid[oy::stride, ox::stride] = True
        traced = grid & candidates
        pick = traced.nonzero()
        if len(pick) == 0:
            return light, traced
        ys, xs = pick[:, 0], pick[:, 1]
        R = torch.as_tensor(camera.R, dtype=colours.dtype)
        pixel = torch.stack([xs + 0.5, ys + 0.5, torch.ones_like(xs, dtype=torch.float64)], -1).to(colours.dtype)
        ray = pixel @ torch.as_tensor(camera.K, dtype=colours.dtype).inverse().T @ R  # world direction, camera z = 1
        centre = torch.as_tensor(camera.center, dtype=colours.dtype)
        x = centre + out.median_depth[ys, xs, None] * ray
        normal = F.normalize(out.normal[ys, xs] @ R, dim=-1)  # camera to world; faces the camera
        view, near = F.normalize(ray, dim=-1), 1e-4 * self.scene_radius
        index = CandidateIndex(g.means, g.quats, g.scales)
        chunks = [slice(k, k + TRACE_CHUNK) for k in range(0, len(x), TRACE_CHUNK)]
        sampled = torch.cat([trace_interface(x[c], view[c], normal[c], self.ior, g, tau, colours, near, index)
                             for c in chunks])
        block = torch.zeros(H, W, 3, dtype=colours.dtype)
        block[ys, xs] = sampled
        # nearest fill: every candidate pixel takes the traced value of its sub-grid cell's corner
        cy = (torch.arange(H) - oy).clamp_min(0) // stride * stride + oy
        cx = (torch.arange(W) - ox).clamp_min(0) // stride * stride + ox
        filled = block[cy.clamp_max(H - 1)][:, cx.clamp_max(W - 1)]
        return torch.where(candidates[..., None], filled, light), traced

    # ---- losses, schedules, checkpoints --------------------------------------------------------
    def loss_state(self) -> dict:
        return {"gaussians": self.gaussians, "rt2dgs": self}

    def update_schedules(self, step: int, scale: float) -> None:
        super().update_schedules(step, scale)
        self.step, self.scale = step, scale

    def neighbour_index(self) -> torch.Tensor:
        """The kNN index of the surfel centres, refreshed every ``smooth_refresh`` steps and whenever the
        rows changed (densification, pruning)."""
        n = len(self.gaussians)
        if len(self.neighbours.index) != n or self.step % self.params.smooth_refresh == 0:
            self.neighbours.refresh(self.gaussians.means)
        return self.neighbours.check(n)

    def state_dict(self) -> dict:
        return {**super().state_dict(), "ior_raw": self.ior_raw.detach().clone(),
                "neighbours": self.neighbours.state_dict(), "step": self.step, "scale": self.scale}

    def load_state_dict(self, state: dict) -> None:
        """The state, and the step (whether the light is traced), so a finished run loaded back renders as at its
        last step; checkpoints from before the step was kept load at step 0, as they did then."""
        self.ior_raw = torch.nn.Parameter(state["ior_raw"].clone(), requires_grad=self.params.learn_ior)
        self.neighbours.load_state_dict(state["neighbours"])
        self.step, self.scale = int(state.get("step", 0)), float(state.get("scale", 1.0))
        super().load_state_dict(state)


def _degree0(settings, background):
    """``settings`` rendering degree-0 colours over ``background``."""
    return replace(settings, sh_degree=0, background=background)


def surface_light(origins: torch.Tensor, directions: torch.Tensor, g: RasterGaussians, tau: torch.Tensor,
                  colours: torch.Tensor, near: float, through_glass: bool, index: CandidateIndex | None = None):
    """(E (R,3), Σ w τ (R,), Σ w τ t (R,), Σ w τ n (R,3)) along rays: the opaque light Σ w (1 − τ) c and the
    τ-weighted sums that place the next interface (module docstring). ``through_glass``: the surfels'
    opacities are o (1 − τ), so the glass does not stop the ray (what lies beyond it; the bounded tree
    ignores further interfaces); else o, to find the interface. ``index``: the surfels' `CandidateIndex`
    (built here when None)."""
    opacities = g.opacities * (1 - tau) if through_glass else g.opacities
    index = index or CandidateIndex(g.means, g.quats, g.scales)
    ray, surfel = index.pairs(origins, directions)
    features = torch.cat([(1 - tau)[:, None] * colours, tau[:, None]], 1)
    out = trace_pairs(origins, directions, g.means, g.quats, g.scales, opacities, features, ray, surfel, near)
    w_tau = out.weights * tau[out.surfel]
    depth = torch.zeros(len(origins), dtype=colours.dtype).index_add(0, out.ray, w_tau * out.t)
    normal = torch.zeros(len(origins), 3, dtype=colours.dtype).index_add(0, out.ray, w_tau[:, None] * out.pair_normal)
    return out.features[:, :3], out.features[:, 3], depth, normal


def trace_interface(x: torch.Tensor, view: torch.Tensor, normal: torch.Tensor, ior: torch.Tensor, g: RasterGaussians,
                    tau: torch.Tensor, colours: torch.Tensor, near: float,
                    index: CandidateIndex | None = None) -> torch.Tensor:
    """L (R, 3) at surface points ``x`` seen along unit ``view`` with unit normals ``normal`` facing the
    viewer (module docstring): one reflection, the refraction in, the exit found along it, the refraction out.
    ``index``: the surfels' `CandidateIndex` (built here when None)."""
    one = torch.ones((), dtype=x.dtype)
    index = index or CandidateIndex(g.means, g.quats, g.scales)
    n = torch.where(((view * normal).sum(-1, keepdim=True) > 0), -normal, normal)  # facing the incoming ray
    r1 = fresnel(-(view * n).sum(-1), one, ior)
    reflected = F.normalize(reflect(view, n), dim=-1)
    e_reflect = surface_light(x, reflected, g, tau, colours, near, through_glass=True, index=index)[0]
    inward, _ = refract(view, n, 1.0 / ior)
    inward = F.normalize(inward, dim=-1)
    e_in, w_exit, depth, exit_normal = surface_light(x, inward, g, tau, colours, near, through_glass=False, index=index)
    found = w_exit > EXIT_MIN
    t_exit = depth / w_exit.clamp_min(EXIT_MIN)
    y = x + t_exit[:, None] * inward
    m = F.normalize(exit_normal, dim=-1)  # faces the ray inside the glass
    r2 = fresnel(-(inward * m).sum(-1), ior, one)
    outward, tir = refract(inward, m, ior)
    outward = F.normalize(torch.where(tir[:, None], inward, outward), dim=-1)
    e_out = surface_light(y, outward, g, tau, colours, near, through_glass=True, index=index)[0]
    through = torch.where(found[:, None], (1 - r2)[:, None] * e_out, e_in)
    return r1[:, None] * e_reflect + (1 - r1)[:, None] * through


def normal_smoothness_term(render, batch: Batch, state: dict) -> torch.Tensor:
    """L_smooth = mean over the kNN pairs (i, j) of log(2 / (|n_i·n_j| + 1)) / (d_ij + ε) (the paper's eq.;
    n the surfel normals, d_ij the centres' distance, ε = ``smooth_epsilon`` x scene radius)."""
    method = method_state(state, "rt2dgs", "normal_smoothness")
    g = method.gaussians
    index = method.neighbour_index()
    if index.shape[1] == 0:
        return g.means.sum() * 0
    normals = surfel_axes(g.params["quats"])[..., 2]
    cos = (normals[:, None, :] * rows(normals, index)).sum(-1).abs()
    distance = (g.means[:, None, :] - rows(g.means, index)).norm(dim=-1).detach()
    eps = method.params.smooth_epsilon * method.scene_radius
    return (torch.log(2.0 / (cos + 1.0)) / (distance + eps)).mean()


NORMAL_SMOOTHNESS = loss_term("normal_smoothness", normal_smoothness_term)

