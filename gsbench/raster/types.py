"""Inputs, settings and outputs of `gsbench.raster.rasterize` — the contract every kernel follows.

Both the fast path (per-Gaussian projection in PyTorch + C++/OpenMP compositing) and the dense
reference (`gsbench.raster.reference`) implement exactly these definitions; tests compare them.

Camera (see `gsbench.data.camera`): world-to-camera ``x_c = R x_w + t``; pixel (i, j) (column i,
row j) is evaluated at ``p = (i + 0.5, j + 0.5)``; its ray is ``r = ((p_x-cx)/fx, (p_y-cy)/fy, 1)``.

Per-Gaussian quantities (camera space, μ = camera-space mean, Σ = R_cw R S² Rᵀ R_cwᵀ):
- Scales and opacity after the optional Mip-Splatting 3D filter (variance ``filter3d`` σ_f², docs/methods/gof.md §2.3):
  ``s_eff = sqrt(s² + σ_f²)``, ``o_eff = o · sqrt(Π s² / Π (s² + σ_f²))``.
- Culled: ``μz <= near`` with ``near = settings.near_plane · settings.scene_radius``.
- EWA 2D covariance (docs/methods/3dgs.md §3.1): ``Σ2D = J W Σ Wᵀ Jᵀ + eps2d·I`` with the Jacobian clamped at
  ``|x/z| <= 1.3·(W/2)/fx``, ``|y/z| <= 1.3·(H/2)/fy``. Mip 2D anti-aliasing (``antialias2d`` = k):
  opacity factor ``sqrt(det(Σ2D) / det(Σ2D + k I))`` and Σ2D += k I (k = 0 → factor 1).
  Conic = Σ2D⁻¹; radius = ceil(3·sqrt(λ_max)), λ_max = mid + sqrt(max(0.1, mid² − det)).
  ``means2d`` = projected centre in pixels (surfel: the centre of its exact 3σ screen box, docs/methods/2dgs.md §3.3).
- SH colour (docs/methods/3dgs.md §2.4) at direction ``normalize(μ_w − camera_centre)``, + 0.5, clamped at >= 0.

Per pixel, per Gaussian i (front to back, sorted per 16x16 tile by centre camera z, ties by index):
- ``ewa``:    G = exp(−½ dᵀ conic d), d = p − means2d (skip if the exponent > 0); depth z_i = μz;
              normal n_i = the shortest scale axis in camera space, flipped so that n·μ < 0.
- ``rade``:   α as ``ewa`` with eps2d = 0 by default; ray distance ``t = l + pᵀδ`` (l = ‖μ‖,
              p = −(Q20, Q21)/Q22, Q = (J_r Σ J_rᵀ)⁻¹, δ = normalised offset of p from the centre,
              docs/methods/radegs.md §3.2) and depth ``z_i = t / ‖r‖``; normal ``n_i = −normalize(Σ⁻¹ μ)``.
- ``raymax``: A = Σ⁻¹, b = Σ⁻¹μ, c = μᵀΣ⁻¹μ; ``t* = (b·r)/(rᵀAr)``, ``q = max(0, c − (b·r)²/(rᵀAr))``,
              G = exp(−q/2); skip if t* <= near; z_i = t*; normal ``n_i = −normalize(A r)``.
              The EWA conic (eps2d = 0) is used only for radius/binning and the densification proxy.
- ``surfel``: 2DGS ray–splat intersection (docs/methods/2dgs.md §3.1–§3.4) with H = K[R_cw s_u t_u | R_cw s_v t_v | μ]
              evaluated at p; ρ = min(u²+v², k·|centre − p|²) with k = ``surfel_filter`` (the 2DGS
              paper's low-pass filter of σ = 1/√k px; 2DGS uses k = 2, σ = √2/2; k = 0: ρ = u²+v²); G = exp(−ρ/2); z_i = the intersection
              depth (skip if z_i < near); n_i = R_cw t_w flipped to face the camera (sign is a constant).
- α_i = min(0.99, o_eff·G); skip if α_i < 1/255; the pixel stops before blending i if T·(1−α_i) < 1e-4.
- w_i = α_i T_i with T_i = Π_{j<i}(1 − α_j).

Outputs (only the requested ones are stored and returned; the compositing loop accumulates rgb always and, when
any geometric output is requested, depth, median depth and normal together):
- ``rgb``          (H,W,3) Σ w_i c_i + T_final · background
- ``alpha``        (H,W)   1 − T_final
- ``depth``        (H,W)   Σ w_i z_i / max(alpha, 1e-10)         (0 where nothing contributes)
- ``median_depth`` (H,W)   z_i of the last blended i with T_i > 0.5 (0 if none)
- ``normal``       (H,W,3) Σ w_i n_i, camera space, not normalised (length ≈ alpha)
- ``distortion``   (H,W)   Σ_i Σ_{j<i} w_i w_j (m_i − m_j)², m = far/(far−near)·(1 − near/z),
                           far = settings.far_plane · settings.scene_radius; with
                           ``detach_distortion_weights`` the w's get no gradient (GOF).
- ``plane_distance`` (H,W) Σ w_i d_i, not normalised (PGSR, docs/methods/pgsr.md §3.1): d_i = −n_i·μ >= 0, the
                           distance from the camera centre of the plane through the centre μ with the
                           Gaussian's normal n_i (ewa, rade, surfel: the kernel's per-Gaussian normal; raymax:
                           its normal on the central ray, −normalize(Σ⁻¹μ)). With the ``normal`` output N
                           the unbiased depth of a pixel is −plane_distance / (N·r).
- ``solid_depth``  (H,W)   ``rade`` only (GGGS, docs/methods/gggs.md §1–§2): camera z of the ray distance t where the
                           transmittance of the pixel's blended Gaussians as stochastic solids crosses ½,
                           T(t) = Π_i T_i(t), T_i = √(1 − α_i g_i) before the Gaussian's peak t*_i (its rade
                           ray distance), (1 − α_i)/√(1 − α_i g_i) after, g_i = exp(−½((t − t*_i)/σ_i)²) with
                           1/σ_i = √(r̂ᵀΣ⁻¹r̂), r̂ the unit direction of its centre. Searched in
                           [init ± ``solid_search_range``] (init: the t* of the last blended Gaussian with T > ½
                           before it), ``solid_rounds`` rounds of 8 cells, then linear interpolation
                           (`gsbench.raster.stochastic_solid`); 0 where T does not cross ½ there or the final
                           transmittance exceeds ``solid_min_transmittance``. Gradient: the implicit function's.
Binning and culling (pinned with the reference, `gsbench.raster.reference` "Decisions"):
- Pixel (i, j) lies in tile (i // T, j // T). A Gaussian's tile rectangle is the half-open
  ``[clamp(floor((m − r)/T), 0, grid), clamp(floor((m + r + T − 1)/T), 0, grid))`` with m = means2d
  (pixel-centre +0.5 convention) and r = radius; a pixel only sees Gaussians whose rectangle holds its
  tile; an empty rectangle culls the Gaussian. ``visible = radius > 0``; culled Gaussians have
  means2d = 0.
- Culled: centre z <= near (every kernel); EWA determinant <= 0 after eps2d/antialias (ewa, rade,
  raymax); surfel exactly edge-on (μ·n == 0). A surfel whose 3σ disc reaches the camera plane (no bounded
  screen box) is binned to the whole image with its projected centre and no low-pass term.
- Densification proxies: for ``raymax`` the mean-2D gradient is GOF's proxy (conic-based ∂α/∂means2d
  times the per-pixel dL/dα, docs/methods/gof.md §3.6) and for ``surfel`` the 2DGS shortcut; the reference gives the
  true partial derivative instead, so those two are tested against their own formulas.

Also: ``means2d`` (N,2 pixels; its ``.grad`` after backward is dL/dmeans2d), ``radii`` (N,) int,
``visible`` (N,) bool, and after backward `RenderOutput.densify_grads()` gives the NDC-unit mean-2D
gradient (N,2) (pixel gradient × (W/2, H/2)) and the abs-gradient (N,) Σ_pixels |g_x| + |g_y| (NDC).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import torch

KERNELS = ("ewa", "surfel", "raymax", "rade")
OUTPUTS = ("rgb", "alpha", "depth", "median_depth", "normal", "distortion", "plane_distance")  # every kernel's
KERNEL_OUTPUTS = {"rade": ("solid_depth",)}  # outputs one kernel defines
ALL_OUTPUTS = OUTPUTS + tuple(o for extra in KERNEL_OUTPUTS.values() for o in extra)


@dataclass
class RasterGaussians:
    """Activated Gaussian parameters, world frame. Tensors may require grad.

    means (N,3); quats (N,4) as (w, x, y, z), normalised inside the rasterizer; scales (N,3) positive
    for 3D kernels, (N,2) or (N,3) for ``surfel`` (only the first two are used); opacities (N,) in
    (0, 1); sh (N, K, 3) with K = (degree+1)² >= (settings.sh_degree+1)²; filter3d optional (N,)
    variance σ_f² of the Mip-Splatting 3D filter (no gradient); sh_rest optional (N, K_r, 3): the SH rows
    after those of ``sh``, when the caller keeps them apart (the training parameters sh_dc / sh_rest: the
    fused projection reads both without concatenating them); then K + K_r counts as K above.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor
    filter3d: torch.Tensor | None = None
    sh_rest: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def map(self, fn) -> RasterGaussians:
        """A copy with ``fn`` applied to every tensor field (fields that are None stay None)."""
        return RasterGaussians(**{f.name: None if getattr(self, f.name) is None else fn(getattr(self, f.name))
                                  for f in dataclasses.fields(self)})

    def all_sh(self) -> torch.Tensor:
        """Every SH row (N, K + K_r, 3): ``sh`` followed by ``sh_rest``."""
        return self.sh if self.sh_rest is None else torch.cat([self.sh, self.sh_rest.to(self.sh.dtype)], 1)


@dataclass(frozen=True)
class RasterSettings:
    """Options of one render. Lengths ``near_plane`` and ``far_plane`` are relative to ``scene_radius``.

    ``eps2d`` None means the kernel's default (ewa 0.3, rade 0.0, raymax 0.0; unused by surfel).
    ``surfel_filter`` is k of the surfel kernel's screen-space low-pass term k·|centre − p|² (2DGS: 2;
    0 switches the filter off; unused by the other kernels).
    ``solid_*`` configure the ``solid_depth`` search (GGGS's defaults: half-width 0.4 in scene units, absolute,
    not relative to ``scene_radius``; 5 rounds in training, 8 for meshing; no depth where T_final > 0.45).
    """

    sh_degree: int = 0
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    near_plane: float = 0.2
    far_plane: float = 100.0
    scene_radius: float = 1.0
    eps2d: float | None = None
    surfel_filter: float = 2.0
    antialias2d: float = 0.0
    detach_distortion_weights: bool = False
    tile_size: int = 16
    solid_search_range: float = 0.4
    solid_rounds: int = 5
    solid_min_transmittance: float = 0.45

    @property
    def near(self) -> float:
        return self.near_plane * self.scene_radius

    @property
    def far(self) -> float:
        return self.far_plane * self.scene_radius

    def eps2d_for(self, kernel: str) -> float:
        if self.eps2d is not None:
            return self.eps2d
        return 0.3 if kernel == "ewa" else 0.0


@dataclass
class RenderOutput:
    """What a render returns; outputs not requested are None. See the module docstring."""

    rgb: torch.Tensor | None = None
    alpha: torch.Tensor | None = None
    depth: torch.Tensor | None = None
    median_depth: torch.Tensor | None = None
    normal: torch.Tensor | None = None
    distortion: torch.Tensor | None = None
    plane_distance: torch.Tensor | None = None
    solid_depth: torch.Tensor | None = None
    means2d: torch.Tensor | None = None
    radii: torch.Tensor | None = None
    visible: torch.Tensor | None = None
    width: int = 0
    height: int = 0
    extras: dict = field(default_factory=dict)

    def densify_grads(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(NDC mean-2D gradient (N,2), NDC abs-gradient (N,)) after ``backward()``; zeros if none."""
        n = self.means2d.shape[0]
        scale = torch.tensor([self.width / 2.0, self.height / 2.0], dtype=self.means2d.dtype)
        grad = self.means2d.grad
        grad = torch.zeros(n, 2, dtype=self.means2d.dtype) if grad is None else grad * scale
        absgrad = self.extras.get("absgrad")
        if absgrad is None:
            absgrad = grad.abs().sum(-1)
        return grad, absgrad
