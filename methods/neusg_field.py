"""NeuSG's implicit side (docs/methods/neusg.md §2): a signed distance field f on a multi-resolution hash
grid with a small MLP, its colour network, a background field outside the SDF's sphere, and NeuS volume
rendering of a batch of pixel rays.

**Encoding** (`MultiGrid`, the multi-resolution grid of Instant-NGP that NeuSG's Neuralangelo base
uses, every level dense, none hashed: docs/methods/neusg.md §5.1): L levels of resolution
N_l = round(N_min · b^l), b = (N_max / N_min)^(1/(L−1)), F features per grid vertex, trilinear
interpolation of the cell's 8 vertices (`gsbench.methods.neusg_grid.grid_features`: a fused kernel, ``grid_sample`` its
reference); the encoding concatenates the levels.
Entries start uniform in ±1e-4 (Instant-NGP).

**Hash encoding** (`HashGrid`, ``method.encoding: hash``, NeuSG's field as published: docs/methods/neusg.md §5.1):
the same levels, each a table of min((N_l + 1)³, 2^T) feature vectors addressed by Instant-NGP's spatial hash of
the cell's vertices (`gsbench.methods.neusg_hash.hash_features`: a fused kernel, its PyTorch reference beside it),
with Neuralangelo's coarse-to-fine schedule: the first `HASH_INITIAL_LEVELS` levels are active, one more every
``method.grid_level_step`` steps after ``method.grid_active_start`` (`NeuSG.update_schedules`); an inactive level's
features are 0, and the numerical gradient's step is the finest active level's cell (Neuralangelo's
``set_normal_epsilon``).

**SDF** (`SDFField`): f(x) = (|x| − r₀) + g(x/R, enc(x)), g an MLP (one hidden layer of 64, softplus
β = 100, NeuS/Neuralangelo's activation) whose output layer starts at zero, so f starts as the sphere of
radius r₀ = R/2 (NeuS's geometric initialisation, bias 0.5 in the unit sphere, written as an explicit
prior). The MLP also outputs a 15-dimensional geometry feature for the colour network. ∇f is the
numerical gradient of Neuralangelo (4 taps on a tetrahedron, step ε = the finest grid cell), which
needs no double backward through the grid sampler.

**Colour** (`ColourNetwork`, NeuS's "IDR" mode): c = sigmoid(MLP([x/R, n, d, feature])), n = ∇f/|∇f|,
d the view direction, two hidden layers of 64.

**Background** (`BackgroundField`, in place of NeuSG's NeRF++ outer network,
docs/methods/neusg.md §5.2): beyond the sphere of radius R, points are contracted as in Mip-NeRF 360,
x ↦ (2 − R/|x|) x/|x| (|x| ≥ R; the contracted ball has radius 2R), encoded by a coarser grid, and an MLP gives a
density σ = softplus(·) and a colour from the feature and d; ``samples`` points per ray are spread
uniformly in inverse distance (disparity) from the sphere's exit to infinity (NeRF++'s inverted-sphere
sampling), and composited with α = 1 − exp(−σ δ).

**NeuS rendering** (`render_rays`, NeuS eq. 13): n_coarse samples uniform in the ray's chord of the
sphere, then one round of importance sampling (NeuS up-samples with a fixed s = 64; here one round of
n_fine samples from the coarse weights at s = 64) and, at the merged, sorted samples p_i,
α_i = max((Φ_s(f(p_i)) − Φ_s(f(p_{i+1}))) / Φ_s(f(p_i)), 0), Φ_s = sigmoid(s ·), s = exp(10 v) with v
learned (NeuS: v₀ = 0.3); w_i = T_i α_i, T_i = Π_{j<i} (1 − α_j). The pixel colour is
Σ w_i c_i + T_in · (background composite). Rays that miss the sphere see the background only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from gsbench.methods.neusg_grid import grid_features
from gsbench.methods.neusg_hash import hash_features

TETRAHEDRON = torch.tensor([[1.0, -1.0, -1.0], [-1.0, -1.0, 1.0], [-1.0, 1.0, -1.0], [1.0, 1.0, 1.0]])
SOFTPLUS_BETA = 100.0
UPSAMPLE_S = 64.0  # NeuS's fixed s for the importance-sampling round
ENCODINGS = ("dense", "hash")  # method.encoding: `MultiGrid`, `HashGrid`
HASH_INITIAL_LEVELS = 4  # levels active from the start (Neuralangelo's coarse2fine.init_active_level)


def level_resolutions(levels: int, min_res: int, max_res: int) -> list[int]:
    """N_l = round(N_min · b^l), b = (N_max / N_min)^(1/(L−1)) (Instant-NGP eqs. 2–3, rounded rather than floored
    so that the finest level is N_max)."""
    growth = (max_res / min_res) ** (1 / max(levels - 1, 1))
    return [int(round(min_res * growth**level)) for level in range(levels)]


class MultiGrid(torch.nn.Module):
    """Multi-resolution dense feature grids over [0, 1]³ (module docstring), sampled trilinearly by
    `gsbench.methods.neusg_grid.grid_features` (grid vertex i at i / N_l)."""

    def __init__(self, levels: int, min_res: int, max_res: int, features: int, seed: int):
        super().__init__()
        self.resolutions = level_resolutions(levels, min_res, max_res)
        gen = torch.Generator().manual_seed(seed)
        self.grids = torch.nn.ParameterList(
            torch.nn.Parameter((torch.rand(1, features, r + 1, r + 1, r + 1, generator=gen) * 2 - 1) * 1e-4)
            for r in self.resolutions)
        self.features = features

    @property
    def dim(self) -> int:
        return len(self.resolutions) * self.features

    @property
    def finest_cell(self) -> float:
        """The finest level's cell, in units of the grid's side."""
        return 1.0 / self.resolutions[-1]

    def forward(self, unit: torch.Tensor) -> torch.Tensor:
        """(N, L·F) features of points ``unit`` (N,3) in [0, 1]³ (outside: the border value)."""
        return grid_features(self.grids, unit)


class HashGrid(torch.nn.Module):
    """Multi-resolution hash tables over [0, 1]³ (module docstring), sampled by
    `gsbench.methods.neusg_hash.hash_features`; ``active`` (a buffer, so checkpoints keep it) levels are used."""

    def __init__(self, levels: int, min_res: int, max_res: int, features: int, table_log2: int, seed: int):
        super().__init__()
        self.resolutions = level_resolutions(levels, min_res, max_res)
        gen = torch.Generator().manual_seed(seed)
        self.tables = torch.nn.ParameterList(
            torch.nn.Parameter((torch.rand(min((r + 1) ** 3, 1 << table_log2), features, generator=gen) * 2 - 1) * 1e-4)
            for r in self.resolutions)
        self.features = features
        self.register_buffer("active", torch.tensor(min(HASH_INITIAL_LEVELS, levels)))

    @property
    def dim(self) -> int:
        return len(self.resolutions) * self.features

    def set_active(self, levels: int) -> None:
        """Use the first ``levels`` levels (clamped to [1, L])."""
        self.active.fill_(min(max(int(levels), 1), len(self.resolutions)))

    @property
    def finest_cell(self) -> float:
        """The finest active level's cell, in units of the grid's side."""
        return 1.0 / self.resolutions[int(self.active) - 1]

    def forward(self, unit: torch.Tensor) -> torch.Tensor:
        """(N, L·F) features of points ``unit`` (N,3) in [0, 1]³ (outside: the border value); 0 for inactive levels."""
        active = int(self.active)
        out = hash_features(self.tables[:active], self.resolutions[:active], unit)
        return F.pad(out, (0, self.dim - out.shape[1]))


def _softplus(x: torch.Tensor) -> torch.Tensor:
    return F.softplus(x, beta=SOFTPLUS_BETA)


class SDFField(torch.nn.Module):
    """f(x) = |x| − r₀ + g(x/R, enc(x)) and the geometry feature (module docstring)."""

    FEATURE_DIM = 15

    def __init__(self, radius: float, grid: MultiGrid | HashGrid, hidden: int = 64):
        super().__init__()
        self.radius, self.sphere = float(radius), 0.5 * float(radius)
        self.grid = grid
        self.hidden = torch.nn.Linear(3 + grid.dim, hidden)
        self.out = torch.nn.Linear(hidden, 1 + self.FEATURE_DIM)
        torch.nn.init.zeros_(self.out.weight)
        torch.nn.init.zeros_(self.out.bias)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(f (N,), feature (N, 15)) at points ``x`` (N,3) in the scene frame."""
        unit = x / self.radius
        h = _softplus(self.hidden(torch.cat([unit, self.grid(0.5 * unit + 0.5)], dim=-1)))
        out = self.out(h)
        return x.norm(dim=-1) - self.sphere + out[:, 0], out[:, 1:]

    @property
    def epsilon(self) -> float:
        """The numerical gradient's step: the grid's finest (active) cell, scene units."""
        return 2 * self.radius * self.grid.finest_cell

    def with_gradient(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(f, ∇f (N,3), feature): ∇f = Σ_k v_k f(x + ε v_k) / (4ε) over the tetrahedron v_k ∈ {(1,−1,−1),
        (−1,−1,1), (−1,1,−1), (1,1,1)}, ε = `epsilon` (Neuralangelo's 4-tap numerical gradient, exact for
        linear f), the five evaluations in one batch; ∇f is differentiable in the field's parameters."""
        eps = self.epsilon
        taps = torch.cat([torch.zeros(1, 3), eps * TETRAHEDRON]).to(x.dtype)
        sdf, feature = self((x[None] + taps[:, None]).reshape(-1, 3))
        sdf = sdf.reshape(5, -1)
        grad = (TETRAHEDRON.to(x.dtype)[:, None, :] * sdf[1:, :, None]).sum(0) / (4 * eps)
        return sdf[0], grad, feature.reshape(5, -1, feature.shape[-1])[0]


class ColourNetwork(torch.nn.Module):
    """c = sigmoid(MLP([x/R, n, d, feature])) (module docstring)."""

    def __init__(self, radius: float, hidden: int = 64):
        super().__init__()
        self.radius = float(radius)
        self.net = torch.nn.Sequential(torch.nn.Linear(9 + SDFField.FEATURE_DIM, hidden), torch.nn.ReLU(),
                                       torch.nn.Linear(hidden, hidden), torch.nn.ReLU(), torch.nn.Linear(hidden, 3))

    def forward(self, x, normal, direction, feature) -> torch.Tensor:
        return torch.sigmoid(self.net(torch.cat([x / self.radius, normal, direction, feature], dim=-1)))


class BackgroundField(torch.nn.Module):
    """Density and colour outside the SDF's sphere, in contracted coordinates (module docstring)."""

    def __init__(self, radius: float, grid: MultiGrid, hidden: int = 64):
        super().__init__()
        self.radius = float(radius)
        self.grid = grid
        self.net = torch.nn.Sequential(torch.nn.Linear(grid.dim + 3, hidden), torch.nn.ReLU(), torch.nn.Linear(hidden, 4))

    def forward(self, x: torch.Tensor, direction: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(σ (N,), colour (N,3)) at points ``x`` with |x| ≥ R."""
        r = x.norm(dim=-1, keepdim=True).clamp_min(self.radius)
        contracted = (2 - self.radius / r) * x / r  # |·| in [R, 2R)
        out = self.net(torch.cat([self.grid(contracted / (4 * self.radius) + 0.5), direction], dim=-1))
        return F.softplus(out[:, 0]), torch.sigmoid(out[:, 1:])


def sphere_chord(origins: torch.Tensor, directions: torch.Tensor, radius: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(near, far, hit) of rays o + t d (|d| = 1) through the sphere |x| = ``radius``; near ≥ 0; for rays
    that miss it near = far = 0 and hit False."""
    b = (origins * directions).sum(-1)
    c = (origins * origins).sum(-1) - radius * radius
    disc = b * b - c
    hit = disc > 0
    root = disc.clamp_min(0).sqrt()
    near, far = (-b - root).clamp_min(0), (-b + root).clamp_min(0)
    hit = hit & (far > near)
    return torch.where(hit, near, 0), torch.where(hit, far, 0), hit


def neus_alpha(sdf: torch.Tensor, s: torch.Tensor | float) -> torch.Tensor:
    """α_i = max((Φ_s(f_i) − Φ_s(f_{i+1})) / Φ_s(f_i), 0) over the last dim (NeuS eq. 13); the last sample of
    each ray has no successor and gets α = 0. Written with Φ_s(f_i) in the denominator kept ≥ 1e-6."""
    cdf = torch.sigmoid(sdf * s)
    alpha = ((cdf[..., :-1] - cdf[..., 1:]) / cdf[..., :-1].clamp_min(1e-6)).clamp(0.0, 1.0)
    return torch.cat([alpha, torch.zeros_like(alpha[..., :1])], dim=-1)


def transmittance_weights(alpha: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(w_i = T_i α_i, T after the last sample) with T_i = Π_{j<i} (1 − α_j) over the last dim."""
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[..., :1]), 1 - alpha + 1e-10], dim=-1), dim=-1)
    return trans[..., :-1] * alpha, trans[..., -1]


def importance_samples(t: torch.Tensor, weights: torch.Tensor, count: int, generator: torch.Generator | None) -> torch.Tensor:
    """``count`` samples per ray from the piecewise-constant pdf of ``weights`` over the intervals of ``t``
    (inverse CDF with uniform random u, seeded)."""
    pdf = weights[:, :-1] + 1e-5
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf / pdf.sum(-1, keepdim=True), dim=-1)], dim=-1)
    u = torch.rand(t.shape[0], count, generator=generator)
    idx = torch.searchsorted(cdf.contiguous(), u, right=True).clamp(1, t.shape[1] - 1)
    lo, hi = torch.gather(cdf, 1, idx - 1), torch.gather(cdf, 1, idx)
    t_lo, t_hi = torch.gather(t, 1, idx - 1), torch.gather(t, 1, idx)
    return t_lo + (u - lo) / (hi - lo).clamp_min(1e-10) * (t_hi - t_lo)


@dataclass
class RayBatch:
    """What `render_rays` returns for R rays: colour (R,3), the SDF's accumulated weight (R,), the points
    and SDF gradients of every sample inside the sphere (for the Eikonal term), and the depth."""

    colour: torch.Tensor
    opacity: torch.Tensor
    depth: torch.Tensor
    gradients: torch.Tensor


class ImplicitScene(torch.nn.Module):
    """The SDF, its colour network, the background and the NeuS variance: everything NeuSG adds.

    ``encoding``: the SDF's grid, `MultiGrid` ("dense") or `HashGrid` ("hash", ``table_log2`` = T).
    The field lives in the frame of its region, the sphere of ``radius`` about ``centre`` (training frame):
    `local` maps a training-frame point into it, and `render_rays` takes training-frame rays."""

    def __init__(self, radius: float, seed: int, *, centre=(0.0, 0.0, 0.0), levels: int = 5, min_res: int = 16,
                 max_res: int = 256, features: int = 2, background_levels: int = 3, background_max_res: int = 64,
                 encoding: str = "dense", table_log2: int = 19):
        super().__init__()
        self.radius = float(radius)
        self.register_buffer("centre", torch.as_tensor(np.asarray(centre, dtype=np.float32)))
        with torch.random.fork_rng():  # the networks' initial weights from ``seed``, the global stream untouched
            torch.manual_seed(seed)
            grid = (HashGrid(levels, min_res, max_res, features, table_log2, seed) if encoding == "hash"
                    else MultiGrid(levels, min_res, max_res, features, seed))
            self.sdf = SDFField(radius, grid)
            self.colour = ColourNetwork(radius)
            self.background = BackgroundField(radius, MultiGrid(background_levels, min_res, background_max_res,
                                                                features, seed + 1))
        self.variance = torch.nn.Parameter(torch.tensor(0.3))

    def local(self, x: torch.Tensor) -> torch.Tensor:
        """Training-frame points (N,3) in the field's frame: x − centre."""
        return x - self.centre.to(x.dtype)

    @property
    def s(self) -> torch.Tensor:
        """NeuS's s = exp(10 v)."""
        return torch.exp(10.0 * self.variance)

    def _background(self, origins, directions, far, samples: int, generator) -> tuple[torch.Tensor, torch.Tensor]:
        """(colour (R,3), opacity (R,)) of the background beyond ``far`` along each ray (module docstring)."""
        exit_points = origins + far[:, None] * directions
        start = exit_points.norm(dim=-1).clamp_min(self.radius)
        u = (torch.arange(samples, dtype=origins.dtype) + torch.rand(samples, generator=generator)) / samples
        inverse = (1 - u)[None] / start[:, None]  # disparity from 1/|exit| down to 0 (excluded)
        depth = 1 / inverse.clamp_min(1e-6 / self.radius)
        delta = torch.cat([depth[:, 1:] - depth[:, :-1], torch.full_like(depth[:, :1], 1e10)], dim=-1)
        points = exit_points[:, None] + (depth - start[:, None])[..., None] * directions[:, None]
        sigma, colour = self.background(points.reshape(-1, 3), directions[:, None].expand_as(points).reshape(-1, 3))
        alpha = 1 - torch.exp(-sigma.reshape(depth.shape) * delta.clamp_max(1e10))
        weights, _ = transmittance_weights(alpha)
        return (weights[..., None] * colour.reshape(*depth.shape, 3)).sum(1), weights.sum(1)

    def render_rays(self, origins: torch.Tensor, directions: torch.Tensor, n_coarse: int, n_fine: int,
                    n_background: int, generator: torch.Generator | None) -> RayBatch:
        """NeuS rendering of rays o + t d, |d| = 1, training frame (module docstring)."""
        origins = self.local(origins)
        near, far, hit = sphere_chord(origins, directions, self.radius)
        rays = origins.shape[0]
        colour = torch.zeros(rays, 3, dtype=origins.dtype)
        opacity = torch.zeros(rays, dtype=origins.dtype)
        depth = torch.zeros(rays, dtype=origins.dtype)
        gradients = torch.zeros(0, 3, dtype=origins.dtype)
        through = torch.ones(rays, dtype=origins.dtype)
        if hit.any():
            o, d, t0, t1 = origins[hit], directions[hit], near[hit], far[hit]
            steps = (torch.arange(n_coarse, dtype=o.dtype) + 0.5) / n_coarse
            t = t0[:, None] + (t1 - t0)[:, None] * steps[None]
            if n_fine > 0:
                with torch.no_grad():
                    coarse_sdf, _ = self.sdf((o[:, None] + t[..., None] * d[:, None]).reshape(-1, 3))
                    w, _ = transmittance_weights(neus_alpha(coarse_sdf.reshape(t.shape), UPSAMPLE_S))
                    t = torch.sort(torch.cat([t, importance_samples(t, w, n_fine, generator)], dim=-1), dim=-1).values
            points = (o[:, None] + t[..., None] * d[:, None]).reshape(-1, 3)
            sdf, grad, feature = self.sdf.with_gradient(points)
            normal = F.normalize(grad, dim=-1)
            dirs = d[:, None].expand(-1, t.shape[1], -1).reshape(-1, 3)
            c = self.colour(points, normal, dirs, feature).reshape(*t.shape, 3)
            w, rest = transmittance_weights(neus_alpha(sdf.reshape(t.shape), self.s))
            colour = colour.index_put((hit,), (w[..., None] * c).sum(1))
            opacity = opacity.index_put((hit,), w.sum(1))
            depth = depth.index_put((hit,), (w * t).sum(1))
            through = through.index_put((hit,), rest)
            gradients = grad
        bg_colour, _ = self._background(origins, directions, torch.where(hit, far, 0.0), n_background, generator)
        return RayBatch(colour=colour + through[:, None] * bg_colour, opacity=opacity, depth=depth, gradients=gradients)
